//! The dominant planes of a single view's depth map (floor, ceiling,
//! walls): the first step of completing the geometry beyond the frame
//! (issue 19), where the scene evidently continues.
//!
//! Sequential RANSAC on the back-projected pixels, deterministic (the
//! candidate triples come from a fixed SplitMix64 stream ([`Rng`]) over a fixed pixel
//! grid, so the planes do not depend on threads or machine): the plane with
//! the most inliers is refined by least squares (its normal the
//! eigenvector of the inliers' smallest covariance eigenvalue, in f64),
//! its inliers are removed, and the search repeats while a plane holds at
//! least `min_fraction` of the pixels with geometry. A pixel is an inlier
//! when its distance to the plane is within `tolerance` × its depth
//! (depth noise grows with depth) and its own normal (from its
//! neighbours' points) is within `normal_tolerance_deg` of the plane's, so
//! that the strip of a neighbouring plane along their shared edge does not
//! join.

use glam::{DMat3, DVec3, Vec3};
use matflow_scene::rng::Rng;
use matflow_scene::{Camera, GrayImage};

/// How a plane lies: against the floor's normal when a floor is found
/// (a tilted camera), else the camera's +y.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PlaneKind {
    /// Horizontal, below the camera, facing up.
    Floor,
    /// Horizontal, above the camera, facing down.
    Ceiling,
    /// Vertical.
    Wall,
    /// Anything else (a slanted surface).
    Other,
}

/// The plane n·p + d = 0 (camera space), n of unit length, oriented
/// towards the camera (d > 0: the origin is on the side n points to).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Plane {
    pub n: Vec3,
    pub d: f32,
}

impl Plane {
    /// Signed distance of `p` (positive on the camera's side).
    pub fn distance(&self, p: Vec3) -> f32 {
        self.n.dot(p) + self.d
    }
}

/// One fitted plane and its support.
#[derive(Clone, Debug, PartialEq)]
pub struct PlaneFit {
    pub plane: Plane,
    pub kind: PlaneKind,
    /// Share of the pixels with geometry that lie on it.
    pub fraction: f64,
    /// RMS distance of its inliers, in depth units.
    pub rms: f64,
    /// Whether its inliers reach the left, right, top and bottom image
    /// border (within [`NORMAL_SPAN`] pixels): where the plane evidently
    /// continues out of the frame.
    pub reaches: [bool; 4],
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PlaneParams {
    /// Inlier distance as a share of the pixel's depth.
    pub tolerance: f64,
    /// Smallest share of the pixels with geometry a plane must hold.
    pub min_fraction: f64,
    /// Most planes returned.
    pub max_planes: usize,
    /// Candidate planes tried per search.
    pub iterations: usize,
    /// Pixels sampled on a grid of this step for the search (every pixel
    /// counts for the refinement).
    pub step: usize,
    /// Degrees between a pixel's normal and the plane's for an inlier.
    pub normal_tolerance_deg: f64,
    /// Degrees from horizontal or vertical still classified as such.
    pub kind_tolerance_deg: f64,
}

impl Default for PlaneParams {
    fn default() -> Self {
        PlaneParams {
            tolerance: 0.01,
            min_fraction: 0.08,
            max_planes: 6,
            iterations: 400,
            step: 4,
            normal_tolerance_deg: 25.0,
            kind_tolerance_deg: 15.0,
        }
    }
}

/// Pixels between a pixel and the neighbours its normal is taken from.
pub const NORMAL_SPAN: usize = 3;

/// The unit eigenvector of the smallest eigenvalue of a symmetric
/// positive semi-definite matrix, by inverse iteration on a slightly
/// shifted matrix (a perfect plane has a zero eigenvalue).
fn smallest_eigenvector(c: DMat3, start: DVec3) -> Option<DVec3> {
    let trace = c.x_axis.x + c.y_axis.y + c.z_axis.z;
    if !(trace > 0.0) || !trace.is_finite() {
        return None;
    }
    let shifted = c + DMat3::from_diagonal(DVec3::splat(trace * 1e-9));
    if shifted.determinant().abs() < 1e-300 {
        return None;
    }
    let inv = shifted.inverse();
    let mut v = start.try_normalize()?;
    for _ in 0..60 {
        v = (inv * v).try_normalize()?;
    }
    Some(v)
}

fn classify(n: Vec3, d: f32, world_up: Vec3, tol_deg: f64) -> PlaneKind {
    let up = n.dot(world_up) as f64;
    let horizontal = tol_deg.to_radians().cos();
    let vertical = tol_deg.to_radians().sin();
    // The plane's point nearest the camera is −d·n: below the camera when
    // n points up (a floor faces the camera from below).
    if up >= horizontal && d > 0.0 {
        PlaneKind::Floor
    } else if up <= -horizontal && d > 0.0 {
        PlaneKind::Ceiling
    } else if up.abs() <= vertical {
        PlaneKind::Wall
    } else {
        PlaneKind::Other
    }
}

/// The plane through three points, oriented towards the camera; None when
/// they are (nearly) collinear.
fn through(a: DVec3, b: DVec3, c: DVec3) -> Option<(DVec3, f64)> {
    let n = (b - a).cross(c - a);
    let l = n.length();
    if !(l > 1e-12 * (b - a).length_squared().max(1e-300)) {
        return None;
    }
    let n = n / l;
    let d = -n.dot(a);
    Some(if d < 0.0 { (-n, -d) } else { (n, d) })
}

/// Where two planes of normals `a` and `b` meeting at 30° or more meet:
/// the sine of their angle and the unit direction of their common line,
/// turned towards the camera's +y (for walls, "up"); `None` for planes
/// nearer parallel.
pub(crate) fn corner_up(a: Vec3, b: Vec3) -> Option<(f32, Vec3)> {
    let c = a.cross(b);
    let s = c.length();
    (s >= 0.5).then(|| (s, if c.y < 0.0 { -c / s } else { c / s }))
}

/// The dominant planes of depth map `z` (0 = no geometry), strongest
/// first.
pub fn fit_planes(z: &GrayImage, cam: &Camera, p: &PlaneParams) -> Vec<PlaneFit> {
    fit_planes_resumable(z, cam, p).0
}

/// The view's "up" (camera space, unit): the floor's normal, or the
/// corner of two walls, or the camera's +y ([`fit_planes`]' rule).
pub fn view_up(z: &GrayImage, cam: &Camera, p: &PlaneParams) -> Vec3 {
    fit_planes_resumable(z, cam, p).2
}

/// [`fit_planes`], and the search as it stopped (None when the view has
/// too little geometry), to be continued with a lower threshold
/// ([`PlaneSearch::next`]); its planes are classified against the same
/// "up" (the second value's third part).
pub(crate) fn fit_planes_resumable(
    z: &GrayImage,
    cam: &Camera,
    p: &PlaneParams,
) -> (Vec<PlaneFit>, Option<PlaneSearch>, Vec3) {
    let Some(mut search) = PlaneSearch::new(z, cam, p) else {
        return (Vec::new(), None, Vec3::Y);
    };
    let mut out = Vec::new();
    while out.len() < p.max_planes {
        match search.next(p.min_fraction) {
            Some(f) => out.push(f),
            None => break,
        }
    }
    let up = world_up(&out);
    for f in &mut out {
        f.kind = classify(f.plane.n, f.plane.d, up, p.kind_tolerance_deg);
    }
    (out, Some(search), up)
}

/// "Up" is the camera's +y, or the normal of the strongest plane within
/// 35° of it facing up from below (a floor seen by a tilted camera), else
/// the line where the two strongest planes within 35° of upright that
/// meet at 30° or more meet (a corner of two walls seen by a tilted
/// camera, no floor in view); every plane is classified against it.
fn world_up(out: &[PlaneFit]) -> Vec3 {
    let near = 35f32.to_radians();
    let upright: Vec<Vec3> = out
        .iter()
        .map(|f| f.plane.n)
        .filter(|n| n.y.abs() <= near.sin())
        .collect();
    let corner = upright.iter().enumerate().find_map(|(i, a)| {
        upright[i + 1..]
            .iter()
            .find_map(|b| corner_up(*a, *b).filter(|&(_, up)| up.y >= near.cos()))
            .map(|(_, up)| up)
    });
    out.iter()
        .find(|f| f.plane.n.y as f64 >= 35f64.to_radians().cos() && f.plane.d > 0.0)
        .map(|f| f.plane.n)
        .or(corner)
        .unwrap_or(Vec3::Y)
}

/// The sequential RANSAC of [`fit_planes`], one plane at a time: the
/// state between planes (pixels not yet taken, the random stream, and the
/// best candidate of a search that fell short of its threshold, which a
/// search with a lower one takes up as the same search repeated with that
/// threshold would).
pub(crate) struct PlaneSearch {
    p: PlaneParams,
    width: usize,
    depth: Vec<f32>,
    points: Vec<DVec3>,
    normals: Vec<Option<DVec3>>,
    valid: Vec<usize>,
    remaining: Vec<bool>,
    rng: Rng,
    /// Cosine of `normal_tolerance_deg`.
    cos_tol: f64,
    /// The last search's best candidate when it fell short.
    pending: Option<Option<(DVec3, f64, usize)>>,
}

impl PlaneSearch {
    fn new(z: &GrayImage, cam: &Camera, p: &PlaneParams) -> Option<PlaneSearch> {
        let (w, h) = (z.width, z.height);
        // Every pixel's point once (the search tests each many times).
        let points: Vec<DVec3> = (0..w * h)
            .map(|i| {
                cam.backproject((i % w) as f32, (i / w) as f32, z.data[i])
                    .as_dvec3()
            })
            .collect();
        let point = |i: usize| points[i];
        let valid: Vec<usize> = (0..w * h)
            .filter(|&i| z.data[i] > 0.0 && z.data[i].is_finite())
            .collect();
        if valid.len() < 16 {
            return None;
        }
        let mut remaining: Vec<bool> = vec![false; w * h];
        for &i in &valid {
            remaining[i] = true;
        }
        // Each pixel's normal: the four triangles it makes with the pixels
        // `NORMAL_SPAN` away (right-down, down-left, left-up, up-right; far
        // enough that depth noise tilts them little), averaged
        // when they agree within the normal tolerance; None on a crease or
        // where fewer than two can be formed (so the pixels along the edge of
        // two planes join neither).
        let cos_tol = p.normal_tolerance_deg.to_radians().cos();
        let ok = |x: usize, y: usize| z.data[y * w + x] > 0.0 && z.data[y * w + x].is_finite();
        let normals: Vec<Option<DVec3>> = (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                if !ok(x, y) {
                    return None;
                }
                let at = |dx: i64, dy: i64| -> Option<DVec3> {
                    let (nx, ny) = (x as i64 + dx, y as i64 + dy);
                    if nx < 0 || ny < 0 || nx >= w as i64 || ny >= h as i64 {
                        return None;
                    }
                    let (nx, ny) = (nx as usize, ny as usize);
                    ok(nx, ny).then(|| point(ny * w + nx))
                };
                let c = point(i);
                const S: i64 = NORMAL_SPAN as i64;
                let around = [at(S, 0), at(0, S), at(-S, 0), at(0, -S)];
                let mut tris = vec![];
                for k in 0..4 {
                    if let (Some(a), Some(b)) = (around[k], around[(k + 1) % 4]) {
                        if let Some(n) = (a - c).cross(b - c).try_normalize() {
                            tris.push(n);
                        }
                    }
                }
                if tris.len() < 2 {
                    return None;
                }
                let first = tris[0];
                if tris.iter().any(|n| n.dot(first) < cos_tol) {
                    return None;
                }
                tris.iter().sum::<DVec3>().try_normalize()
            })
            .collect();
        Some(PlaneSearch {
            p: *p,
            width: w,
            depth: z.data.clone(),
            points,
            normals,
            valid,
            remaining,
            rng: Rng(0x5eed_01a7_e5f1_77ed),
            cos_tol,
            pending: None,
        })
    }

    #[inline]
    fn inlier(&self, n: DVec3, d: f64, i: usize) -> bool {
        (n.dot(self.points[i]) + d).abs() <= self.p.tolerance * self.depth[i] as f64
            && self.normals[i].is_some_and(|m| m.dot(n).abs() >= self.cos_tol)
    }

    /// The next plane holding at least `min_fraction` of the pixels with
    /// geometry (its inliers taken out), unclassified; None when none
    /// does.
    pub(crate) fn next(&mut self, min_fraction: f64) -> Option<PlaneFit> {
        let (w, step) = (self.width, self.p.step.max(1));
        let h = self.depth.len() / w;
        let total = self.valid.len() as f64;
        let grid: Vec<usize> = (0..h)
            .step_by(step)
            .flat_map(|y| (0..w).step_by(step).map(move |x| y * w + x))
            .filter(|&i| self.remaining[i])
            .collect();
        if grid.len() < 3 {
            return None;
        }
        let need_grid = min_fraction * total / (step * step) as f64;
        if (grid.len() as f64) < need_grid {
            return None;
        }
        let best = match self.pending.take() {
            Some(b) => b,
            None => {
                let mut best: Option<(DVec3, f64, usize)> = None;
                for _ in 0..self.p.iterations {
                    let a = grid[self.rng.below_mod(grid.len())];
                    let b = grid[self.rng.below_mod(grid.len())];
                    let c = grid[self.rng.below_mod(grid.len())];
                    let Some((n, d)) = through(self.points[a], self.points[b], self.points[c])
                    else {
                        continue;
                    };
                    let count = grid.iter().filter(|&&i| self.inlier(n, d, i)).count();
                    if best.is_none_or(|(_, _, k)| count > k) {
                        best = Some((n, d, count));
                    }
                }
                best
            }
        };
        let Some((mut n, mut d, k)) = best else {
            self.pending = Some(None);
            return None;
        };
        if (k as f64) < need_grid {
            self.pending = Some(best);
            return None;
        }
        // Refine on every remaining pixel, twice (the inliers of the
        // refined plane, then its refinement).
        let members_of = |s: &PlaneSearch, n: DVec3, d: f64| -> Vec<usize> {
            s.valid
                .iter()
                .copied()
                .filter(|&i| s.remaining[i] && s.inlier(n, d, i))
                .collect()
        };
        for _ in 0..2 {
            let members = members_of(self, n, d);
            if members.len() < 3 {
                break;
            }
            let m = members.len() as f64;
            let centroid = members.iter().map(|&i| self.points[i]).sum::<DVec3>() / m;
            let mut c = DMat3::ZERO;
            for &i in &members {
                let q = self.points[i] - centroid;
                c += DMat3::from_cols(q * q.x, q * q.y, q * q.z);
            }
            let Some(v) = smallest_eigenvector(c / m, n) else {
                break;
            };
            let dd = -v.dot(centroid);
            (n, d) = if dd < 0.0 { (-v, -dd) } else { (v, dd) };
        }
        let members = members_of(self, n, d);
        let fraction = members.len() as f64 / total;
        if fraction < min_fraction {
            self.pending = Some(best);
            return None;
        }
        let rms = (members
            .iter()
            .map(|&i| (n.dot(self.points[i]) + d).powi(2))
            .sum::<f64>()
            / members.len() as f64)
            .sqrt();
        let mut reaches = [false; 4];
        for &i in &members {
            let (x, y) = (i % w, i / w);
            // Within the normal span of a border: pixels nearer a border
            // than that can be left out as crease pixels.
            reaches[0] |= x <= NORMAL_SPAN;
            reaches[1] |= x + 1 + NORMAL_SPAN >= w;
            reaches[2] |= y <= NORMAL_SPAN;
            reaches[3] |= y + 1 + NORMAL_SPAN >= h;
            self.remaining[i] = false;
        }
        Some(PlaneFit {
            plane: Plane {
                n: n.as_vec3(),
                d: d as f32,
            },
            kind: PlaneKind::Other,
            fraction,
            rms,
            reaches,
        })
    }

    /// `f` classified against "up" `up` (see [`fit_planes_resumable`]).
    pub(crate) fn classified(&self, mut f: PlaneFit, up: Vec3) -> PlaneFit {
        f.kind = classify(f.plane.n, f.plane.d, up, self.p.kind_tolerance_deg);
        f
    }
}

/// Analytic depth maps for the tests here and in `complete`.
#[cfg(test)]
pub(crate) mod testmaps {
    use glam::Vec3;
    use matflow_scene::{Camera, GrayImage};

    /// Depth of the nearest of `planes` (n·p + d = 0, n towards the
    /// camera) along each pixel's ray; 0 where none is hit in front.
    pub fn render_planes(cam: &Camera, planes: &[(Vec3, f32)]) -> GrayImage {
        let mut z = GrayImage::new(cam.width, cam.height, 0.0);
        for y in 0..cam.height {
            for x in 0..cam.width {
                let dir = cam.backproject(x as f32, y as f32, 1.0); // z = −1
                let mut best = f32::INFINITY;
                for &(n, d) in planes {
                    let t = -d / n.dot(dir);
                    if t > 0.0 && t < best {
                        best = t;
                    }
                }
                if best.is_finite() {
                    z.data[y * cam.width + x] = best;
                }
            }
        }
        z
    }

    /// A `n`×`n` wavy surface around depth 3 with no plane in it.
    pub fn wavy(n: usize) -> GrayImage {
        let mut z = GrayImage::new(n, n, 0.0);
        for y in 0..n {
            for x in 0..n {
                let (u, v) = (x as f32 / 64.0, y as f32 / 64.0);
                z.data[y * n + x] = 3.0
                    + 1.0 * (u * 23.0).sin() * (v * 19.0).cos()
                    + 0.6 * (u * u * 11.0 + v * 9.0).sin();
            }
        }
        z
    }
}

#[cfg(test)]
mod tests {
    use super::testmaps::{render_planes, wavy};
    use super::*;

    fn close(a: &Plane, n: Vec3, d: f32) -> bool {
        a.n.dot(n) > 0.9999 && (a.d - d).abs() < 1e-3 * d.max(1.0)
    }

    #[test]
    fn a_box_room_seen_from_inside_gives_its_five_planes() {
        let cam = Camera::new(96, 72);
        // Floor 0.9 below, ceiling 0.8 above, walls 1 and 1.1 to the
        // sides, back wall 8 ahead: each holds more than 8 % of the view.
        let planes = [
            (Vec3::Y, 0.9),
            (-Vec3::Y, 0.8),
            (Vec3::X, 1.0),
            (-Vec3::X, 1.1),
            (Vec3::Z, 8.0),
        ];
        let z = render_planes(&cam, &planes);
        let fits = fit_planes(&z, &cam, &PlaneParams::default());
        assert_eq!(fits.len(), 5, "{fits:?}");
        for (n, d) in planes {
            let f = fits
                .iter()
                .find(|f| close(&f.plane, n, d))
                .unwrap_or_else(|| panic!("no plane {n} {d}: {fits:?}"));
            let want = if n == Vec3::Y {
                PlaneKind::Floor
            } else if n == -Vec3::Y {
                PlaneKind::Ceiling
            } else {
                PlaneKind::Wall
            };
            assert_eq!(f.kind, want);
            assert!(f.rms < 1e-4, "{f:?}");
        }
        // All but the pixels within NORMAL_SPAN of a crease (13 % of so
        // small a view).
        let total: f64 = fits.iter().map(|f| f.fraction).sum();
        assert!(total > 0.85, "{total}");
        let floor = fits.iter().find(|f| f.kind == PlaneKind::Floor).unwrap();
        // The floor reaches the bottom only (the walls are nearer in the
        // lower corners); the left wall reaches left, top and bottom.
        assert_eq!(floor.reaches, [false, false, false, true]);
        let left = fits.iter().find(|f| f.plane.n.x > 0.99).unwrap();
        assert_eq!(left.reaches, [true, false, true, true]);
        let back = fits.iter().find(|f| f.plane.n.z > 0.99).unwrap();
        assert_eq!(back.reaches, [false, false, false, false]);
    }

    #[test]
    fn one_plane_is_found_once_and_noise_within_tolerance_is_absorbed() {
        let cam = Camera::new(64, 64);
        let n = Vec3::new(0.0, 0.8, 0.6).normalize();
        let mut z = render_planes(&cam, &[(n, 2.0)]);
        // 0.3 % multiplicative noise, deterministic.
        let mut r = Rng(7);
        for v in z.data.iter_mut().filter(|v| **v > 0.0) {
            *v *= 1.0 + 0.003 * ((r.next_u64() % 2001) as f32 / 1000.0 - 1.0);
        }
        let fits = fit_planes(&z, &cam, &PlaneParams::default());
        assert_eq!(fits.len(), 1, "{fits:?}");
        assert!(fits[0].fraction > 0.95, "{fits:?}");
        assert!(fits[0].plane.n.dot(n) > 0.999);
        assert_eq!(fits[0].kind, PlaneKind::Other);
        assert_eq!(fit_planes(&z, &cam, &PlaneParams::default()), fits);
    }

    #[test]
    fn a_scene_without_planes_gives_none() {
        let cam = Camera::new(64, 64);
        // A wavy surface: no plane holds 8 % of it within 1 % of depth.
        let z = wavy(64);
        let fits = fit_planes(&z, &cam, &PlaneParams::default());
        assert!(fits.is_empty(), "{fits:?}");
        // Empty and tiny maps too.
        assert!(fit_planes(&GrayImage::new(64, 64, 0.0), &cam, &PlaneParams::default()).is_empty());
    }

    /// A camera tilted down 12°: walls still come out as walls (the floor
    /// found sets "up").
    #[test]
    fn kinds_follow_the_floor_under_a_tilted_camera() {
        let cam = Camera::new(96, 72);
        let r = glam::Mat3::from_rotation_x(12f32.to_radians());
        let planes = [
            (r * Vec3::Y, 0.9),
            (r * Vec3::X, 1.0),
            (r * -Vec3::X, 1.1),
            (r * Vec3::Z, 8.0),
        ];
        let z = render_planes(&cam, &planes);
        let fits = fit_planes(&z, &cam, &PlaneParams::default());
        assert_eq!(fits.len(), 4, "{fits:?}");
        for f in &fits {
            let want = if f.plane.n.dot(r * Vec3::Y) > 0.99 {
                PlaneKind::Floor
            } else {
                PlaneKind::Wall
            };
            assert_eq!(f.kind, want, "{f:?}");
        }
    }

    /// A camera tilted down 25° at a corner of two walls, no floor in view:
    /// "up" is where the walls meet, so both are walls (against the
    /// camera's +y they lean 25°, past the tolerance).
    #[test]
    fn kinds_follow_a_corner_of_two_walls_under_a_tilted_camera() {
        let cam = Camera::new(96, 72);
        let r = glam::Mat3::from_rotation_x(25f32.to_radians());
        let planes = [
            (r * Vec3::new(1.0, 0.0, 1.0).normalize(), 2.0),
            (r * Vec3::new(-1.0, 0.0, 1.0).normalize(), 2.0),
        ];
        let z = render_planes(&cam, &planes);
        let fits = fit_planes(&z, &cam, &PlaneParams::default());
        assert_eq!(fits.len(), 2, "{fits:?}");
        assert!(fits.iter().all(|f| f.kind == PlaneKind::Wall), "{fits:?}");
        // Without the corner they would not be.
        let one = render_planes(&cam, &planes[..1]);
        let fits = fit_planes(&one, &cam, &PlaneParams::default());
        assert_eq!(fits.len(), 1, "{fits:?}");
        assert_eq!(fits[0].kind, PlaneKind::Other, "{fits:?}");
    }
}
