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

/// Azimuth columns per revolution of a spinning lidar, from its points and rings: 2π over the median
/// azimuth step between consecutive returns of a ring. `None` when no ring has two distinct returns.
pub fn columns_from_azimuths(positions: &[DVec3], ring: &[u16]) -> Option<usize> {
    let mut per_ring: std::collections::BTreeMap<u16, Vec<f64>> = Default::default();
    for (p, &r) in positions.iter().zip(ring) {
        if p.is_finite() && r != u16::MAX {
            per_ring.entry(r).or_default().push(p.y.atan2(p.x));
        }
    }
    let mut steps = Vec::new();
    for az in per_ring.values_mut() {
        az.sort_by(f64::total_cmp);
        steps.extend(az.windows(2).map(|w| w[1] - w[0]).filter(|&d| d > 1e-5));
    }
    if steps.is_empty() {
        return None;
    }
    let mid = steps.len() / 2;
    steps.select_nth_unstable_by(mid, f64::total_cmp);
    Some(
        (std::f64::consts::TAU / steps[mid])
            .round()
            .clamp(16.0, 16384.0) as usize,
    )
}

/// Column of a point for a lidar with `columns` azimuth steps per revolution: column c looks along azimuth
/// 2πc/columns, counter-clockwise from the sensor's +x (the convention of [`RangeImage`] and the sky mask).
pub fn column_of(p: DVec3, columns: usize) -> u16 {
    let az = p.y.atan2(p.x).rem_euclid(std::f64::consts::TAU);
    ((az / std::f64::consts::TAU * columns as f64).round() as usize % columns.max(1)) as u16
}

/// A range image for a sweep whose driver gives no ring or column (DGP `.npz`, KITTI `.bin`, PCD files):
/// each point's elevation and azimuth binned on a square angular grid sized so that cells are about as
/// many as points over the elevation band the sweep covers. Returns per-point (ring, column) and the grid
/// size (rings, columns); column c is centred on azimuth 2πc/columns, like a spinning lidar's.
pub fn angular_grid(positions: &[DVec3]) -> (Vec<u16>, Vec<u16>, usize, usize) {
    let el_az = |p: &DVec3| {
        let r = p.length();
        (p.is_finite() && r > 0.0).then(|| ((p.z / r).asin(), p.y.atan2(p.x)))
    };
    let (mut lo, mut hi, mut n) = (f64::INFINITY, f64::NEG_INFINITY, 0usize);
    for (el, _) in positions.iter().filter_map(el_az) {
        lo = lo.min(el);
        hi = hi.max(el);
        n += 1;
    }
    if n < 2 || hi <= lo {
        return (
            vec![u16::MAX; positions.len()],
            vec![0; positions.len()],
            1,
            1,
        );
    }
    let step = ((hi - lo) * std::f64::consts::TAU / n as f64)
        .sqrt()
        .max(1e-4);
    let columns = ((std::f64::consts::TAU / step).round() as usize).clamp(8, 16_384);
    let rings = (((hi - lo) / step).floor() as usize + 1).min(u16::MAX as usize - 1);
    let mut ring = Vec::with_capacity(positions.len());
    let mut column = Vec::with_capacity(positions.len());
    for p in positions {
        match el_az(p) {
            Some((el, az)) => {
                ring.push((((el - lo) / step).floor() as usize).min(rings - 1) as u16);
                let c = (az.rem_euclid(std::f64::consts::TAU) / std::f64::consts::TAU
                    * columns as f64)
                    .round() as usize
                    % columns;
                column.push(c as u16);
            }
            None => {
                ring.push(u16::MAX);
                column.push(0);
            }
        }
    }
    (ring, column, rings, columns)
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

/// How [`newell_normals`] picks and screens neighbours.
#[derive(Clone, Copy, Debug)]
pub struct NormalParams {
    /// Column offset of the horizontal neighbours. Rings are usually several times further apart in angle
    /// than columns; stepping `k` columns makes the neighbourhood roughly square, so range noise tilts the
    /// normal about equally little in both directions ([`RangeImage::balanced_column_step`]).
    pub column_step: usize,
    /// A neighbour whose offset from the point is within this angle (rad) of the viewing ray is taken to be
    /// across a depth discontinuity (a foreground edge against the background) and left out. Surfaces seen
    /// at grazing incidence (the road far ahead) are rejected by the same rule, and their normals are
    /// unreliable anyway.
    pub min_offset_angle: f64,
}

impl Default for NormalParams {
    fn default() -> Self {
        Self {
            column_step: 1,
            min_offset_angle: 5f64.to_radians(),
        }
    }
}

impl RangeImage {
    /// The column step that best matches the ring spacing, estimated from the points themselves
    /// (median elevation per ring, azimuth step = 360° / columns), so it works for any sensor.
    pub fn balanced_column_step(&self, positions: &[DVec3]) -> usize {
        let mut el: Vec<Vec<f64>> = vec![Vec::new(); self.rings];
        for (cell, i) in self.cells.iter().enumerate() {
            if let Some(i) = i {
                let p = positions[*i as usize];
                if p.is_finite() && p.length() > 0.0 {
                    el[cell / self.columns].push((p.z / p.length()).asin());
                }
            }
        }
        let med: Vec<f64> = el
            .into_iter()
            .filter(|v| !v.is_empty())
            .map(|mut v| {
                let m = v.len() / 2;
                v.select_nth_unstable_by(m, f64::total_cmp);
                v[m]
            })
            .collect();
        if med.len() < 2 || self.columns == 0 {
            return 1;
        }
        let mut steps: Vec<f64> = med.windows(2).map(|w| (w[1] - w[0]).abs()).collect();
        let m = steps.len() / 2;
        steps.select_nth_unstable_by(m, f64::total_cmp);
        let az = std::f64::consts::TAU / self.columns as f64;
        ((steps[m] / az).round() as usize).clamp(1, 16)
    }
}

/// Per-point unit normals (NaN where undefined) for points in a frame whose origin is the sensor.
/// `positions[i]` sits at cell (ring[i], column[i]) of `image`. The neighbourhood is the 8 cells around
/// the point (columns `column_step` apart) in cyclic order; at least 3 must survive the screening.
pub fn newell_normals(
    positions: &[DVec3],
    image: &RangeImage,
    ring: &[u16],
    column: &[u16],
    params: NormalParams,
) -> Vec<DVec3> {
    let k = params.column_step.max(1) as isize;
    let cos_min = params.min_offset_angle.cos();
    // Counter-clockwise in (column, ring): right, up-right, up, up-left, left, down-left, down, down-right.
    let ring_of = [
        (0, k),
        (1, k),
        (1, 0),
        (1, -k),
        (0, -k),
        (-1, -k),
        (-1, 0),
        (-1, k),
    ];
    positions
        .iter()
        .enumerate()
        .map(|(i, &p)| {
            if !p.is_finite() {
                return DVec3::NAN;
            }
            let (r, c) = (ring[i] as isize, column[i] as isize);
            let ray = p.normalize();
            let mut poly = Vec::with_capacity(8);
            for (dr, dc) in ring_of {
                if let Some(j) = image.get(r + dr, c + dc) {
                    let q = positions[j as usize];
                    let off = q - p;
                    let len = off.length();
                    if q.is_finite() && len > 0.0 && (off.dot(ray) / len).abs() < cos_min {
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

/// The whole normal step for one sweep, as the pipeline runs it: organise the points into a
/// `rings` x `columns` range image, balance the column step to the ring spacing, and compute Newell normals
/// with the default screening. Returns the range image too (the sky mask reads it).
pub fn sweep_normals(
    positions: &[DVec3],
    rings: usize,
    columns: usize,
    ring: &[u16],
    column: &[u16],
) -> (RangeImage, Vec<DVec3>) {
    let image = RangeImage::new(rings, columns, ring, column);
    let params = NormalParams {
        column_step: image.balanced_column_step(positions),
        ..Default::default()
    };
    let normals = newell_normals(positions, &image, ring, column, params);
    (image, normals)
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
        let params = NormalParams::default();
        let n = newell_normals(&pos, &img, &ring, &col, params);
        let centre = 2 * cols + 3;
        assert!((n[centre] + DVec3::X).length() < 1e-9, "{}", n[centre]);
        // A corner point has three neighbours (right, up-right, up): still enough.
        assert!((n[0] + DVec3::X).length() < 1e-9, "{}", n[0]);
        // Neighbours across a depth jump are left out: with the whole right and left columns pushed far
        // back only the two vertical neighbours remain, too few for a normal.
        let mut far = pos.clone();
        for r in 1..4 {
            far[r * cols + 4] *= 10.0;
            far[r * cols + 2] *= 10.0;
        }
        let n = newell_normals(&far, &img, &ring, &col, params);
        assert!(n[centre].is_nan(), "{}", n[centre]);
        // Rings 0.05 rad apart, columns 2π/360 apart: about 3 columns per ring.
        assert_eq!(img.balanced_column_step(&pos), 3);
    }

    #[test]
    fn angular_grid_gives_ground_normals_without_rings() {
        // A ground plane 1.7 m below a sensor with irregular beams (no ring field), shuffled.
        let mut pts = Vec::new();
        for b in 0..24 {
            let el = (-25.0 + b as f64 * 0.9 + 0.1 * ((b * 7) % 3) as f64).to_radians();
            for c in 0..900 {
                let az = c as f64 / 900.0 * std::f64::consts::TAU;
                let d = DVec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin());
                pts.push(d * (1.7 / -d.z));
            }
        }
        let n = pts.len();
        let shuffled: Vec<DVec3> = (0..n).map(|i| pts[(i * 7919) % n]).collect();
        let (ring, column, rings, columns) = angular_grid(&shuffled);
        assert!(rings > 10 && columns > 300, "{rings} x {columns}");
        let (_, normals) = sweep_normals(&shuffled, rings, columns, &ring, &column);
        let good = normals
            .iter()
            .filter(|m| m.is_finite() && m.z.abs() > 0.99)
            .count();
        assert!(good as f64 > 0.8 * n as f64, "{good} of {n} vertical");
        // Degenerate input: no usable grid, no panic.
        let (r, _, rr, cc) = angular_grid(&[DVec3::ZERO, DVec3::NAN]);
        assert_eq!((r, rr, cc), (vec![u16::MAX; 2], 1, 1));
    }
}
