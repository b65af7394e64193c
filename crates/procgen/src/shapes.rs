//! Procedural closed meshes for inserted objects and tests: sphere, torus,
//! surfaces of revolution (a jug) and boxes. Triangles are counter-clockwise
//! seen from outside, so face normals point outwards; each shape also
//! returns its exact per-vertex normals.

use std::f32::consts::PI;

use glam::{Vec2, Vec3};

use matflow_geom::mesh::{box_corner, TriMesh, BOX_QUADS};

/// A mesh with per-vertex shading normals.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Shape {
    pub mesh: TriMesh,
    pub normals: Vec<Vec3>,
}

impl Shape {
    fn push(&mut self, p: Vec3, n: Vec3) -> u32 {
        self.mesh.positions.push(p);
        self.normals.push(n.normalize_or(Vec3::Y));
        (self.mesh.positions.len() - 1) as u32
    }

    /// Adds the quad (a, b, c, d), counter-clockwise from outside, as two
    /// triangles; degenerate halves (at poles) are skipped.
    fn quad(&mut self, a: u32, b: u32, c: u32, d: u32) {
        for t in [[a, b, c], [a, c, d]] {
            let [p, q, r] = t.map(|i| self.mesh.positions[i as usize]);
            if (q - p).cross(r - p).length_squared() > 0.0 {
                self.mesh.indices.push(t);
            }
        }
    }

    /// The shape moved by `offset` and scaled by `scale` about the origin.
    pub fn transformed(mut self, scale: f32, offset: Vec3) -> Shape {
        for p in &mut self.mesh.positions {
            *p = *p * scale + offset;
        }
        self
    }
}

/// A sphere of radius `r` about the origin: `rings` bands of latitude,
/// `segments` of longitude.
pub fn sphere(r: f32, rings: usize, segments: usize) -> Shape {
    let profile: Vec<Vec2> = (0..=rings.max(2))
        .map(|i| {
            let t = PI * i as f32 / rings.max(2) as f32;
            // Exactly on the axis at the poles.
            let x = if i == 0 || i == rings.max(2) {
                0.0
            } else {
                r * t.sin()
            };
            Vec2::new(x, -r * t.cos())
        })
        .collect();
    let normals: Vec<Vec2> = profile.iter().map(|p| p.normalize_or(Vec2::Y)).collect();
    revolve(&profile, Some(&normals), segments)
}

/// A torus about the y axis: ring radius `big`, tube radius `small`.
pub fn torus(big: f32, small: f32, rings: usize, segments: usize) -> Shape {
    let (rings, segments) = (rings.max(3), segments.max(3));
    let mut s = Shape::default();
    for i in 0..segments {
        let phi = 2.0 * PI * i as f32 / segments as f32;
        let radial = Vec3::new(phi.cos(), 0.0, -phi.sin());
        for j in 0..rings {
            let th = 2.0 * PI * j as f32 / rings as f32;
            let n = radial * th.cos() + Vec3::Y * th.sin();
            s.push(radial * big + n * small, n);
        }
    }
    let idx = |i: usize, j: usize| ((i % segments) * rings + j % rings) as u32;
    for i in 0..segments {
        for j in 0..rings {
            s.quad(idx(i, j), idx(i + 1, j), idx(i + 1, j + 1), idx(i, j + 1));
        }
    }
    s
}

/// The surface of revolution about the y axis of `profile`, points (radius,
/// height) from the bottom to the top; an end with non-zero radius is
/// closed by a flat cap. `normals` are the profile's outward normals in
/// the (radius, height) plane (computed from the profile when `None`).
pub fn revolve(profile: &[Vec2], normals: Option<&[Vec2]>, segments: usize) -> Shape {
    let segments = segments.max(3);
    let m = profile.len();
    let computed: Vec<Vec2>;
    let normals = match normals {
        Some(n) if n.len() == m => n,
        _ => {
            computed = (0..m)
                .map(|k| {
                    let a = profile[k.saturating_sub(1)];
                    let b = profile[(k + 1).min(m - 1)];
                    let t = b - a;
                    Vec2::new(t.y, -t.x).normalize_or(Vec2::X)
                })
                .collect();
            &computed
        }
    };
    let mut s = Shape::default();
    let dir = |phi: f32| Vec3::new(phi.cos(), 0.0, -phi.sin());
    for i in 0..segments {
        let d = dir(2.0 * PI * i as f32 / segments as f32);
        for k in 0..m {
            let (p, n) = (profile[k], normals[k]);
            s.push(d * p.x + Vec3::Y * p.y, d * n.x + Vec3::Y * n.y);
        }
    }
    let idx = |i: usize, k: usize| ((i % segments) * m + k) as u32;
    for i in 0..segments {
        for k in 0..m.saturating_sub(1) {
            s.quad(idx(i, k), idx(i + 1, k), idx(i + 1, k + 1), idx(i, k + 1));
        }
    }
    // Flat caps where the profile does not end on the axis.
    for (k, down) in [(0usize, true), (m - 1, false)] {
        if m == 0 || profile[k].x <= 0.0 {
            continue;
        }
        let n = if down { -Vec3::Y } else { Vec3::Y };
        let c = s.push(Vec3::Y * profile[k].y, n);
        let ring: Vec<u32> = (0..segments)
            .map(|i| {
                let d = dir(2.0 * PI * i as f32 / segments as f32);
                s.push(d * profile[k].x + Vec3::Y * profile[k].y, n)
            })
            .collect();
        for i in 0..segments {
            let (a, b) = (ring[i], ring[(i + 1) % segments]);
            s.mesh
                .indices
                .push(if down { [c, b, a] } else { [c, a, b] });
        }
    }
    s
}

/// A jug: a closed surface of revolution with a round belly, a neck and a
/// flared lip (height 1, base on y = 0, widest radius about 0.4).
pub fn jug(segments: usize) -> Shape {
    let pts = 48;
    let profile: Vec<Vec2> = (0..=pts)
        .map(|k| {
            let y = k as f32 / pts as f32;
            // Belly (a sine bump), a narrowing neck and a flared lip.
            let belly = 0.18 + 0.22 * (PI * (y / 0.75).min(1.0)).sin().max(0.0);
            let lip = 0.06 * ((y - 0.8) / 0.2).clamp(0.0, 1.0).powi(2);
            let base = 0.25 * (1.0 - (y / 0.05).min(1.0));
            Vec2::new((belly + lip).max(base), y)
        })
        .collect();
    revolve(&profile, None, segments)
}

/// An axis-aligned box with flat normals (a [`TriMesh::add_box`] whose
/// faces do not share vertices).
pub fn cuboid(lo: Vec3, hi: Vec3) -> Shape {
    let mut s = Shape::default();
    for q in BOX_QUADS {
        let c = q.map(|k| box_corner(lo, hi, k));
        let n = (c[1] - c[0]).cross(c[2] - c[0]);
        let ids = c.map(|p| s.push(p, n));
        s.quad(ids[0], ids[1], ids[2], ids[3]);
    }
    s
}

/// A hollow vessel of revolution: the outer profile `outer(y)` (radius at
/// height y in [0, height]) with walls `wall` thick and a floor as thick,
/// open at the top (a rim joins the outer and inner walls). One closed
/// surface whose normals face out of the material: the outside, the rim,
/// the inside of the cavity and its floor.
pub fn vessel(outer: impl Fn(f32) -> f32, height: f32, wall: f32, segments: usize) -> Shape {
    let pts = 48;
    let mut profile = vec![Vec2::new(0.0, 0.0)];
    for k in 0..=pts {
        let y = height * k as f32 / pts as f32;
        profile.push(Vec2::new(outer(y).max(2.0 * wall), y));
    }
    for k in (0..=pts).rev() {
        let y = wall + (height - wall) * k as f32 / pts as f32;
        profile.push(Vec2::new((outer(y) - wall).max(wall), y));
    }
    profile.push(Vec2::new(0.0, wall));
    revolve(&profile, None, segments)
}

/// A solid blob: a sphere of radius `r` whose radius varies smoothly with
/// direction by up to `bump`·r (a fruit-like shape), seeded by `seed`.
pub fn blob(r: f32, bump: f32, seed: u32, rings: usize, segments: usize) -> Shape {
    let mut s = sphere(1.0, rings, segments);
    let k = seed as f32 * 0.618;
    let f = |d: Vec3| {
        1.0 + bump
            * ((3.0 * d.x + k).sin() * 0.5
                + (2.0 * d.y + 2.0 * k).sin() * 0.3
                + (4.0 * d.z - k).sin() * 0.2)
    };
    for p in &mut s.mesh.positions {
        let d = p.normalize_or(Vec3::Y);
        *p = d * r * f(d);
    }
    // Normals of the displaced surface, from its faces.
    let mut acc = vec![Vec3::ZERO; s.mesh.positions.len()];
    for t in &s.mesh.indices {
        let [a, b, c] = t.map(|i| s.mesh.positions[i as usize]);
        let n = (b - a).cross(c - a);
        for &i in t {
            acc[i as usize] += n;
        }
    }
    s.normals = acc.iter().map(|n| n.normalize_or(Vec3::Y)).collect();
    s
}

/// The names of [`refraction_objects`], in order.
pub const REFRACTION_OBJECT_NAMES: &[&str] = &[
    "cup",
    "jug",
    "bottle",
    "vase",
    "ellipsoid",
    "apple",
    "lemon",
    "box",
    "torus",
    "ball",
];

/// Whether the built-in refraction object `name` is hollow (the vessels).
pub fn refraction_object_is_hollow(name: &str) -> bool {
    matches!(name, "cup" | "jug" | "bottle" | "vase")
}

/// The objects of the refraction-length dataset (the paper's supplement
/// §10): name, shape (standing on y = 0, about 1 high) and whether it is
/// hollow (eq. 24's rule). Vessels — a cup, a jug, a bottle, a vase — are
/// hollow; an ellipsoid, fruit-like blobs, a box, a torus and a ball are
/// solid.
pub fn refraction_objects() -> Vec<(&'static str, Shape, bool)> {
    use std::f32::consts::PI;
    let seg = 64;
    vec![
        ("cup", vessel(|y| 0.32 + 0.05 * y, 0.8, 0.03, seg), true),
        (
            "jug",
            vessel(
                |y| 0.2 + 0.22 * (PI * (y / 0.75).min(1.0)).sin().max(0.0),
                1.0,
                0.03,
                seg,
            ),
            true,
        ),
        (
            "bottle",
            vessel(
                |y| {
                    let t = ((y - 0.55) / 0.2).clamp(0.0, 1.0);
                    0.28 * (1.0 - t) + 0.08 * t
                },
                1.1,
                0.025,
                seg,
            ),
            true,
        ),
        (
            "vase",
            vessel(|y| 0.22 + 0.1 * (2.0 * PI * y / 1.2).sin(), 1.2, 0.03, seg),
            true,
        ),
        (
            "ellipsoid",
            {
                let mut e = sphere(1.0, 32, seg);
                for p in &mut e.mesh.positions {
                    *p = Vec3::new(0.45 * p.x, 0.3 * p.y + 0.3, 0.35 * p.z);
                }
                for n in &mut e.normals {
                    *n = Vec3::new(n.x / 0.45, n.y / 0.3, n.z / 0.35).normalize_or(Vec3::Y);
                }
                e
            },
            false,
        ),
        (
            "apple",
            blob(0.4, 0.12, 1, 32, seg).transformed(1.0, Vec3::new(0.0, 0.4, 0.0)),
            false,
        ),
        (
            "lemon",
            blob(0.3, 0.2, 2, 32, seg).transformed(1.0, Vec3::new(0.0, 0.3, 0.0)),
            false,
        ),
        (
            "box",
            cuboid(Vec3::new(-0.3, 0.0, -0.2), Vec3::new(0.3, 0.5, 0.2)),
            false,
        ),
        (
            "torus",
            torus(0.35, 0.12, 24, seg).transformed(1.0, Vec3::new(0.0, 0.12, 0.0)),
            false,
        ),
        (
            "ball",
            sphere(0.4, 32, seg).transformed(1.0, Vec3::new(0.0, 0.4, 0.0)),
            false,
        ),
    ]
}

/// The shapes matflow ships for inserting (`pipelines/meshes/`), each
/// standing on y = 0 with its base centred on the origin (so `anchor`
/// stands it on a surface): a jug 1 high, a torus lying flat (outer
/// radius 0.55, tube 0.15), a sphere of radius 0.5 and a unit cube.
pub fn shipped() -> Vec<(&'static str, Shape)> {
    vec![
        ("jug", jug(40)),
        (
            "torus",
            torus(0.4, 0.15, 20, 40).transformed(1.0, Vec3::new(0.0, 0.15, 0.0)),
        ),
        (
            "sphere",
            sphere(0.5, 20, 40).transformed(1.0, Vec3::new(0.0, 0.5, 0.0)),
        ),
        (
            "cube",
            cuboid(Vec3::new(-0.5, 0.0, -0.5), Vec3::new(0.5, 1.0, 0.5)),
        ),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Signed volume by the divergence theorem: positive when every face
    /// is wound counter-clockwise from outside.
    fn volume(m: &TriMesh) -> f64 {
        m.indices
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| m.positions[i as usize].as_dvec3());
                a.dot(b.cross(c)) / 6.0
            })
            .sum()
    }

    /// Every edge is shared by exactly two triangles, once in each
    /// direction: the surface is closed and consistently oriented.
    fn closed(m: &TriMesh) -> bool {
        let mut edges = std::collections::HashMap::new();
        for t in &m.indices {
            for k in 0..3 {
                let key = (t[k], t[(k + 1) % 3]);
                *edges.entry(key).or_insert(0) += 1;
            }
        }
        // Poles and seams repeat positions; compare by position.
        let pos = |i: u32| {
            m.positions[i as usize]
                .to_array()
                .map(|x| (x + 0.0).to_bits())
        };
        let mut by_pos = std::collections::HashMap::new();
        for (&(a, b), &n) in &edges {
            *by_pos.entry((pos(a), pos(b))).or_insert(0) += n;
        }
        by_pos
            .iter()
            .all(|(&(a, b), &n)| n == 1 && by_pos.get(&(b, a)) == Some(&1))
    }

    #[test]
    fn refraction_objects_are_closed_and_hollow_vessels_hold_a_cavity() {
        let names: Vec<&str> = refraction_objects().iter().map(|o| o.0).collect();
        assert_eq!(names, REFRACTION_OBJECT_NAMES);
        for (name, s, hollow) in refraction_objects() {
            assert_eq!(refraction_object_is_hollow(name), hollow, "{name}");
            assert!(closed(&s.mesh), "{name} is not closed");
            let v = volume(&s.mesh);
            assert!(v > 0.0, "{name}: volume {v}");
            assert_eq!(s.normals.len(), s.mesh.positions.len(), "{name}");
            if hollow {
                // The material is a thin shell: far less than the solid of
                // the same outline.
                let lo = s.mesh.positions.iter().fold(f32::MAX, |m, p| m.min(p.y));
                let hi = s.mesh.positions.iter().fold(f32::MIN, |m, p| m.max(p.y));
                let r = s
                    .mesh
                    .positions
                    .iter()
                    .fold(0.0f32, |m, p| m.max(p.x.hypot(p.z)));
                let cylinder = std::f64::consts::PI * (r * r) as f64 * (hi - lo) as f64;
                assert!(v < 0.5 * cylinder, "{name}: {v} of {cylinder}");
            }
        }
    }

    #[test]
    fn shapes_are_closed_outward_and_of_the_right_volume() {
        let s = sphere(2.0, 48, 96);
        let v = volume(&s.mesh);
        assert!(
            (v / (4.0 / 3.0 * std::f64::consts::PI * 8.0) - 1.0).abs() < 0.01,
            "{v}"
        );
        assert!(closed(&s.mesh));
        let t = torus(1.0, 0.25, 32, 64);
        let v = volume(&t.mesh);
        let want = 2.0 * std::f64::consts::PI.powi(2) * 1.0 * 0.0625;
        assert!((v / want - 1.0).abs() < 0.02, "{v} {want}");
        assert!(closed(&t.mesh));
        let j = jug(48);
        assert!(volume(&j.mesh) > 0.1 && closed(&j.mesh));
        let b = cuboid(Vec3::ZERO, Vec3::new(1.0, 2.0, 3.0));
        assert!((volume(&b.mesh) - 6.0).abs() < 1e-5 && closed(&b.mesh));
        // Vertex normals agree with the faces around them.
        for s in [&s, &t, &j, &b] {
            for tri in &s.mesh.indices {
                let [a, b2, c] = tri.map(|i| s.mesh.positions[i as usize]);
                let f = (b2 - a).cross(c - a).normalize();
                for &i in tri {
                    assert!(s.normals[i as usize].dot(f) > 0.0);
                }
            }
        }
    }
}
