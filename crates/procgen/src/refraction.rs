//! Refraction lengths (the paper's supplement §10, eq. 24): along a camera
//! ray through an object, the distance to its secondary interface, as the
//! refraction-length dataset labels it — with straight rays, the paper's
//! simplification for an index of refraction near 1.
//!
//! With P_n the n-th intersection of the ray with the object (n = 1, 2, …)
//! and n its outward normal there,
//!
//! d = ‖P_{n+1} − P_n‖ if ω·n > 0 and the object is hollow,
//!     ‖P_{n+1} − P_n‖ if ω·n < 0 and the object is solid,
//!     0 otherwise;
//!
//! the pixel's label is the first non-zero d along the ray (a solid
//! object's chord from where the ray enters; a hollow one's crossing of its
//! cavity, from where the ray leaves the wall), 0 when there is none (a
//! miss, a hit on a single surface).
//!
//! The transparency edit's two distances come from the same hits: d1 from
//! where the ray enters the object to where it finally leaves it (all of
//! its crossings), d2 from there to the next surface behind (the
//! background; 0 when there is none).

use glam::Vec3;

use matflow_geom::{Bvh, TriMesh};

/// Every intersection of a ray with `bvh` beyond `tmin`, nearest first:
/// (distance, triangle). Hits closer together than `eps` (a ray through an
/// edge or a vertex meets two triangles at one point) count once.
pub fn all_hits(bvh: &Bvh, origin: Vec3, dir: Vec3, tmin: f32, eps: f32) -> Vec<(f32, u32)> {
    let mut out: Vec<(f32, u32)> = Vec::new();
    let mut t0 = tmin;
    // A ray crosses a closed mesh a bounded number of times; the cap only
    // guards against degenerate input.
    for _ in 0..4096 {
        let Some(h) = bvh.intersect(origin, dir, t0, f32::INFINITY) else {
            break;
        };
        if out.last().is_none_or(|&(t, _)| h.t - t > eps) {
            out.push((h.t, h.prim));
        }
        // Step past this hit, relative to its distance.
        t0 = h.t + eps.max(h.t.abs() * 1e-6);
    }
    out
}

/// Eq. 24 along the ray `origin + t·dir` (`dir` unit) through `mesh`
/// (outward-facing triangles) and its `bvh`.
pub fn refraction_length(mesh: &TriMesh, bvh: &Bvh, origin: Vec3, dir: Vec3, hollow: bool) -> f32 {
    let hits = all_hits(bvh, origin, dir, 0.0, 1e-5);
    for w in hits.windows(2) {
        let (t, prim) = w[0];
        let n = mesh.face_normal(prim as usize);
        let c = dir.dot(n);
        let counts = if hollow { c > 0.0 } else { c < 0.0 };
        if counts {
            let d = w[1].0 - t;
            if d.is_finite() && d > 0.0 {
                return d;
            }
        }
    }
    0.0
}

/// The transparency edit's (d1, d2) along the ray: from the first hit on
/// the object to the last, and from there to the first hit on `behind`
/// (0 without one); (0, 0) when the ray misses the object.
pub fn transparency_distances(
    object: &Bvh,
    behind: Option<&Bvh>,
    origin: Vec3,
    dir: Vec3,
) -> (f32, f32) {
    let hits = all_hits(object, origin, dir, 0.0, 1e-5);
    let (Some(&(t_in, _)), Some(&(t_out, _))) = (hits.first(), hits.last()) else {
        return (0.0, 0.0);
    };
    let d2 = behind
        .and_then(|b| b.intersect(origin, dir, t_out + 1e-5, f32::INFINITY))
        .map_or(0.0, |h| h.t - t_out);
    ((t_out - t_in).max(0.0), d2.max(0.0))
}

/// Normalises labels to [0, 1] by their largest value; returns the labels
/// and the normaliser (what to multiply by to get lengths back; 1 when all
/// are 0).
pub fn normalise(d: &[f32]) -> (Vec<f32>, f32) {
    let m = d
        .iter()
        .copied()
        .filter(|x| x.is_finite())
        .fold(0.0f32, f32::max);
    if !(m > 0.0) {
        return (vec![0.0; d.len()], 1.0);
    }
    (
        d.iter()
            .map(|&x| {
                if x.is_finite() {
                    (x / m).clamp(0.0, 1.0)
                } else {
                    0.0
                }
            })
            .collect(),
        m,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::shapes::sphere;

    /// A solid ball of radius `r` at the origin, and a hollow one: the
    /// outer surface and an inner one of radius `inner` facing the cavity
    /// (its triangles reversed).
    fn ball(r: f32) -> TriMesh {
        sphere(r, 96, 192).mesh
    }
    fn shell(r: f32, inner: f32) -> TriMesh {
        let mut m = ball(r);
        let i = ball(inner);
        let base = m.positions.len() as u32;
        m.positions.extend(i.positions);
        m.indices.extend(
            i.indices
                .iter()
                .map(|t| [t[0] + base, t[2] + base, t[1] + base]),
        );
        m
    }

    #[test]
    fn a_solid_ball_gives_its_chord() {
        let (r, cam) = (1.0f32, Vec3::new(0.0, 0.0, 5.0));
        let m = ball(r);
        let bvh = Bvh::build(&m);
        for b in [0.0f32, 0.3, 0.6, 0.9] {
            let target = Vec3::new(b, 0.0, 0.0);
            let dir = (target - cam).normalize();
            // Distance of the line from the centre.
            let dist = cam.cross(dir).length();
            let want = 2.0 * (r * r - dist * dist).max(0.0).sqrt();
            let got = refraction_length(&m, &bvh, cam, dir, false);
            // The tessellation is within 0.1 % of the sphere.
            assert!((got - want).abs() < 3e-3 * r, "b={b}: {got} vs {want}");
            // As hollow, a single surface has no cavity: 0.
            assert_eq!(refraction_length(&m, &bvh, cam, dir, true), 0.0);
        }
        // A miss gives 0.
        assert_eq!(refraction_length(&m, &bvh, cam, Vec3::Y, false), 0.0);
    }

    #[test]
    fn a_hollow_shell_gives_its_cavity_crossing_and_a_solid_one_its_wall() {
        let (r, inner) = (1.0f32, 0.7f32);
        let m = shell(r, inner);
        let bvh = Bvh::build(&m);
        let cam = Vec3::new(0.0, 0.0, 5.0);
        for b in [0.0f32, 0.4] {
            let dir = (Vec3::new(b, 0.0, 0.0) - cam).normalize();
            let dist = cam.cross(dir).length();
            let chord = |rad: f32| 2.0 * (rad * rad - dist * dist).max(0.0).sqrt();
            // Hollow: from the wall into the cavity, across it.
            let got = refraction_length(&m, &bvh, cam, dir, true);
            assert!(
                (got - chord(inner)).abs() < 3e-3,
                "b={b}: {got} vs {}",
                chord(inner)
            );
            // Solid (the rule for non-hollow objects): the first wall crossing.
            let wall = (chord(r) - chord(inner)) / 2.0;
            let got = refraction_length(&m, &bvh, cam, dir, false);
            assert!((got - wall).abs() < 3e-3, "b={b}: {got} vs {wall}");
        }
        // Past the cavity the ray crosses only the wall: hollow gives 0.
        let dir = (Vec3::new(0.85, 0.0, 0.0) - cam).normalize();
        assert_eq!(refraction_length(&m, &bvh, cam, dir, true), 0.0);
    }

    #[test]
    fn a_cup_seen_from_the_side_gives_its_cavity() {
        let (_, cup, hollow) = crate::shapes::refraction_objects()
            .into_iter()
            .find(|(n, ..)| *n == "cup")
            .unwrap();
        assert!(hollow);
        let bvh = Bvh::build(&cup.mesh);
        let y = 0.4;
        let cam = Vec3::new(0.0, y, 5.0);
        let d = refraction_length(&cup.mesh, &bvh, cam, -Vec3::Z, true);
        // Outer radius 0.32 + 0.05·y, walls 0.03; 64 segments shave 0.12 %.
        let want = 2.0 * (0.32 + 0.05 * y - 0.03);
        assert!((d - want).abs() < 2e-3 * want + 1e-3, "{d} vs {want}");
        // The same cup taken as solid: the wall it enters through.
        let w = refraction_length(&cup.mesh, &bvh, cam, -Vec3::Z, false);
        assert!((w - 0.03).abs() < 2e-3, "{w}");
    }

    #[test]
    fn transparency_distances_span_the_object_and_the_gap_behind() {
        let m = ball(1.0);
        let bvh = Bvh::build(&m);
        let mut wall = TriMesh::default();
        wall.add_box(Vec3::new(-10.0, -10.0, -4.0), Vec3::new(10.0, 10.0, -3.0));
        let wb = Bvh::build(&wall);
        let cam = Vec3::new(0.0, 0.0, 5.0);
        let (d1, d2) = transparency_distances(&bvh, Some(&wb), cam, -Vec3::Z);
        assert!(
            (d1 - 2.0).abs() < 3e-3 && (d2 - 2.0).abs() < 3e-3,
            "{d1} {d2}"
        );
        assert_eq!(transparency_distances(&bvh, None, cam, -Vec3::Z).1, 0.0);
        assert_eq!(
            transparency_distances(&bvh, Some(&wb), cam, Vec3::Y),
            (0.0, 0.0)
        );
    }

    #[test]
    fn the_normaliser_round_trips() {
        let d = [0.0f32, 0.5, 2.0, 1.25, f32::NAN];
        let (n, k) = normalise(&d);
        assert_eq!(k, 2.0);
        for (a, b) in n.iter().zip(&d[..4]) {
            assert!((a * k - b).abs() < 1e-6);
        }
        assert_eq!(n[4], 0.0);
        assert_eq!(normalise(&[0.0, 0.0]), (vec![0.0, 0.0], 1.0));
    }
}

/// What the refraction-length dataset stores per sample about the object,
/// per pixel of `camera` (through the pixel centre): whether the object is
/// seen, its camera-space depth z and outward normal where it is, the eq.
/// 24 label and the transparency edit's d1 and d2 (d2: from where the ray
/// leaves the object to the first surface of `behind`; 0 without one).
#[derive(Clone, Debug, PartialEq)]
pub struct ObjectLabels {
    pub mask: matflow_scene::Image<bool>,
    pub depth: matflow_scene::GrayImage,
    pub normal: matflow_scene::RgbImage,
    pub length: matflow_scene::GrayImage,
    pub d1: matflow_scene::GrayImage,
    pub d2: matflow_scene::GrayImage,
}

/// [`ObjectLabels`] of `object` (camera space, outward-facing) seen by
/// `camera` from the origin down −z.
pub fn object_labels(
    camera: &matflow_scene::Camera,
    object: &TriMesh,
    hollow: bool,
    behind: Option<&TriMesh>,
) -> ObjectLabels {
    use matflow_scene::Image;
    let (w, h) = (camera.width, camera.height);
    let bvh = Bvh::build(object);
    let behind = behind.filter(|m| m.triangle_count() > 0).map(Bvh::build);
    let f = camera.focal();
    let pp = camera.principal_point();
    let per_pixel: Vec<(bool, f32, Vec3, f32, f32, f32)> = (0..w * h)
        .map(|k| {
            let (x, y) = ((k % w) as f32 + 0.5, (k / w) as f32 + 0.5);
            let dir = Vec3::new((x - 0.5 - pp.x) / f, -(y - 0.5 - pp.y) / f, -1.0).normalize();
            let hits = all_hits(&bvh, Vec3::ZERO, dir, 0.0, 1e-5);
            let Some(&(t0, prim)) = hits.first() else {
                return (false, 0.0, Vec3::ZERO, 0.0, 0.0, 0.0);
            };
            let n = object.face_normal(prim as usize);
            let t1 = hits.last().map_or(t0, |&(t1, _)| t1);
            let d2 = behind
                .as_ref()
                .and_then(|b| b.intersect(Vec3::ZERO, dir, t1 + 1e-5, f32::INFINITY))
                .map_or(0.0, |hit| (hit.t - t1).max(0.0));
            let len = refraction_length(object, &bvh, Vec3::ZERO, dir, hollow);
            (true, -(dir * t0).z, n, len, (t1 - t0).max(0.0), d2)
        })
        .collect();
    ObjectLabels {
        mask: Image::from_vec(w, h, per_pixel.iter().map(|p| p.0).collect()),
        depth: Image::from_vec(w, h, per_pixel.iter().map(|p| p.1).collect()),
        normal: Image::from_vec(w, h, per_pixel.iter().map(|p| p.2).collect()),
        length: Image::from_vec(w, h, per_pixel.iter().map(|p| p.3).collect()),
        d1: Image::from_vec(w, h, per_pixel.iter().map(|p| p.4).collect()),
        d2: Image::from_vec(w, h, per_pixel.iter().map(|p| p.5).collect()),
    }
}

#[cfg(test)]
mod label_tests {
    use super::*;
    use crate::shapes::sphere;

    #[test]
    fn labels_of_a_ball_in_view() {
        let n = 32;
        let cam = matflow_scene::Camera::new(n, n);
        let ball = sphere(1.0, 64, 128).transformed(1.0, Vec3::new(0.0, 0.0, -6.0));
        let mut wall = TriMesh::default();
        wall.add_box(Vec3::new(-50.0, -50.0, -11.0), Vec3::new(50.0, 50.0, -10.0));
        let l = object_labels(&cam, &ball.mesh, false, Some(&wall));
        // The ball covers about π·(1/6·f)² pixels.
        let r_px = cam.focal() / 6.0;
        let want = std::f32::consts::PI * r_px * r_px;
        let got = l.mask.data.iter().filter(|&&m| m).count() as f32;
        assert!((got - want).abs() < 0.1 * want, "{got} vs {want}");
        let c = (n / 2) * n + n / 2;
        // Near the centre: depth 5, the normal faces the camera, the chord
        // and d1 are the diameter.
        assert!((l.depth.data[c] - 5.0).abs() < 0.02, "{}", l.depth.data[c]);
        assert!(l.normal.data[c].z > 0.99);
        assert!((l.length.data[c] - 2.0).abs() < 0.02 && (l.d1.data[c] - 2.0).abs() < 0.02);
        // The wall is 3 behind the ball's back (at z = -7).
        assert!((l.d2.data[c] - 3.0).abs() < 0.02, "{}", l.d2.data[c]);
        assert_eq!(l.d2.data[0], 0.0);
        // Off the ball: nothing.
        assert!(!l.mask.data[0] && l.length.data[0] == 0.0 && l.depth.data[0] == 0.0);
        // Every label finite, lengths within the diameter.
        assert!(l
            .length
            .data
            .iter()
            .all(|v| v.is_finite() && (0.0..=2.01).contains(v)));
    }
}
