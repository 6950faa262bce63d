//! Lidar normals by Newell's method on the range image.
//!
//! A spinning lidar's sweep is a grid (ring x column). For each point, the valid 4-neighbours (up, right,
//! down, left, in cyclic order) that lie on the same surface form a polygon around it; Newell's method gives
//! that polygon's normal robustly even when it is non-planar or has only three vertices. The normal is
//! turned to face the sensor. Neighbours across a depth discontinuity (relative range jump above
//! `max_jump`) are left out, so normals never bridge a foreground edge and the background.

use glam::DVec3;

/// A sweep organised as rings x columns; `None` where there was no return.
#[derive(Clone, Debug)]
pub struct RangeImage {
    pub rings: usize,
    pub columns: usize,
    /// Row-major (ring, column) → index into the point list.
    pub cells: Vec<Option<u32>>,
}

impl RangeImage {
    /// Builds the grid from per-point ring and column numbers; out-of-range entries are ignored and the
    /// first point claims a cell.
    pub fn new(rings: usize, columns: usize, ring: &[u16], column: &[u16]) -> RangeImage {
        let mut cells = vec![None; rings * columns];
        for (i, (&r, &c)) in ring.iter().zip(column).enumerate() {
            let (r, c) = (r as usize, c as usize);
            if r < rings && c < columns && cells[r * columns + c].is_none() {
                cells[r * columns + c] = Some(i as u32);
            }
        }
        RangeImage {
            rings,
            columns,
            cells,
        }
    }

    pub fn get(&self, ring: isize, column: isize) -> Option<u32> {
        if ring < 0 || ring as usize >= self.rings {
            return None;
        }
        // Columns wrap around a full revolution.
        let c = column.rem_euclid(self.columns as isize) as usize;
        self.cells[ring as usize * self.columns + c]
    }
}

/// Newell's normal of a closed polygon (not normalised).
pub fn newell(polygon: &[DVec3]) -> DVec3 {
    let mut n = DVec3::ZERO;
    for (j, a) in polygon.iter().enumerate() {
        let b = polygon[(j + 1) % polygon.len()];
        n.x += (a.y - b.y) * (a.z + b.z);
        n.y += (a.z - b.z) * (a.x + b.x);
        n.z += (a.x - b.x) * (a.y + b.y);
    }
    n
}

/// Per-point unit normals (NaN where undefined) for points in a frame whose origin is the sensor.
/// `positions[i]` sits at cell (ring[i], column[i]) of `image`.
pub fn newell_normals(
    positions: &[DVec3],
    image: &RangeImage,
    ring: &[u16],
    column: &[u16],
    max_jump: f64,
) -> Vec<DVec3> {
    positions
        .iter()
        .enumerate()
        .map(|(i, &p)| {
            if !p.is_finite() {
                return DVec3::NAN;
            }
            let (r, c) = (ring[i] as isize, column[i] as isize);
            let range = p.length();
            // Rings go up with elevation and columns counter-clockwise, so up, left(+col), down, right(-col)
            // is a consistent cyclic order; orientation is fixed afterwards anyway.
            let mut poly = Vec::with_capacity(4);
            for (dr, dc) in [(1, 0), (0, 1), (-1, 0), (0, -1)] {
                if let Some(j) = image.get(r + dr, c + dc) {
                    let q = positions[j as usize];
                    if q.is_finite() && ((q.length() - range).abs() / range) <= max_jump {
                        poly.push(q);
                    }
                }
            }
            if poly.len() < 3 {
                return DVec3::NAN;
            }
            let n = newell(&poly);
            let len = n.length();
            if len < 1e-12 {
                return DVec3::NAN;
            }
            let n = n / len;
            // Face the sensor at the origin.
            if n.dot(p) > 0.0 {
                -n
            } else {
                n
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn newell_of_a_square_is_its_normal() {
        let sq = [
            DVec3::new(0.0, 0.0, 0.0),
            DVec3::new(1.0, 0.0, 0.0),
            DVec3::new(1.0, 1.0, 0.0),
            DVec3::new(0.0, 1.0, 0.0),
        ];
        let n = newell(&sq);
        assert!((n.normalize() - DVec3::Z).length() < 1e-12);
    }

    #[test]
    fn plane_seen_by_a_scanner_gets_its_normal_facing_the_sensor() {
        // A wall x = 5 scanned on a small grid; the normal must be -x (towards the origin).
        let (rings, cols) = (5usize, 7usize);
        let mut pos = Vec::new();
        let mut ring = Vec::new();
        let mut col = Vec::new();
        for r in 0..rings {
            for c in 0..cols {
                let el = (r as f64 - 2.0) * 0.05;
                let az = (c as f64 - 3.0) * 0.05;
                let d = DVec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin());
                pos.push(d * (5.0 / d.x));
                ring.push(r as u16);
                col.push(c as u16);
            }
        }
        let img = RangeImage::new(rings, 360, &ring, &col);
        let n = newell_normals(&pos, &img, &ring, &col, 0.2);
        let centre = 2 * cols + 3;
        assert!((n[centre] + DVec3::X).length() < 1e-9, "{}", n[centre]);
        // A corner point has only two neighbours: undefined.
        assert!(n[0].is_nan());
        // A depth jump excludes a neighbour.
        let mut far = pos.clone();
        far[centre + 1] *= 3.0;
        far[centre - 1] *= 3.0;
        let n = newell_normals(&far, &img, &ring, &col, 0.2);
        assert!(n[centre].is_nan());
    }
}
