//! Mesh from a depth map (paper §3.1, Fig. 3), following the reference
//! implementation step by step so its meshes and ours agree:
//!
//! 1. **Back-projection.** Pixel (row i, column j) with camera-space depth
//!    z > 0 becomes the vertex ((j − cx)·z/f, −(i − cy)·z/f, −z); z = 0 means
//!    "no geometry" (masked).
//! 2. **Boundary detection.** For every interior pixel, the four fan
//!    triangles to its 4-neighbours are tested: a triangle is nearly parallel
//!    to the view ray when asin(|n̂·ĉ|) < τ (ĉ the unit ray to its centroid).
//!    If so and the pixel is nearer than the triangle's other vertices, the
//!    pixel points at the deepest such neighbour.
//! 3. **Depth replacement.** Boundary pixels follow their pointers (always
//!    to strictly deeper pixels) and take the depth where the chain ends: the
//!    near side of a depth discontinuity moves to the background depth.
//!    That is the reference's rule ([`Silhouettes::Reference`]); it removes
//!    the pixels a predicted depth map smears between two depths, but it
//!    also shrinks every object by a pixel and a half where the depth is
//!    sharp. matflow's default ([`Silhouettes::Kept`]) moves only the
//!    pixels *between* two depths (steep towards a nearer neighbour and a
//!    deeper one); the foreground's own edge pixel keeps its depth and its
//!    vertex moves half a pixel towards each deeper neighbour, so the
//!    silhouette lies on the pixel border, midway between the last pixel
//!    centre of the object and the first of what is behind it. A surface
//!    seen at a grazing angle (distant ground: a long run of steep
//!    segments whose 1/z steps alike, as a plane's do) is no boundary at
//!    all under `Kept`: its pixels keep their depth and its triangles are
//!    kept, where the reference cuts it into a staircase of camera-facing
//!    steps that shade and shadow as walls.
//! 4. **Triangulation** of every pixel quad along the "/" diagonal; a
//!    triangle whose angle to the view ray is still ≤ τ joins two objects.
//! 5. **Boundary duplication.** Such a triangle is rebuilt behind the
//!    foreground: its nearest vertex is replaced by a copy on the same pixel
//!    ray at the triangle's largest depth (one copy per pixel, reused); if
//!    still too steep, the second-nearest vertex too; if still too steep the
//!    triangle is dropped. The foreground keeps its own vertices, and the
//!    background continues behind it, so no hole (white border) opens at
//!    object silhouettes.
//! 6. **Backs** (matflow's, [`Silhouettes::Kept`] only; the reference's
//!    mesh is a shell). A shell lets light through where a solid's unseen
//!    back half should stop it: a cylinder casts the shadow of a sheet.
//!    Each row's runs without a jump whose ends are silhouettes get a back,
//!    the front mirrored about the surface through the ends
//!    ([`mirrored_backs`]), with vertices of its own so the front's
//!    shading normals are unchanged. A plane is its own mirror and gets
//!    none. Down each column, a solid standing on the ground whose top
//!    the view looks down on gets the prism under its top's far edge
//!    ([`extruded_backs`]): a box seen face-on, which its rows cannot
//!    tell from a plane. The deeper of the two backs is taken.
//!
//! The reference code uses τ = 6° (the paper says 3°); 6° is the default.

use glam::{DVec3, Vec2, Vec3};
use matflow_scene::{Camera, GrayImage};
use rayon::prelude::*;

use crate::mesh::TriMesh;

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MeshParams {
    /// Angle threshold τ in degrees.
    pub min_angle_deg: f64,
    /// What happens to the near side of a depth discontinuity.
    pub silhouettes: Silhouettes,
}

impl Default for MeshParams {
    fn default() -> Self {
        MeshParams {
            min_angle_deg: 6.0,
            silhouettes: Silhouettes::default(),
        }
    }
}

impl MeshParams {
    /// The reference implementation's mesh at angle τ (its meshes, counts
    /// and renders, vertex for vertex).
    pub fn reference(min_angle_deg: f64) -> Self {
        MeshParams {
            min_angle_deg,
            silhouettes: Silhouettes::Reference,
        }
    }
}

/// The near side of a depth discontinuity (step 3 of the module's doc).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum Silhouettes {
    /// Every boundary pixel takes the background's depth (the reference's
    /// rule): objects lose a pixel and a half at their silhouettes.
    Reference,
    /// Only pixels between two depths take the background's depth; an
    /// object's own edge keeps its depth and reaches the pixel border,
    /// and a solid's unseen back is its front mirrored about its
    /// silhouettes (step 6).
    #[default]
    Kept,
}

impl Silhouettes {
    pub const NAMES: [&'static str; 2] = ["kept", "reference"];

    pub fn name(self) -> &'static str {
        match self {
            Silhouettes::Kept => "kept",
            Silhouettes::Reference => "reference",
        }
    }

    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "kept" => Some(Silhouettes::Kept),
            "reference" => Some(Silhouettes::Reference),
            _ => None,
        }
    }
}

impl std::fmt::Display for Silhouettes {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for Silhouettes {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        Silhouettes::parse(s).ok_or_else(|| format!("`{s}`: expected kept or reference"))
    }
}

/// Statistics of one meshing run (what the steps above did).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct MeshStats {
    pub boundary_pixels: usize,
    /// Boundary pixels that kept their depth (an object's own edge,
    /// [`Silhouettes::Kept`]).
    pub kept_edges: usize,
    pub copies: usize,
    pub emitted_direct: usize,
    pub emitted_one_copy: usize,
    pub emitted_two_copies: usize,
    pub dropped: usize,
    /// Vertices and triangles of the solids' far sides ([`mirrored_backs`]).
    pub back_vertices: usize,
    pub back_triangles: usize,
}

#[derive(Clone, Debug)]
pub struct DepthMesh {
    pub mesh: TriMesh,
    /// Depth after boundary replacement.
    pub depth: GrayImage,
    pub stats: MeshStats,
}

#[derive(Debug, thiserror::Error)]
pub enum MeshError {
    #[error("depth map is {got_w}x{got_h} but the camera is {want_w}x{want_h}")]
    Size {
        got_w: usize,
        got_h: usize,
        want_w: usize,
        want_h: usize,
    },
    #[error("depth map has {count} non-finite or negative value(s) (first at x={x}, y={y})")]
    BadDepth { count: usize, x: usize, y: usize },
    #[error("depth map must be at least 2x2")]
    TooSmall,
}

struct Grid<'a> {
    z: &'a [f32],
    w: usize,
    f: f64,
    cx: f64,
    cy: f64,
}

impl Grid<'_> {
    #[inline]
    fn point(&self, i: usize, j: usize, z: f64) -> DVec3 {
        DVec3::new(
            (j as f64 - self.cx) * z / self.f,
            -(i as f64 - self.cy) * z / self.f,
            -z,
        )
    }
    /// The point at depth z on the ray through film offset (di, dj)
    /// pixels from pixel (i, j)'s centre.
    #[inline]
    fn point_off(&self, i: usize, j: usize, di: f64, dj: f64, z: f64) -> DVec3 {
        DVec3::new(
            (j as f64 + dj - self.cx) * z / self.f,
            -(i as f64 + di - self.cy) * z / self.f,
            -z,
        )
    }
    #[inline]
    fn p(&self, i: usize, j: usize) -> DVec3 {
        self.point(i, j, self.z[i * self.w + j] as f64)
    }
    #[inline]
    fn zz(&self, i: usize, j: usize) -> f32 {
        self.z[i * self.w + j]
    }
}

/// An object's own edge: pixel (i, j), a boundary pixel with all four
/// neighbours, is steep (its segment within τ of the view ray) only
/// towards deeper neighbours. Returns its vertex's film offset (half a
/// pixel towards each of them, per axis at most half a pixel), or None when
/// it is steep towards a nearer neighbour too (a pixel between two depths).
fn foreground_edge(g: &Grid, i: usize, j: usize, tau: f64) -> Option<Vec2> {
    let zc = g.zz(i, j);
    let mut d = Vec2::ZERO;
    for (di, dj) in [(1isize, 0isize), (-1, 0), (0, 1), (0, -1)] {
        let (a, b) = ((i as isize + di) as usize, (j as isize + dj) as usize);
        if !seg_steep(g, (i, j), (a, b), tau) {
            continue;
        }
        if g.zz(a, b) > zc {
            d += Vec2::new(dj as f32, di as f32) * 0.5;
        } else {
            return None;
        }
    }
    Some(d.clamp(Vec2::splat(-0.5), Vec2::splat(0.5)))
}

/// Pixels of a surface seen at a grazing angle: runs of at least
/// GRAZING_RUN steep segments along a row or a column whose inverse depth
/// changes by the same step (a plane's 1/z is affine in the pixel
/// coordinates; a depth discontinuity's step differs from the surface's
/// beside it, and a predicted map's smeared edge is a few pixels long).
fn grazing_planes(g: &Grid, h: usize, tau: f64) -> Vec<bool> {
    const GRAZING_RUN: usize = 8;
    const SAME_STEP: f64 = 0.25;
    let w = g.w;
    let mut out = vec![false; w * h];
    // (start pixel, step between pixels, count) of every row and column.
    let lines = (0..h)
        .map(|i| (i * w, 1usize, w))
        .chain((0..w).map(|j| (j, w, h)));
    for (start, step, count) in lines {
        let at = |t: usize| start + t * step;
        let px = |t: usize| (at(t) / w, at(t) % w);
        let valid = |t: usize| g.z[at(t)] > 0.0;
        // Segment t joins pixels t and t + 1: its 1/z step when steep.
        let steps: Vec<Option<f64>> = (0..count.saturating_sub(1))
            .map(|t| {
                (valid(t) && valid(t + 1) && seg_steep(g, px(t), px(t + 1), tau))
                    .then(|| 1.0 / g.z[at(t + 1)] as f64 - 1.0 / g.z[at(t)] as f64)
            })
            .collect();
        let flat = |t: usize| steps[t].is_none() && valid(t) && valid(t + 1);
        let mut t = 0;
        while t < steps.len() {
            let Some(first) = steps[t] else {
                t += 1;
                continue;
            };
            // The run of steep segments stepping alike from segment t.
            let (mut e, mut last) = (t, first);
            while let Some(d) = steps.get(e + 1).copied().flatten() {
                if (d - last).abs() > SAME_STEP * d.abs().max(last.abs()) {
                    break;
                }
                last = d;
                e += 1;
            }
            if e + 1 - t >= GRAZING_RUN {
                // Pixels t..=e+1, and one more at either end where the
                // surface goes on less steeply (not across a jump).
                let lo = if t > 0 && flat(t - 1) { t - 1 } else { t };
                let hi = if e + 1 < steps.len() && flat(e + 1) {
                    e + 2
                } else {
                    e + 1
                };
                for q in lo..=hi {
                    out[at(q)] = true;
                }
            }
            t = e + 1;
        }
    }
    out
}

/// The far side of every convex solid the view shows, as a depth per
/// pixel (0: no back; the pixel's own surface is all there is).
///
/// A depth mesh is a shell: it has the surfaces the camera sees and
/// nothing behind them, so light that should cross an object's unseen back
/// half passes (a cylinder casts the shadow of a sheet). Along each row, a
/// run of pixels with no jump inside it whose ends meet something deeper
/// (or the sky) is taken as the front of a solid whose silhouettes are at
/// its ends. Its back is the front mirrored about the surface through the
/// ends (1/z interpolated, so a plane is its own mirror): back =
/// 2·z_mid − z_front where that lies behind the front, never deeper than
/// what is seen beyond the ends. A cylinder or a sphere gets its back
/// half, a box seen corner-on its hidden corner; a plane (a wall between
/// two windows, the floor) and a concave run (a room's corner) get
/// nothing. The run's end pixels lie a little nearer than the true
/// silhouettes (the pixels on a curved flank seen edge-on are cut as
/// steep), so backs come out thinner than the truth, not thicker.
/// With one end at the frame, the run is mirrored about the depth of its
/// one silhouette, but only when its nearest point is in view and the
/// front turns away before the frame (an object cut past its middle); a
/// surface still coming nearer at the frame may go on past it (a wall,
/// the ground). A run that meets something nearer at either end is partly
/// hidden, so its silhouette is unknown: no back.
fn mirrored_backs(g: &Grid, h: usize, tau: f64, on_plane: &dyn Fn(usize) -> bool) -> Vec<f32> {
    // A frame's end pixel this share deeper than the run's nearest pixel
    // has turned away.
    const TURN_TOLERANCE: f64 = 0.001;
    let w = g.w;
    let mut back = vec![0.0f32; w * h];
    for i in 0..h {
        let row = i * w;
        for (a, b) in runs(g, Line::Row(i), tau, on_plane) {
            let left = run_end(g, Line::Row(i), a, a.checked_sub(1));
            let right = run_end(g, Line::Row(i), b, (b + 1 < w).then_some(b + 1));
            if b >= a + 2 {
                let (za, zb) = (g.z[row + a] as f64, g.z[row + b] as f64);
                let (ia, ib) = (1.0 / za, 1.0 / zb);
                let through_ends = |j: usize| {
                    let t = (j - a) as f64 / (b - a) as f64;
                    1.0 / (ia + (ib - ia) * t)
                };
                // The surface the front is mirrored about: through both
                // silhouettes. With one end at the frame, the depth of the
                // one silhouette seen (a solid is widest at its
                // silhouette), but only where the run's nearest point is
                // in view, the front turning away again before the frame
                // (a cylinder cut past its axis). A surface still coming
                // nearer at the frame (a wall, the ground, a panel seen
                // obliquely) may go on past it: no back.
                let turns_before_frame = |frame_end: usize, silhouette: usize| {
                    // The run's nearest pixel.
                    let (jmin, zmin) = (a..=b)
                        .map(|j| (j, g.z[row + j] as f64))
                        .fold((a, f64::INFINITY), |m, p| if p.1 < m.1 { p } else { m });
                    jmin != silhouette
                        && jmin.abs_diff(frame_end) >= 2
                        && g.z[row + frame_end] as f64 > zmin * (1.0 + TURN_TOLERANCE)
                };
                // Some(None): about the surface through the ends;
                // Some(Some(z)): about depth z.
                let mirror: Option<Option<f64>> = match (left, right) {
                    (RunEnd::Beyond(_), RunEnd::Beyond(_)) => Some(None),
                    (RunEnd::Beyond(_), RunEnd::Frame) if turns_before_frame(b, a) => {
                        Some(Some(za))
                    }
                    (RunEnd::Frame, RunEnd::Beyond(_)) if turns_before_frame(a, b) => {
                        Some(Some(zb))
                    }
                    _ => None,
                };
                if let Some(fixed) = mirror {
                    // The far limit: what is seen beyond the ends.
                    let far = |e: RunEnd| match e {
                        RunEnd::Beyond(z) => 1.0 / z,
                        _ => 0.0,
                    };
                    let (fa, fb) = (far(left), far(right));
                    for j in a + 1..b {
                        let t = (j - a) as f64 / (b - a) as f64;
                        let front = g.z[row + j] as f64;
                        let mut z = 2.0 * fixed.unwrap_or_else(|| through_ends(j)) - front;
                        let limit_inv = fa + (fb - fa) * t;
                        if limit_inv > 0.0 {
                            z = z.min(1.0 / limit_inv);
                        }
                        if z > front * (1.0 + BACK_MIN_THICKNESS) && z.is_finite() {
                            back[row + j] = z as f32;
                        }
                    }
                }
            }
        }
    }
    back
}

/// The runs `(first, last)` of `line`'s pixels with geometry and no jump
/// between neighbours (a segment within τ of the view ray that is not on
/// a grazing plane), in order.
fn runs(g: &Grid, line: Line, tau: f64, on_plane: &dyn Fn(usize) -> bool) -> Vec<(usize, usize)> {
    let len = line.len(g);
    let index = |k: usize| {
        let (i, j) = line.pix(k);
        i * g.w + j
    };
    let valid = |k: usize| g.z[index(k)] > 0.0;
    let jump = |k: usize| {
        seg_steep(g, line.pix(k), line.pix(k + 1), tau)
            && !(on_plane(index(k)) && on_plane(index(k + 1)))
    };
    let mut out = Vec::new();
    let mut a = 0;
    while a < len {
        if !valid(a) {
            a += 1;
            continue;
        }
        let mut b = a;
        while b + 1 < len && valid(b + 1) && !jump(b) {
            b += 1;
        }
        out.push((a, b));
        a = b + 1;
    }
    out
}

/// Backs of solids that stand on the ground, from the columns: where the
/// view looks down on a solid's top, the top's far edge is its back.
///
/// [`mirrored_backs`] finds a solid from its silhouettes left and right,
/// so a box seen face-on (a plane between them) gets none and casts the
/// shadow of a sheet. Down a column, a run without a jump whose top end
/// is a silhouette (something deeper, or the sky, above it) and whose
/// bottom goes on into the ground (to the frame, or hidden by something
/// nearer: no silhouette under it) is a solid standing on the ground,
/// its top seen up to its far edge, if some of it is upright
/// ([`UPRIGHT_COS`]). It is taken as the prism under that
/// edge: each pixel's back is where its ray reaches the upright plane
/// through the top silhouette that faces the camera (its normal the
/// silhouette's ray, level), or the ground (level with its front's foot:
/// the end of the first upright stretch down the run),
/// whichever comes first, never deeper than what is seen above the
/// silhouette; the ground before its foot gets none. Down from
/// the silhouette the run must come nearer or stay ([`NEARING_SLACK`]):
/// a surface that goes deeper again is open beneath (a table's top, then
/// the floor under it). A box or a standing cylinder seen from above
/// gets its far side; a wall facing the camera lies in that plane and
/// gets nothing; a solid seen from below its top (no top in view) gets
/// nothing either. A column of a table's leg runs from the top's far
/// edge to the ground too: backs far deeper than the row run they lie in
/// is wide ([`MAX_DEPTH_PER_WIDTH`]) are taken as such and dropped.
fn extruded_backs(
    g: &Grid,
    h: usize,
    tau: f64,
    on_plane: &dyn Fn(usize) -> bool,
    up: DVec3,
) -> Vec<f32> {
    let w = g.w;
    let mut back = vec![0.0f32; w * h];
    let up = up.normalize_or_zero();
    if up == DVec3::ZERO {
        return back;
    }
    for j in 0..w {
        for (a, b) in runs(g, Line::Col(j), tau, on_plane) {
            // A silhouette on top, the ground going on below.
            let RunEnd::Beyond(z_above) = run_end(g, Line::Col(j), a, a.checked_sub(1)) else {
                continue;
            };
            let bottom = run_end(g, Line::Col(j), b, (b + 1 < h).then_some(b + 1));
            if !matches!(bottom, RunEnd::Frame | RunEnd::Hidden) {
                continue;
            }
            // Down from its top's far edge, a solid standing on the
            // ground comes nearer or stays (its top, its front, the
            // ground before it); a surface that goes deeper again is open
            // beneath (the floor under a table seen below its top).
            if !(a..b).all(|i| g.z[(i + 1) * w + j] <= g.z[i * w + j] * NEARING_SLACK) {
                continue;
            }
            // Its front: the first upright stretch down the run (gaps of
            // UPRIGHT_GAP segments bridged), standing on the ground at its
            // foot; the ground alone, however uneven, is no solid.
            let upright = |i: usize| {
                let s = g.p(i + 1, j) - g.p(i, j);
                s.dot(up).abs() > UPRIGHT_COS * s.length()
            };
            let Some(first) = (a..b).find(|&i| upright(i)) else {
                continue;
            };
            let mut last = first;
            for k in first + 1..b {
                if upright(k) {
                    last = k;
                } else if k - last > UPRIGHT_GAP {
                    break;
                }
            }
            let foot = last + 1;
            let ps = g.p(a, j);
            let n = (ps - up * up.dot(ps)).normalize_or_zero();
            // The ground: the front's foot.
            let ground = up.dot(g.p(foot, j));
            if n == DVec3::ZERO || ground >= up.dot(ps) {
                continue;
            }
            let far = n.dot(ps);
            let above = if z_above.is_finite() && a > 0 {
                n.dot(g.point(a - 1, j, z_above))
            } else {
                f64::INFINITY
            };
            for i in a + 1..=foot {
                let front = g.z[i * w + j] as f64;
                // The ray at depth 1.
                let d = g.point(i, j, 1.0);
                let nd = n.dot(d);
                if !(nd > 0.0) {
                    continue;
                }
                let mut t = far.min(above) / nd;
                let ud = up.dot(d);
                if ud < 0.0 {
                    t = t.min(ground / ud);
                }
                if t > front * (1.0 + BACK_MIN_THICKNESS) && t.is_finite() {
                    back[i * w + j] = t as f32;
                }
            }
        }
    }
    // A leg, a pole: backs deeper than MAX_DEPTH_PER_WIDTH times the
    // width of the row run they lie in.
    for i in 0..h {
        let row = i * w;
        let mut a = 0;
        while a < w {
            if back[row + a] <= 0.0 {
                a += 1;
                continue;
            }
            let mut b = a;
            while b + 1 < w && back[row + b + 1] > 0.0 {
                b += 1;
            }
            let (mut width, mut deepest) = (0.0f64, 0.0f64);
            for j in a..=b {
                let front = g.z[row + j] as f64;
                width += front / g.f;
                deepest = deepest.max(back[row + j] as f64 - front);
            }
            if deepest > MAX_DEPTH_PER_WIDTH * width {
                back[row + a..=row + b].fill(0.0);
            }
            a = b + 1;
        }
    }
    back
}

/// How much deeper a pixel of an [`extruded_backs`] column may be than
/// the one above it (noise in a predicted depth map).
const NEARING_SLACK: f32 = 1.005;

/// A segment of an [`extruded_backs`] column this close to "up" (cos 45°)
/// is upright: a solid's front, not the ground.
const UPRIGHT_COS: f64 = std::f64::consts::FRAC_1_SQRT_2;

/// How many segments that are not upright an [`extruded_backs`] front
/// may have in a row (a predicted depth map's noise).
const UPRIGHT_GAP: usize = 2;

/// Backs thinner than this share of the depth are no solid worth one.
const BACK_MIN_THICKNESS: f64 = 0.01;

/// An [`extruded_backs`] prism at most this many times as deep as it is
/// wide.
const MAX_DEPTH_PER_WIDTH: f64 = 2.0;

/// What the end pixel of a row's run meets past it.
#[derive(Clone, Copy, Debug)]
enum RunEnd {
    /// Something deeper (at this depth) or the sky (infinity): the end
    /// pixel is a silhouette.
    Beyond(f64),
    /// The frame's edge: the surface may go on.
    Frame,
    /// Something nearer: the run is partly hidden.
    Hidden,
}

/// A row or a column of pixels.
#[derive(Clone, Copy, Debug)]
enum Line {
    Row(usize),
    Col(usize),
}

impl Line {
    /// Pixel (row, column) of the line's `k`-th pixel.
    #[inline]
    fn pix(self, k: usize) -> (usize, usize) {
        match self {
            Line::Row(i) => (i, k),
            Line::Col(j) => (k, j),
        }
    }
    /// How many pixels it has.
    fn len(self, g: &Grid) -> usize {
        match self {
            Line::Row(_) => g.w,
            Line::Col(_) => g.z.len() / g.w,
        }
    }
}

/// What run end pixel `end` of `line` meets past it, `next` its
/// neighbour outside the run (None at the frame). Beyond a silhouette
/// lies the solid's own flank seen edge-on (pixels still steeper and
/// deeper), then what is behind it: the depth beyond is where that chain
/// of deeper pixels ends.
fn run_end(g: &Grid, line: Line, end: usize, next: Option<usize>) -> RunEnd {
    let Some(mut n) = next else {
        return RunEnd::Frame;
    };
    let z = |k: usize| {
        let (i, j) = line.pix(k);
        g.zz(i, j)
    };
    if z(n) <= 0.0 {
        return RunEnd::Beyond(f64::INFINITY);
    }
    if z(n) <= z(end) {
        return RunEnd::Hidden;
    }
    let len = line.len(g);
    let outward = n > end;
    let step = |k: usize| {
        if outward {
            k.checked_add(1).filter(|&m| m < len)
        } else {
            k.checked_sub(1)
        }
    };
    while let Some(m) = step(n) {
        if z(m) <= 0.0 {
            return RunEnd::Beyond(f64::INFINITY);
        }
        if !(z(m) > z(n) && seg_steep(g, line.pix(n.min(m)), line.pix(n.max(m)), FLANK_STEEP_DEG)) {
            break;
        }
        n = m;
    }
    RunEnd::Beyond(z(n) as f64)
}

/// Segments steeper than this (degrees to the view ray) past a silhouette
/// are still the solid's flank or the jump behind it.
const FLANK_STEEP_DEG: f64 = 30.0;

/// Whether the segment between pixels a and b lies within τ of the view
/// ray through its middle.
fn seg_steep(g: &Grid, a: (usize, usize), b: (usize, usize), tau: f64) -> bool {
    let (pa, pb) = (g.p(a.0, a.1), g.p(b.0, b.1));
    let seg = pb - pa;
    let mid = (pa + pb) * 0.5;
    let (ls, lm) = (seg.length(), mid.length());
    if !(ls > 0.0 && lm > 0.0) {
        return false;
    }
    (seg.cross(mid).length() / (ls * lm))
        .min(1.0)
        .asin()
        .to_degrees()
        < tau
}

/// Angle in degrees between a triangle's plane and the ray to its centroid;
/// NaN for degenerate triangles.
#[inline]
fn view_angle_deg(a: DVec3, b: DVec3, c: DVec3) -> f64 {
    let n = (a - b).cross(a - c);
    let ln = n.length();
    let cen = (a + b + c) / 3.0;
    let lc = cen.length();
    if !(ln > 0.0) || !(lc > 0.0) {
        return f64::NAN;
    }
    let cosang = (n.dot(cen) / (ln * lc)).abs().min(1.0);
    cosang.asin().to_degrees()
}

/// The mesh of a depth map seen by the default camera of its size (the
/// one every bundle uses): the one way the CLI, the renderer's scene
/// builder and the pipeline's mesh stage mesh a view.
pub fn mesh_for_view(
    depth: &GrayImage,
    params: &MeshParams,
) -> Result<(Camera, DepthMesh), MeshError> {
    let cam = Camera::new(depth.width, depth.height);
    let mesh = mesh_from_depth(depth, &cam, params)?;
    Ok((cam, mesh))
}

/// A pixel with no boundary pointer (see [`boundary_pointers`]).
const NONE: u32 = u32::MAX;

/// The mesh's vertices as built: f64 positions (for the angle tests), the
/// f32 ones it keeps, and each vertex's film position.
struct Verts {
    pos64: Vec<DVec3>,
    positions: Vec<Vec3>,
    film: Vec<Vec2>,
}

impl Verts {
    /// A vertex at `p` made from pixel `pix`'s film position (a copy or a
    /// back of that pixel's own vertex); returns its index.
    fn copy(&mut self, p: DVec3, pix: usize) -> u32 {
        self.pos64.push(p);
        self.positions.push(p.as_vec3());
        self.film.push(self.film[pix]);
        (self.pos64.len() - 1) as u32
    }
}

/// Builds the mesh from camera-space depth `z` (0 = no geometry), in the
/// reference's steps: boundary pointers, depth replacement along them,
/// the grid's vertices, each quad's triangles tested, then emitted with
/// boundary vertices duplicated; with kept silhouettes, solids' backs.
pub fn mesh_from_depth(
    z: &GrayImage,
    cam: &Camera,
    params: &MeshParams,
) -> Result<DepthMesh, MeshError> {
    check_depth(z, cam)?;
    let (w, h) = (z.width, z.height);
    let pp = cam.principal_point();
    let g = Grid {
        z: &z.data,
        w,
        f: cam.width as f64 * 0.5 / (cam.fov_x_deg as f64 * 0.5).to_radians().tan(),
        cx: pp.x as f64,
        cy: pp.y as f64,
    };
    let tau = params.min_angle_deg;

    // 2. Boundary detection: refer[k] = index of the deeper pixel, or NONE.
    let refer = boundary_pointers(&g, h, tau);

    // 3. Depth replacement by following pointer chains.
    let mut znew = z.data.clone();
    let mut boundary_pixels = 0;
    let kept = params.silhouettes == Silhouettes::Kept;
    // Film offsets of the kept edges' vertices (empty for the reference).
    let mut offset: Vec<Vec2> = vec![Vec2::ZERO; if kept { w * h } else { 0 }];
    let mut kept_edges = 0;
    let grazing = if kept {
        grazing_planes(&g, h, tau)
    } else {
        Vec::new()
    };
    let on_plane = |k: usize| grazing.get(k).copied().unwrap_or(false);
    for k in 0..w * h {
        if refer[k] == NONE {
            continue;
        }
        boundary_pixels += 1;
        if on_plane(k) {
            kept_edges += 1;
            continue;
        }
        if kept {
            if let Some(d) = foreground_edge(&g, k / w, k % w, tau) {
                offset[k] = d;
                kept_edges += 1;
                continue;
            }
        }
        let mut e = k;
        while refer[e] != NONE {
            e = refer[e] as usize;
        }
        znew[k] = z.data[e];
    }
    let gn = Grid {
        z: &znew,
        w,
        f: g.f,
        cx: g.cx,
        cy: g.cy,
    };

    // Vertices: the full grid (masked ones at the origin), then copies.
    let mut v = grid_vertices(&gn, h, &offset, &znew);

    // 4. Validity of every quad's two triangles, in parallel.
    let status = quad_status(w, h, &znew, &v.pos64, tau, &on_plane);

    // 5. Emit, duplicating boundary vertices sequentially (copies are shared).
    let mut stats = MeshStats {
        boundary_pixels,
        kept_edges,
        ..Default::default()
    };
    let quads_w = w - 1;
    let mut indices: Vec<[u32; 3]> = Vec::with_capacity(2 * (h - 1) * quads_w);
    let mut copy_of: Vec<u32> = vec![NONE; w * h];
    for q in 0..(h - 1) * quads_w {
        let (i, j) = (q / quads_w, q % quads_w);
        for (n, second) in [false, true].into_iter().enumerate() {
            let t = tri_of(w, i, j, second);
            match status[q][n] {
                0 => {}
                1 => {
                    indices.push(t.map(|k| k as u32));
                    stats.emitted_direct += 1;
                }
                _ => match duplicated(&gn, t, &znew, &mut v, &mut copy_of, &mut stats, tau) {
                    Some((idx, round)) => {
                        indices.push(idx);
                        if round == 0 {
                            stats.emitted_one_copy += 1;
                        } else {
                            stats.emitted_two_copies += 1;
                        }
                    }
                    None => stats.dropped += 1,
                },
            }
        }
    }

    // 6. Backs: the far side of what the view shows as a convex solid.
    if kept {
        let up = crate::planes::view_up(z, cam, &crate::planes::PlaneParams::default());
        let backs = Backs {
            g: &gn,
            h,
            tau,
            offset: &offset,
            status: &status,
        };
        backs.add(up.as_dvec3(), &on_plane, &mut v, &mut indices, &mut stats);
    }

    Ok(DepthMesh {
        mesh: TriMesh {
            positions: v.positions,
            indices,
            film: v.film,
            material_pixel: Vec::new(),
            openness: Vec::new(),
            portals: Vec::new(),
            normals: Vec::new(),
        },
        depth: GrayImage::from_vec(w, h, znew),
        stats,
    })
}

/// The depth map fits the camera, is at least 2×2 and holds no NaN,
/// infinity or negative depth (the first such pixel is named).
fn check_depth(z: &GrayImage, cam: &Camera) -> Result<(), MeshError> {
    let (w, h) = (z.width, z.height);
    if w != cam.width || h != cam.height {
        return Err(MeshError::Size {
            got_w: w,
            got_h: h,
            want_w: cam.width,
            want_h: cam.height,
        });
    }
    if w < 2 || h < 2 {
        return Err(MeshError::TooSmall);
    }
    let bad: Vec<usize> = z
        .data
        .iter()
        .enumerate()
        .filter(|(_, v)| !v.is_finite() || **v < 0.0)
        .map(|(i, _)| i)
        .collect();
    if let Some(&first) = bad.first() {
        return Err(MeshError::BadDepth {
            count: bad.len(),
            x: first % w,
            y: first / w,
        });
    }
    Ok(())
}

/// Per pixel, the deeper neighbour its depth is replaced from (the
/// reference's boundary detection), or [`NONE`]: an inner pixel is a
/// boundary where one of its four fans is seen at a grazing angle (under
/// `tau`) and it is nearer than a neighbour of that fan.
fn boundary_pointers(g: &Grid, h: usize, tau: f64) -> Vec<u32> {
    let w = g.w;
    (0..h)
        .into_par_iter()
        .flat_map_iter(|i| {
            (0..w).map(move |j| {
                if i == 0 || j == 0 || i + 1 >= h || j + 1 >= w {
                    return NONE;
                }
                let nb = [(i, j), (i + 1, j), (i, j + 1), (i - 1, j), (i, j - 1)];
                if nb.iter().any(|&(a, b)| g.zz(a, b) == 0.0) {
                    return NONE;
                }
                let p: Vec<DVec3> = nb.iter().map(|&(a, b)| g.p(a, b)).collect();
                const FANS: [(usize, usize, isize, isize); 4] =
                    [(1, 2, 1, 1), (2, 3, -1, 1), (3, 4, -1, -1), (4, 1, 1, -1)];
                let zc = g.zz(i, j);
                let mut best: Option<(usize, usize)> = None;
                for (a, b, dr, dc) in FANS {
                    let ang = view_angle_deg(p[0], p[a], p[b]);
                    if !(ang < tau) {
                        continue;
                    }
                    let rn = ((i as isize + dr) as usize, j);
                    let cn = (i, (j as isize + dc) as usize);
                    let (zr, zcn) = (g.zz(rn.0, rn.1), g.zz(cn.0, cn.1));
                    if !(zc < zcn || zc < zr) {
                        continue;
                    }
                    let cand = if zcn > zr { cn } else { rn };
                    let better = match best {
                        None => true,
                        Some(bp) => g.zz(cand.0, cand.1) > g.zz(bp.0, bp.1),
                    };
                    if better {
                        best = Some(cand);
                    }
                }
                best.map(|(a, b)| (a * w + b) as u32).unwrap_or(NONE)
            })
        })
        .collect()
}

/// One vertex per pixel (masked ones at the origin); a kept edge's
/// vertex moves by its film offset.
fn grid_vertices(gn: &Grid, h: usize, offset: &[Vec2], znew: &[f32]) -> Verts {
    let w = gn.w;
    let mut v = Verts {
        positions: Vec::with_capacity(w * h + w * h / 32),
        film: Vec::with_capacity(w * h + w * h / 32),
        pos64: Vec::with_capacity(w * h + w * h / 32),
    };
    for i in 0..h {
        for j in 0..w {
            let p = match offset.get(i * w + j) {
                Some(d) if *d != Vec2::ZERO => {
                    gn.point_off(i, j, d.y as f64, d.x as f64, znew[i * w + j] as f64)
                }
                _ => gn.p(i, j),
            };
            v.pos64.push(p);
            v.positions.push(p.as_vec3());
            v.film.push(Vec2::new(j as f32 + 0.5, i as f32 + 0.5));
        }
    }
    v
}

/// The pixels of quad (i, j)'s first or second triangle.
fn tri_of(w: usize, i: usize, j: usize, second: bool) -> [usize; 3] {
    let v = |a: usize, b: usize| a * w + b;
    if second {
        [v(i, j + 1), v(i + 1, j), v(i + 1, j + 1)]
    } else {
        [v(i, j), v(i + 1, j), v(i, j + 1)]
    }
}

/// Per quad and triangle: 0 = skipped (a masked vertex), 1 = valid,
/// 2 = seen at a grazing angle, to emit with duplicated vertices.
fn quad_status(
    w: usize,
    h: usize,
    znew: &[f32],
    pos64: &[DVec3],
    tau: f64,
    on_plane: &(dyn Fn(usize) -> bool + Sync),
) -> Vec<[u8; 2]> {
    let quads_w = w - 1;
    (0..(h - 1) * quads_w)
        .into_par_iter()
        .map(|q| {
            let (i, j) = (q / quads_w, q % quads_w);
            let t1 = tri_of(w, i, j, false);
            if t1.iter().any(|&k| znew[k] == 0.0) {
                return [0, 0];
            }
            let mut s = [0u8; 2];
            for (n, second) in [false, true].into_iter().enumerate() {
                let t = tri_of(w, i, j, second);
                if t.iter().any(|&k| znew[k] == 0.0) {
                    s[n] = 0;
                    continue;
                }
                let ang = view_angle_deg(pos64[t[0]], pos64[t[1]], pos64[t[2]]);
                s[n] = if ang > tau || t.iter().all(|&k| on_plane(k)) {
                    1
                } else {
                    2
                };
            }
            s
        })
        .collect()
}

/// A grazing triangle `t` re-emitted with its nearest vertex (then the
/// next nearest) copied back to the triangle's farthest depth, until it
/// faces the camera by more than `tau`: its indices and how many rounds
/// that took (0 or 1), or `None` (dropped). Copies are shared between
/// triangles through `copy_of`.
fn duplicated(
    gn: &Grid,
    t: [usize; 3],
    znew: &[f32],
    v: &mut Verts,
    copy_of: &mut [u32],
    stats: &mut MeshStats,
    tau: f64,
) -> Option<([u32; 3], usize)> {
    let w = gn.w;
    let mut d = t.map(|k| znew[k] as f64);
    let zmax = d.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let mut idx = t.map(|k| k as u32);
    for round in 0..2 {
        // argmin, first index on ties.
        let mut kmin = 0;
        for c in 1..3 {
            if d[c] < d[kmin] {
                kmin = c;
            }
        }
        let pix = t[kmin];
        if copy_of[pix] == NONE {
            let p = gn.point(pix / w, pix % w, zmax);
            copy_of[pix] = v.copy(p, pix);
            stats.copies += 1;
        }
        idx[kmin] = copy_of[pix];
        let ang = view_angle_deg(
            v.pos64[idx[0] as usize],
            v.pos64[idx[1] as usize],
            v.pos64[idx[2] as usize],
        );
        if ang > tau {
            return Some((idx, round));
        }
        d[kmin] = zmax;
    }
    None
}

/// What adding solids' backs needs: the replaced depth's grid, the kept
/// edges' film offsets and each triangle's status.
struct Backs<'a> {
    g: &'a Grid<'a>,
    h: usize,
    tau: f64,
    offset: &'a [Vec2],
    status: &'a [[u8; 2]],
}

impl Backs<'_> {
    /// The far side of what the view shows as a convex solid (mirrored
    /// about its silhouettes, or extruded along `up` from its columns, the
    /// deeper of the two), added behind every valid triangle that has
    /// one, facing away from the camera.
    fn add(
        &self,
        up: DVec3,
        on_plane: &dyn Fn(usize) -> bool,
        v: &mut Verts,
        indices: &mut Vec<[u32; 3]>,
        stats: &mut MeshStats,
    ) {
        let (gn, h, w) = (self.g, self.h, self.g.w);
        let mut back = mirrored_backs(gn, h, self.tau, on_plane);
        let from_columns = extruded_backs(gn, h, self.tau, on_plane, up);
        for (b, c) in back.iter_mut().zip(&from_columns) {
            *b = b.max(*c);
        }
        let quads_w = w - 1;
        let mut back_of: Vec<u32> = vec![NONE; w * h];
        for q in 0..(h - 1) * quads_w {
            let (i, j) = (q / quads_w, q % quads_w);
            for (n, second) in [false, true].into_iter().enumerate() {
                if self.status[q][n] != 1 {
                    continue;
                }
                let t = tri_of(w, i, j, second);
                if !t.iter().any(|&k| back[k] > 0.0) {
                    continue;
                }
                // Vertices of their own, even where the back meets the
                // front (same place): the front's vertex normals, and so
                // its shading, stay as they were.
                let mut idx = [0u32; 3];
                for (c, &pix) in t.iter().enumerate() {
                    if back_of[pix] == NONE {
                        let p = if back[pix] > 0.0 {
                            let d = self.offset.get(pix).copied().unwrap_or(Vec2::ZERO);
                            gn.point_off(pix / w, pix % w, d.y as f64, d.x as f64, back[pix] as f64)
                        } else {
                            v.pos64[pix]
                        };
                        back_of[pix] = v.copy(p, pix);
                        stats.back_vertices += 1;
                    }
                    idx[c] = back_of[pix];
                }
                // Reversed: the back faces away from the camera.
                indices.push([idx[0], idx[2], idx[1]]);
                stats.back_triangles += 1;
            }
        }
    }
}

/// Angle-weighted vertex normals (as Mitsuba recomputes them for meshes
/// without normals). Vertices without faces get +z.
pub fn vertex_normals(mesh: &TriMesh) -> Vec<Vec3> {
    let mut acc = vec![DVec3::ZERO; mesh.positions.len()];
    for t in &mesh.indices {
        let p = t.map(|k| mesh.positions[k as usize].as_dvec3());
        let n = (p[1] - p[0]).cross(p[2] - p[0]);
        let ln = n.length();
        if !(ln > 0.0) || !ln.is_finite() {
            continue;
        }
        let n = n / ln;
        for c in 0..3 {
            let e1 = p[(c + 1) % 3] - p[c];
            let e2 = p[(c + 2) % 3] - p[c];
            let (l1, l2) = (e1.length(), e2.length());
            if l1 > 0.0 && l2 > 0.0 {
                let ang = (e1.dot(e2) / (l1 * l2)).clamp(-1.0, 1.0).acos();
                acc[t[c] as usize] += n * ang;
            }
        }
    }
    acc.iter()
        .map(|v| {
            let l = v.length();
            if l > 0.0 && l.is_finite() {
                (*v / l).as_vec3()
            } else {
                Vec3::Z
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bvh::Bvh;

    fn cam(n: usize) -> Camera {
        Camera::new(n, n)
    }

    #[test]
    fn flat_wall_is_a_full_grid_facing_the_camera() {
        let n = 16;
        let z = GrayImage::new(n, n, 5.0);
        let m = mesh_from_depth(&z, &cam(n), &MeshParams::default()).unwrap();
        assert_eq!(m.mesh.triangle_count(), 2 * (n - 1) * (n - 1));
        assert_eq!(m.stats.copies, 0);
        for t in 0..m.mesh.triangle_count() {
            assert!(m.mesh.face_normal(t).z > 0.99);
        }
        // Vertices sit on their pixel-centre rays at depth 5.
        let c = cam(n);
        for (k, p) in m.mesh.positions.iter().enumerate() {
            let f = c.project(*p).unwrap();
            assert!((f - m.mesh.film[k]).length() < 1e-3);
            assert!((p.z + 5.0).abs() < 1e-5);
        }
    }

    /// Pixels 20..44 on each axis at depth 4 (a box), the rest at 10 (a
    /// wall behind it).
    fn box_before_wall(n: usize) -> GrayImage {
        GrayImage::from_fn(n, n, |x, y| {
            if (20..44).contains(&x) && (20..44).contains(&y) {
                4.0
            } else {
                10.0
            }
        })
    }

    /// A box in front of a wall: the silhouette must be closed by duplicated
    /// background triangles, so rays between pixel centres never escape.
    #[test]
    fn boundary_duplication_leaves_no_gap() {
        let n = 64;
        let z = box_before_wall(n);
        let c = cam(n);
        let m = mesh_from_depth(&z, &c, &MeshParams::default()).unwrap();
        assert!(m.stats.copies > 0, "{:?}", m.stats);
        let bvh = Bvh::build(&m.mesh);
        // Shoot rays through a fine sub-pixel grid inside the mesh's extent.
        let mut escaped = 0;
        for sy in 0..(n - 1) * 4 {
            for sx in 0..(n - 1) * 4 {
                let film = Vec2::new(
                    0.5 + 0.125 + sx as f32 * 0.25,
                    0.5 + 0.125 + sy as f32 * 0.25,
                );
                let d = c.film_to_dir(film).normalize();
                if bvh.intersect(Vec3::ZERO, d, 0.0, f32::INFINITY).is_none() {
                    escaped += 1;
                }
            }
        }
        assert_eq!(escaped, 0);
    }

    /// The depth of the first surface hit through film position `film`.
    fn hit_depth(bvh: &Bvh, c: &Camera, film: Vec2) -> Option<f32> {
        let d = c.film_to_dir(film);
        bvh.intersect(Vec3::ZERO, d.normalize(), 0.0, f32::INFINITY)
            .map(|h| h.t * d.normalize().z.abs())
    }

    /// A box of pixels 20..44 at depth 4 before a wall at 10, its depth
    /// sharp (every pixel the depth at its centre): the box spans film
    /// [20, 44) on each axis, and with kept silhouettes the mesh's box
    /// does too, to a hair; the reference's rule shrinks it by a pixel
    /// and a half on every side.
    #[test]
    fn kept_silhouettes_lie_on_the_pixel_border() {
        let n = 64;
        let z = box_before_wall(n);
        let c = cam(n);
        let kept = mesh_from_depth(&z, &c, &MeshParams::default()).unwrap();
        let reference = mesh_from_depth(&z, &c, &MeshParams::reference(6.0)).unwrap();
        // Every boundary pixel of the box is its own edge: none moves.
        assert_eq!(kept.stats.kept_edges, kept.stats.boundary_pixels);
        assert_eq!(kept.stats.kept_edges, 4 * 24 - 4);
        assert_eq!(reference.stats.kept_edges, 0);
        assert_eq!(kept.depth.data, z.data);
        let (bk, br) = (Bvh::build(&kept.mesh), Bvh::build(&reference.mesh));
        // Across the middle row, and down the middle column.
        for t in [19.9f32, 20.05, 21.2, 42.8, 43.95, 44.1] {
            let inside = (20.0..44.0).contains(&t);
            for film in [Vec2::new(t, 32.0), Vec2::new(32.0, t)] {
                let zk = hit_depth(&bk, &c, film).unwrap();
                assert!(
                    (zk - if inside { 4.0 } else { 10.0 }).abs() < 1e-3,
                    "kept, film {film}: depth {zk}"
                );
                let zr = hit_depth(&br, &c, film).unwrap();
                let in_ref = (21.5..42.5).contains(&t);
                assert!(
                    (zr - if in_ref { 4.0 } else { 10.0 }).abs() < 1e-3,
                    "reference, film {film}: depth {zr}"
                );
            }
        }
        // The corner reaches the pixels' corner.
        assert!((hit_depth(&bk, &c, Vec2::new(20.05, 20.05)).unwrap() - 4.0).abs() < 1e-3);
        assert!((hit_depth(&bk, &c, Vec2::new(19.95, 19.95)).unwrap() - 10.0).abs() < 1e-3);
    }

    /// Flat ground under a camera 1.5 high looking level: its far rows
    /// are seen within 6° of the view ray. With kept silhouettes it stays
    /// one plane (every triangle's normal points up, no copies); the
    /// reference's rule cuts its far rows into camera-facing steps. A box
    /// standing on it is still cut off from the ground behind.
    #[test]
    fn ground_seen_at_a_grazing_angle_stays_a_plane() {
        let n = 64;
        let c = cam(n);
        let f = c.focal() as f64;
        let cy = (n as f64 - 1.0) / 2.0;
        // Ground y = -1.5: a pixel row i below the horizon sees it at z =
        // 1.5 f / (i - cy); rows at or above the horizon see the sky (0).
        let ground = |i: usize| {
            if (i as f64) > cy + 0.5 {
                (1.5 * f / (i as f64 - cy)) as f32
            } else {
                0.0
            }
        };
        let z = GrayImage::from_fn(n, n, |_, y| ground(y));
        let kept = mesh_from_depth(&z, &c, &MeshParams::default()).unwrap();
        let reference = mesh_from_depth(&z, &c, &MeshParams::reference(6.0)).unwrap();
        assert_eq!(kept.stats.copies, 0, "{:?}", kept.stats);
        assert_eq!(kept.depth.data, z.data);
        for t in 0..kept.mesh.triangle_count() {
            let nrm = kept.mesh.face_normal(t);
            assert!(nrm.y.abs() > 0.999, "triangle {t}: normal {nrm}");
        }
        assert!(reference.stats.copies > 0, "{:?}", reference.stats);
        let steps = (0..reference.mesh.triangle_count())
            .filter(|&t| reference.mesh.face_normal(t).y.abs() < 0.5)
            .count();
        assert!(steps > 0);
        // A box on the ground, its front face at z = 8, columns 28..36, rows
        // from the ground (row 50) up to row 40, where the ground behind
        // is seen at a grazing angle (rows 33 to 42): the ground behind its
        // top edge is not joined to it.
        let top = 40;
        let zb = GrayImage::from_fn(n, n, |x, y| {
            let g = ground(y);
            if (28..36).contains(&x) && y >= top && (g == 0.0 || g > 8.0) {
                8.0
            } else {
                g
            }
        });
        let m = mesh_from_depth(&zb, &c, &MeshParams::default()).unwrap();
        let bvh = Bvh::build(&m.mesh);
        // Just above the box's top edge (film row 30): the ground far
        // behind, not a sheet at the box's depth.
        let behind = hit_depth(&bvh, &c, Vec2::new(32.5, top as f32 - 0.2)).unwrap();
        assert!(behind > 18.0, "above the box: depth {behind}");
        let on = hit_depth(&bvh, &c, Vec2::new(32.5, top as f32 + 0.2)).unwrap();
        assert!((on - 8.0).abs() < 1e-3, "the box's top row: depth {on}");
    }

    /// A predicted depth map smears an edge over pixels between the two
    /// depths; those still move to the background, as in the reference,
    /// and only the object's own edge pixel stays.
    /// Depth of an upright cylinder (axis x = x0, z = −6, radius 1, rows
    /// y ∈ [−1.5, 1]) before a wall at depth 10.
    fn cylinder_before_wall(c: &Camera, x0: f32) -> GrayImage {
        let (r, zc) = (1.0f32, 6.0f32);
        GrayImage::from_fn(c.width, c.height, |x, y| {
            let d = c.film_to_dir(Vec2::new(x as f32 + 0.5, y as f32 + 0.5));
            // (dx t − x0)² + (zc − t)² = r², the nearest root.
            let a = d.x * d.x + 1.0;
            let b = -2.0 * (d.x * x0 + zc);
            let k = x0 * x0 + zc * zc - r * r;
            let disc = b * b - 4.0 * a * k;
            if disc >= 0.0 {
                let t = (-b - disc.sqrt()) / (2.0 * a);
                if (-1.5..=1.0).contains(&(d.y * t)) {
                    return t;
                }
            }
            10.0
        })
    }

    /// The first hit from `o` along `d` (any side), its distance.
    fn hit_from(bvh: &Bvh, o: Vec3, d: Vec3) -> Option<f32> {
        bvh.intersect(o, d.normalize(), 1e-4, f32::INFINITY)
            .map(|h| h.t)
    }

    /// A depth mesh is a shell; a solid's unseen back half is the front
    /// mirrored about its silhouettes, so light crossing the solid is
    /// stopped (a cylinder casts a cylinder's shadow, not a sheet's).
    #[test]
    fn a_solid_gets_its_back_half() {
        // The runs end at the last pixel whose segments are not edge-on
        // (and pixels between two depths have moved back), a little nearer
        // than the silhouette itself, so the back is thinner than the
        // truth, never thicker: it stops light crossing the solid's
        // middle, and lies within the radius.
        let n = 256;
        let c = cam(n);
        let z = cylinder_before_wall(&c, 0.3);
        let m = mesh_from_depth(&z, &c, &MeshParams::default()).unwrap();
        assert!(m.stats.back_vertices > 0, "{:?}", m.stats);
        let bvh = Bvh::build(&m.mesh);
        let axis = Vec3::new(0.3, 0.0, -6.0);
        // From the axis, away from the camera or sideways and backwards
        // (towards a light behind and beside it): the back, within the
        // radius, not the wall 4 away or nothing.
        for d in [
            Vec3::NEG_Z,
            Vec3::new(1.0, 0.0, -1.0),
            Vec3::new(-1.0, 0.3, -1.0),
        ] {
            let t = hit_from(&bvh, axis, d).unwrap();
            assert!((0.4..1.02).contains(&t), "along {d}: hit at {t}, radius 1");
        }
        // The camera still sees the front (6 − 1 on the axis).
        let front = hit_depth(&bvh, &c, c.project(axis).unwrap()).unwrap();
        assert!((front - 5.0).abs() < 0.01, "front at depth {front}");
        // The reference's mesh is the shell: the ray leaves through the
        // open back (the wall behind the cylinder is not seen, so not
        // there either).
        let shell = mesh_from_depth(&z, &c, &MeshParams::reference(6.0)).unwrap();
        assert_eq!(shell.stats.back_vertices, 0);
        let t = hit_from(&Bvh::build(&shell.mesh), axis, Vec3::NEG_Z);
        assert!(
            t.is_none_or(|t| t > 3.9),
            "the shell stops the ray at {t:?}"
        );
        // Cut by the frame past its nearest point: mirrored about its one
        // silhouette seen, so it still has a back.
        let cut =
            mesh_from_depth(&cylinder_before_wall(&c, 1.0), &c, &MeshParams::default()).unwrap();
        let bvh = Bvh::build(&cut.mesh);
        let t = hit_from(&bvh, Vec3::new(1.0, 0.0, -6.0), Vec3::NEG_Z).unwrap();
        assert!((0.4..1.02).contains(&t), "cut by the frame: back at {t}");
    }

    /// Depth of axis-aligned boxes (min, max corners) on a floor 1.5
    /// below the camera, before a wall 10 away.
    fn boxes_on_floor(c: &Camera, boxes: &[(Vec3, Vec3)]) -> GrayImage {
        GrayImage::from_fn(c.width, c.height, |x, y| {
            let d = c.film_to_dir(Vec2::new(x as f32 + 0.5, y as f32 + 0.5));
            let d = d / -d.z;
            let mut best = 10.0f32;
            if d.y < 0.0 {
                best = best.min(1.5 / -d.y);
            }
            for (lo, hi) in boxes {
                // Slabs: the ray p = d·t.
                let (mut t0, mut t1) = (0.0f32, f32::INFINITY);
                for k in 0..3 {
                    let (a, b) = (lo[k] / d[k], hi[k] / d[k]);
                    let (a, b) = if a < b { (a, b) } else { (b, a) };
                    t0 = t0.max(a);
                    t1 = t1.min(b);
                }
                if t0 <= t1 && t0 > 0.0 {
                    best = best.min(t0);
                }
            }
            best
        })
    }

    /// A box seen face-on has no silhouettes left and right to mirror
    /// its front about (a plane), but seen from above, its top's far edge
    /// is its back: it stops light crossing it. A table open beneath its
    /// top gets no such back.
    #[test]
    fn a_box_standing_on_the_ground_gets_the_back_its_top_shows() {
        let n = 128;
        let c = cam(n);
        // A box 1 wide, 0.8 high, 1 deep, its front 5 away.
        let block = (Vec3::new(-0.5, -1.5, -6.0), Vec3::new(0.5, -0.7, -5.0));
        let m = mesh_from_depth(&boxes_on_floor(&c, &[block]), &c, &MeshParams::default()).unwrap();
        assert!(m.stats.back_vertices > 0, "{:?}", m.stats);
        let bvh = Bvh::build(&m.mesh);
        // From just behind its front, away from the camera: the back,
        // at most the box's depth on (a little nearer: the silhouette
        // pixel lies before the true edge), not the wall 5 on.
        for x in [-0.3f32, 0.0, 0.3] {
            for y in [-1.3f32, -1.0, -0.8] {
                let t = hit_from(&bvh, Vec3::new(x, y, -5.02), Vec3::NEG_Z).unwrap();
                assert!((0.6..1.0).contains(&t), "from ({x}, {y}): hit at {t}");
            }
        }
        // The camera still sees the front.
        let front = hit_depth(&bvh, &c, c.project(Vec3::new(0.0, -1.0, -5.0)).unwrap()).unwrap();
        assert!((front - 5.0).abs() < 0.01, "front at depth {front}");
        // A table 0.5 deep, its top 0.1 thick over two panels set 0.05
        // back from its front edge (0.3 wide: no pole) and two thin legs
        // at its back corners; open beneath. Down a panel's column the
        // depth steps back under the top's edge: no prism under the top.
        let table = [
            (Vec3::new(-0.6, -0.8, -5.5), Vec3::new(0.6, -0.7, -5.0)),
            (Vec3::new(-0.55, -1.5, -5.1), Vec3::new(-0.25, -0.8, -5.05)),
            (Vec3::new(0.25, -1.5, -5.1), Vec3::new(0.55, -0.8, -5.05)),
            (Vec3::new(-0.6, -1.5, -5.5), Vec3::new(-0.56, -0.8, -5.46)),
            (Vec3::new(0.56, -1.5, -5.5), Vec3::new(0.6, -0.8, -5.46)),
        ];
        let m = mesh_from_depth(&boxes_on_floor(&c, &table), &c, &MeshParams::default()).unwrap();
        let bvh = Bvh::build(&m.mesh);
        // Beneath its top, between and behind its panels: nothing, or the
        // wall.
        for x in [-0.4f32, 0.0, 0.4] {
            for y in [-1.3f32, -1.0] {
                let t = hit_from(&bvh, Vec3::new(x, y, -5.12), Vec3::NEG_Z);
                assert!(
                    t.is_none_or(|t| t > 4.5),
                    "under the table at ({x}, {y}): hit at {t:?}"
                );
            }
        }
    }

    /// Planes get no back: a wall, a box's face, the ground, and a side
    /// wall that comes nearer up to the frame's edge (it may go on past
    /// it) and ends against the sky.
    #[test]
    fn planes_get_no_back() {
        let n = 64;
        let c = cam(n);
        let f = c.focal() as f64;
        let cx = (n as f64 - 1.0) / 2.0;
        // Wall x = −2 from depth 2 to 12, the sky past it.
        let side = GrayImage::from_fn(n, n, |x, _| {
            let dx = (x as f64 - cx) / f;
            let t = if dx < 0.0 { -2.0 / dx } else { 0.0 };
            if (0.0..=12.0).contains(&t) {
                t as f32
            } else {
                0.0
            }
        });
        for z in [GrayImage::new(n, n, 5.0), box_before_wall(n), side] {
            let m = mesh_from_depth(&z, &c, &MeshParams::default()).unwrap();
            assert_eq!(m.stats.back_vertices, 0, "{:?}", m.stats);
        }
    }

    #[test]
    fn pixels_between_two_depths_still_move_back() {
        let n = 32;
        let z = GrayImage::from_fn(n, n, |x, _| match x {
            0..=11 => 4.0,
            12 => 6.0,
            13 => 8.0,
            _ => 10.0,
        });
        let m = mesh_from_depth(&z, &cam(n), &MeshParams::default()).unwrap();
        for y in 1..n - 1 {
            assert_eq!(m.depth.get(11, y), 4.0, "row {y}: the edge keeps its depth");
            assert_eq!(m.depth.get(12, y), 10.0, "row {y}");
            assert_eq!(m.depth.get(13, y), 10.0, "row {y}");
        }
    }

    #[test]
    fn masked_pixels_carry_no_geometry() {
        let n = 16;
        let z = GrayImage::from_fn(n, n, |x, _| if x < 8 { 0.0 } else { 3.0 });
        let m = mesh_from_depth(&z, &cam(n), &MeshParams::default()).unwrap();
        for t in &m.mesh.indices {
            for &k in t {
                assert!(m.mesh.positions[k as usize].z < -1.0);
            }
        }
        assert!(m.mesh.triangle_count() > 0);
    }

    #[test]
    fn bad_depth_is_reported() {
        let mut z = GrayImage::new(8, 8, 1.0);
        z.set(3, 2, f32::NAN);
        let e = mesh_from_depth(&z, &cam(8), &MeshParams::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains("x=3, y=2"), "{e}");
        let e = mesh_from_depth(&GrayImage::new(8, 4, 1.0), &cam(8), &MeshParams::default())
            .unwrap_err();
        assert!(matches!(e, MeshError::Size { .. }));
    }

    #[test]
    fn vertex_normals_of_a_plane() {
        let z = GrayImage::new(8, 8, 2.0);
        let m = mesh_from_depth(&z, &cam(8), &MeshParams::default()).unwrap();
        for n in vertex_normals(&m.mesh) {
            assert!((n - Vec3::Z).length() < 1e-4);
        }
    }
}
