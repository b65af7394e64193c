//! Object selection: a region grown from one clicked pixel over albedo,
//! depth and surface orientation together, so that one click takes an
//! object rather than a patch of colour.
//!
//! A pixel joins the region from a 4-neighbour already in it when all
//! three hold:
//!
//! - **colour**: its γ-encoded albedo, averaged over its 3×3
//!   neighbourhood (predicted albedo is noisy), is within `albedo_tol` of
//!   the clicked pixel's in every channel (against the seed, not the
//!   neighbour, so a slow gradient cannot carry the region away);
//! - **no occlusion edge**: one of the two points lies within `max_gap`
//!   pixel-widths (`z / f`, f the focal length in pixels) of the other's
//!   tangent plane. Along a surface the distance is 0, across a fold about
//!   a pixel, and where one surface passes in front of another it is the
//!   gap between them (even a grazing floor's plane passes well below the
//!   outline of an object standing on it, but near where it stands; there
//!   the fold rule below decides). In pixel-widths, the rule is the same
//!   at any resolution, and a surface seen at grazing incidence (whose
//!   depth steps by many pixel-widths) still grows;
//! - **no inward fold**: where the surface folds *inwards* (the
//!   two are not each behind the other's tangent plane, by half a pixel's
//!   width between them, as where a box
//!   stands on a floor or a wall meets the floor) by more than
//!   `crease_deg`, the region stops. Outward folds (a box's own edges, a
//!   cup's rim) are crossed: they are the object's, not its support's.
//!
//! Normals are given, or estimated from the depth by one-sided
//! differences on the side with the smaller depth step (so an estimate
//! never straddles an occlusion edge). A predicted normal map, where there
//! is one, separates better (`matflow-bench select` on the reference's
//! photos: the table stops at the pot, the courtyard at the tree). Sky
//! (depth ≤ 0)
//! grows only over sky, by colour alone.

use std::collections::VecDeque;

use glam::Vec3;

use crate::color::linear_to_gamma3;
use crate::{Camera, GrayImage, Image, RgbImage};

/// The photo's step (γ-encoded, between neighbours' 3×3 means) that
/// stops a region in [`grow_object_within_edges`] by default: the `edit`
/// stage's `object_edges` and the studio's click.
pub const PHOTO_EDGE_STEP: f32 = 0.03;

/// How far a region may grow; see the module's rule.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Grow {
    /// Largest per-channel difference of γ-encoded albedo from the seed.
    pub albedo_tol: f32,
    /// Largest distance of a neighbour from the surface continued from
    /// the other (its tangent plane, along its ray), in pixel-widths.
    pub max_gap: f32,
    /// Largest inward fold between neighbours' normals, degrees.
    pub crease_deg: f32,
}

impl Default for Grow {
    fn default() -> Self {
        Grow {
            albedo_tol: 0.2,
            max_gap: 2.0,
            crease_deg: 30.0,
        }
    }
}

/// The region grown from `seed` (column, row) by the rule above; empty
/// when the seed is outside the image. `normals`, when given, are
/// camera-space unit normals of the image's size.
pub fn grow_object(
    albedo: &RgbImage,
    depth: &GrayImage,
    normals: Option<&RgbImage>,
    camera: &Camera,
    seed: (usize, usize),
    g: &Grow,
) -> Image<bool> {
    grow_object_within_edges(albedo, depth, normals, None, camera, seed, g)
}

/// [`grow_object`], and also stopped by the photo's own edges where
/// `edges` is `Some((photo, step))`: a neighbour does not join where the
/// photo (γ-encoded, 3×3 means) steps by more than `step` in any channel
/// between the two, and a pixel on a strong edge (3× `step`) is
/// not entered. Shading varies slowly across a surface, an object's
/// outline is a step, so this holds a region to its object where the
/// predictions are too blurred to (a weak model's albedo and depth run
/// smoothly from an object into what is behind it). `None`, or a photo
/// of another size: the predictions alone, as [`grow_object`].
pub fn grow_object_within_edges(
    albedo: &RgbImage,
    depth: &GrayImage,
    normals: Option<&RgbImage>,
    edges: Option<(&RgbImage, f32)>,
    camera: &Camera,
    seed: (usize, usize),
    g: &Grow,
) -> Image<bool> {
    let (w, h) = (albedo.width, albedo.height);
    let mut m = Image::new(w, h, false);
    if seed.0 >= w || seed.1 >= h || !depth.same_size(albedo) {
        return m;
    }
    let edges = edges
        .filter(|(photo, _)| photo.same_size(albedo))
        .map(|(photo, step)| (smoothed_gamma(photo), gamma(photo), step));
    let estimated;
    let normals = match normals {
        Some(n) if n.same_size(albedo) => n,
        _ => {
            estimated = depth_normals(depth, camera);
            &estimated
        }
    };
    let colour = smoothed_gamma(albedo);
    let seen = |z: f32| z.is_finite() && z > 0.0;
    let c0 = colour.get(seed.0, seed.1);
    let sky = !seen(depth.get(seed.0, seed.1));
    let f = camera.focal().max(1e-6);
    let cos_crease = g.crease_deg.to_radians().cos();
    let predicted = |p: (usize, usize), q: (usize, usize)| -> bool {
        if !((colour.get(q.0, q.1) - c0).abs().max_element() <= g.albedo_tol) {
            return false;
        }
        let (zp, zq) = (depth.get(p.0, p.1), depth.get(q.0, q.1));
        if sky || !seen(zp) || !seen(zq) {
            return sky && !seen(zq);
        }
        let width = zp.min(zq) / f;
        let (np, nq) = (normals.get(p.0, p.1), normals.get(q.0, q.1));
        let pp = camera.backproject(p.0 as f32, p.1 as f32, zp);
        let pq = camera.backproject(q.0 as f32, q.1 as f32, zq);
        // Each point's distance from the other's tangent plane, the nearer
        // of the two: 0 along a surface, about a pixel's width across a
        // fold, the gap between them where one surface passes in front of
        // another.
        let gap = plane_gap(np, pp, pq).min(plane_gap(nq, pq, pp));
        if !(gap <= g.max_gap * width) {
            return false;
        }
        if np.dot(nq) >= cos_crease {
            return true;
        }
        // An outward (convex) fold, the object's own edge: each point lies
        // behind the other's tangent plane. Where a surface passes behind
        // an object's outline near where it stands, one of them does not.
        // Clearly so, by half a pixel's width between them: on an outline
        // seen edge-on both are about 0.
        let (a, b) = (np.dot(pq - pp), nq.dot(pp - pq));
        a <= 0.0 && b <= 0.0 && a + b <= -0.5 * width
    };
    let step_between = |img: &RgbImage, p: (usize, usize), q: (usize, usize)| {
        step(img.get(p.0, p.1), img.get(q.0, q.1))
    };
    let strong = edges
        .as_ref()
        .map(|(smooth, _, step)| strong_edges(smooth, STRONG_EDGE * step));
    let joins = |p: (usize, usize), q: (usize, usize)| -> bool {
        predicted(p, q)
            && edges
                .as_ref()
                .is_none_or(|(smooth, _, step)| step_between(smooth, p, q) <= *step)
            && strong.as_ref().is_none_or(|s| !s.get(q.0, q.1))
    };
    let mut queue = VecDeque::from([seed]);
    m.set(seed.0, seed.1, true);
    while let Some((x, y)) = queue.pop_front() {
        for q in neighbours4(x, y) {
            if q.0 < w && q.1 < h && !m.get(q.0, q.1) && joins((x, y), q) {
                m.set(q.0, q.1, true);
                queue.push_back(q);
            }
        }
    }
    // The 3×3 means spread an outline over three pixels, so the region
    // stops a pixel inside it; the object's own outline pixels join when
    // their own colour is within `step` of the region's (two rings: the
    // second takes the corners).
    for (_, raw, step) in edges.iter().chain(edges.iter()) {
        let mut ring = vec![];
        for y in 0..h {
            for x in 0..w {
                if m.get(x, y) {
                    continue;
                }
                let q = (x, y);
                if neighbours4(x, y).into_iter().any(|p| {
                    p.0 < w
                        && p.1 < h
                        && m.get(p.0, p.1)
                        && predicted(p, q)
                        && step_between(raw, p, q) <= *step
                }) {
                    ring.push(q);
                }
            }
        }
        for (x, y) in ring {
            m.set(x, y, true);
        }
    }
    m
}

/// How many times the photo's `step` makes a strong edge: a pixel whose
/// 3×3-mean photo steps by more than that to a 4-neighbour lies on an
/// outline, and the growth does not enter it (its ring joins afterwards).
/// A soft outline a little off the pixel grid blends the object's colour
/// into the background's *along* a column or row of its ramp by steps far
/// below `step`, and a region that entered the ramp where it was nearly
/// the object's colour walked down it and out (`matflow-bench select` on
/// `pipelines/photos/room.png`: the cylinder's click took the floor with
/// a model whose normals did not fold at the cylinder's foot). Three
/// times `step` leaves texture to the step rule (the courtyard of the
/// reference's jinjya grows as before).
const STRONG_EDGE: f32 = 3.0;

/// Where `smooth` steps by more than `limit` (any channel) between a
/// pixel and one of its 4-neighbours.
fn strong_edges(smooth: &RgbImage, limit: f32) -> Image<bool> {
    let (w, h) = (smooth.width, smooth.height);
    Image::from_fn(w, h, |x, y| {
        let c = smooth.get(x, y);
        neighbours4(x, y)
            .into_iter()
            .any(|(xx, yy)| xx < w && yy < h && !(step(c, smooth.get(xx, yy)) <= limit))
    })
}

/// The largest per-channel difference between two colours.
fn step(a: Vec3, b: Vec3) -> f32 {
    (b - a).abs().max_element()
}

/// A pixel's 4-neighbours; those off the image's left or top edge wrap
/// to `usize::MAX` and fail the caller's `< w`, `< h` test.
fn neighbours4(x: usize, y: usize) -> [(usize, usize); 4] {
    [
        (x.wrapping_sub(1), y),
        (x + 1, y),
        (x, y.wrapping_sub(1)),
        (x, y + 1),
    ]
}

/// The image γ-encoded, per channel.
fn gamma(img: &RgbImage) -> RgbImage {
    img.map(linear_to_gamma3)
}

/// The albedo γ-encoded and averaged over each pixel's 3×3 neighbourhood
/// (clipped at the border): predicted albedo is noisy, and noise in a dark
/// channel grows under the γ curve, so a pixel is compared by its
/// neighbourhood's colour.
fn smoothed_gamma(albedo: &RgbImage) -> RgbImage {
    let (w, h) = (albedo.width, albedo.height);
    let enc = gamma(albedo);
    Image::from_fn(w, h, |x, y| {
        let (mut sum, mut n) = (Vec3::ZERO, 0.0);
        for yy in y.saturating_sub(1)..(y + 2).min(h) {
            for xx in x.saturating_sub(1)..(x + 2).min(w) {
                sum += enc.get(xx, yy);
                n += 1.0;
            }
        }
        sum / n
    })
}

/// How far `q` is from the plane through `p` with normal `n`.
fn plane_gap(n: Vec3, p: Vec3, q: Vec3) -> f32 {
    n.dot(q - p).abs()
}

/// Camera-space unit normals from depth, facing the camera: along each
/// image axis the one-sided difference with the smaller depth step (so no
/// estimate straddles an occlusion edge); +z where depth is missing.
pub fn depth_normals(depth: &GrayImage, camera: &Camera) -> RgbImage {
    let (w, h) = (depth.width, depth.height);
    let seen = |x: usize, y: usize| {
        let z = depth.get(x, y);
        z.is_finite() && z > 0.0
    };
    let point = |x: usize, y: usize| camera.backproject(x as f32, y as f32, depth.get(x, y));
    // The difference along one axis: towards the neighbour whose depth is
    // closer, oriented along +axis.
    let along = |x: usize, y: usize, dx: usize, dy: usize| -> Vec3 {
        let z = depth.get(x, y);
        let fwd = (x + dx < w && y + dy < h && seen(x + dx, y + dy)).then(|| (x + dx, y + dy));
        let back = (x >= dx && y >= dy && seen(x - dx, y - dy)).then(|| (x - dx, y - dy));
        let step = |q: (usize, usize)| (depth.get(q.0, q.1) - z).abs();
        match (back, fwd) {
            (Some(b), Some(f)) if step(b) < step(f) => point(x, y) - point(b.0, b.1),
            (_, Some(f)) => point(f.0, f.1) - point(x, y),
            (Some(b), None) => point(x, y) - point(b.0, b.1),
            (None, None) => Vec3::ZERO,
        }
    };
    Image::from_fn(w, h, |x, y| {
        if !seen(x, y) {
            return Vec3::Z;
        }
        // Image x runs along +x and image y along −y, so (d/dy × d/dx)
        // faces the camera for a surface that does.
        let n = along(x, y, 0, 1)
            .cross(along(x, y, 1, 0))
            .normalize_or(Vec3::Z);
        if n.dot(-point(x, y)) < 0.0 {
            -n
        } else {
            n
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// What each pixel sees of a room: a floor (y = −0.5), a back wall
    /// (z = −8) and a box standing on the floor, all of one albedo.
    #[derive(Clone, Copy, PartialEq, Debug)]
    enum Part {
        Floor,
        Wall,
        Box,
    }

    /// The room ray-cast at n²: depth, true normals, what each pixel sees.
    fn room(n: usize) -> (GrayImage, RgbImage, Image<Part>, Camera) {
        let cam = Camera::new(n, n);
        let (lo, hi) = (Vec3::new(-0.25, -0.5, -5.0), Vec3::new(0.25, -0.2, -4.5));
        let mut depth = GrayImage::new(n, n, 0.0);
        let mut normal = RgbImage::new(n, n, Vec3::Z);
        let mut part = Image::new(n, n, Part::Wall);
        for y in 0..n {
            for x in 0..n {
                // z = −1, so the ray parameter is the depth.
                let d = cam.backproject(x as f32, y as f32, 1.0);
                let mut best = (8.0, Vec3::Z, Part::Wall);
                if d.y < 0.0 && -0.5 / d.y < best.0 {
                    best = (-0.5 / d.y, Vec3::Y, Part::Floor);
                }
                let inv = Vec3::ONE / d;
                let (t0, t1) = (lo * inv, hi * inv);
                let (tmin, tmax) = (t0.min(t1).max_element(), t0.max(t1).min_element());
                if tmax >= tmin && tmin > 0.0 && tmin < best.0 {
                    let p = d * tmin;
                    let nn = if (p.z - hi.z).abs() < 1e-4 {
                        Vec3::Z
                    } else if (p.y - hi.y).abs() < 1e-4 {
                        Vec3::Y
                    } else {
                        Vec3::X * p.x.signum()
                    };
                    best = (tmin, nn, Part::Box);
                }
                depth.set(x, y, best.0);
                normal.set(x, y, best.1);
                part.set(x, y, best.2);
            }
        }
        (depth, normal, part, cam)
    }

    fn wrong(m: &Image<bool>, part: &Image<Part>, want: Part) -> (usize, usize) {
        let bad = m
            .data
            .iter()
            .zip(&part.data)
            .filter(|(&a, &p)| a != (p == want))
            .count();
        (bad, part.data.iter().filter(|&&p| p == want).count())
    }

    /// One click on a box of the floor's colour takes the box and neither
    /// the floor it stands on (an inward fold, and an outline where its
    /// depth nearly meets the floor's) nor the wall behind (a step). A
    /// flood over albedo alone takes everything.
    #[test]
    fn one_click_takes_the_box_not_the_floor_or_the_wall() {
        for n in [64, 128, 256] {
            let (depth, normal, part, cam) = room(n);
            let albedo = RgbImage::new(n, n, Vec3::splat(0.5));
            let seed = (n / 2, n / 2 + (0.12 * n as f32) as usize);
            assert_eq!(part.get(seed.0, seed.1), Part::Box);
            for normals in [Some(&normal), None] {
                let m = grow_object(&albedo, &depth, normals, &cam, seed, &Grow::default());
                let (bad, area) = wrong(&m, &part, Part::Box);
                assert!(
                    bad == 0,
                    "{n}px, given normals {}: {bad} of {area} wrong",
                    normals.is_some()
                );
            }
            let flood = crate::edit::flood_mask(&albedo, seed, 0.2);
            assert!(flood.data.iter().all(|&b| b));
        }
    }

    /// The floor clicked stops at the box and at the wall, and a patch of
    /// another colour on it stays out.
    #[test]
    fn the_floor_stops_at_folds_and_at_another_colour() {
        let n = 96;
        let (depth, normal, part, cam) = room(n);
        let mut albedo = RgbImage::new(n, n, Vec3::splat(0.5));
        let patch = |x: usize, y: usize| x < 6 && y >= n - 6;
        for y in 0..n {
            for x in 0..n {
                if patch(x, y) {
                    albedo.set(x, y, Vec3::new(0.9, 0.1, 0.1));
                }
            }
        }
        for normals in [Some(&normal), None] {
            let m = grow_object(
                &albedo,
                &depth,
                normals,
                &cam,
                (n - 3, n - 3),
                &Grow::default(),
            );
            for y in 0..n {
                for x in 0..n {
                    // The patch's rim is judged by a neighbourhood that
                    // is partly floor: either way is right there.
                    if (5..=6).contains(&x) && y >= n - 7
                        || x <= 6 && y == n - 7
                        || x <= 6 && y == n - 6
                    {
                        continue;
                    }
                    let want = part.get(x, y) == Part::Floor && !patch(x, y);
                    assert_eq!(m.get(x, y), want, "({x}, {y}) {:?}", part.get(x, y));
                }
            }
        }
    }

    #[test]
    fn estimated_normals_face_the_camera_and_match_planes() {
        let (depth, normal, _, cam) = room(64);
        let est = depth_normals(&depth, &cam);
        let mut good = 0;
        for (a, b) in est.data.iter().zip(&normal.data) {
            assert!(a.is_finite() && (a.length() - 1.0).abs() < 1e-3);
            if a.dot(*b) > 0.999 {
                good += 1;
            }
        }
        assert!(good as f32 > 0.95 * est.data.len() as f32, "{good}");
    }

    #[test]
    fn a_seed_outside_or_sky_behaves() {
        let cam = Camera::new(4, 4);
        let albedo = RgbImage::new(4, 4, Vec3::ONE);
        let mut depth = GrayImage::new(4, 4, 2.0);
        let none = grow_object(&albedo, &depth, None, &cam, (9, 0), &Grow::default());
        assert!(!none.data.iter().any(|&b| b));
        for x in 0..4 {
            depth.set(x, 0, 0.0);
        }
        let sky = grow_object(&albedo, &depth, None, &cam, (1, 0), &Grow::default());
        assert_eq!(sky.data.iter().filter(|&&b| b).count(), 4);
        assert!((0..4).all(|x| sky.get(x, 0)));
    }

    /// Predictions too blurred to tell anything apart: one albedo and a
    /// flat depth over an n² image, with its camera.
    fn blurred(n: usize) -> (Camera, RgbImage, GrayImage) {
        (
            Camera::new(n, n),
            RgbImage::new(n, n, Vec3::splat(0.5)),
            GrayImage::new(n, n, 4.0),
        )
    }

    /// The region grown from `seed` over [`blurred`] predictions of n²
    /// within `photo`'s edges at the default step.
    fn within_edges(n: usize, photo: &RgbImage, seed: (usize, usize)) -> Image<bool> {
        let (cam, albedo, depth) = blurred(n);
        let edges = Some((photo, PHOTO_EDGE_STEP));
        grow_object_within_edges(&albedo, &depth, None, edges, &cam, seed, &Grow::default())
    }

    /// Blurred predictions (one albedo, one flat depth) cannot tell a
    /// painted panel from the wall it is on; the photo can. Grown within
    /// the photo's edges, the region is the panel, shading ramp and all;
    /// by the predictions alone it is the whole wall.
    #[test]
    fn the_photo_s_edges_hold_a_region_to_its_object() {
        let n = 48;
        let (cam, albedo, depth) = blurred(n);
        let inside = |x: usize, y: usize| (12..30).contains(&x) && (16..36).contains(&y);
        // The panel a step brighter than the wall; across both, a smooth
        // shading ramp (0.3 over the image) and a little noise.
        let photo = Image::from_fn(n, n, |x, y| {
            let ramp = 0.2 + 0.3 * x as f32 / n as f32;
            let noise = 0.004 * ((x * 7 + y * 13) % 5) as f32;
            Vec3::splat(ramp + noise + if inside(x, y) { 0.25 } else { 0.0 })
        });
        let g = Grow::default();
        let alone = grow_object(&albedo, &depth, None, &cam, (20, 25), &g);
        assert_eq!(alone.data.iter().filter(|&&b| b).count(), n * n);
        let held = within_edges(n, &photo, (20, 25));
        for y in 0..n {
            for x in 0..n {
                assert_eq!(held.get(x, y), inside(x, y), "({x}, {y})");
            }
        }
        // A photo of another size is ignored (the predictions alone).
        let small = RgbImage::new(4, 4, Vec3::ONE);
        let ignored = within_edges(n, &small, (20, 25));
        assert_eq!(ignored.data, alone.data);
    }

    /// A soft outline a little off the pixel grid: along a column of the
    /// ramp between the object and what is behind it the photo drifts
    /// from the one's colour to the other's by steps far below `step`, so
    /// a region entering the ramp where it is nearly the object's colour
    /// could walk down it and out where it is the background's. Pixels on
    /// a strong edge are not entered: the region is the object, its
    /// outline's ring and no more.
    #[test]
    fn a_region_does_not_walk_out_along_a_slanted_outline() {
        let n = 64;
        // The outline's centre moves 8 px across over the height; the
        // ramp from 0.25 (the object, left) to 0.65 is 3 px wide, so its
        // steps across (0.13) stop a region and those down it (0.017)
        // do not.
        let centre = |y: usize| 26.0 + 8.0 * y as f32 / n as f32;
        let cover = |x: usize, y: usize| ((x as f32 + 0.5 - centre(y)) / 3.0 + 0.5).clamp(0.0, 1.0);
        let photo = Image::from_fn(n, n, |x, y| Vec3::splat(0.25 + 0.4 * cover(x, y)));
        let held = within_edges(n, &photo, (8, 32));
        let mut outside = 0;
        for y in 0..n {
            for x in 0..n {
                if held.get(x, y) {
                    assert!(cover(x, y) < 1.0, "({x}, {y}) is the background");
                    outside += (cover(x, y) > 0.5) as usize;
                } else {
                    assert!(cover(x, y) > 0.0, "({x}, {y}) is the object's, left out");
                }
            }
        }
        assert!(outside < n, "{outside} pixels past the outline's middle");
    }
}
