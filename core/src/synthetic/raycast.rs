//! An analytic ray caster: boxes, an infinite ground plane, vertical cylinders, spheres and triangles in a
//! bounding-volume hierarchy. The same code renders camera pixels, lidar returns and the ground-truth
//! depth and normals, so the sensors and the truth can never disagree about where a surface is.
//! Everything is f64: ground truth must be exact to well below a millimetre.

use glam::DVec3;
use serde::{Deserialize, Serialize};

/// One surface of the world. `material` indexes the world's material table.
#[derive(Clone, Copy, Debug, Serialize, Deserialize)]
pub enum Shape {
    /// Axis-aligned box.
    Cuboid {
        min: DVec3,
        max: DVec3,
    },
    /// Vertical cylinder with flat caps.
    Cylinder {
        base: DVec3,
        radius: f64,
        height: f64,
    },
    Sphere {
        center: DVec3,
        radius: f64,
    },
    /// Double-sided triangle; the stored normal follows the (a, b, c) winding.
    Triangle {
        a: DVec3,
        b: DVec3,
        c: DVec3,
    },
}

#[derive(Clone, Copy, Debug, Serialize, Deserialize)]
pub struct Primitive {
    pub shape: Shape,
    pub material: u16,
}

/// The nearest intersection along a ray.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    /// Distance along the (unit) ray direction.
    pub t: f64,
    pub point: DVec3,
    /// Unit surface normal facing the ray origin.
    pub normal: DVec3,
    /// Index into [`Scene::primitives`], or [`GROUND`] for the ground plane.
    pub primitive: u32,
    pub material: u16,
}

/// Marks a hit on the infinite ground plane z = 0.
pub const GROUND: u32 = u32::MAX;

/// Axis-aligned bounding box.
#[derive(Clone, Copy, Debug, Serialize, Deserialize)]
pub struct Aabb {
    pub min: DVec3,
    pub max: DVec3,
}

impl Aabb {
    pub const EMPTY: Aabb = Aabb {
        min: DVec3::splat(f64::INFINITY),
        max: DVec3::splat(f64::NEG_INFINITY),
    };

    pub fn union(self, o: Aabb) -> Aabb {
        Aabb {
            min: self.min.min(o.min),
            max: self.max.max(o.max),
        }
    }

    pub fn center(&self) -> DVec3 {
        (self.min + self.max) * 0.5
    }

    /// Slab test; returns the entry distance when the ray meets the box before `t_max`.
    #[inline]
    fn hit(&self, origin: DVec3, inv_dir: DVec3, t_max: f64) -> Option<f64> {
        let t0 = (self.min - origin) * inv_dir;
        let t1 = (self.max - origin) * inv_dir;
        let tmin = t0.min(t1).max_element().max(0.0);
        let tmax = t0.max(t1).min_element().min(t_max);
        (tmin <= tmax).then_some(tmin)
    }
}

impl Shape {
    pub fn bounds(&self) -> Aabb {
        match *self {
            Shape::Cuboid { min, max } => Aabb { min, max },
            Shape::Cylinder {
                base,
                radius,
                height,
            } => Aabb {
                min: base - DVec3::new(radius, radius, 0.0),
                max: base + DVec3::new(radius, radius, height),
            },
            Shape::Sphere { center, radius } => Aabb {
                min: center - DVec3::splat(radius),
                max: center + DVec3::splat(radius),
            },
            Shape::Triangle { a, b, c } => Aabb {
                min: a.min(b).min(c),
                max: a.max(b).max(c),
            },
        }
    }

    /// Nearest intersection with t in (T_MIN, t_max): (t, outward normal).
    fn intersect(&self, o: DVec3, d: DVec3, t_max: f64) -> Option<(f64, DVec3)> {
        const T_MIN: f64 = 1e-9;
        match *self {
            Shape::Cuboid { min, max } => {
                let inv = d.recip();
                let t0 = (min - o) * inv;
                let t1 = (max - o) * inv;
                let tn = t0.min(t1);
                let tf = t0.max(t1);
                let t_near = tn.max_element();
                let t_far = tf.min_element();
                if t_near > t_far || t_far <= T_MIN {
                    return None;
                }
                // Outside: enter at t_near; inside (origin in the box): leave at t_far.
                let (t, axis_t) = if t_near > T_MIN {
                    (t_near, tn)
                } else {
                    (t_far, tf)
                };
                if t >= t_max {
                    return None;
                }
                let axis = if axis_t.x == t {
                    0
                } else if axis_t.y == t {
                    1
                } else {
                    2
                };
                let mut n = DVec3::ZERO;
                n[axis] = if d[axis] > 0.0 { -1.0 } else { 1.0 };
                if t_near <= T_MIN {
                    n = -n;
                }
                Some((t, n))
            }
            Shape::Sphere { center, radius } => {
                let oc = o - center;
                let b = oc.dot(d);
                let c = oc.length_squared() - radius * radius;
                let disc = b * b - c;
                if disc < 0.0 {
                    return None;
                }
                let s = disc.sqrt();
                let mut t = -b - s;
                if t <= T_MIN {
                    t = -b + s;
                }
                if t <= T_MIN || t >= t_max {
                    return None;
                }
                Some((t, (o + d * t - center) / radius))
            }
            Shape::Cylinder {
                base,
                radius,
                height,
            } => {
                let mut best: Option<(f64, DVec3)> = None;
                // Side: solve in the xy plane.
                let ox = o.x - base.x;
                let oy = o.y - base.y;
                let a = d.x * d.x + d.y * d.y;
                if a > 1e-18 {
                    let b = ox * d.x + oy * d.y;
                    let c = ox * ox + oy * oy - radius * radius;
                    let disc = b * b - a * c;
                    if disc >= 0.0 {
                        let s = disc.sqrt();
                        for t in [(-b - s) / a, (-b + s) / a] {
                            if t > T_MIN && t < t_max && best.is_none_or(|(bt, _)| t < bt) {
                                let z = o.z + d.z * t;
                                if z >= base.z && z <= base.z + height {
                                    let n = DVec3::new(ox + d.x * t, oy + d.y * t, 0.0) / radius;
                                    best = Some((t, n));
                                    break;
                                }
                            }
                        }
                    }
                }
                // Caps.
                if d.z.abs() > 1e-18 {
                    for (z, nz) in [(base.z, -1.0), (base.z + height, 1.0)] {
                        let t = (z - o.z) / d.z;
                        if t > T_MIN && t < t_max && best.is_none_or(|(bt, _)| t < bt) {
                            let px = ox + d.x * t;
                            let py = oy + d.y * t;
                            if px * px + py * py <= radius * radius {
                                best = Some((t, DVec3::new(0.0, 0.0, nz)));
                            }
                        }
                    }
                }
                best
            }
            Shape::Triangle { a, b, c } => {
                // Möller–Trumbore.
                let e1 = b - a;
                let e2 = c - a;
                let p = d.cross(e2);
                let det = e1.dot(p);
                if det.abs() < 1e-15 {
                    return None;
                }
                let inv = 1.0 / det;
                let s = o - a;
                let u = s.dot(p) * inv;
                if !(0.0..=1.0).contains(&u) {
                    return None;
                }
                let q = s.cross(e1);
                let v = d.dot(q) * inv;
                if v < 0.0 || u + v > 1.0 {
                    return None;
                }
                let t = e2.dot(q) * inv;
                if t <= T_MIN || t >= t_max {
                    return None;
                }
                Some((t, e1.cross(e2).normalize()))
            }
        }
    }
}

#[derive(Clone, Copy, Debug, Serialize, Deserialize)]
struct Node {
    bounds: Aabb,
    /// Leaf: first primitive index in `order`; inner: index of the right child (left is next).
    index: u32,
    /// Leaf: primitive count (> 0); inner: 0.
    count: u32,
}

/// A set of primitives with a BVH, plus the ground plane z = 0 (material `ground_material`).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Scene {
    pub primitives: Vec<Primitive>,
    pub ground_material: u16,
    nodes: Vec<Node>,
    order: Vec<u32>,
}

impl Scene {
    /// Builds the BVH (median split on the longest axis of the centroid bounds, ≤ 2 primitives a leaf).
    pub fn new(primitives: Vec<Primitive>, ground_material: u16) -> Scene {
        let mut order: Vec<u32> = (0..primitives.len() as u32).collect();
        let bounds: Vec<Aabb> = primitives.iter().map(|p| p.shape.bounds()).collect();
        let mut nodes = Vec::with_capacity(primitives.len() * 2);
        if !primitives.is_empty() {
            build(&mut nodes, &mut order, &bounds, 0, primitives.len());
        }
        Scene {
            primitives,
            ground_material,
            nodes,
            order,
        }
    }

    /// Nearest hit along the unit direction `dir` from `origin`, closer than `t_max`.
    pub fn cast(&self, origin: DVec3, dir: DVec3, t_max: f64) -> Option<Hit> {
        let mut best_t = t_max;
        let mut best: Option<(u32, DVec3)> = None;
        if dir.z < 0.0 && origin.z > 0.0 {
            let t = -origin.z / dir.z;
            if t < best_t {
                best_t = t;
                best = Some((GROUND, DVec3::Z));
            }
        }
        if !self.nodes.is_empty() {
            let inv = dir.recip();
            let mut stack = [0u32; 64];
            let mut sp = 1;
            while sp > 0 {
                sp -= 1;
                let ni = stack[sp];
                let node = &self.nodes[ni as usize];
                if node.bounds.hit(origin, inv, best_t).is_none() {
                    continue;
                }
                if node.count > 0 {
                    for &pi in &self.order[node.index as usize..(node.index + node.count) as usize]
                    {
                        if let Some((t, n)) = self.primitives[pi as usize]
                            .shape
                            .intersect(origin, dir, best_t)
                        {
                            best_t = t;
                            best = Some((pi, n));
                        }
                    }
                } else {
                    // Left child follows its parent; the right child's index is stored.
                    stack[sp] = ni + 1;
                    stack[sp + 1] = node.index;
                    sp += 2;
                }
            }
        }
        best.map(|(prim, n)| {
            let normal = if n.dot(dir) > 0.0 { -n } else { n };
            Hit {
                t: best_t,
                point: origin + dir * best_t,
                normal,
                primitive: prim,
                material: if prim == GROUND {
                    self.ground_material
                } else {
                    self.primitives[prim as usize].material
                },
            }
        })
    }

    /// True when `p` lies strictly inside a solid primitive other than `except` (by more than `eps`).
    /// Used to drop ground-truth samples of faces buried in other solids (a building's base in a slab).
    pub fn inside_solid(&self, p: DVec3, except: Option<u32>, eps: f64) -> bool {
        self.primitives.iter().enumerate().any(|(i, prim)| {
            if Some(i as u32) == except {
                return false;
            }
            match prim.shape {
                Shape::Cuboid { min, max } => {
                    (p - min).min_element() > eps && (max - p).min_element() > eps
                }
                Shape::Cylinder {
                    base,
                    radius,
                    height,
                } => {
                    let r = (p.truncate() - base.truncate()).length();
                    r < radius - eps && p.z > base.z + eps && p.z < base.z + height - eps
                }
                Shape::Sphere { center, radius } => (p - center).length() < radius - eps,
                Shape::Triangle { .. } => false,
            }
        }) || p.z < -eps
    }

    /// True when something lies between `a` and `b` (shadow / visibility rays).
    pub fn occluded(&self, a: DVec3, b: DVec3) -> bool {
        let d = b - a;
        let len = d.length();
        len > 1e-9 && self.cast(a, d / len, len - 1e-6).is_some()
    }
}

fn build(
    nodes: &mut Vec<Node>,
    order: &mut [u32],
    bounds: &[Aabb],
    start: usize,
    end: usize,
) -> u32 {
    let me = nodes.len() as u32;
    let b = order[start..end]
        .iter()
        .fold(Aabb::EMPTY, |acc, &i| acc.union(bounds[i as usize]));
    nodes.push(Node {
        bounds: b,
        index: start as u32,
        count: (end - start) as u32,
    });
    if end - start <= 2 {
        return me;
    }
    let cb = order[start..end].iter().fold(Aabb::EMPTY, |acc, &i| {
        let c = bounds[i as usize].center();
        acc.union(Aabb { min: c, max: c })
    });
    let ext = cb.max - cb.min;
    let axis = if ext.x >= ext.y && ext.x >= ext.z {
        0
    } else if ext.y >= ext.z {
        1
    } else {
        2
    };
    let mid = (start + end) / 2;
    order[start..end].select_nth_unstable_by(mid - start, |&a, &b| {
        bounds[a as usize].center()[axis].total_cmp(&bounds[b as usize].center()[axis])
    });
    let left = build(nodes, order, bounds, start, mid);
    debug_assert_eq!(left, me + 1);
    let right = build(nodes, order, bounds, mid, end);
    nodes[me as usize].index = right;
    nodes[me as usize].count = 0;
    me
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn brute(prims: &[Primitive], o: DVec3, d: DVec3) -> Option<(f64, u32)> {
        let mut best: Option<(f64, u32)> = None;
        if d.z < 0.0 && o.z > 0.0 {
            best = Some((-o.z / d.z, GROUND));
        }
        for (i, p) in prims.iter().enumerate() {
            if let Some((t, _)) = p.shape.intersect(o, d, f64::INFINITY) {
                if best.is_none_or(|(bt, _)| t < bt) {
                    best = Some((t, i as u32));
                }
            }
        }
        best
    }

    #[test]
    fn bvh_agrees_with_brute_force() {
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(5);
        let mut prims = Vec::new();
        for i in 0..200 {
            let c = DVec3::new(
                rng.random_range(-30.0..30.0),
                rng.random_range(-30.0..30.0),
                rng.random_range(0.0..8.0),
            );
            let s = rng.random_range(0.2..3.0);
            let shape = match i % 4 {
                0 => Shape::Cuboid {
                    min: c - DVec3::splat(s),
                    max: c + DVec3::new(s, 0.5 * s, 2.0 * s),
                },
                1 => Shape::Sphere {
                    center: c,
                    radius: s,
                },
                2 => Shape::Cylinder {
                    base: c,
                    radius: 0.3 * s,
                    height: 2.0 * s,
                },
                _ => Shape::Triangle {
                    a: c,
                    b: c + DVec3::new(s, 0.0, 0.3),
                    c: c + DVec3::new(0.0, s, 1.0),
                },
            };
            prims.push(Primitive {
                shape,
                material: i as u16,
            });
        }
        let scene = Scene::new(prims.clone(), 999);
        for _ in 0..5000 {
            let o = DVec3::new(
                rng.random_range(-40.0..40.0),
                rng.random_range(-40.0..40.0),
                rng.random_range(0.1..12.0),
            );
            let d = DVec3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            )
            .normalize();
            let a = scene.cast(o, d, f64::INFINITY).map(|h| (h.t, h.primitive));
            let b = brute(&prims, o, d);
            match (a, b) {
                (None, None) => {}
                (Some((ta, _)), Some((tb, _))) => assert!((ta - tb).abs() < 1e-9, "{ta} vs {tb}"),
                other => panic!("bvh {:?} vs brute {:?}", other.0, other.1),
            }
        }
    }

    #[test]
    fn shapes_report_exact_distances_and_outward_normals() {
        let scene = Scene::new(
            vec![
                Primitive {
                    shape: Shape::Cuboid {
                        min: DVec3::new(5.0, -1.0, 0.0),
                        max: DVec3::new(6.0, 1.0, 3.0),
                    },
                    material: 1,
                },
                Primitive {
                    shape: Shape::Sphere {
                        center: DVec3::new(0.0, 10.0, 2.0),
                        radius: 1.5,
                    },
                    material: 2,
                },
                Primitive {
                    shape: Shape::Cylinder {
                        base: DVec3::new(0.0, -10.0, 0.0),
                        radius: 0.5,
                        height: 4.0,
                    },
                    material: 3,
                },
            ],
            0,
        );
        let o = DVec3::new(0.0, 0.0, 2.0);
        let h = scene.cast(o, DVec3::X, 100.0).unwrap();
        assert_eq!((h.t, h.normal, h.material), (5.0, -DVec3::X, 1));
        let h = scene.cast(o, DVec3::Y, 100.0).unwrap();
        assert!((h.t - 8.5).abs() < 1e-12 && (h.normal + DVec3::Y).length() < 1e-12);
        let h = scene.cast(o, -DVec3::Y, 100.0).unwrap();
        assert!((h.t - 9.5).abs() < 1e-12 && (h.normal - DVec3::Y).length() < 1e-12);
        let h = scene.cast(o, DVec3::new(0.0, 0.6, -0.8), 100.0).unwrap();
        assert_eq!(h.primitive, GROUND);
        assert!((h.t - 2.5).abs() < 1e-12 && h.normal == DVec3::Z);
        assert!(scene.cast(o, DVec3::Z, 100.0).is_none(), "nothing above");
        assert!(scene.cast(o, DVec3::X, 4.9).is_none(), "t_max respected");
        // From inside a box the ray leaves through the far face, normal facing back at the origin.
        let h = scene
            .cast(DVec3::new(5.5, 0.0, 1.0), DVec3::X, 100.0)
            .unwrap();
        assert!((h.t - 0.5).abs() < 1e-12 && h.normal == -DVec3::X);
    }
}
