//! Bounding volume hierarchy over a triangle mesh and the two ray queries the
//! renderer needs: closest hit and occlusion.
//!
//! Built with `obvhs`' BVH2 (PLOC + reinsertion). Its CWBVH layout is not
//! used: it misses hits on axis-aligned planar geometry (see
//! DEPENDENCIES.md), and depth meshes of rooms are full of such planes.
//! Occlusion uses `ray_traverse_miss` (early exit on the first hit), not
//! `ray_traverse_anyhit`, which visits every hit.
//!
//! Triangles are stored in BVH leaf order with precomputed edges; the
//! intersection test is Möller–Trumbore with a small barycentric tolerance so
//! rays through shared edges of the grid mesh never slip between triangles.

use std::time::Duration;

use glam::{Vec3, Vec3A};
use obvhs::bvh2::builder::build_bvh2_from_tris;
use obvhs::bvh2::Bvh2;
use obvhs::ray::{Ray, RayHit};
use obvhs::triangle::Triangle;
use obvhs::BvhBuildParams;

use crate::mesh::TriMesh;

/// Barycentric tolerance (relative, so independent of scale).
const BARY_EPS: f32 = 1e-4;

#[derive(Clone, Copy, Debug)]
struct PrecompTri {
    v0: Vec3A,
    e1: Vec3A,
    e2: Vec3A,
}

/// A closest-hit result.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    /// Distance along the (not necessarily unit) ray direction.
    pub t: f32,
    /// Index of the triangle in the original mesh.
    pub prim: u32,
    /// Barycentric coordinates of vertices 1 and 2.
    pub u: f32,
    pub v: f32,
}

pub struct Bvh {
    bvh: Bvh2,
    tris: Vec<PrecompTri>,
    /// BVH order → original triangle index.
    prim_ids: Vec<u32>,
}

#[inline(always)]
fn intersect_tri(
    tri: &PrecompTri,
    o: Vec3A,
    d: Vec3A,
    tmin: f32,
    tmax: f32,
) -> Option<(f32, f32, f32)> {
    let p = d.cross(tri.e2);
    let det = tri.e1.dot(p);
    if det == 0.0 || !det.is_finite() {
        return None;
    }
    let inv = 1.0 / det;
    let s = o - tri.v0;
    let u = s.dot(p) * inv;
    if !(-BARY_EPS..=1.0 + BARY_EPS).contains(&u) {
        return None;
    }
    let q = s.cross(tri.e1);
    let v = d.dot(q) * inv;
    if v < -BARY_EPS || u + v > 1.0 + BARY_EPS {
        return None;
    }
    let t = tri.e2.dot(q) * inv;
    if t > tmin && t < tmax {
        Some((t, u, v))
    } else {
        None
    }
}

impl Bvh {
    /// Builds the hierarchy. Degenerate (zero-area or non-finite) triangles
    /// are kept out of it.
    pub fn build(mesh: &TriMesh) -> Bvh {
        let mut tris = Vec::with_capacity(mesh.indices.len());
        let mut orig = Vec::with_capacity(mesh.indices.len());
        for (i, idx) in mesh.indices.iter().enumerate() {
            let [a, b, c] = idx.map(|k| Vec3A::from(mesh.positions[k as usize]));
            let area2 = (b - a).cross(c - a).length_squared();
            if !(area2 > 0.0) || !area2.is_finite() {
                continue;
            }
            tris.push(Triangle {
                v0: a,
                v1: b,
                v2: c,
            });
            orig.push(i as u32);
        }
        let bvh = if tris.is_empty() {
            Bvh2::default()
        } else {
            build_bvh2_from_tris(
                &tris,
                BvhBuildParams::medium_build(),
                &mut Duration::default(),
            )
        };
        let mut pre = Vec::with_capacity(bvh.primitive_indices.len());
        let mut prim_ids = Vec::with_capacity(bvh.primitive_indices.len());
        for &pi in &bvh.primitive_indices {
            let t = &tris[pi as usize];
            pre.push(PrecompTri {
                v0: t.v0,
                e1: t.v1 - t.v0,
                e2: t.v2 - t.v0,
            });
            prim_ids.push(orig[pi as usize]);
        }
        Bvh {
            bvh,
            tris: pre,
            prim_ids,
        }
    }

    pub fn triangle_count(&self) -> usize {
        self.tris.len()
    }

    pub fn node_count(&self) -> usize {
        self.bvh.nodes.len()
    }

    /// Closest hit with t in (tmin, tmax). Ties at equal t go to the lower
    /// original triangle index, so the answer does not depend on the order
    /// in which the hierarchy is traversed.
    #[inline]
    pub fn intersect(&self, origin: Vec3, dir: Vec3, tmin: f32, tmax: f32) -> Option<Hit> {
        if self.tris.is_empty() {
            return None;
        }
        let o = Vec3A::from(origin);
        let d = Vec3A::from(dir);
        let ray = Ray::new(o, d, tmin, tmax);
        let mut best: Option<Hit> = None;
        let mut hit = RayHit::none();
        let tris = &self.tris;
        let ids = &self.prim_ids;
        self.bvh.ray_traverse(ray, &mut hit, |r, id| {
            let tri = &tris[id];
            // Accept t == current tmax so ties can be resolved by index.
            match intersect_tri(tri, o, d, r.tmin, r.tmax.next_up_f32()) {
                Some((t, u, v)) => {
                    let prim = ids[id];
                    let better = match best {
                        None => true,
                        Some(b) => t < b.t || (t == b.t && prim < b.prim),
                    };
                    if better {
                        best = Some(Hit { t, prim, u, v });
                    }
                    t
                }
                None => f32::INFINITY,
            }
        });
        best
    }

    /// True when anything lies on the segment t in (tmin, tmax).
    #[inline]
    pub fn occluded(&self, origin: Vec3, dir: Vec3, tmin: f32, tmax: f32) -> bool {
        if self.tris.is_empty() {
            return false;
        }
        let o = Vec3A::from(origin);
        let d = Vec3A::from(dir);
        let ray = Ray::new(o, d, tmin, tmax);
        let tris = &self.tris;
        !self.bvh.ray_traverse_miss(ray, |r, id| {
            match intersect_tri(&tris[id], o, d, r.tmin, r.tmax) {
                Some((t, _, _)) => t,
                None => f32::INFINITY,
            }
        })
    }
}

trait NextUp {
    fn next_up_f32(self) -> f32;
}
impl NextUp for f32 {
    #[inline(always)]
    fn next_up_f32(self) -> f32 {
        if self.is_nan() || self == f32::INFINITY {
            return self;
        }
        let bits = self.to_bits();
        if self == 0.0 {
            return f32::from_bits(1);
        }
        if self > 0.0 {
            f32::from_bits(bits + 1)
        } else {
            f32::from_bits(bits - 1)
        }
    }
}

/// Brute-force closest hit over every triangle (the test oracle).
pub fn brute_force_intersect(
    mesh: &TriMesh,
    origin: Vec3,
    dir: Vec3,
    tmin: f32,
    tmax: f32,
) -> Option<Hit> {
    let o = Vec3A::from(origin);
    let d = Vec3A::from(dir);
    let mut best: Option<Hit> = None;
    for (i, idx) in mesh.indices.iter().enumerate() {
        let [a, b, c] = idx.map(|k| Vec3A::from(mesh.positions[k as usize]));
        let tri = PrecompTri {
            v0: a,
            e1: b - a,
            e2: c - a,
        };
        let area2 = tri.e1.cross(tri.e2).length_squared();
        if !(area2 > 0.0) || !area2.is_finite() {
            continue;
        }
        let limit = best.map(|b| b.t.next_up_f32()).unwrap_or(tmax);
        if let Some((t, u, v)) = intersect_tri(&tri, o, d, tmin, limit) {
            let better = match best {
                None => true,
                Some(b) => t < b.t || (t == b.t && (i as u32) < b.prim),
            };
            if better {
                best = Some(Hit {
                    t,
                    prim: i as u32,
                    u,
                    v,
                });
            }
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::TriMesh;

    /// A deterministic xorshift for test rays.
    struct Rng(u64);
    impl Rng {
        fn f(&mut self) -> f32 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            (self.0 >> 40) as f32 / (1u64 << 24) as f32
        }
        fn dir(&mut self) -> Vec3 {
            loop {
                let v = Vec3::new(
                    self.f() * 2.0 - 1.0,
                    self.f() * 2.0 - 1.0,
                    self.f() * 2.0 - 1.0,
                );
                let l = v.length();
                if l > 0.1 && l <= 1.0 {
                    return v / l;
                }
            }
        }
    }

    /// An axis-aligned box room (12 triangles, planes on all three axes),
    /// a tessellated floor grid and a sloped quad.
    fn test_mesh() -> TriMesh {
        let mut m = TriMesh::default();
        m.add_box(Vec3::splat(-5.0), Vec3::splat(5.0));
        m.add_box(Vec3::new(-1.0, -5.0, -1.0), Vec3::new(1.0, -3.0, 1.0));
        // 40×40 grid on the plane y = -2 (axis-aligned, many shared edges).
        let n = 40;
        let base = m.positions.len() as u32;
        for j in 0..=n {
            for i in 0..=n {
                m.positions.push(Vec3::new(
                    -4.0 + 8.0 * i as f32 / n as f32,
                    -2.0,
                    -4.0 + 8.0 * j as f32 / n as f32,
                ));
            }
        }
        for j in 0..n {
            for i in 0..n {
                let a = base + (j * (n + 1) + i) as u32;
                let b = a + 1;
                let c = a + (n + 1) as u32;
                let d = c + 1;
                m.indices.push([a, c, b]);
                m.indices.push([b, c, d]);
            }
        }
        m
    }

    #[test]
    fn closest_hit_matches_brute_force_on_axis_aligned_planes() {
        let mesh = test_mesh();
        let bvh = Bvh::build(&mesh);
        let mut rng = Rng(0x9e3779b97f4a7c15);
        let mut hits = 0;
        for k in 0..4000 {
            let o = if k % 2 == 0 {
                Vec3::new(
                    rng.f() * 8.0 - 4.0,
                    rng.f() * 8.0 - 4.0,
                    rng.f() * 8.0 - 4.0,
                )
            } else {
                // Axis-aligned rays straight at the planes.
                Vec3::new(rng.f() * 6.0 - 3.0, 0.5, rng.f() * 6.0 - 3.0)
            };
            let d = if k % 2 == 0 { rng.dir() } else { Vec3::NEG_Y };
            let a = bvh.intersect(o, d, 1e-4, f32::INFINITY);
            let b = brute_force_intersect(&mesh, o, d, 1e-4, f32::INFINITY);
            match (a, b) {
                (Some(a), Some(b)) => {
                    assert_eq!(a.prim, b.prim, "ray {k}: {a:?} vs {b:?}");
                    assert_eq!(a.t, b.t);
                    hits += 1;
                }
                (None, None) => {}
                _ => panic!("ray {k} from {o} dir {d}: bvh {a:?} brute {b:?}"),
            }
            let occl = bvh.occluded(o, d, 1e-4, 3.0);
            let bf = b.map(|h| h.t < 3.0).unwrap_or(false);
            assert_eq!(occl, bf, "occlusion ray {k}");
        }
        // Inside a closed room every ray hits something.
        assert_eq!(hits, 4000);
    }

    #[test]
    fn rays_through_shared_grid_edges_never_leak() {
        // Rays aimed exactly at grid vertices and edge midpoints of the floor.
        let mesh = test_mesh();
        let bvh = Bvh::build(&mesh);
        for j in 1..80 {
            for i in 1..80 {
                let x = -4.0 + 0.1 * i as f32;
                let z = -4.0 + 0.1 * j as f32;
                let o = Vec3::new(x * 0.5, 1.0, z * 0.5);
                let target = Vec3::new(x, -2.0, z);
                let d = (target - o).normalize();
                let h = bvh.intersect(o, d, 1e-4, f32::INFINITY).expect("hit");
                let p = o + d * h.t;
                assert!(
                    (p.y + 2.0).abs() < 1e-3,
                    "leaked through the floor at {target}: {p}"
                );
            }
        }
    }

    #[test]
    fn empty_and_degenerate_meshes() {
        let mut m = TriMesh::default();
        let bvh = Bvh::build(&m);
        assert!(bvh.intersect(Vec3::ZERO, Vec3::X, 0.0, 1e9).is_none());
        assert!(!bvh.occluded(Vec3::ZERO, Vec3::X, 0.0, 1e9));
        m.positions = vec![Vec3::ZERO, Vec3::X, Vec3::X * 2.0];
        m.indices = vec![[0, 1, 2]];
        assert_eq!(Bvh::build(&m).triangle_count(), 0);
    }
}
