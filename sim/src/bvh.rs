//! A bounding-volume hierarchy over triangles for closest-hit and any-hit ray queries.
//!
//! Written here rather than taken from a crate: the scenes are small (thousands of
//! triangles), the queries are two (closest hit, occlusion between two points), and the
//! maintained BVH crates bring their own maths types (nalgebra) and shape traits for
//! what is about 150 lines on glam. Built once per scene by median splits along the
//! longest axis of the centroid bounds; traversal is iterative, nearer child first.
use glam::DVec3;

use crate::mesh::Mesh;

const LEAF_SIZE: usize = 4;

#[derive(Clone, Copy, Debug)]
struct Aabb {
    min: DVec3,
    max: DVec3,
}

impl Aabb {
    const EMPTY: Aabb = Aabb {
        min: DVec3::splat(f64::INFINITY),
        max: DVec3::splat(f64::NEG_INFINITY),
    };

    fn grow(&mut self, p: DVec3) {
        self.min = self.min.min(p);
        self.max = self.max.max(p);
    }

    /// Entry distance of the ray into the box within [0, t_max], if it hits.
    ///
    /// Slab by slab. Along an axis the ray does not move in (its direction component
    /// zero, the reciprocal infinite) the slab is passed or missed whole: passed where
    /// the origin lies within it, its faces included. The vector form computed
    /// 0 · ∞ = NaN there when the origin lay on a face, and glam's `min`/`max` kept
    /// NaN or the infinite side by the order of their operands, so a box was missed
    /// by a ray lying in its face: an axis-aligned ray down a wall's grid line (where
    /// leaves' boxes meet) or along its edge went through it.
    fn hit(&self, origin: DVec3, inv_dir: DVec3, t_max: f64) -> Option<f64> {
        let (mut near, mut far) = (0.0f64, t_max);
        for axis in 0..3 {
            let (o, inv) = (origin[axis], inv_dir[axis]);
            let (lo, hi) = (self.min[axis], self.max[axis]);
            if inv.is_infinite() {
                if !(lo <= o && o <= hi) {
                    return None;
                }
                continue;
            }
            let (t0, t1) = ((lo - o) * inv, (hi - o) * inv);
            near = near.max(t0.min(t1));
            far = far.min(t0.max(t1));
        }
        (near <= far).then_some(near)
    }
}

#[derive(Clone, Copy, Debug)]
struct Node {
    bounds: Aabb,
    /// Leaf: first triangle index into `order`; inner: index of the left child.
    start: u32,
    /// Leaf: triangle count (> 0); inner: 0 (right child is left + 1).
    count: u32,
}

/// A ray hit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    /// Distance along the (unit) direction.
    pub t: f64,
    /// Triangle index in the mesh.
    pub triangle: usize,
}

/// The hierarchy over one mesh.
#[derive(Clone, Debug)]
pub struct Bvh {
    nodes: Vec<Node>,
    order: Vec<u32>,
    tris: Vec<[DVec3; 3]>,
}

impl Bvh {
    /// Builds the hierarchy over `mesh`'s triangles.
    pub fn new(mesh: &Mesh) -> Bvh {
        let tris: Vec<[DVec3; 3]> = (0..mesh.triangles.len()).map(|i| mesh.corners(i)).collect();
        let centroids: Vec<DVec3> = tris.iter().map(|t| (t[0] + t[1] + t[2]) / 3.0).collect();
        let mut bvh = Bvh {
            nodes: Vec::with_capacity(2 * tris.len() / LEAF_SIZE + 1),
            order: (0..tris.len() as u32).collect(),
            tris,
        };
        bvh.nodes.push(Node {
            bounds: Aabb::EMPTY,
            start: 0,
            count: 0,
        });
        bvh.build(0, 0, bvh.order.len(), &centroids);
        bvh
    }

    fn build(&mut self, node: usize, start: usize, end: usize, centroids: &[DVec3]) {
        let mut bounds = Aabb::EMPTY;
        let mut cb = Aabb::EMPTY;
        for &i in &self.order[start..end] {
            for p in self.tris[i as usize] {
                bounds.grow(p);
            }
            cb.grow(centroids[i as usize]);
        }
        self.nodes[node].bounds = bounds;
        if end - start <= LEAF_SIZE {
            self.nodes[node].start = start as u32;
            self.nodes[node].count = (end - start) as u32;
            return;
        }
        let extent = cb.max - cb.min;
        let axis = if extent.x >= extent.y && extent.x >= extent.z {
            0
        } else if extent.y >= extent.z {
            1
        } else {
            2
        };
        let mid = (start + end) / 2;
        self.order[start..end].select_nth_unstable_by(mid - start, |&a, &b| {
            centroids[a as usize][axis].total_cmp(&centroids[b as usize][axis])
        });
        let left = self.nodes.len();
        for _ in 0..2 {
            self.nodes.push(Node {
                bounds: Aabb::EMPTY,
                start: 0,
                count: 0,
            });
        }
        self.nodes[node].start = left as u32;
        self.build(left, start, mid, centroids);
        self.build(left + 1, mid, end, centroids);
    }

    /// Closest hit along the unit direction `dir` within `(t_min, t_max)`; with `any`
    /// the first hit found (for occlusion).
    fn query(&self, origin: DVec3, dir: DVec3, t_min: f64, t_max: f64, any: bool) -> Option<Hit> {
        if self.tris.is_empty() {
            return None;
        }
        let inv = dir.recip();
        let mut best: Option<Hit> = None;
        let mut limit = t_max;
        let mut stack = [0u32; 64];
        let mut top = 1;
        while top > 0 {
            top -= 1;
            let node = self.nodes[stack[top] as usize];
            if node.bounds.hit(origin, inv, limit).is_none() {
                continue;
            }
            if node.count > 0 {
                for &i in &self.order[node.start as usize..(node.start + node.count) as usize] {
                    if let Some(t) = intersect(&self.tris[i as usize], origin, dir)
                        && t > t_min
                        && t < limit
                    {
                        best = Some(Hit {
                            t,
                            triangle: i as usize,
                        });
                        if any {
                            return best;
                        }
                        limit = t;
                    }
                }
            } else {
                let (l, r) = (node.start, node.start + 1);
                let dl = self.nodes[l as usize].bounds.hit(origin, inv, limit);
                let dr = self.nodes[r as usize].bounds.hit(origin, inv, limit);
                // Push the farther child first so the nearer is visited first.
                let (first, second) = match (dl, dr) {
                    (Some(a), Some(b)) if b < a => (l, r),
                    _ => (r, l),
                };
                if top + 2 <= stack.len() {
                    stack[top] = first;
                    stack[top + 1] = second;
                    top += 2;
                }
            }
        }
        best
    }

    /// Closest hit of the ray `origin + t·dir` (unit `dir`) with `t` in `(t_min, t_max)`.
    pub fn closest(&self, origin: DVec3, dir: DVec3, t_min: f64, t_max: f64) -> Option<Hit> {
        self.query(origin, dir, t_min, t_max, false)
    }

    /// Whether anything lies strictly between `a` and `b` (ends excluded by `eps`).
    pub fn occluded(&self, a: DVec3, b: DVec3, eps: f64) -> bool {
        let d = b - a;
        let len = d.length();
        len > 2.0 * eps && self.query(a, d / len, eps, len - eps, true).is_some()
    }
}

/// Möller–Trumbore; two-sided.
fn intersect(t: &[DVec3; 3], origin: DVec3, dir: DVec3) -> Option<f64> {
    let e1 = t[1] - t[0];
    let e2 = t[2] - t[0];
    let p = dir.cross(e2);
    let det = e1.dot(p);
    if det.abs() < 1e-14 {
        return None;
    }
    let inv = 1.0 / det;
    let s = origin - t[0];
    let u = s.dot(p) * inv;
    if !(0.0..=1.0).contains(&u) {
        return None;
    }
    let q = s.cross(e1);
    let v = dir.dot(q) * inv;
    if v < 0.0 || u + v > 1.0 {
        return None;
    }
    Some(e2.dot(q) * inv)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn agrees_with_brute_force() {
        let mut mesh = Mesh::ellipsoid(DVec3::new(0.3, 0.2, 0.25), 24);
        mesh.append(
            &Mesh::cuboid(DVec3::splat(0.1)).transformed(glam::DMat3::IDENTITY, DVec3::new(0.5, 0.0, 0.0)),
        );
        let bvh = Bvh::new(&mesh);
        let mut state = 1u64;
        let mut r = move || {
            state = state.wrapping_mul(6364136223846793005).wrapping_add(1);
            (state >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        };
        for _ in 0..500 {
            let origin = DVec3::new(r(), r(), r()) * 3.0;
            let dir = (DVec3::new(r(), r(), r()) * 0.6 - origin * 0.3).normalize();
            let brute = (0..mesh.triangles.len())
                .filter_map(|i| {
                    intersect(&mesh.corners(i), origin, dir)
                        .filter(|t| *t > 1e-9)
                        .map(|t| (t, i))
                })
                .min_by(|a, b| a.0.total_cmp(&b.0));
            let hit = bvh.closest(origin, dir, 1e-9, f64::INFINITY);
            assert_eq!(hit.map(|h| h.triangle), brute.map(|b| b.1));
            assert_eq!(
                bvh.occluded(origin, origin + dir * 10.0, 1e-9),
                brute.is_some_and(|b| b.0 < 10.0 - 1e-9)
            );
        }
    }

    /// An axis-aligned ray lying exactly in a box's face still enters the box and hits
    /// the triangle there: rays along −z through an axis-aligned wall, down its grid
    /// lines (where the leaves' boxes meet) and along its outer edges (the root box's
    /// faces), with both signs of the zero direction components. The slab test made
    /// NaN of 0 · ∞ on a face, and such rays went through the wall; its edge at
    /// x = −0.5 was missed altogether.
    #[test]
    fn an_axis_aligned_ray_in_a_box_face_hits_the_triangle_there() {
        // 8 × 8 quads over [−0.5, 0.5]² at z = 0: 128 triangles, many leaves. Dyadic
        // coordinates keep every edge hit exact.
        let wall = Mesh::parametric(8, 8, |u, v| DVec3::new(u - 0.5, v - 0.5, 0.0));
        let bvh = Bvh::new(&wall);
        let line = |i: u32| f64::from(i) / 8.0 - 0.5;
        for zero in [0.0, -0.0] {
            let dir = DVec3::new(zero, zero, -1.0);
            for i in 0..=8 {
                for j in 0..8 {
                    // Between two grid lines of the other axis, off the wall's vertices.
                    let between = line(j) + 1.0 / 32.0;
                    for origin in [
                        DVec3::new(line(i), between, 1.0),
                        DVec3::new(between, line(i), 1.0),
                    ] {
                        let hit = bvh.closest(origin, dir, 1e-9, f64::INFINITY);
                        assert_eq!(hit.map(|h| h.t), Some(1.0), "from {origin} along {dir}");
                        assert!(
                            bvh.occluded(origin, origin + 2.0 * dir, 1e-9),
                            "from {origin} along {dir}"
                        );
                    }
                }
            }
        }
    }
}
