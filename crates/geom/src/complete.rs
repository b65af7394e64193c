//! Geometry beyond the frame (issue 19): a single view's depth mesh has
//! nothing outside the image, so light that the room's unseen walls,
//! floor and ceiling would block reaches everything. Where the view shows
//! a bounding plane of the scene continuing out of the frame — a floor, a
//! ceiling or a wall that reaches an image border and has (nearly) all
//! the seen geometry on the camera's side — that plane is extended past
//! the frame:
//!
//! 1. its polygon is a square of side 2·`extent`·(largest depth) centred
//!    on the camera's foot point on the plane;
//! 2. clipped to the camera's side of every other bounding plane (those
//!    reaching no border too), so the extended floor, walls and ceiling
//!    meet as a convex room; without a ceiling in view, walls stop at the
//!    highest point seen on them (the room may be open to the sky);
//! 3. with the part inside the camera's frustum (through the outermost
//!    pixel centres, where the depth mesh ends) cut away, so the extension
//!    never covers what the image shows (nor a window's opening): the
//!    rest is split into convex pieces outside the left, right, top and
//!    bottom side of the frustum in turn (disjoint), fanned into
//!    triangles facing the camera's side.
//!
//! Planes inside the scene (a cabinet's front) fail the bounding test and
//! are left alone; a view without such planes is unchanged.

use glam::{Vec2, Vec3};
use matflow_scene::{Camera, GrayImage};

use crate::mesh::TriMesh;
use crate::planes::{fit_planes, Plane, PlaneFit, PlaneKind, PlaneParams};

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CompleteParams {
    pub planes: PlaneParams,
    /// Half-size of an extended plane, in multiples of the largest depth.
    pub extent: f32,
    /// Smallest share of the seen geometry on a plane's camera side (within
    /// the plane tolerance) for it to count as bounding the scene.
    pub support: f64,
}

impl Default for CompleteParams {
    fn default() -> Self {
        CompleteParams {
            planes: PlaneParams::default(),
            extent: 4.0,
            support: 0.98,
        }
    }
}

/// What a completion did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Completion {
    /// The planes extended.
    pub extended: Vec<PlaneFit>,
    /// Planes found but not extended (inside the scene, reaching no
    /// border, or slanted).
    pub kept_in: usize,
    pub triangles: usize,
}

/// One extended plane: its fit, the triangles added beyond the frame
/// (facing the room; no film positions) and the pixels of the view that
/// lie on it (row-major indices), e.g. to give the extension their mean
/// material.
#[derive(Clone, Debug, PartialEq)]
pub struct Extension {
    pub fit: PlaneFit,
    pub mesh: TriMesh,
    pub pixels: Vec<u32>,
}

/// Keeps the part of convex polygon `poly` where `n·p + d ≥ 0`.
fn clip(poly: &[Vec3], n: Vec3, d: f32) -> Vec<Vec3> {
    let mut out = Vec::with_capacity(poly.len() + 2);
    for i in 0..poly.len() {
        let a = poly[i];
        let b = poly[(i + 1) % poly.len()];
        let (da, db) = (n.dot(a) + d, n.dot(b) + d);
        if da >= 0.0 {
            out.push(a);
        }
        if (da >= 0.0) != (db >= 0.0) {
            let t = da / (da - db);
            if t.is_finite() {
                out.push(a + (b - a) * t);
            }
        }
    }
    out
}

/// A hundredth of a pixel: how far outside the outermost pixel centres
/// the extension starts (so no camera ray through a pixel centre grazes
/// its edge).
const FRUSTUM_MARGIN: f32 = 0.01;

/// The frustum's four side planes just outside the outermost pixel
/// centres, oriented inwards (left, right, top, bottom).
fn frustum_sides(cam: &Camera) -> [Vec3; 4] {
    let (w, h) = (cam.width as f32, cam.height as f32);
    let d = |x: f32, y: f32| cam.film_to_dir(Vec2::new(x, y));
    let (lo, hx, hy) = (
        0.5 - FRUSTUM_MARGIN,
        w - 0.5 + FRUSTUM_MARGIN,
        h - 0.5 + FRUSTUM_MARGIN,
    );
    let (tl, tr) = (d(lo, lo), d(hx, lo));
    let (bl, br) = (d(lo, hy), d(hx, hy));
    let centre = d(w * 0.5, h * 0.5);
    [(bl, tl), (tr, br), (tl, tr), (br, bl)].map(|(a, b)| {
        let n = a.cross(b).normalize_or_zero();
        if n.dot(centre) < 0.0 {
            -n
        } else {
            n
        }
    })
}

/// Whether `f` bounds the seen scene: a floor, ceiling or wall with
/// `support` of the seen points on its camera side.
fn bounds_scene(f: &PlaneFit, points: &[(Vec3, f32)], p: &CompleteParams) -> bool {
    if !matches!(
        f.kind,
        PlaneKind::Floor | PlaneKind::Ceiling | PlaneKind::Wall
    ) {
        return false;
    }
    let tol = p.planes.tolerance as f32;
    let front = points
        .iter()
        .filter(|(q, z)| f.plane.distance(*q) >= -tol * z)
        .count();
    front as f64 >= p.support * points.len() as f64
}

/// The extensions of the bounding planes of depth map `z` past the frame,
/// and how many planes were found but not extended.
pub fn extensions(z: &GrayImage, cam: &Camera, p: &CompleteParams) -> (Vec<Extension>, usize) {
    let fits = fit_planes(z, cam, &p.planes);
    let (w, h) = (z.width, z.height);
    let valid: Vec<usize> = (0..w * h)
        .filter(|&i| z.data[i] > 0.0 && z.data[i].is_finite())
        .collect();
    let points: Vec<(Vec3, f32)> = valid
        .iter()
        .map(|&i| {
            (
                cam.backproject((i % w) as f32, (i / w) as f32, z.data[i]),
                z.data[i],
            )
        })
        .collect();
    let mut out = Vec::new();
    let Some(zmax) = points.iter().map(|&(_, z)| z).reduce(f32::max) else {
        return (out, 0);
    };
    let (bounding, inside): (Vec<PlaneFit>, Vec<PlaneFit>) =
        fits.into_iter().partition(|f| bounds_scene(f, &points, p));
    let mut kept_in = inside.len();
    let sides = frustum_sides(cam);
    let r = p.extent * zmax;
    // Without a ceiling in view a wall's height is unknown (the room may
    // be open to the sky): walls then stop at the highest point seen on
    // them, measured along "up" (the floor's normal, else the camera's y).
    let has_ceiling = bounding.iter().any(|f| f.kind == PlaneKind::Ceiling);
    let up = bounding
        .iter()
        .find(|f| f.kind == PlaneKind::Floor)
        .map(|f| f.plane.n)
        .unwrap_or(Vec3::Y);
    let tol = p.planes.tolerance as f32;
    for (k, f) in bounding.iter().enumerate() {
        // Only a plane that runs out of the frame continues beyond it; the
        // others still close the room (they clip the extensions).
        if !f.reaches.iter().any(|&r| r) {
            kept_in += 1;
            continue;
        }
        let Plane { n, d } = f.plane;
        let on: Vec<usize> = (0..points.len())
            .filter(|&j| f.plane.distance(points[j].0).abs() <= tol * points[j].1)
            .collect();
        let foot = -n * d;
        let u = n.any_orthonormal_vector();
        let v = n.cross(u);
        let mut poly = vec![
            foot + (u + v) * r,
            foot + (v - u) * r,
            foot - (u + v) * r,
            foot + (u - v) * r,
        ];
        for (j, o) in bounding.iter().enumerate() {
            if j != k {
                poly = clip(&poly, o.plane.n, o.plane.d);
            }
        }
        if f.kind == PlaneKind::Wall && !has_ceiling {
            if let Some(top) = on.iter().map(|&j| up.dot(points[j].0)).reduce(f32::max) {
                poly = clip(&poly, -up, top);
            }
        }
        let mut mesh = TriMesh::default();
        let mut inner = poly;
        for s in sides {
            if inner.len() < 3 {
                break;
            }
            let outside = clip(&inner, -s, 0.0);
            inner = clip(&inner, s, 0.0);
            if outside.len() < 3 {
                continue;
            }
            let base = mesh.positions.len() as u32;
            mesh.positions.extend_from_slice(&outside);
            for t in 1..outside.len() - 1 {
                let (a, b, c) = (outside[0], outside[t], outside[t + 1]);
                if (b - a).cross(c - a).length_squared() <= 1e-12 * r * r {
                    continue;
                }
                mesh.indices.push(if (b - a).cross(c - a).dot(n) >= 0.0 {
                    [base, base + t as u32, base + t as u32 + 1]
                } else {
                    [base, base + t as u32 + 1, base + t as u32]
                });
            }
        }
        if mesh.indices.is_empty() {
            kept_in += 1;
            continue;
        }
        out.push(Extension {
            fit: f.clone(),
            mesh,
            pixels: on.iter().map(|&j| valid[j] as u32).collect(),
        });
    }
    (out, kept_in)
}

/// Extends the bounding planes of depth map `z` past the frame, appending
/// the triangles to `mesh` (the depth mesh of the same view; film
/// positions of the new vertices: their projection clamped to the image,
/// 0 behind the camera).
pub fn complete_beyond_frame(
    mesh: &mut TriMesh,
    z: &GrayImage,
    cam: &Camera,
    p: &CompleteParams,
) -> Completion {
    let (exts, kept_in) = extensions(z, cam, p);
    let (w, h) = (z.width as f32, z.height as f32);
    let mut done = Completion {
        kept_in,
        ..Completion::default()
    };
    for e in exts {
        let base = mesh.positions.len() as u32;
        mesh.positions.extend_from_slice(&e.mesh.positions);
        if !mesh.film.is_empty() {
            mesh.film.extend(e.mesh.positions.iter().map(|&q| {
                cam.project(q)
                    .map(|f| f.clamp(Vec2::ZERO, Vec2::new(w, h)))
                    .unwrap_or(Vec2::ZERO)
            }));
        }
        mesh.indices
            .extend(e.mesh.indices.iter().map(|t| t.map(|k| k + base)));
        done.triangles += e.mesh.indices.len();
        done.extended.push(e.fit);
    }
    done
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::planes::testmaps::{render_planes, wavy};
    use crate::planes::PlaneKind;

    /// The nearest hit of a ray from the origin on `mesh`'s triangles from
    /// index `from` on (Möller–Trumbore).
    fn hit(mesh: &TriMesh, from: usize, dir: Vec3) -> Option<f32> {
        let mut best: Option<f32> = None;
        for tri in &mesh.indices[from..] {
            let [a, b, c] = tri.map(|k| mesh.positions[k as usize]);
            let (e1, e2) = (b - a, c - a);
            let pv = dir.cross(e2);
            let det = e1.dot(pv);
            if det.abs() < 1e-12 {
                continue;
            }
            let tv = -a;
            let u = tv.dot(pv) / det;
            let qv = tv.cross(e1);
            let v = dir.dot(qv) / det;
            let t = e2.dot(qv) / det;
            if u >= -1e-6 && v >= -1e-6 && u + v <= 1.0 + 1e-6 && t > 1e-6 {
                best = Some(best.map_or(t, |b: f32| b.min(t)));
            }
        }
        best
    }

    const ROOM: [(Vec3, f32); 5] = [
        (Vec3::Y, 0.9),
        (Vec3::NEG_Y, 0.8),
        (Vec3::X, 1.0),
        (Vec3::NEG_X, 1.1),
        (Vec3::Z, 8.0),
    ];

    #[test]
    fn a_box_room_is_closed_around_the_camera_outside_the_view() {
        let cam = Camera::new(96, 72);
        let z = render_planes(&cam, &ROOM);
        let mut mesh = TriMesh::default();
        let c = complete_beyond_frame(&mut mesh, &z, &cam, &CompleteParams::default());
        // The floor, the ceiling and both side walls reach borders; the
        // back wall reaches none.
        assert_eq!(c.extended.len(), 4, "{c:?}");
        assert!(c.extended.iter().all(|f| f.kind != PlaneKind::Other));
        assert_eq!(mesh.triangle_count(), c.triangles);
        // Nothing added is inside the view, and everything lies inside the
        // room (on the camera's side of every wall).
        let sides = frustum_sides(&cam);
        for tri in &mesh.indices {
            let cen = tri.map(|k| mesh.positions[k as usize]).iter().sum::<Vec3>() / 3.0;
            assert!(sides.iter().any(|s| s.dot(cen) < 1e-4), "{cen} is in view");
            for (n, d) in ROOM {
                assert!(n.dot(cen) + d > -1e-3, "{cen} outside the room");
            }
            // Facing the room.
            let [a, b, c2] = tri.map(|k| mesh.positions[k as usize]);
            let fnrm = (b - a).cross(c2 - a);
            assert!(ROOM
                .iter()
                .any(|(n, d)| (n.dot(cen) + d).abs() < 1e-3 && fnrm.dot(*n) > 0.0));
        }
        // Rays out of the view find the room's walls where they are.
        let cases = [
            (Vec3::new(-1.0, 0.0, 0.0), 1.0), // left wall
            (Vec3::new(1.0, 0.0, 0.0), 1.1),  // right wall
            (Vec3::new(0.0, -1.0, 0.0), 0.9), // floor under the camera
            (Vec3::new(0.0, 1.0, 0.0), 0.8),  // ceiling over it
            (Vec3::new(0.0, -1.0, 1.0).normalize(), 0.9 * 2f32.sqrt()), // floor behind
        ];
        for (dir, want) in cases {
            let t = hit(&mesh, 0, dir).unwrap_or_else(|| panic!("nothing towards {dir}"));
            assert!((t - want).abs() < 1e-3, "{dir}: {t} vs {want}");
        }
        // Straight back, out of the room's seen planes: open (no wall was
        // seen there).
        assert!(hit(&mesh, 0, Vec3::Z).is_none());
        // No ray through a pixel centre meets the extension.
        for y in (0..72).step_by(7) {
            for x in (0..96).step_by(7) {
                let dir = cam.backproject(x as f32, y as f32, 1.0).normalize();
                assert!(hit(&mesh, 0, dir).is_none(), "pixel {x},{y}");
            }
        }
    }

    #[test]
    fn a_plane_inside_the_scene_is_not_extended_the_wall_behind_it_is() {
        let cam = Camera::new(96, 72);
        // A cabinet front at z = 3 over the left half, the back wall at 8
        // on the right: the front has the back wall behind it.
        let mut z = render_planes(&cam, &[(Vec3::Z, 8.0)]);
        for y in 0..72 {
            for x in 0..48 {
                z.data[y * 96 + x] = 3.0;
            }
        }
        let mut mesh = TriMesh::default();
        let c = complete_beyond_frame(&mut mesh, &z, &cam, &CompleteParams::default());
        assert_eq!(c.kept_in, 1, "{c:?}");
        assert_eq!(c.extended.len(), 1, "{c:?}");
        assert!((c.extended[0].plane.d - 8.0).abs() < 1e-3);
    }

    #[test]
    fn a_view_without_planes_is_unchanged() {
        let cam = Camera::new(64, 64);
        let z = wavy(64);
        let mut mesh = TriMesh::default();
        mesh.add_box(Vec3::splat(-1.0), Vec3::splat(1.0));
        let before = mesh.clone();
        let c = complete_beyond_frame(&mut mesh, &z, &cam, &CompleteParams::default());
        assert_eq!(c.triangles, 0);
        assert_eq!(mesh, before);
        // Nor is an empty one.
        let c = complete_beyond_frame(
            &mut mesh,
            &GrayImage::new(64, 64, 0.0),
            &cam,
            &CompleteParams::default(),
        );
        assert_eq!((c.triangles, mesh == before), (0, true));
    }
}
