//! The campus: a grid of blocks between streets, for missions of thousands of images with loops.
//!
//! Every block is one of four kinds, so each appears wherever the walk goes: a **courtyard** building (four
//! wings round a yard, the south wing pierced by a passage), a **row** of houses with gaps, an **arcade**
//! (an upper storey on columns over a recessed ground floor) and a **glass tower** (a uniform curtain wall:
//! as hard for vision as the white walls, which some houses have). Buildings outside the perimeter streets
//! face them, so no camera looks out onto an empty field. Deterministic from the seed.

use glam::{DVec2, DVec3};
use rand::{Rng, SeedableRng};
use rand_xoshiro::Xoshiro256PlusPlus;

use super::super::raycast::{Primitive, Shape};
use super::{CampusParams, Material, WorldParams, PAINTS, PALETTE};

/// The block kinds, in the order the seed shuffles them over the grid.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum BlockKind {
    Courtyard,
    Row,
    Arcade,
    Tower,
}

struct Builder {
    rng: Xoshiro256PlusPlus,
    prims: Vec<Primitive>,
    materials: Vec<Material>,
}

impl Builder {
    fn material(&mut self, m: Material) -> u16 {
        self.materials.push(m);
        (self.materials.len() - 1) as u16
    }

    fn cuboid(&mut self, min: DVec3, max: DVec3, material: u16) {
        self.prims.push(Primitive {
            shape: Shape::Cuboid { min, max },
            material,
        });
    }

    /// A facade material: textured (brick or plaster), or with probability `p_white` a white wall.
    fn facade(&mut self, p_white: f64) -> u16 {
        let base = PALETTE[self.rng.random_range(0..PALETTE.len())];
        let brick = self.rng.random_bool(0.5);
        let white = self.rng.random_bool(p_white);
        self.material(Material::Building {
            base,
            brick,
            white,
            glass: false,
        })
    }

    /// A curtain wall: its `base` colour everywhere.
    fn glass(&mut self) -> u16 {
        self.material(Material::Building {
            base: [0.16, 0.20, 0.25],
            brick: false,
            white: false,
            glass: true,
        })
    }

    /// Buildings along a straight frontage from `a` to `b` (2D, the facade line), extending `depth`
    /// away on the side of `outward`, with random widths, gaps and heights.
    fn frontage(&mut self, a: DVec2, b: DVec2, outward: DVec2, depth: f64) {
        let along = (b - a).normalize();
        let len = (b - a).length();
        let mut s = self.rng.random_range(0.0..4.0);
        while s < len - 6.0 {
            let w = self.rng.random_range(10.0..22.0f64).min(len - s);
            let h = self.rng.random_range(6.0..16.0);
            let m = self.facade(0.15);
            let p0 = a + along * s;
            let p1 = a + along * (s + w) + outward * depth;
            self.cuboid(p0.min(p1).extend(0.0), p0.max(p1).extend(h), m);
            s += w + self.rng.random_range(2.0..6.0);
        }
    }
}

/// The campus's primitives and materials (materials 0 and 1 are the ground and the sidewalk).
pub(super) fn build(
    params: &WorldParams,
    c: &CampusParams,
    seed: u64,
) -> (Vec<Primitive>, Vec<Material>) {
    let mut b = Builder {
        rng: Xoshiro256PlusPlus::seed_from_u64(seed ^ 0xCA4B_0515),
        prims: Vec::new(),
        materials: vec![Material::Ground, Material::Sidewalk],
    };
    let (rw, sw, kh) = (params.road_width, params.sidewalk_width, params.kerb_height);
    let [nx, ny] = c.blocks;
    let lo = c.crossing(rw, 0, 0) - DVec2::splat(0.5 * rw);
    let hi = c.crossing(rw, nx, ny) + DVec2::splat(0.5 * rw);

    let kinds = block_kinds(c, seed);
    let mut kerbs: Vec<(DVec2, DVec2)> = Vec::new();
    for bj in 0..ny {
        for bi in 0..nx {
            let min = c.crossing(rw, bi, bj) + DVec2::splat(0.5 * rw);
            let max = c.crossing(rw, bi + 1, bj + 1) - DVec2::splat(0.5 * rw);
            b.cuboid(min.extend(0.0), max.extend(kh), 1);
            kerbs.push((min, max));
            let (imin, imax) = (min + DVec2::splat(sw), max - DVec2::splat(sw));
            match kinds[bj * nx + bi] {
                BlockKind::Courtyard => courtyard(&mut b, imin, imax),
                BlockKind::Row => row(&mut b, imin, imax),
                BlockKind::Arcade => arcade(&mut b, imin, imax, kh),
                BlockKind::Tower => tower(&mut b, imin, imax),
            }
        }
    }

    // The perimeter: an outer sidewalk, and buildings facing the perimeter streets.
    let (olo, ohi) = (lo - DVec2::splat(sw), hi + DVec2::splat(sw));
    for (min, max) in [
        (DVec2::new(olo.x, olo.y), DVec2::new(ohi.x, lo.y)),
        (DVec2::new(olo.x, hi.y), DVec2::new(ohi.x, ohi.y)),
        (DVec2::new(olo.x, lo.y), DVec2::new(lo.x, hi.y)),
        (DVec2::new(hi.x, lo.y), DVec2::new(ohi.x, hi.y)),
    ] {
        b.cuboid(min.extend(0.0), max.extend(kh), 1);
    }
    let f = 0.5;
    let (flo, fhi) = (olo - DVec2::splat(f), ohi + DVec2::splat(f));
    b.frontage(
        DVec2::new(flo.x, flo.y),
        DVec2::new(fhi.x, flo.y),
        -DVec2::Y,
        12.0,
    );
    b.frontage(
        DVec2::new(flo.x, fhi.y),
        DVec2::new(fhi.x, fhi.y),
        DVec2::Y,
        12.0,
    );
    b.frontage(
        DVec2::new(flo.x, flo.y + 2.0),
        DVec2::new(flo.x, fhi.y - 2.0),
        -DVec2::X,
        12.0,
    );
    b.frontage(
        DVec2::new(fhi.x, flo.y + 2.0),
        DVec2::new(fhi.x, fhi.y - 2.0),
        DVec2::X,
        12.0,
    );

    // Street furniture on the blocks' sidewalks, 0.5 m in from the kerb: a pole every ~20 m and a tree
    // every ~30 m along the long sides, and cars parked against some kerbs.
    let pole = b.material(Material::Pole);
    let trunk = b.material(Material::Trunk);
    let canopy = b.material(Material::Canopy);
    for (min, max) in kerbs {
        for y in [min.y + 0.5, max.y - 0.5] {
            let mut x = min.x + b.rng.random_range(2.0..8.0);
            while x < max.x - 2.0 {
                b.prims.push(Primitive {
                    shape: Shape::Cylinder {
                        base: DVec3::new(x, y, kh),
                        radius: 0.08,
                        height: 4.0,
                    },
                    material: pole,
                });
                x += b.rng.random_range(16.0..24.0);
            }
            let x = b.rng.random_range(min.x + 6.0..max.x - 6.0);
            let inward = if y < 0.5 * (min.y + max.y) { 0.9 } else { -0.9 };
            let (h, r) = (b.rng.random_range(2.2..3.0), b.rng.random_range(1.2..1.7));
            let base = DVec3::new(x, y + inward, kh);
            b.prims.push(Primitive {
                shape: Shape::Cylinder {
                    base,
                    radius: 0.15,
                    height: h,
                },
                material: trunk,
            });
            b.prims.push(Primitive {
                shape: Shape::Sphere {
                    center: base + DVec3::new(0.0, 0.0, h + r * 0.7),
                    radius: r,
                },
                material: canopy,
            });
        }
        // A car against the block's west kerb (on the road, clear of the walking line on the centre).
        if b.rng.random_bool(0.5) {
            let paint = PAINTS[b.rng.random_range(0..PAINTS.len())];
            let m = b.material(Material::Car { paint });
            let y = b.rng.random_range(min.y + 1.0..max.y - 5.5);
            b.cuboid(
                DVec3::new(min.x - 2.1, y, 0.0),
                DVec3::new(min.x - 0.3, y + 4.5, 1.5),
                m,
            );
        }
    }
    (b.prims, b.materials)
}

/// Each block's kind, row-major from the south-west: the four kinds in turn, in a seeded order, so every
/// kind appears `blocks / 4` times or more.
pub(super) fn block_kinds(c: &CampusParams, seed: u64) -> Vec<BlockKind> {
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(seed ^ 0x000B_10C4);
    let mut order = [
        BlockKind::Courtyard,
        BlockKind::Row,
        BlockKind::Arcade,
        BlockKind::Tower,
    ];
    for i in (1..order.len()).rev() {
        order.swap(i, rng.random_range(0..=i));
    }
    let n = c.blocks[0] * c.blocks[1];
    // Shifting by the row keeps equal kinds off the same column.
    (0..n)
        .map(|k| order[(k + k / c.blocks[0]) % order.len()])
        .collect()
}

/// Four wings round a yard; a 4 m passage under the south wing (a bridge from 4.5 m up) opens the yard to
/// the street.
fn courtyard(b: &mut Builder, min: DVec2, max: DVec2) {
    let m = b.facade(0.25);
    let h = b.rng.random_range(10.0..18.0);
    let d = 8.0f64.min(0.3 * (max.y - min.y));
    let mx = 0.5 * (min.x + max.x);
    // South wing, split by the passage.
    b.cuboid(min.extend(0.0), DVec3::new(mx - 2.0, min.y + d, h), m);
    b.cuboid(
        DVec3::new(mx + 2.0, min.y, 0.0),
        DVec3::new(max.x, min.y + d, h),
        m,
    );
    b.cuboid(
        DVec3::new(mx - 2.0, min.y, 4.5),
        DVec3::new(mx + 2.0, min.y + d, h),
        m,
    );
    // North, west and east wings.
    b.cuboid(DVec3::new(min.x, max.y - d, 0.0), max.extend(h), m);
    b.cuboid(
        DVec3::new(min.x, min.y + d, 0.0),
        DVec3::new(min.x + d, max.y - d, h),
        m,
    );
    b.cuboid(
        DVec3::new(max.x - d, min.y + d, 0.0),
        DVec3::new(max.x, max.y - d, h),
        m,
    );
}

/// Two to four houses side by side with gaps, of different heights; some white.
fn row(b: &mut Builder, min: DVec2, max: DVec2) {
    let n = b.rng.random_range(2..=4usize);
    let w = (max.x - min.x) / n as f64;
    for i in 0..n {
        let m = b.facade(0.3);
        let h = b.rng.random_range(6.0..20.0);
        let gap = b.rng.random_range(0.8..2.0);
        let x0 = min.x + i as f64 * w + if i > 0 { 0.5 * gap } else { 0.0 };
        let x1 = min.x + (i + 1) as f64 * w - if i + 1 < n { 0.5 * gap } else { 0.0 };
        b.cuboid(DVec3::new(x0, min.y, 0.0), DVec3::new(x1, max.y, h), m);
    }
}

/// An arcade on the south side: the ground floor recessed 3 m, the storeys above on columns every 4 m.
fn arcade(b: &mut Builder, min: DVec2, max: DVec2, kerb: f64) {
    let m = b.facade(0.0);
    let h = b.rng.random_range(9.0..15.0);
    let depth = 3.0;
    b.cuboid(DVec3::new(min.x, min.y + depth, 0.0), max.extend(h), m);
    b.cuboid(
        DVec3::new(min.x, min.y, 4.0),
        DVec3::new(max.x, min.y + depth, h),
        m,
    );
    let column = b.material(Material::Pole);
    let mut x = min.x + 0.5;
    while x < max.x {
        b.prims.push(Primitive {
            shape: Shape::Cylinder {
                base: DVec3::new(x, min.y + 0.4, kerb),
                radius: 0.25,
                height: 4.0 - kerb,
            },
            material: column,
        });
        x += 4.0;
    }
}

/// A glass tower on a low textured podium.
fn tower(b: &mut Builder, min: DVec2, max: DVec2) {
    let podium = b.facade(0.0);
    let glass = b.glass();
    let h = b.rng.random_range(25.0..40.0);
    b.cuboid(min.extend(0.0), max.extend(4.0), podium);
    let inset = DVec2::new(0.25 * (max.x - min.x), 0.2 * (max.y - min.y));
    b.cuboid(
        (min + inset).extend(4.0),
        (max - inset).extend(4.0 + h),
        glass,
    );
}
