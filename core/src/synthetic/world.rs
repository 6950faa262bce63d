//! The built-in town: a ring road around a central block, deterministic from a seed.
//!
//! It is built to exercise exactly what SiLVR claims: near-textureless asphalt and one plain white facade
//! (vision struggles, lidar helps), richly textured facades with windows (vision works), a tower far beyond
//! lidar range (camera-only geometry), and everything behind the rig (lidar-only: there is no rear camera).
//! Shading is view-independent (Lambert + ambient, no shadows by default) so a radiance field can fit it.

use glam::{DVec2, DVec3, Vec3};
use rand::{Rng, SeedableRng};
use serde::{Deserialize, Serialize};

use super::raycast::{Hit, Primitive, Scene, Shape};

mod campus;

/// Semantic classes written to `gt/semantic/*.png` (the pixel value is the discriminant).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[repr(u8)]
pub enum Label {
    Sky = 0,
    Road = 1,
    Sidewalk = 2,
    Facade = 3,
    WhiteWall = 4,
    Roof = 5,
    Pole = 6,
    Tree = 7,
    Car = 8,
    Tower = 9,
}

impl Label {
    pub const ALL: [Label; 10] = [
        Label::Sky,
        Label::Road,
        Label::Sidewalk,
        Label::Facade,
        Label::WhiteWall,
        Label::Roof,
        Label::Pole,
        Label::Tree,
        Label::Car,
        Label::Tower,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Label::Sky => "sky",
            Label::Road => "road",
            Label::Sidewalk => "sidewalk",
            Label::Facade => "facade",
            Label::WhiteWall => "white_wall",
            Label::Roof => "roof",
            Label::Pole => "pole",
            Label::Tree => "tree",
            Label::Car => "car",
            Label::Tower => "tower",
        }
    }
}

/// How a surface is coloured.
#[derive(Clone, Copy, Debug, Serialize, Deserialize)]
pub enum Material {
    /// The ground plane: asphalt with lane markings (everything at z = 0 is road).
    Ground,
    /// Raised sidewalk slabs: concrete with a faint 1 m tile grid; kerb faces plain.
    Sidewalk,
    /// A building: textured facade with a window grid (or, if `white`, a uniform white wall; if `glass`, a
    /// uniform dark curtain wall) and a flat roof.
    Building {
        base: [f32; 3],
        brick: bool,
        white: bool,
        #[serde(default)]
        glass: bool,
    },
    /// Pitched roof planes.
    Roof {
        base: [f32; 3],
    },
    Pole,
    Trunk,
    Canopy,
    Car {
        paint: [f32; 3],
    },
    Tower,
}

/// World layout parameters (metres).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct WorldParams {
    /// Half extents of the central block (incl. its sidewalk).
    pub block_half: [f64; 2],
    pub road_width: f64,
    pub sidewalk_width: f64,
    pub kerb_height: f64,
    /// Distance of the far tower from the origin.
    pub tower_distance: f64,
    pub n_trees: usize,
    pub n_poles: usize,
    pub n_cars: usize,
    /// Which world: the town around one block (the default), or the campus of many blocks. Not written
    /// for the town, so the town's manifests are what they were before the campus existed.
    #[serde(default, skip_serializing_if = "Layout::is_town")]
    pub layout: Layout,
}

/// The world's plan.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub enum Layout {
    /// The ring road around one central block (`ci`, `micro`, `default`).
    #[default]
    Town,
    /// A grid of blocks, each a courtyard building, a row of houses, an arcade or a glass tower, ringed
    /// by buildings outside the perimeter streets (`campus`).
    Campus(CampusParams),
}

/// The campus's street grid: `blocks[0] x blocks[1]` blocks of `block_size` (sidewalk included)
/// between streets of the world's `road_width`, centred on the origin.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CampusParams {
    pub blocks: [usize; 2],
    pub block_size: [f64; 2],
}

impl Layout {
    pub fn is_town(&self) -> bool {
        matches!(self, Layout::Town)
    }
}

impl Default for CampusParams {
    fn default() -> Self {
        Self {
            blocks: [4, 3],
            block_size: [40.0, 30.0],
        }
    }
}

impl CampusParams {
    /// Distance between neighbouring streets' centre lines, per axis.
    pub fn pitch(&self, road_width: f64) -> DVec2 {
        DVec2::new(
            self.block_size[0] + road_width,
            self.block_size[1] + road_width,
        )
    }

    /// Centre of the crossing of vertical street `i` (0..=blocks[0], west to east) and horizontal street
    /// `j` (0..=blocks[1], south to north).
    pub fn crossing(&self, road_width: f64, i: usize, j: usize) -> DVec2 {
        let p = self.pitch(road_width);
        DVec2::new(
            (i as f64 - 0.5 * self.blocks[0] as f64) * p.x,
            (j as f64 - 0.5 * self.blocks[1] as f64) * p.y,
        )
    }
}

impl Default for WorldParams {
    fn default() -> Self {
        Self {
            block_half: [20.0, 12.0],
            road_width: 7.0,
            sidewalk_width: 2.0,
            kerb_height: 0.12,
            tower_distance: 100.0,
            n_trees: 6,
            n_poles: 12,
            n_cars: 4,
            layout: Layout::Town,
        }
    }
}

/// A generated world: geometry, materials and the texture seed.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct World {
    pub params: WorldParams,
    pub seed: u64,
    pub scene: Scene,
    pub materials: Vec<Material>,
}

/// Sun direction (towards the sun): 45° elevation.
pub fn sun_direction() -> DVec3 {
    DVec3::new(-0.5, -0.5, std::f64::consts::FRAC_1_SQRT_2).normalize()
}

const AMBIENT: f32 = 0.35;

/// Facade base colours the town and the campus draw from.
const PALETTE: [[f32; 3]; 5] = [
    [0.55, 0.27, 0.18],
    [0.62, 0.45, 0.30],
    [0.70, 0.62, 0.48],
    [0.45, 0.42, 0.40],
    [0.58, 0.50, 0.62],
];

/// Car paints.
const PAINTS: [[f32; 3]; 5] = [
    [0.70, 0.08, 0.06],
    [0.08, 0.20, 0.65],
    [0.85, 0.70, 0.10],
    [0.10, 0.45, 0.15],
    [0.85, 0.85, 0.85],
];

impl World {
    /// Builds the town for `seed`. The structure is fixed (so presets and tests can rely on where the road,
    /// the white wall and the tower are); sizes, heights, colours and street furniture vary with the seed.
    pub fn generate(params: WorldParams, seed: u64) -> World {
        if let Layout::Campus(c) = &params.layout {
            let (prims, materials) = campus::build(&params, c, seed);
            return World {
                params,
                seed,
                scene: Scene::new(prims, 0),
                materials,
            };
        }
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(seed ^ 0x5117_7e12);
        let mut prims: Vec<Primitive> = Vec::new();
        let mut materials = vec![Material::Ground, Material::Sidewalk];
        let (bx, by) = (params.block_half[0], params.block_half[1]);
        let (rw, sw, kh) = (params.road_width, params.sidewalk_width, params.kerb_height);
        let cuboid = |min: DVec3, max: DVec3| Shape::Cuboid { min, max };
        // Central block slab and the outer sidewalk ring (4 slabs).
        prims.push(Primitive {
            shape: cuboid(DVec3::new(-bx, -by, 0.0), DVec3::new(bx, by, kh)),
            material: 1,
        });
        let (ox, oy) = (bx + rw, by + rw);
        for (min, max) in [
            (
                DVec3::new(-ox - sw, -oy - sw, 0.0),
                DVec3::new(ox + sw, -oy, kh),
            ),
            (
                DVec3::new(-ox - sw, oy, 0.0),
                DVec3::new(ox + sw, oy + sw, kh),
            ),
            (DVec3::new(-ox - sw, -oy, 0.0), DVec3::new(-ox, oy, kh)),
            (DVec3::new(ox, -oy, 0.0), DVec3::new(ox + sw, oy, kh)),
        ] {
            prims.push(Primitive {
                shape: cuboid(min, max),
                material: 1,
            });
        }

        let add_building = |rng: &mut rand_xoshiro::Xoshiro256PlusPlus,
                            prims: &mut Vec<Primitive>,
                            materials: &mut Vec<Material>,
                            min: DVec2,
                            max: DVec2,
                            height: f64,
                            white: bool,
                            pitched: bool| {
            let base = PALETTE[rng.random_range(0..PALETTE.len())];
            let brick = rng.random_bool(0.5);
            materials.push(Material::Building {
                base,
                brick,
                white,
                glass: false,
            });
            let m = (materials.len() - 1) as u16;
            prims.push(Primitive {
                shape: cuboid(min.extend(0.0), max.extend(height)),
                material: m,
            });
            if pitched {
                materials.push(Material::Roof {
                    base: [0.35, 0.22, 0.18],
                });
                let r = (materials.len() - 1) as u16;
                let ridge = 0.25 * (max.y - min.y);
                let ym = 0.5 * (min.y + max.y);
                let (a, b) = (min.x, max.x);
                let z = height;
                let p = |x: f64, y: f64, z: f64| DVec3::new(x, y, z);
                let tris = [
                    (p(a, min.y, z), p(b, min.y, z), p(b, ym, z + ridge)),
                    (p(a, min.y, z), p(b, ym, z + ridge), p(a, ym, z + ridge)),
                    (p(a, max.y, z), p(a, ym, z + ridge), p(b, ym, z + ridge)),
                    (p(a, max.y, z), p(b, ym, z + ridge), p(b, max.y, z)),
                    (p(a, min.y, z), p(a, ym, z + ridge), p(a, max.y, z)),
                    (p(b, min.y, z), p(b, max.y, z), p(b, ym, z + ridge)),
                ];
                for (a, b, c) in tris {
                    prims.push(Primitive {
                        shape: Shape::Triangle { a, b, c },
                        material: r,
                    });
                }
            }
        };

        // Central block: three buildings inset behind the block's own sidewalk.
        let inner = DVec2::new(bx - sw, by - sw);
        let splits = [
            -inner.x,
            -inner.x / 3.0 + rng.random_range(-2.0..2.0),
            inner.x / 3.0 + rng.random_range(-2.0..2.0),
            inner.x,
        ];
        for i in 0..3 {
            let h = rng.random_range(8.0..16.0);
            add_building(
                &mut rng,
                &mut prims,
                &mut materials,
                DVec2::new(splits[i] + 0.5, -inner.y),
                DVec2::new(splits[i + 1] - 0.5, inner.y),
                h,
                false,
                i == 1,
            );
        }

        // Outer ring. South side (y < 0), where every trajectory starts walking east: the white wall faces
        // the street at x in [2, 16]; textured neighbours on either side.
        let face = oy + sw + 0.5;
        let south: [(f64, f64, bool); 4] = [
            (-30.0, -17.0, false),
            (-16.0, 1.0, false),
            (2.0, 16.0, true),
            (17.0, 26.0, false),
        ];
        for (x0, x1, white) in south {
            let depth = rng.random_range(8.0..13.0);
            let h = rng.random_range(7.0..17.0);
            add_building(
                &mut rng,
                &mut prims,
                &mut materials,
                DVec2::new(x0, -face - depth),
                DVec2::new(x1, -face),
                h,
                white,
                false,
            );
        }
        // North side.
        let mut x = -30.0;
        while x < 26.0 {
            let w = rng.random_range(9.0..18.0f64).min(30.0 - x);
            let depth = rng.random_range(8.0..13.0);
            let h = rng.random_range(6.0..18.0);
            add_building(
                &mut rng,
                &mut prims,
                &mut materials,
                DVec2::new(x, face),
                DVec2::new(x + w, face + depth),
                h,
                false,
                false,
            );
            x += w + rng.random_range(1.0..3.0);
        }
        // West and east sides; the east side leaves the south street's line of sight open to the tower.
        let facex = ox + sw + 0.5;
        for (y0, y1) in [(-10.0, 2.0), (4.0, 16.0)] {
            let depth = rng.random_range(8.0..12.0);
            let h = rng.random_range(6.0..16.0);
            add_building(
                &mut rng,
                &mut prims,
                &mut materials,
                DVec2::new(-facex - depth, y0),
                DVec2::new(-facex, y1),
                h,
                false,
                false,
            );
        }
        for (y0, y1) in [(-8.0, 4.0), (6.0, 18.0)] {
            let depth = rng.random_range(8.0..12.0);
            let h = rng.random_range(6.0..16.0);
            add_building(
                &mut rng,
                &mut prims,
                &mut materials,
                DVec2::new(facex, y0),
                DVec2::new(facex + depth, y1),
                h,
                false,
                false,
            );
        }

        // The tower: far east, on the axis of the south street, beyond any lidar's range.
        materials.push(Material::Tower);
        let tm = (materials.len() - 1) as u16;
        let ty = -(by + rw * 0.5);
        let td = params.tower_distance;
        prims.push(Primitive {
            shape: cuboid(
                DVec3::new(td - 5.0, ty - 6.0, 0.0),
                DVec3::new(td + 5.0, ty + 6.0, rng.random_range(40.0..50.0)),
            ),
            material: tm,
        });

        // Street furniture on the outer sidewalks.
        materials.push(Material::Pole);
        let pole = (materials.len() - 1) as u16;
        materials.push(Material::Trunk);
        let trunk = (materials.len() - 1) as u16;
        materials.push(Material::Canopy);
        let canopy = (materials.len() - 1) as u16;
        let kerb_spot = |i: usize, n: usize, rng: &mut rand_xoshiro::Xoshiro256PlusPlus| -> DVec2 {
            // Spread along the outer kerb, 0.5 m from the road edge, alternating north/south sides.
            let x =
                -ox + 2.0 + (2.0 * ox - 4.0) * (i as f64 + rng.random_range(0.2..0.8)) / n as f64;
            let y = if i.is_multiple_of(2) {
                -oy - 0.5
            } else {
                oy + 0.5
            };
            DVec2::new(x, y)
        };
        for i in 0..params.n_poles {
            let p = kerb_spot(i, params.n_poles, &mut rng);
            prims.push(Primitive {
                shape: Shape::Cylinder {
                    base: p.extend(kh),
                    radius: 0.08,
                    height: 4.0,
                },
                material: pole,
            });
        }
        for i in 0..params.n_trees {
            let mut p = kerb_spot(i, params.n_trees, &mut rng);
            p.y += if p.y < 0.0 { -0.9 } else { 0.9 };
            let h = rng.random_range(2.2..3.0);
            let r = rng.random_range(1.2..1.7);
            prims.push(Primitive {
                shape: Shape::Cylinder {
                    base: p.extend(kh),
                    radius: 0.15,
                    height: h,
                },
                material: trunk,
            });
            prims.push(Primitive {
                shape: Shape::Sphere {
                    center: p.extend(kh + h + r * 0.7),
                    radius: r,
                },
                material: canopy,
            });
        }
        for i in 0..params.n_cars {
            materials.push(Material::Car {
                paint: PAINTS[rng.random_range(0..PAINTS.len())],
            });
            let m = (materials.len() - 1) as u16;
            // Parked against the north outer kerb and along the west/east streets, never in the walking lane
            // of the south street.
            let (min, max) = match i % 3 {
                0 => {
                    let x = rng.random_range(-ox + 3.0..ox - 8.0);
                    (
                        DVec3::new(x, oy - 2.1, 0.0),
                        DVec3::new(x + 4.5, oy - 0.3, 1.5),
                    )
                }
                1 => {
                    let y = rng.random_range(-by..by - 4.5);
                    (
                        DVec3::new(-ox + 0.3, y, 0.0),
                        DVec3::new(-ox + 2.1, y + 4.5, 1.5),
                    )
                }
                _ => {
                    let y = rng.random_range(-by..by - 4.5);
                    (
                        DVec3::new(ox - 2.1, y, 0.0),
                        DVec3::new(ox - 0.3, y + 4.5, 1.5),
                    )
                }
            };
            prims.push(Primitive {
                shape: cuboid(min, max),
                material: m,
            });
        }
        World {
            params,
            seed,
            scene: Scene::new(prims, 0),
            materials,
        }
    }

    /// Semantic class of a hit.
    pub fn label(&self, hit: &Hit) -> Label {
        match self.materials[hit.material as usize] {
            Material::Ground => Label::Road,
            Material::Sidewalk => Label::Sidewalk,
            Material::Building { white, .. } => {
                if hit.normal.z > 0.5 {
                    Label::Roof
                } else if white {
                    Label::WhiteWall
                } else {
                    Label::Facade
                }
            }
            Material::Roof { .. } => Label::Roof,
            Material::Pole => Label::Pole,
            Material::Trunk | Material::Canopy => Label::Tree,
            Material::Car { .. } => Label::Car,
            Material::Tower => Label::Tower,
        }
    }

    /// Linear albedo at a hit. Procedural textures are band-limited by construction (no detail finer than
    /// a few centimetres), and the camera supersamples, so images do not alias.
    pub fn albedo(&self, hit: &Hit) -> Vec3 {
        let p = hit.point;
        let n = hit.normal;
        let s = self.seed;
        match self.materials[hit.material as usize] {
            Material::Ground => {
                let base =
                    0.20 * (1.0 + 0.02 * (value_noise2(p.x / 2.0, p.y / 2.0, s) * 2.0 - 1.0));
                let w = self.lane_marking(p.truncate());
                Vec3::splat(((1.0 - w) * base + w * 0.8) as f32)
            }
            Material::Sidewalk => {
                if n.z < 0.5 {
                    return Vec3::splat(0.5);
                }
                let fx = (p.x - p.x.round()).abs();
                let fy = (p.y - p.y.round()).abs();
                let joint = if fx.min(fy) < 0.015 { -0.03 } else { 0.0 };
                let v = 0.45
                    * (1.0
                        + joint
                        + 0.01 * (value_noise2(p.x * 3.0, p.y * 3.0, s + 1) * 2.0 - 1.0));
                Vec3::splat(v as f32)
            }
            Material::Building {
                base,
                brick,
                white,
                glass,
            } => {
                if n.z.abs() > 0.5 {
                    let v = 0.25 * (1.0 + 0.05 * (value_noise2(p.x, p.y, s + 2) * 2.0 - 1.0));
                    return Vec3::splat(v as f32);
                }
                if white {
                    return Vec3::splat(0.8);
                }
                if glass {
                    return Vec3::from(base);
                }
                let u = if n.x.abs() > 0.5 { p.y } else { p.x };
                facade(u, p.z, Vec3::from(base), brick, s)
            }
            Material::Roof { base } => {
                let v = 1.0 + 0.08 * (value_noise2(p.x * 4.0, p.y * 4.0 + p.z, s + 3) * 2.0 - 1.0);
                Vec3::from(base) * v as f32
            }
            Material::Pole => Vec3::splat(0.4),
            Material::Trunk => {
                Vec3::new(0.30, 0.20, 0.10)
                    * (0.8 + 0.4 * value_noise2(p.z * 8.0, (p.x + p.y) * 8.0, s + 4) as f32)
            }
            Material::Canopy => {
                let v = value_noise3(p * 6.0, s + 5) * 0.6 + value_noise3(p * 1.5, s + 6) * 0.4;
                Vec3::new(0.10, 0.28, 0.06) * (0.6 + 0.8 * v as f32)
            }
            Material::Car { paint } => {
                if p.z > 1.0 && p.z < 1.4 {
                    Vec3::splat(0.06)
                } else if p.z < 0.45 {
                    Vec3::splat(0.05)
                } else {
                    Vec3::from(paint)
                }
            }
            Material::Tower => {
                let u = if n.x.abs() > 0.5 { p.y } else { p.x };
                let win = (u.rem_euclid(2.5) > 0.6) && (p.z.rem_euclid(3.5) > 1.0) && n.z < 0.5;
                if win {
                    Vec3::new(0.12, 0.13, 0.15)
                } else {
                    Vec3::splat(0.6)
                }
            }
        }
    }

    /// Displayed colour of a hit: Lambert with a fixed sun plus ambient, then display gamma.
    pub fn shade(&self, hit: &Hit) -> Vec3 {
        let a = self.albedo(hit);
        let lambert = hit.normal.dot(sun_direction()).max(0.0) as f32;
        to_display(a * (AMBIENT + (1.0 - AMBIENT) * lambert))
    }

    /// Lane markings: dashed centre lines (3 m on, 6 m off) and solid edge lines, as a coverage weight in
    /// [0, 1] with 2 cm of analytic anti-aliasing. Town: the ring road; campus: every street, none on the
    /// crossings.
    fn lane_marking(&self, q: DVec2) -> f64 {
        let rw = self.params.road_width;
        let (d, along) = match &self.params.layout {
            Layout::Town => {
                let (bx, by) = (self.params.block_half[0], self.params.block_half[1]);
                // Signed distance outwards from the block boundary, and an along-road coordinate.
                let dx = q.x.abs() - bx;
                let dy = q.y.abs() - by;
                if dy >= dx {
                    (dy, q.x)
                } else {
                    (dx, q.y)
                }
            }
            Layout::Campus(c) => {
                let p = c.pitch(rw);
                let lo = c.crossing(rw, 0, 0);
                let hi = c.crossing(rw, c.blocks[0], c.blocks[1]);
                let off = |v: f64, o: f64, pitch: f64, n: usize| {
                    let i = ((v - o) / pitch).round().clamp(0.0, n as f64);
                    v - (o + i * pitch)
                };
                let ox = off(q.x, lo.x, p.x, c.blocks[0]);
                let oy = off(q.y, lo.y, p.y, c.blocks[1]);
                let inside = |v: f64, a: f64, b: f64| v > a - 0.5 * rw && v < b + 0.5 * rw;
                let on_x = ox.abs() < 0.5 * rw && inside(q.y, lo.y, hi.y);
                let on_y = oy.abs() < 0.5 * rw && inside(q.x, lo.x, hi.x);
                match (on_x, on_y) {
                    (true, false) => (ox + 0.5 * rw, q.y),
                    (false, true) => (oy + 0.5 * rw, q.x),
                    _ => return 0.0,
                }
            }
        };
        if d < 0.0 || d > rw {
            return 0.0;
        }
        let band = |center: f64, half: f64| -> f64 {
            (((half - (d - center).abs()) / 0.02) + 0.5).clamp(0.0, 1.0)
        };
        let centre = band(rw * 0.5, 0.06)
            * if along.rem_euclid(9.0) < 3.0 {
                1.0
            } else {
                0.0
            };
        let edges = band(0.3, 0.05).max(band(rw - 0.3, 0.05));
        centre.max(edges)
    }

    /// Half the side of the ground square the mesh export draws (everything any sensor can see).
    pub fn ground_half_extent(&self) -> f64 {
        match &self.params.layout {
            Layout::Town => self.params.tower_distance + 50.0,
            Layout::Campus(c) => {
                let hi = c.crossing(self.params.road_width, c.blocks[0], c.blocks[1]);
                hi.x.max(hi.y) + 80.0
            }
        }
    }
}

/// Sky colour for a world-frame viewing direction: horizon (0.85, 0.90, 1.00) to zenith (0.35, 0.55, 0.90).
pub fn sky(dir: DVec3) -> Vec3 {
    let e = dir.z.clamp(0.0, 1.0) as f32;
    let t = e.sqrt();
    Vec3::new(0.85, 0.90, 1.00).lerp(Vec3::new(0.35, 0.55, 0.90), t)
}

fn to_display(linear: Vec3) -> Vec3 {
    linear.clamp(Vec3::ZERO, Vec3::ONE).powf(1.0 / 2.2)
}

/// Facade: plaster or brick base, 3 m floors with 1.2 x 1.6 m windows on a 3 m pitch, sills at 1 m,
/// dark glass and light frames; a door on the ground floor.
fn facade(u: f64, z: f64, base: Vec3, brick: bool, seed: u64) -> Vec3 {
    let grain = 0.85 + 0.3 * value_noise2(u * 4.0, z * 4.0, seed + 7) as f32;
    let mut c = base * grain;
    if brick {
        let course = (z / 0.075).floor();
        let offset = if course as i64 % 2 == 0 { 0.0 } else { 0.12 };
        let bu = (u + offset).rem_euclid(0.24);
        let bz = z.rem_euclid(0.075);
        if bu < 0.012 || bz < 0.01 {
            c = Vec3::splat(0.7);
        }
    }
    let cell_u = u.rem_euclid(3.0);
    let floor = (z / 3.0).floor();
    let cell_z = z.rem_euclid(3.0);
    let (w0, w1) = (0.9, 2.1);
    let (h0, h1) = (1.0, 2.6);
    let in_win = cell_u > w0 && cell_u < w1 && cell_z > h0 && cell_z < h1;
    if floor == 0.0 && (u / 3.0).floor().rem_euclid(4.0) == 1.0 {
        // Door.
        if cell_u > 1.0 && cell_u < 2.0 && cell_z < 2.2 {
            return Vec3::new(0.25, 0.15, 0.08);
        }
    }
    if in_win {
        let frame = (cell_u - w0)
            .min(w1 - cell_u)
            .min(cell_z - h0)
            .min(h1 - cell_z)
            < 0.07
            || (cell_u - 1.5).abs() < 0.03;
        if frame {
            return Vec3::splat(0.6);
        }
        return Vec3::new(0.07, 0.08, 0.10);
    }
    if cell_u > w0 - 0.1 && cell_u < w1 + 0.1 && cell_z > h0 - 0.12 && cell_z < h0 {
        return Vec3::splat(0.55);
    }
    c
}

fn hash(ix: i64, iy: i64, iz: i64, seed: u64) -> f64 {
    let mut h = seed
        .wrapping_mul(0x9E37_79B9_7F4A_7C15)
        .wrapping_add((ix as u64).wrapping_mul(0xBF58_476D_1CE4_E5B9))
        .wrapping_add((iy as u64).wrapping_mul(0x94D0_49BB_1331_11EB))
        .wrapping_add((iz as u64).wrapping_mul(0xD6E8_FEB8_6659_FD93));
    h ^= h >> 31;
    h = h.wrapping_mul(0x7FB5_D329_728E_A185);
    h ^= h >> 27;
    h = h.wrapping_mul(0x81DA_DEF4_BC2D_D44D);
    h ^= h >> 33;
    (h >> 11) as f64 / (1u64 << 53) as f64
}

fn smooth(t: f64) -> f64 {
    t * t * (3.0 - 2.0 * t)
}

/// Smooth value noise in [0, 1] with unit feature size.
pub fn value_noise2(x: f64, y: f64, seed: u64) -> f64 {
    let (ix, iy) = (x.floor(), y.floor());
    let (fx, fy) = (smooth(x - ix), smooth(y - iy));
    let (ix, iy) = (ix as i64, iy as i64);
    let a = hash(ix, iy, 0, seed);
    let b = hash(ix + 1, iy, 0, seed);
    let c = hash(ix, iy + 1, 0, seed);
    let d = hash(ix + 1, iy + 1, 0, seed);
    let ab = a + (b - a) * fx;
    let cd = c + (d - c) * fx;
    ab + (cd - ab) * fy
}

fn value_noise3(p: DVec3, seed: u64) -> f64 {
    let i = p.floor();
    let f = p - i;
    let (fx, fy, fz) = (smooth(f.x), smooth(f.y), smooth(f.z));
    let (ix, iy, iz) = (i.x as i64, i.y as i64, i.z as i64);
    let mut acc = 0.0;
    for dz in 0..2 {
        for dy in 0..2 {
            for dx in 0..2 {
                let w = (if dx == 1 { fx } else { 1.0 - fx })
                    * (if dy == 1 { fy } else { 1.0 - fy })
                    * (if dz == 1 { fz } else { 1.0 - fz });
                acc += w * hash(ix + dx, iy + dy, iz + dz, seed);
            }
        }
    }
    acc
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn same_seed_same_world_different_seed_different_layout() {
        let a = World::generate(WorldParams::default(), 1);
        let b = World::generate(WorldParams::default(), 1);
        let c = World::generate(WorldParams::default(), 2);
        let ja = serde_json::to_string(&a.scene.primitives).unwrap();
        assert_eq!(ja, serde_json::to_string(&b.scene.primitives).unwrap());
        assert_ne!(ja, serde_json::to_string(&c.scene.primitives).unwrap());
    }

    #[test]
    fn the_hard_and_the_easy_surfaces_are_where_the_presets_expect() {
        let w = World::generate(WorldParams::default(), 3);
        let street_y = -(w.params.block_half[1] + w.params.road_width * 0.5);
        let eye = DVec3::new(0.0, street_y, 1.6);
        // Looking down at the road: asphalt, nearly uniform.
        let h = w
            .scene
            .cast(eye, DVec3::new(0.2, 0.0, -1.0).normalize(), 100.0)
            .unwrap();
        assert_eq!(w.label(&h), Label::Road);
        // South (right when walking east) at x = 9: the white wall.
        let h = w
            .scene
            .cast(DVec3::new(9.0, street_y, 1.6), -DVec3::Y, 100.0)
            .unwrap();
        assert_eq!(w.label(&h), Label::WhiteWall);
        assert_eq!(w.albedo(&h), Vec3::splat(0.8));
        // Straight down the street to the east: the tower, ~100 m away.
        let h = w
            .scene
            .cast(DVec3::new(-5.0, street_y, 10.0), DVec3::X, 1000.0)
            .unwrap();
        assert_eq!(w.label(&h), Label::Tower);
        assert!(h.t > 80.0);
        // Up: sky.
        assert!(w.scene.cast(eye, DVec3::Z, 1000.0).is_none());
        // Asphalt contrast is tiny away from markings; facades vary a lot.
        let road: Vec<f32> = (0..200)
            .map(|i| {
                let p = DVec3::new(i as f64 * 0.37, street_y + 1.2, 0.0);
                w.albedo(&Hit {
                    t: 1.0,
                    point: p,
                    normal: DVec3::Z,
                    primitive: super::super::raycast::GROUND,
                    material: 0,
                })
                .x
            })
            .collect();
        let spread = road.iter().cloned().fold(f32::MIN, f32::max)
            - road.iter().cloned().fold(f32::MAX, f32::min);
        assert!(spread < 0.02, "asphalt spread {spread}");
    }
}

#[cfg(test)]
mod campus_tests {
    use super::*;

    fn campus() -> World {
        let params = WorldParams {
            road_width: 8.0,
            layout: Layout::Campus(CampusParams::default()),
            ..WorldParams::default()
        };
        World::generate(params, 1)
    }

    #[test]
    fn every_block_kind_is_built_and_the_streets_are_clear() {
        let w = campus();
        let Layout::Campus(c) = w.params.layout.clone() else {
            unreachable!()
        };
        let kinds = campus::block_kinds(&c, 1);
        for k in [
            campus::BlockKind::Courtyard,
            campus::BlockKind::Row,
            campus::BlockKind::Arcade,
            campus::BlockKind::Tower,
        ] {
            assert!(kinds.iter().filter(|&&x| x == k).count() >= 3, "{k:?}");
        }
        // Along every street's centre line at eye height, nothing within a metre: the walk is free.
        let rw = w.params.road_width;
        let [nx, ny] = c.blocks;
        for i in 0..=nx {
            for j in 0..=ny {
                let o = c.crossing(rw, i, j).extend(1.6);
                for d in [DVec3::X, -DVec3::X, DVec3::Y, -DVec3::Y] {
                    if let Some(h) = w.scene.cast(o, d, 100.0) {
                        assert!(h.t > 3.9, "crossing ({i},{j}) blocked at {} m", h.t);
                    }
                }
            }
        }
        // Looking north across each street at mid-block, most blocks show a textured facade.
        let mut labels = std::collections::BTreeMap::new();
        for j in 0..ny {
            for i in 0..nx {
                let o = (c.crossing(rw, i, j) + DVec2::new(0.5 * c.pitch(rw).x, 0.0)).extend(6.0);
                if let Some(h) = w.scene.cast(o, DVec3::Y, 100.0) {
                    *labels.entry(w.label(&h).name()).or_insert(0) += 1;
                }
            }
        }
        assert!(labels.get("facade").is_some_and(|&n| n >= 4), "{labels:?}");
    }

    #[test]
    fn a_courtyard_opens_to_the_street_through_its_passage_and_glass_is_uniform() {
        let w = campus();
        let Layout::Campus(c) = w.params.layout.clone() else {
            unreachable!()
        };
        let rw = w.params.road_width;
        let kinds = campus::block_kinds(&c, 1);
        let mut found = (false, false);
        for (b, kind) in kinds.iter().enumerate() {
            let (bi, bj) = (b % c.blocks[0], b / c.blocks[0]);
            let south = c.crossing(rw, bi, bj);
            let mx = south.x + 0.5 * c.pitch(rw).x;
            // From the middle of the block's south street, looking north at 2 m height.
            let o = DVec3::new(mx, south.y, 2.0);
            let h = w
                .scene
                .cast(o, DVec3::Y, 200.0)
                .expect("a block faces the street");
            match kind {
                campus::BlockKind::Courtyard => {
                    // Through the passage and across the yard to the north wing: past the south wing.
                    let wing = 0.5 * rw + w.params.sidewalk_width + 8.0;
                    assert!(h.t > wing + 5.0, "passage shut: hit at {} m", h.t);
                    found.0 = true;
                }
                campus::BlockKind::Tower => {
                    // Above the podium: the curtain wall, one colour wherever it is hit.
                    let o = DVec3::new(mx, south.y, 12.0);
                    let a = w.scene.cast(o, DVec3::Y, 200.0).unwrap();
                    let b = w
                        .scene
                        .cast(o + DVec3::new(3.0, 0.0, 5.0), DVec3::Y, 200.0)
                        .unwrap();
                    assert_eq!(w.label(&a), Label::Facade);
                    assert_eq!(w.albedo(&a), w.albedo(&b));
                    found.1 = true;
                }
                _ => {}
            }
        }
        assert_eq!(found, (true, true));
    }
}
