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
//! Every bounding plane is also filled in view behind what hides it
//! ([`fill_in_view`]: furniture and objects), so no light passes through
//! the holes a depth mesh has there, while what the image shows (a
//! window's sky included) stays open. With `close`, a room the view
//! evidently shows is closed ([`closure`]: an assumed ceiling and walls),
//! each assumed wall keeping a typical window open (`assumed_opening`).
//! A floor alone is not a room (it may be ground outdoors) unless an
//! upright wall bounding the scene shows as a strip too small for the
//! plane fit's own threshold (`small_wall`: a camera pitched down).
//!
//! Planes inside the scene (a cabinet's front) fail the bounding test and
//! are left alone; a view without such planes is unchanged. Everything is
//! computed from the depth alone, so the same depth always gives the same
//! completion (and [`complete_beyond_frame`] names, per added triangle,
//! the pixel of its plane whose material it takes).

use glam::{Vec2, Vec3};
use matflow_scene::{Camera, GrayImage};

use crate::mesh::{Portal, TriMesh};
use crate::planes::{
    corner_up, fit_planes_resumable, Plane, PlaneFit, PlaneKind, PlaneParams, PlaneSearch,
};

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CompleteParams {
    pub planes: PlaneParams,
    /// Half-size of an extended plane, in multiples of the largest depth.
    pub extent: f32,
    /// Smallest share of the seen geometry on a plane's camera side (within
    /// the plane tolerance) for it to count as bounding the scene.
    pub support: f64,
    /// Close the room where the view evidently shows one (a floor and a
    /// wall or ceiling): a ceiling and the walls the view does not show
    /// are assumed (see [`closure`]).
    pub close: bool,
    /// Assumed ceiling height, in camera heights above the floor (rooms:
    /// 2.4–3 m ceilings over a camera held at 1.3–1.7 m), or just above
    /// the highest point seen when that is higher.
    pub ceiling_ratio: f32,
    /// Smallest distance of an assumed wall from the camera, in camera
    /// heights (a wall behind the photographer).
    pub wall_ratio: f32,
    /// Width of the window left open in each assumed wall, as a share of
    /// the wall (over [`WINDOW_BAND`] of the room's height); 0 closes them.
    pub assumed_opening: f32,
    /// Share of light that passes the rest of an assumed wall or ceiling
    /// ([`TriMesh::openness`]): openings the view cannot show (windows,
    /// skylights, a lamp's light standing in as the sky's) spread over the
    /// surfaces that might hold them; 0 makes them solid.
    pub assumed_openness: f32,
    /// How far objects cut by the frame border are continued past it
    /// ([`border_margins`]), as a share of the image's larger side; 0
    /// turns it off.
    pub border_margin: f32,
    /// With `close`, when the view's bounding planes are a floor alone:
    /// the smallest share of the seen pixels an upright wall must hold to
    /// show that the floor is a room's (below the plane fit's own
    /// `min_fraction`: a camera pitched down may see its room's walls
    /// only as strips along the top). Such a wall must bound the seen
    /// scene like any other; 0 or `planes.min_fraction` turns it off.
    pub small_wall: f64,
    /// With `close`, the windows of the closed room chosen one by one
    /// instead of `assumed_opening`'s typical window in each assumed
    /// wall: bit `5·k + t` opens part `t` ([`WindowSlot::part`]) of the `k`-th bounding
    /// plane that runs past the frame (a wall, seen or assumed, or the
    /// ceiling; see [`WindowSlot`]). `Some(0)` closes every window;
    /// [`window_slots`] lists the slots a view has.
    pub windows: Option<u32>,
    /// With `close`, which of the ceiling and walls the closure assumes
    /// are kept: bit `k` keeps the `k`-th ([`assumed_planes`]); `None`
    /// keeps them all. An assumed wall of a room without its ceiling
    /// stands as high as the ceiling would; with [`RAISE_SEEN_WALLS`] the
    /// walls seen do too (else they stop at the highest point seen on
    /// them).
    pub assumed: Option<u32>,
    /// With [`RAISE_WALLS_HIGH`] in `assumed`: how high the walls stand,
    /// in camera heights above the floor (never lower than the room's
    /// ceiling would be). The photo can tell it (the shadows the walls'
    /// tops cast); [`HIGH_WALLS`] by default.
    pub wall_height: f32,
}

/// The bit of [`CompleteParams::assumed`] that raises the walls seen of a
/// room without a ceiling to the height its ceiling would have.
pub const RAISE_SEEN_WALLS: u32 = 1 << 31;
/// The bit of [`CompleteParams::assumed`] that raises every wall of a
/// room without a ceiling, seen or assumed, to
/// [`CompleteParams::wall_height`] camera heights above the floor (or the
/// ceiling's height, if higher): a courtyard's walls, taller than a
/// room's.
pub const RAISE_WALLS_HIGH: u32 = 1 << 30;
/// How high [`RAISE_WALLS_HIGH`] raises walls by default, in camera
/// heights.
pub const HIGH_WALLS: f32 = 3.0;

impl Default for CompleteParams {
    fn default() -> Self {
        CompleteParams {
            planes: PlaneParams::default(),
            extent: 4.0,
            support: 0.98,
            close: false,
            ceiling_ratio: 1.8,
            wall_ratio: 0.5,
            assumed_opening: 0.4,
            assumed_openness: 0.0,
            border_margin: 0.1,
            small_wall: 0.02,
            windows: None,
            assumed: None,
            wall_height: HIGH_WALLS,
        }
    }
}

/// The ways of completing a view, by name (the CLI's `--complete` and the
/// pipeline's `mesh.complete`): the depth mesh alone; bounding planes
/// extended and filled (and objects cut by the border continued); also a
/// room the view shows closed, each assumed wall keeping a typical
/// window; closed without windows.
pub const COMPLETE_MODES: [&str; 4] = ["none", "planes", "room", "closed"];

impl CompleteParams {
    /// The parameters of a mode of [`COMPLETE_MODES`]; `None` for "none"
    /// (and any other name).
    pub fn for_mode(name: &str) -> Option<CompleteParams> {
        let d = CompleteParams::default();
        match name {
            "planes" => Some(CompleteParams { close: false, ..d }),
            "room" => Some(CompleteParams { close: true, ..d }),
            "closed" => Some(CompleteParams {
                close: true,
                assumed_opening: 0.0,
                ..d
            }),
            _ => None,
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
    /// Of those, the ones continuing objects cut by the border.
    pub border_triangles: usize,
    /// Where lamps may hang in a closed room (camera space; empty unless
    /// a room was closed): a grid of [`LAMP_GRID`]² points under its
    /// ceiling, [`LAMP_DROP`] of the room's height below it, over the
    /// box the closure assumed. Lamps a view does not show are the other
    /// light of a closed room; inverse rendering fits their intensity.
    pub lamp_sites: Vec<Vec3>,
    /// The closed room's height, floor to ceiling (0 if none).
    pub room_height: f32,
    /// Windows left open in assumed walls, added to the mesh's
    /// [`TriMesh::portals`].
    pub portals: usize,
}

/// Lamp sites per side of a closed room's box ([`Completion::lamp_sites`]).
pub const LAMP_GRID: usize = 3;
/// How far lamp sites hang under the ceiling, as a share of the room's
/// height.
pub const LAMP_DROP: f32 = 0.12;

/// The box a closed room was taken as: "up", the camera's height above
/// the floor, the ceiling's, the box's horizontal axes and its extent
/// from the camera along a0, a1, −a0, −a1.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RoomBox {
    pub up: Vec3,
    pub camera_height: f32,
    pub height: f32,
    pub axes: [Vec3; 2],
    pub extent: [f32; 4],
}

impl RoomBox {
    /// A grid of [`LAMP_GRID`]² points [`LAMP_DROP`]·height under the
    /// ceiling, at the centres of equal cells of the box's footprint.
    pub fn lamp_sites(&self) -> Vec<Vec3> {
        let y = self.height * (1.0 - LAMP_DROP) - self.camera_height;
        let [a0, a1] = self.axes;
        let [e0, e1, f0, f1] = self.extent;
        let mut out = Vec::with_capacity(LAMP_GRID * LAMP_GRID);
        for i in 0..LAMP_GRID {
            let s = (i as f32 + 0.5) / LAMP_GRID as f32;
            for j in 0..LAMP_GRID {
                let t = (j as f32 + 0.5) / LAMP_GRID as f32;
                let u = -f0 + s * (e0 + f0);
                let v = -f1 + t * (e1 + f1);
                out.push(self.up * y + a0 * u + a1 * v);
            }
        }
        out
    }
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
    /// An assumed plane of the closed room (no pixel shows it).
    pub assumed: bool,
}

/// What [`extensions`] finds: the planes extended, how many were found
/// but not extended, the box of a closed room and the windows left in
/// its assumed walls.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Extensions {
    pub planes: Vec<Extension>,
    pub kept_in: usize,
    pub room: Option<RoomBox>,
    pub portals: Vec<Portal>,
    /// Where a closed room may have a window past the frame (empty
    /// unless a room was closed).
    pub window_slots: Vec<WindowSlot>,
    /// The ceiling and walls the closure assumed, kept or not
    /// ([`CompleteParams::assumed`]).
    pub assumed_planes: Vec<AssumedPlane>,
}

/// A ceiling or wall that closing the room assumes: its bit in
/// [`CompleteParams::assumed`], its kind and its normal (towards the
/// camera's side).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AssumedPlane {
    pub bit: u32,
    pub kind: PlaneKind,
    pub normal: Vec3,
}

impl AssumedPlane {
    /// Where it is, in words ("ceiling", "wall left", ...).
    pub fn describe(&self) -> String {
        if 1 << self.bit == RAISE_SEEN_WALLS {
            return "the walls seen raised to the room's height".to_string();
        }
        if 1 << self.bit == RAISE_WALLS_HIGH {
            return format!("every wall raised to {HIGH_WALLS} camera heights");
        }
        WindowSlot {
            bit: self.bit,
            kind: self.kind,
            assumed: true,
            normal: self.normal,
            part: 0,
        }
        .place()
    }
}

/// The ceiling and walls that closing the room of view `z` would assume,
/// and, when no ceiling is seen, the walls raised ([`RAISE_SEEN_WALLS`],
/// [`RAISE_WALLS_HIGH`]) (empty when the view shows no room).
pub fn assumed_planes(z: &GrayImage, cam: &Camera, p: &CompleteParams) -> Vec<AssumedPlane> {
    let q = CompleteParams {
        close: true,
        windows: Some(0),
        ..*p
    };
    let e = extensions(z, cam, &q);
    let mut out = e.assumed_planes;
    // Walls seen, when the room has no ceiling in view, may stand higher
    // than the frame shows.
    let seen_wall = e
        .planes
        .iter()
        .find(|x| !x.assumed && x.fit.kind == PlaneKind::Wall);
    let seen_ceiling = e
        .planes
        .iter()
        .any(|x| !x.assumed && x.fit.kind == PlaneKind::Ceiling);
    if let (Some(w), false, Some(_)) = (seen_wall, seen_ceiling, e.room) {
        for bit in [RAISE_SEEN_WALLS, RAISE_WALLS_HIGH] {
            out.push(AssumedPlane {
                bit: bit.trailing_zeros(),
                kind: PlaneKind::Wall,
                normal: w.fit.plane.n,
            });
        }
    }
    out
}

/// A place past the frame where a closed room may have a window
/// ([`CompleteParams::windows`]): a third of a wall's length, or all of
/// its length, over the window band ([`WINDOW_BAND`] of the room's
/// height), or the whole wall (missing); on the ceiling likewise, over
/// the middle half of its width (skylights), or the whole ceiling.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WindowSlot {
    /// Its bit in [`CompleteParams::windows`].
    pub bit: u32,
    pub kind: PlaneKind,
    /// On a plane the closure assumed (no pixel shows it).
    pub assumed: bool,
    /// The plane's normal (towards the camera's side): the plane lies in
    /// the direction −normal from the camera.
    pub normal: Vec3,
    /// Which part of it: a third along it (0, 1, 2), its whole band
    /// ([`SLOT_BAND`]) or all of it ([`SLOT_ALL`]: the plane missing past
    /// the frame, a wall left out or a room open to the sky).
    pub part: u32,
}

impl WindowSlot {
    /// Where it is, in words: the plane (ceiling; the wall ahead, behind,
    /// left or right, as the camera sees it; seen or assumed) and the third.
    pub fn describe(&self) -> String {
        let part = match self.part {
            SLOT_BAND => "its window band".to_string(),
            SLOT_ALL => "all of it".to_string(),
            t => format!("third {}", t + 1),
        };
        format!(
            "{} ({}), {part}",
            self.place(),
            if self.assumed { "assumed" } else { "seen" }
        )
    }

    /// Its plane in words: the ceiling, or the wall ahead, behind, left
    /// or right as the camera sees it.
    fn place(&self) -> String {
        if self.kind == PlaneKind::Ceiling {
            "ceiling".to_string()
        } else {
            let d = -self.normal;
            let dir = if d.x.abs() > d.z.abs() {
                if d.x < 0.0 {
                    "left"
                } else {
                    "right"
                }
            } else if d.z < 0.0 {
                "ahead"
            } else {
                "behind"
            };
            format!("wall {dir}")
        }
    }
}

/// Slots a plane has: three thirds, its band, all of it.
pub const SLOT_PARTS: u32 = 5;
/// [`WindowSlot::part`] of a window along all of the plane's band.
pub const SLOT_BAND: u32 = 3;
/// [`WindowSlot::part`] of the plane missing past the frame altogether.
pub const SLOT_ALL: u32 = 4;

/// Bounding planes past [`MAX_WINDOW_PLANES`] get no window slots (the
/// mask's bits run out).
pub const MAX_WINDOW_PLANES: usize = 6;

/// The window slots of the room that completion `p` closes in the view
/// `z` (empty when it closes none).
pub fn window_slots(z: &GrayImage, cam: &Camera, p: &CompleteParams) -> Vec<WindowSlot> {
    let q = CompleteParams {
        close: true,
        windows: Some(0),
        ..*p
    };
    extensions(z, cam, &q).window_slots
}

/// The planes that close a room the view shows only part of. "Up" is the
/// normal of the floor seen, else the opposite of the ceiling's, else the
/// direction along which two walls seen at 30° or more to each other meet
/// (a corner), else the camera's up made parallel to the largest wall seen
/// (walls stand upright); the camera's height h above the floor is the floor's
/// distance, or, with no floor in view, that of the lowest point seen (what
/// stands in a room stands on its floor), where a floor is then assumed.
/// The room is taken as a box aligned with the largest wall seen (else with
/// the view direction). A ceiling not in view is put `ceiling_ratio`·h
/// above the floor (or just above the highest point seen); of the box's
/// four wall directions, each with no wall seen within 30° gets a wall just
/// beyond the farthest point seen that way, and at least `wall_ratio`·h
/// from the camera. Nothing when the view shows no room: a floor alone (the
/// scene may be outdoors: ground without walls; [`extensions`] first looks
/// for a strip of wall under the fit's threshold, `small_wall`), or no up
/// at all.
fn closure(
    bounding: &[PlaneFit],
    points: &[(Vec3, f32)],
    p: &CompleteParams,
) -> (Vec<PlaneFit>, Option<RoomBox>) {
    let by_fraction = |a: &&PlaneFit, b: &&PlaneFit| a.fraction.total_cmp(&b.fraction);
    let floor = bounding
        .iter()
        .filter(|f| f.kind == PlaneKind::Floor)
        .max_by(by_fraction);
    let walls: Vec<&PlaneFit> = bounding
        .iter()
        .filter(|f| f.kind == PlaneKind::Wall)
        .collect();
    let largest_wall = walls.iter().copied().max_by(by_fraction);
    let ceiling = bounding
        .iter()
        .filter(|f| f.kind == PlaneKind::Ceiling)
        .max_by(by_fraction);
    let has_ceiling = ceiling.is_some();
    if points.is_empty() {
        return (Vec::new(), None);
    }
    let (up, h, floor_seen) = match floor {
        Some(f) => {
            if walls.is_empty() && !has_ceiling {
                return (Vec::new(), None);
            }
            (f.plane.n, f.plane.d, true)
        }
        None => {
            let Some(up) = ceiling
                .map(|c| -c.plane.n)
                .or_else(|| walls_up(&walls))
                .or_else(|| largest_wall.and_then(upright_wall_up))
            else {
                return (Vec::new(), None);
            };
            let low = points
                .iter()
                .map(|(q, _)| -up.dot(*q))
                .fold(f32::NEG_INFINITY, f32::max);
            (up, low * (1.0 + FLOOR_MARGIN), false)
        }
    };
    if !(h > 0.0) || !h.is_finite() {
        return (Vec::new(), None);
    }
    let horizontal = |v: Vec3| (v - up * up.dot(v)).normalize_or_zero();
    let a0 = largest_wall
        .map(|w| horizontal(-w.plane.n))
        .filter(|a| *a != Vec3::ZERO)
        .unwrap_or_else(|| horizontal(Vec3::NEG_Z));
    if a0 == Vec3::ZERO {
        return (Vec::new(), None);
    }
    let a1 = up.cross(a0).normalize_or_zero();
    let margin = 0.05 * h;
    let assumed = |n: Vec3, d: f32, kind: PlaneKind| PlaneFit {
        plane: Plane { n, d },
        kind,
        fraction: 0.0,
        rms: 0.0,
        reaches: [true; 4],
    };
    let mut out = Vec::new();
    if !floor_seen {
        out.push(assumed(up, h, PlaneKind::Floor));
    }
    let height = match ceiling {
        Some(c) => c.plane.d + h,
        None => {
            let top = points
                .iter()
                .map(|(q, _)| up.dot(*q) + h)
                .fold(0.0f32, f32::max);
            let height = (top + margin).max(p.ceiling_ratio * h);
            out.push(assumed(-up, height - h, PlaneKind::Ceiling));
            height
        }
    };
    let mut extent = [0.0f32; 4];
    let cos30 = 30f32.to_radians().cos();
    for (k, a) in [a0, a1, -a0, -a1].into_iter().enumerate() {
        let far = points
            .iter()
            .map(|(q, _)| a.dot(*q))
            .fold(f32::NEG_INFINITY, f32::max);
        let d = (far + margin).max(p.wall_ratio * h);
        extent[k] = d;
        if walls.iter().any(|w| horizontal(-w.plane.n).dot(a) > cos30) {
            continue;
        }
        out.push(assumed(-a, d, PlaneKind::Wall));
    }
    let room = (height > h && extent.iter().all(|e| e.is_finite())).then_some(RoomBox {
        up,
        camera_height: h,
        height,
        axes: [a0, a1],
        extent,
    });
    (out, room)
}

/// Whether the bounding planes are a floor with neither a wall nor a
/// ceiling.
fn floor_alone(bounding: &[PlaneFit]) -> bool {
    bounding.iter().any(|f| f.kind == PlaneKind::Floor)
        && !bounding
            .iter()
            .any(|f| matches!(f.kind, PlaneKind::Wall | PlaneKind::Ceiling))
}

/// The upright walls bounding the seen scene among the planes that hold
/// less than the plane fit's `min_fraction` but at least `small_wall` of
/// the seen pixels: the plane fit's deterministic search continued with
/// the lower threshold past the `found` planes it returned (up to
/// [`SMALL_WALL_SEARCH`] more than it may return), classified against
/// the same "up" `up`.
fn small_walls(
    search: Option<PlaneSearch>,
    up: Vec3,
    p: &CompleteParams,
    found: usize,
    points: &[(Vec3, f32)],
    reveal: &[bool],
) -> Vec<PlaneFit> {
    let Some(mut search) = search else {
        return Vec::new();
    };
    if !(p.small_wall > 0.0 && p.small_wall < p.planes.min_fraction) {
        return Vec::new();
    }
    let more = (p.planes.max_planes + SMALL_WALL_SEARCH).saturating_sub(found);
    let mut walls = Vec::new();
    for _ in 0..more {
        let Some(f) = search.next(p.small_wall) else {
            break;
        };
        let f = search.classified(f, up);
        if f.kind == PlaneKind::Wall && bounds_scene(&f, points, reveal, p) {
            walls.push(f);
        }
    }
    walls
}

/// How many more planes [`small_walls`] looks at.
const SMALL_WALL_SEARCH: usize = 4;

/// How far below the lowest point seen an assumed floor lies, as a share of
/// that point's height below the camera.
const FLOOR_MARGIN: f32 = 0.01;

/// "Up" from walls alone: the direction along which the two walls seen at
/// the widest angle (30° at least) meet, turned towards the camera's +y;
/// None without such a pair, or when it leans more than 35° from +y (not
/// a corner of upright walls).
fn walls_up(walls: &[&PlaneFit]) -> Option<Vec3> {
    let mut best: Option<(f32, Vec3)> = None;
    for (i, a) in walls.iter().enumerate() {
        for b in &walls[i + 1..] {
            if let Some((s, up)) = corner_up(a.plane.n, b.plane.n) {
                if best.is_none_or(|(t, _)| s > t) {
                    best = Some((s, up));
                }
            }
        }
    }
    upright(best?.1)
}

/// "Up" from one wall: the camera's up (+y) made parallel to the wall,
/// since walls stand upright; None when that leans more than 35° from +y
/// (the camera looks along a slanted plane, not at a wall).
fn upright_wall_up(wall: &PlaneFit) -> Option<Vec3> {
    let n = wall.plane.n;
    upright((Vec3::Y - n * n.dot(Vec3::Y)).normalize_or_zero())
}

/// `up` when it leans at most 35° from the camera's +y (a room's up as
/// walls give it), else None.
fn upright(up: Vec3) -> Option<Vec3> {
    (up.y >= 35f32.to_radians().cos()).then_some(up)
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

/// How far behind a plane (a share of the depth) a point next to an
/// opening may lie and still count as the plane's: a window's reveal, the
/// wall's own thickness around the hole.
pub const REVEAL_DEPTH: f32 = 0.06;
/// How near (in pixels) to a pixel that shows nothing a point must be
/// to be part of an opening's reveal.
pub const REVEAL_PIXELS: usize = 3;

/// Whether `f` bounds the seen scene: a floor, ceiling or wall with
/// `support` of the seen points on its camera side, a point of an
/// opening's reveal (`reveal`: within [`REVEAL_PIXELS`] of a pixel
/// showing nothing) counting as on it up to [`REVEAL_DEPTH`] behind it.
fn bounds_scene(f: &PlaneFit, points: &[(Vec3, f32)], reveal: &[bool], p: &CompleteParams) -> bool {
    if !matches!(
        f.kind,
        PlaneKind::Floor | PlaneKind::Ceiling | PlaneKind::Wall
    ) {
        return false;
    }
    let tol = p.planes.tolerance as f32;
    let front = points
        .iter()
        .zip(reveal)
        .filter(|&(&(q, z), &r)| {
            let behind = if r { tol.max(REVEAL_DEPTH) } else { tol };
            f.plane.distance(q) >= -behind * z
        })
        .count();
    front as f64 >= p.support * points.len() as f64
}

/// Per valid pixel of `valid` (row-major indices into the `w`×`h` depth
/// `z`): whether a pixel within [`REVEAL_PIXELS`] (a square) shows
/// nothing, i.e. it may be part of an opening's reveal.
fn near_openings(z: &GrayImage, valid: &[usize]) -> Vec<bool> {
    let (w, h) = (z.width, z.height);
    let r = REVEAL_PIXELS;
    let open = |i: usize| !(z.data[i] > 0.0 && z.data[i].is_finite());
    // Rows then columns: a square dilation of the open pixels.
    let mut rows = vec![false; w * h];
    for y in 0..h {
        for x in 0..w {
            let (a, b) = (x.saturating_sub(r), (x + r).min(w - 1));
            rows[y * w + x] = (a..=b).any(|k| open(y * w + k));
        }
    }
    valid
        .iter()
        .map(|&i| {
            let (x, y) = (i % w, i / w);
            let (a, b) = (y.saturating_sub(r), (y + r).min(h - 1));
            (a..=b).any(|k| rows[k * w + x])
        })
        .collect()
}

/// The extensions of the bounding planes of depth map `z` past the frame,
/// and how many planes were found but not extended ([`Extensions`]).
/// With `close`, also the box of the room closed, if one was, and the
/// windows of its assumed walls.
pub fn extensions(z: &GrayImage, cam: &Camera, p: &CompleteParams) -> Extensions {
    let (fits, search, up) = fit_planes_resumable(z, cam, &p.planes);
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
        return Extensions::default();
    };
    let found = fits.len();
    let reveal = near_openings(z, &valid);
    let (mut bounding, inside): (Vec<PlaneFit>, Vec<PlaneFit>) = fits
        .into_iter()
        .partition(|f| bounds_scene(f, &points, &reveal, p));
    if p.close && floor_alone(&bounding) {
        bounding.extend(small_walls(search, up, p, found, &points, &reveal));
    }
    let seen = bounding.len();
    let mut room = None;
    let mut assumed_planes = Vec::new();
    if p.close {
        let (extra, r) = closure(&bounding, &points, p);
        // The assumed ceiling and walls kept (an assumed floor always is).
        let mut k = 0;
        for f in extra {
            if f.kind == PlaneKind::Floor {
                bounding.push(f);
                continue;
            }
            let keep = p.assumed.is_none_or(|m| m >> k & 1 == 1);
            assumed_planes.push(AssumedPlane {
                bit: k,
                kind: f.kind,
                normal: f.plane.n,
            });
            k += 1;
            if keep {
                bounding.push(f);
            }
        }
        room = r;
    }
    let mut kept_in = inside.len();
    let sides = frustum_sides(cam);
    let r = p.extent * zmax;
    // Without a ceiling in view a wall's height is unknown (the room may
    // be open to the sky): walls then stop at the highest point seen on
    // them, measured along "up" (the floor's normal, else the camera's y).
    let has_ceiling = bounding.iter().any(|f| f.kind == PlaneKind::Ceiling);
    let floor = bounding
        .iter()
        .find(|f| f.kind == PlaneKind::Floor)
        .map(|f| f.plane);
    let up = floor.map(|f| f.n).unwrap_or(Vec3::Y);
    // The ceiling's height above the floor (for openings in assumed walls).
    let ceiling_height = floor.and_then(|fl| {
        bounding
            .iter()
            .filter(|f| f.kind == PlaneKind::Ceiling)
            .map(|c| c.plane.d + fl.d)
            .reduce(f32::max)
    });
    let tol = p.planes.tolerance as f32;
    let mut portals = Vec::new();
    let mut window_slots = Vec::new();
    for (k, f) in bounding.iter().enumerate() {
        let Plane { n, d } = f.plane;
        let others: Vec<Plane> = bounding
            .iter()
            .enumerate()
            .filter(|&(j, _)| j != k)
            .map(|(_, o)| o.plane)
            .collect();
        let mut mesh = fill_in_view(&f.plane, &others, z, cam, tol);
        // Only a plane that runs out of the frame continues beyond it; the
        // others still close the room (they clip the extensions).
        if !f.reaches.iter().any(|&r| r) && mesh.indices.is_empty() {
            kept_in += 1;
            continue;
        }
        let assumed = k >= seen;
        let on: Vec<usize> = if assumed {
            Vec::new()
        } else {
            (0..points.len())
                .filter(|&j| f.plane.distance(points[j].0).abs() <= tol * points[j].1)
                .collect()
        };
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
        // Walls taken to continue up past the frame's top: to where the
        // room's ceiling would be, or higher.
        let raised = |bit: u32| room.filter(|_| p.assumed.is_some_and(|m| m & bit != 0));
        let raise_to = raised(RAISE_WALLS_HIGH)
            .map(|rb| rb.height.max(p.wall_height * rb.camera_height) - rb.camera_height)
            .or(raised(RAISE_SEEN_WALLS).map(|rb| rb.height - rb.camera_height));
        if let Some(top) = raise_to.filter(|_| f.kind == PlaneKind::Wall && !has_ceiling) {
            poly = clip(&poly, -up, top);
        } else if f.kind == PlaneKind::Wall && !has_ceiling {
            if let Some(top) = on.iter().map(|&j| up.dot(points[j].0)).reduce(f32::max) {
                poly = clip(&poly, -up, top);
            } else if let Some(rb) = room.filter(|_| assumed) {
                // An assumed wall of a room left open above: as high as
                // the room's ceiling would be.
                poly = clip(&poly, -up, rb.height - rb.camera_height);
            }
        }
        let slot_plane = (room.is_some()
            && p.windows.is_some()
            && f.reaches.iter().any(|&r| r)
            && matches!(f.kind, PlaneKind::Wall | PlaneKind::Ceiling))
        .then_some(window_slots.len() / SLOT_PARTS as usize)
        .filter(|&j| j < MAX_WINDOW_PLANES);
        if let Some(j) = slot_plane {
            window_slots.extend((0..SLOT_PARTS).map(|t| WindowSlot {
                bit: SLOT_PARTS * j as u32 + t,
                kind: f.kind,
                assumed,
                normal: n,
                part: t,
            }));
        }
        let pieces = if !f.reaches.iter().any(|&r| r) {
            Vec::new()
        } else if let (Some(j), Some(mask), Some(rb)) = (slot_plane, p.windows, room) {
            let parts: Vec<u32> = (0..SLOT_PARTS)
                .filter(|t| mask >> (SLOT_PARTS * j as u32 + t) & 1 == 1)
                .collect();
            let (pieces, windows) = with_windows(&poly, f, floor, ceiling_height, &rb, &parts);
            portals.extend(windows);
            pieces
        } else if assumed && f.kind == PlaneKind::Wall && p.assumed_opening > 0.0 {
            let (pieces, window) =
                with_opening(&poly, f.plane, floor, ceiling_height, p.assumed_opening);
            portals.extend(window);
            pieces
        } else {
            vec![poly]
        };
        for piece in pieces {
            outside_view(&mut mesh, piece, &sides, n, r);
        }
        if mesh.indices.is_empty() {
            kept_in += 1;
            continue;
        }
        out.push(Extension {
            fit: f.clone(),
            mesh,
            pixels: on.iter().map(|&j| valid[j] as u32).collect(),
            assumed,
        });
    }
    Extensions {
        planes: out,
        kept_in,
        room,
        portals,
        window_slots,
        assumed_planes,
    }
}

/// Adds the part of convex polygon `poly` (on the plane of normal `n`)
/// outside the view to `mesh`: split into convex pieces outside the left,
/// right, top and bottom side of the frustum in turn (disjoint), fanned
/// into triangles facing the camera's side.
fn outside_view(mesh: &mut TriMesh, poly: Vec<Vec3>, sides: &[Vec3; 4], n: Vec3, r: f32) {
    let mut inner = poly;
    for &s in sides {
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
}

/// Share of an assumed wall's height range (from its foot) that a typical
/// window spans: from sill to lintel, as fractions of the ceiling height.
const WINDOW_BAND: (f32, f32) = (0.3, 0.85);

/// Convex polygon `poly` of an assumed wall (plane `wall`) less a window:
/// the central `width` share of the wall's horizontal extent over the
/// [`WINDOW_BAND`] of the room's height, as four convex pieces (below,
/// above, left and right of it), and the window as a [`Portal`] (the
/// rectangle of the wall's plane that bounds it, facing the camera's
/// side). Without a floor (no "up") or a ceiling height, the wall is kept
/// whole.
fn with_opening(
    poly: &[Vec3],
    wall: Plane,
    floor: Option<Plane>,
    ceiling_height: Option<f32>,
    width: f32,
) -> (Vec<Vec<Vec3>>, Option<Portal>) {
    let n = wall.n;
    let (Some(fl), Some(height)) = (floor, ceiling_height) else {
        return (vec![poly.to_vec()], None);
    };
    let up = fl.n;
    let along = up.cross(n).normalize_or_zero();
    if poly.len() < 3 || along == Vec3::ZERO || !(height > 0.0) {
        return (vec![poly.to_vec()], None);
    }
    let (s0, s1) = extent_along(poly, along);
    let (c, half) = (0.5 * (s0 + s1), 0.5 * width.clamp(0.0, 1.0) * (s1 - s0));
    // Height above the floor: up·q + fl.d.
    let (t0, t1) = (WINDOW_BAND.0 * height, WINDOW_BAND.1 * height);
    let below = clip(poly, -up, t0 - fl.d);
    let above = clip(poly, up, fl.d - t1);
    let band = clip(&clip(poly, up, fl.d - t0), -up, t1 - fl.d);
    let left = clip(&band, -along, c - half);
    let right = clip(&band, along, -(c + half));
    let window = clip(&clip(&band, along, half - c), -along, c + half);
    let pieces = [below, above, left, right]
        .into_iter()
        .filter(|q| q.len() >= 3)
        .collect();
    (pieces, bounding_portal(&window, wall, along))
}

/// Convex polygon `poly` of plane `f` (a wall or a ceiling of the closed
/// room `rb`) less windows at the given `thirds` of its length: on a wall,
/// over the [`WINDOW_BAND`] of the room's height (as `with_opening`); on
/// a ceiling, thirds along the room's first axis over the middle half of
/// its extent along the second. Returns the convex pieces left and the
/// windows as [`Portal`]s.
fn with_windows(
    poly: &[Vec3],
    f: &PlaneFit,
    floor: Option<Plane>,
    ceiling_height: Option<f32>,
    rb: &RoomBox,
    parts: &[u32],
) -> (Vec<Vec<Vec3>>, Vec<Portal>) {
    if parts.is_empty() || poly.len() < 3 {
        return (vec![poly.to_vec()], Vec::new());
    }
    let n = f.plane.n;
    // `across`: the direction of the band; `along`: that of the thirds.
    let (across, band, along) = if f.kind == PlaneKind::Ceiling {
        let (a, b) = (rb.axes[1], rb.axes[0]);
        let (lo, hi) = extent_along(poly, a);
        (a, (lo + 0.25 * (hi - lo), hi - 0.25 * (hi - lo)), b)
    } else {
        let (Some(fl), Some(height)) = (floor, ceiling_height) else {
            return (vec![poly.to_vec()], Vec::new());
        };
        let along = fl.n.cross(n).normalize_or_zero();
        (
            fl.n,
            (WINDOW_BAND.0 * height - fl.d, WINDOW_BAND.1 * height - fl.d),
            along,
        )
    };
    if along == Vec3::ZERO || across == Vec3::ZERO || !(band.1 > band.0) {
        return (vec![poly.to_vec()], Vec::new());
    }
    if parts.contains(&SLOT_ALL) {
        // The plane missing past the frame: open from edge to edge.
        return (
            Vec::new(),
            bounding_portal(poly, f.plane, along).into_iter().collect(),
        );
    }
    let (s0, s1) = extent_along(poly, along);
    let third = (s1 - s0) / 3.0;
    let holes: Vec<(f32, f32)> = if parts.contains(&SLOT_BAND) {
        // One window along all of the band but its ends.
        vec![(s0 + 0.05 * (s1 - s0), s1 - 0.05 * (s1 - s0))]
    } else {
        // Each window spans the middle 80 % of its third.
        parts
            .iter()
            .map(|&t| {
                let a = s0 + third * t as f32;
                (a + 0.1 * third, a + 0.9 * third)
            })
            .collect()
    };
    // s ≤ c: clip(−axis, c); s ≥ c: clip(axis, −c).
    let below = clip(poly, -across, band.0);
    let above = clip(poly, across, -band.1);
    let strip = clip(&clip(poly, across, -band.0), -across, band.1);
    let mut pieces: Vec<Vec<Vec3>> = vec![below, above];
    let mut portals = Vec::new();
    let mut from = f32::NEG_INFINITY;
    for &(a, b) in &holes {
        pieces.push(if from.is_finite() {
            clip(&clip(&strip, along, -from), -along, a)
        } else {
            clip(&strip, -along, a)
        });
        let hole = clip(&clip(&strip, along, -a), -along, b);
        portals.extend(bounding_portal(&hole, f.plane, along));
        from = b;
    }
    pieces.push(clip(&strip, along, -from));
    (
        pieces.into_iter().filter(|q| q.len() >= 3).collect(),
        portals,
    )
}

/// The smallest and largest of `a · q` over the points `q` of `poly`.
fn extent_along(poly: &[Vec3], a: Vec3) -> (f32, f32) {
    poly.iter()
        .map(|q| a.dot(*q))
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), s| {
            (lo.min(s), hi.max(s))
        })
}

/// The rectangle of plane `wall` (axes `along`, which lies in it, and
/// `wall.n × along`) that bounds convex polygon `window` on it, as a
/// [`Portal`] facing the camera's side of the plane; `None` for a
/// degenerate window.
fn bounding_portal(window: &[Vec3], wall: Plane, along: Vec3) -> Option<Portal> {
    if window.len() < 3 {
        return None;
    }
    let across = wall.n.cross(along).normalize_or_zero();
    let ((a0, a1), (b0, b1)) = (extent_along(window, along), extent_along(window, across));
    let corner = -wall.n * wall.d + along * a0 + across * b0;
    let (u, v) = (along * (a1 - a0), across * (b1 - b0));
    // along × across = n: inward (towards the camera) when d > 0.
    let portal = if wall.d >= 0.0 {
        Portal { corner, u, v }
    } else {
        Portal { corner, u: v, v: u }
    };
    portal.is_valid().then_some(portal)
}

/// The part of plane `f` that the view shows hidden behind nearer
/// geometry, as triangles over the pixel-centre grid (facing the camera's
/// side): a pixel whose point lies in front of the plane (by more than
/// `tol`·z) is *occluded*, one on it (within `tol`·z) is *covered* by the
/// depth mesh, one behind it or showing nothing (a window's sky) is *open*.
/// Every grid quad of occluded or covered pixels, one at least occluded,
/// whose plane points are in front of the camera and on the camera's side
/// of the `others`, is filled: the plane then continues behind furniture
/// and objects, so no light passes through where the view cannot see,
/// while what the image shows (openings included) is left as it is.
fn fill_in_view(f: &Plane, others: &[Plane], z: &GrayImage, cam: &Camera, tol: f32) -> TriMesh {
    let (w, h) = (z.width, z.height);
    const OPEN: u8 = 0;
    const COVERED: u8 = 1;
    const OCCLUDED: u8 = 2;
    let mut state = vec![OPEN; w * h];
    let mut point = vec![Vec3::ZERO; w * h];
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            let zi = z.data[i];
            if !(zi > 0.0 && zi.is_finite()) {
                continue;
            }
            // The pixel's ray (z = −1) and its point at the pixel's depth.
            let dir = cam.backproject(x as f32, y as f32, 1.0);
            let dist = f.distance(dir * zi);
            let st = if dist.abs() <= tol * zi {
                COVERED
            } else if dist > 0.0 {
                OCCLUDED
            } else {
                continue;
            };
            // Where the pixel's ray meets the plane.
            let den = f.n.dot(dir);
            if den.abs() < 1e-9 {
                continue;
            }
            let s = -f.d / den;
            let q = dir * s;
            // A hidden point must be well inside the room (not on a crease
            // with another of its planes); a covered one may be on it.
            let inside = if st == OCCLUDED { tol * s } else { -tol * s };
            if !(s > 0.0 && s.is_finite()) || others.iter().any(|o| o.distance(q) < inside) {
                continue;
            }
            state[i] = st;
            point[i] = q;
        }
    }
    let mut mesh = TriMesh::default();
    let mut index = vec![u32::MAX; w * h];
    for y in 0..h.saturating_sub(1) {
        for x in 0..w.saturating_sub(1) {
            let q = [
                y * w + x,
                y * w + x + 1,
                (y + 1) * w + x + 1,
                (y + 1) * w + x,
            ];
            if q.iter().any(|&i| state[i] == OPEN) || !q.iter().any(|&i| state[i] == OCCLUDED) {
                continue;
            }
            let v = q.map(|i| {
                if index[i] == u32::MAX {
                    index[i] = mesh.positions.len() as u32;
                    mesh.positions.push(point[i]);
                }
                index[i]
            });
            for t in [[v[0], v[1], v[2]], [v[0], v[2], v[3]]] {
                let [a, b, c] = t.map(|k| mesh.positions[k as usize]);
                let nrm = (b - a).cross(c - a);
                if nrm.length_squared() <= 0.0 {
                    continue;
                }
                mesh.indices.push(if nrm.dot(f.n) >= 0.0 {
                    t
                } else {
                    [t[0], t[2], t[1]]
                });
            }
        }
    }
    mesh
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
    let Extensions {
        planes: exts,
        kept_in,
        room,
        portals,
        ..
    } = extensions(z, cam, p);
    let (w, h) = (z.width, z.height);
    let mut done = Completion {
        kept_in,
        lamp_sites: room.map(|r| r.lamp_sites()).unwrap_or_default(),
        room_height: room.map_or(0.0, |r| r.height),
        portals: portals.len(),
        ..Completion::default()
    };
    // The assumed walls' windows, for renderers to sample as lights.
    mesh.portals.extend(portals);
    // Without planes to extend, what the border cuts still continues past
    // it (else the rays through the outer half of the border pixels, past
    // the last pixel centres, leave the scene: a bright frame on the
    // render); only a view with no geometry, or no margin, is left as it is.
    let margin = (p.border_margin.max(0.0) * w.max(h) as f32).round() as usize;
    let seen = |i: usize| z.data[i] > 0.0 && z.data[i].is_finite();
    if exts.is_empty() && (margin == 0 || !(0..w * h).any(seen)) {
        return done;
    }
    // Assumed planes continue the walls seen (else the whole view).
    let walls: Vec<u32> = exts
        .iter()
        .filter(|e| !e.assumed && e.fit.kind == PlaneKind::Wall)
        .flat_map(|e| e.pixels.iter().copied())
        .collect();
    // The nearest pixel with geometry: built only where a plane has no
    // pixels of its own to continue, and then once.
    let seen_map: std::cell::OnceCell<Vec<u32>> = std::cell::OnceCell::new();
    let all_seen = || {
        let pixels: Vec<u32> = (0..w * h).filter(|&i| seen(i)).map(|i| i as u32).collect();
        nearest_seed_map(w, h, &pixels)
    };
    mesh.material_pixel
        .resize(mesh.indices.len(), crate::mesh::PROJECTED);
    let mut on_plane = vec![false; w * h];
    for e in exts.iter().filter(|e| !e.assumed) {
        for &i in &e.pixels {
            on_plane[i as usize] = true;
        }
    }
    // Every assumed plane continues the same pixels: one map for them all.
    let mut assumed_map: Option<Vec<u32>> = None;
    for e in exts {
        let own;
        let nearest: &[u32] = if e.assumed && !walls.is_empty() {
            assumed_map.get_or_insert_with(|| nearest_seed_map(w, h, &walls))
        } else if e.assumed || e.pixels.is_empty() {
            seen_map.get_or_init(&all_seen)
        } else {
            own = nearest_seed_map(w, h, &e.pixels);
            &own
        };
        let centre = nearest[(h / 2) * w + w / 2];
        let film = e
            .mesh
            .positions
            .iter()
            .map(|&q| cam.project(q).unwrap_or(Vec2::ZERO));
        let pixels = e.mesh.indices.iter().map(|t| {
            let c = t
                .iter()
                .map(|&k| e.mesh.positions[k as usize])
                .sum::<Vec3>()
                / 3.0;
            cam.project(c)
                .map_or(centre, |f| nearest[pixel_at(f, w, h)])
        });
        let start = mesh.indices.len();
        append(mesh, &e.mesh, film, pixels, w, h);
        let open = p.assumed_openness.clamp(0.0, 1.0);
        if e.assumed && matches!(e.fit.kind, PlaneKind::Wall | PlaneKind::Ceiling) && open > 0.0 {
            mesh.openness.resize(start, 0.0);
            mesh.openness.resize(mesh.indices.len(), open);
        }
        done.triangles += e.mesh.indices.len();
        done.extended.push(e.fit);
    }
    // Objects cut by the border continue past it (what lies on an
    // extended plane is already continued by its extension).
    if margin > 0 {
        let extra = border_margins(z, cam, &on_plane, margin);
        append(
            mesh,
            &extra,
            extra.film.iter().copied(),
            extra.material_pixel.iter().copied(),
            w,
            h,
        );
        done.triangles += extra.indices.len();
        done.border_triangles = extra.indices.len();
    }
    if !mesh.openness.is_empty() {
        mesh.openness.resize(mesh.indices.len(), 0.0);
    }
    done
}

/// The pixel of a `w`×`h` image a film position falls in, clamped to the
/// frame (row-major index).
fn pixel_at(f: Vec2, w: usize, h: usize) -> usize {
    let x = (f.x.floor().max(0.0) as usize).min(w - 1);
    let y = (f.y.floor().max(0.0) as usize).min(h - 1);
    y * w + x
}

/// Appends `part`'s triangles to `mesh`, each taking the material of the
/// matching pixel of `pixels`; when `mesh` keeps film positions, `film`
/// gives `part`'s (clamped to the `w`×`h` frame).
fn append(
    mesh: &mut TriMesh,
    part: &TriMesh,
    film: impl Iterator<Item = Vec2>,
    pixels: impl Iterator<Item = u32>,
    w: usize,
    h: usize,
) {
    let base = mesh.positions.len() as u32;
    mesh.positions.extend_from_slice(&part.positions);
    if !mesh.film.is_empty() {
        let frame = Vec2::new(w as f32, h as f32);
        mesh.film.extend(film.map(|f| f.clamp(Vec2::ZERO, frame)));
    }
    mesh.material_pixel.extend(pixels);
    mesh.indices
        .extend(part.indices.iter().map(|t| t.map(|k| k + base)));
}

/// Inward pixels whose inverse depth is fitted to continue a surface past
/// the border.
const BORDER_RUN: usize = 6;
/// Largest relative change of inverse depth between neighbours of such a
/// run (more is an occluding edge, not one surface).
const BORDER_JUMP: f32 = 0.05;
/// How far a continued surface may recede or approach: its depth stays
/// within this factor of the border pixel's.
const BORDER_RANGE: f32 = 2.0;

/// Surfaces cut by the frame border, continued `margin` pixels past it:
/// along each border pixel's row (left and right borders) or column (top
/// and bottom), the inverse depth of the last [`BORDER_RUN`] pixels is
/// fitted by a line in the pixel coordinate and extrapolated (exact for
/// a plane, whose inverse depth is affine in the film position; a first
/// order continuation of a curved one). A run that is not one surface
/// (an occluding edge, sky, a pixel flagged in `skip`) is not continued,
/// nor is the part of a continuation whose depth leaves
/// [`BORDER_RANGE`] of the border pixel's. The continuation is meshed
/// like the view (pixel-centre grid, same cuts at discontinuities) on a
/// camera with the same focal length widened by the margin; each added
/// triangle takes the material of the border pixel it continues. The
/// result's film positions lie outside the frame (unclamped).
pub fn border_margins(z: &GrayImage, cam: &Camera, skip: &[bool], margin: usize) -> TriMesh {
    let (w, h) = (z.width, z.height);
    let mut out = TriMesh::default();
    if w < BORDER_RUN || h < BORDER_RUN || margin == 0 || skip.len() != w * h {
        return out;
    }
    let (pw, ph) = (w + 2 * margin, h + 2 * margin);
    let mut padded = GrayImage::new(pw, ph, 0.0);
    let at = |x: isize, y: isize| -> Option<usize> {
        (x >= 0 && y >= 0 && (x as usize) < w && (y as usize) < h)
            .then(|| y as usize * w + x as usize)
    };
    // The original's border strips (for the seam) ...
    for y in 0..h {
        for x in 0..w {
            if x < BORDER_RUN || y < BORDER_RUN || x + BORDER_RUN >= w || y + BORDER_RUN >= h {
                padded.data[(y + margin) * pw + x + margin] = z.data[y * w + x];
            }
        }
    }
    // ... and each side's continuation: (start pixel, inward step).
    let mut starts: Vec<((isize, isize), (isize, isize))> = Vec::new();
    for y in 0..h as isize {
        starts.push(((0, y), (1, 0)));
        starts.push(((w as isize - 1, y), (-1, 0)));
    }
    for x in 0..w as isize {
        starts.push(((x, 0), (0, 1)));
        starts.push(((x, h as isize - 1), (0, -1)));
    }
    for ((x0, y0), (dx, dy)) in starts {
        let mut inv = [0.0f32; BORDER_RUN];
        let mut ok = true;
        for (k, v) in inv.iter_mut().enumerate() {
            let k = k as isize;
            match at(x0 + k * dx, y0 + k * dy) {
                Some(i) if z.data[i] > 0.0 && z.data[i].is_finite() && !skip[i] => {
                    *v = 1.0 / z.data[i];
                }
                _ => ok = false,
            }
        }
        if !ok
            || inv
                .windows(2)
                .any(|p| (p[1] - p[0]).abs() > BORDER_JUMP * p[0].max(p[1]))
        {
            continue;
        }
        // Least squares line through (k, inv[k]).
        let n = BORDER_RUN as f64;
        let mk = (n - 1.0) / 2.0;
        let mv = inv.iter().map(|&v| v as f64).sum::<f64>() / n;
        let (mut sxy, mut sxx) = (0.0f64, 0.0f64);
        for (k, &v) in inv.iter().enumerate() {
            let dk = k as f64 - mk;
            sxy += dk * (v as f64 - mv);
            sxx += dk * dk;
        }
        let slope = if sxx > 0.0 { sxy / sxx } else { 0.0 };
        let s0 = inv[0] as f64;
        for t in 1..=margin as isize {
            let s = mv + slope * (-(t as f64) - mk);
            if !(s > s0 / BORDER_RANGE as f64 && s < s0 * BORDER_RANGE as f64) {
                break;
            }
            let (px, py) = (x0 - t * dx + margin as isize, y0 - t * dy + margin as isize);
            padded.data[py as usize * pw + px as usize] = (1.0 / s) as f32;
        }
    }
    // Same focal length, principal point shifted by the margin.
    let fov = (2.0 * ((pw as f64 * 0.5) / cam.focal() as f64).atan()).to_degrees() as f32;
    let wide = Camera {
        width: pw,
        height: ph,
        fov_x_deg: fov,
    };
    let Ok(dm) = crate::depth_mesh::mesh_from_depth(&padded, &wide, &Default::default()) else {
        return out;
    };
    let m = margin as f32;
    let inside = |f: Vec2| f.x > m && f.y > m && f.x < m + w as f32 && f.y < m + h as f32;
    let mut remap = vec![u32::MAX; dm.mesh.positions.len()];
    for tri in &dm.mesh.indices {
        let films = tri.map(|k| dm.mesh.film[k as usize]);
        if films.iter().all(|&f| inside(f)) {
            continue;
        }
        let idx = tri.map(|k| {
            let k = k as usize;
            if remap[k] == u32::MAX {
                remap[k] = out.positions.len() as u32;
                out.positions.push(dm.mesh.positions[k]);
                out.film.push(dm.mesh.film[k] - Vec2::splat(m));
            }
            remap[k]
        });
        let c = (films[0] + films[1] + films[2]) / 3.0 - Vec2::splat(m);
        out.indices.push(idx);
        out.material_pixel.push(pixel_at(c, w, h) as u32);
    }
    out
}

/// For every pixel of a `w`×`h` image, the nearest of the `seeds` (pixel
/// indices; [`crate::mesh::PROJECTED`] everywhere when there are none):
/// the seeds propagated by two raster passes over the 8-neighbourhood
/// (the usual distance-transform approximation: within a pixel or so of
/// the true nearest seed, deterministic).
fn nearest_seed_map(w: usize, h: usize, seeds: &[u32]) -> Vec<u32> {
    let mut near = vec![crate::mesh::PROJECTED; w * h];
    for &s in seeds {
        if (s as usize) < w * h {
            near[s as usize] = s;
        }
    }
    let d2 = |i: usize, s: u32| -> i64 {
        let (dx, dy) = (
            (i % w) as i64 - (s as usize % w) as i64,
            (i / w) as i64 - (s as usize / w) as i64,
        );
        dx * dx + dy * dy
    };
    let mut relax = |i: usize, j: usize| {
        let s = near[j];
        if s != crate::mesh::PROJECTED
            && (near[i] == crate::mesh::PROJECTED || d2(i, s) < d2(i, near[i]))
        {
            near[i] = s;
        }
    };
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            if x > 0 {
                relax(i, i - 1);
            }
            if y > 0 {
                relax(i, i - w);
                if x > 0 {
                    relax(i, i - w - 1);
                }
                if x + 1 < w {
                    relax(i, i - w + 1);
                }
            }
        }
    }
    for y in (0..h).rev() {
        for x in (0..w).rev() {
            let i = y * w + x;
            if x + 1 < w {
                relax(i, i + 1);
            }
            if y + 1 < h {
                relax(i, i + w);
                if x + 1 < w {
                    relax(i, i + w + 1);
                }
                if x > 0 {
                    relax(i, i + w - 1);
                }
            }
        }
    }
    near
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::planes::testmaps::render_planes;
    use crate::planes::PlaneKind;

    /// The nearest hit of a ray from the origin on `mesh`'s triangles from
    /// index `from` on (Möller–Trumbore).
    fn hit(mesh: &TriMesh, from: usize, dir: Vec3) -> Option<f32> {
        hit_at(mesh, from, Vec3::ZERO, dir)
    }

    /// [`hit`] from `origin`, over every triangle.
    fn hit_from(mesh: &TriMesh, origin: Vec3, dir: Vec3) -> Option<f32> {
        hit_at(mesh, 0, origin, dir)
    }

    fn hit_at(mesh: &TriMesh, from: usize, origin: Vec3, dir: Vec3) -> Option<f32> {
        let mut best: Option<f32> = None;
        for tri in &mesh.indices[from..] {
            let [a, b, c] = tri.map(|k| mesh.positions[k as usize] - origin);
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

    /// The completion alone (no depth mesh) of `z` with the room closed
    /// and no windows in the assumed walls.
    fn closed_without_windows(z: &GrayImage, cam: &Camera) -> (TriMesh, Completion) {
        let closed = CompleteParams {
            close: true,
            assumed_opening: 0.0,
            ..CompleteParams::default()
        };
        let mut mesh = TriMesh::default();
        let c = complete_beyond_frame(&mut mesh, z, cam, &closed);
        (mesh, c)
    }

    /// No ray through every `step`-th pixel centre of a 96×72 view meets
    /// `mesh` (the completion covers nothing the image shows).
    fn assert_view_open(mesh: &TriMesh, cam: &Camera, step: usize) {
        for y in (0..72).step_by(step) {
            for x in (0..96).step_by(step) {
                let dir = cam.backproject(x as f32, y as f32, 1.0).normalize();
                assert!(hit(mesh, 0, dir).is_none(), "pixel {x},{y}");
            }
        }
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
        assert_view_open(&mesh, &cam, 7);
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
    fn hidden_parts_of_a_wall_are_filled_and_what_the_view_shows_is_kept() {
        let cam = Camera::new(96, 72);
        let mut z = render_planes(&cam, &ROOM);
        // A cabinet front at depth 3 in front of the back wall, and a
        // window in the back wall showing the sky (no depth).
        let (cabinet, window) = ((44..52, 32..40), (10..16, 20..26));
        for y in cabinet.1.clone() {
            for x in cabinet.0.clone() {
                z.data[y * 96 + x] = 3.0;
            }
        }
        for y in window.1.clone() {
            for x in window.0.clone() {
                z.data[y * 96 + x] = 0.0;
            }
        }
        let exts = extensions(&z, &cam, &CompleteParams::default()).planes;
        let back = exts
            .iter()
            .find(|e| (e.fit.plane.d - 8.0).abs() < 1e-2 && e.fit.plane.n.z > 0.99)
            .expect("the back wall is filled behind the cabinet");
        let dir = |x: usize, y: usize| cam.backproject(x as f32, y as f32, 1.0).normalize();
        // Behind the cabinet, the wall is there at its own depth.
        let d = dir(47, 36);
        let t = hit(&back.mesh, 0, d).expect("wall behind the cabinet");
        assert!((t * -d.z - 8.0).abs() < 1e-2, "{}", t * -d.z);
        // The window and the wall the view shows are left alone.
        for (x, y) in [(12, 22), (11, 21), (80, 60), (30, 50)] {
            assert!(hit(&back.mesh, 0, dir(x, y)).is_none(), "{x},{y}");
        }
    }

    /// Floor 0.9 below the camera and a front wall 8 ahead, nothing else.
    const FLOOR_AND_WALL: [(Vec3, f32); 2] = [(Vec3::Y, 0.9), (Vec3::Z, 8.0)];

    #[test]
    fn a_room_is_closed_with_a_ceiling_and_walls_where_the_view_shows_one() {
        let cam = Camera::new(96, 72);
        let z = render_planes(&cam, &FLOOR_AND_WALL);
        let (mesh, c) = closed_without_windows(&z, &cam);
        // Floor and wall seen; ceiling and three walls assumed.
        assert_eq!(c.extended.len(), 6, "{c:?}");
        // The ceiling is just above the highest point seen (the wall's top
        // edge, higher than 1.8 camera heights here).
        let top = (z.height as f32 - 1.0) * 0.5 / cam.focal() * 8.0;
        let up = hit(&mesh, 0, Vec3::Y).expect("a ceiling");
        assert!((up - (top + 0.05 * 0.9)).abs() < 0.02, "{up} vs {top}");
        // Behind the camera, a wall half a camera height away; to the
        // sides, walls just beyond the floor seen.
        let back = hit(&mesh, 0, Vec3::Z).expect("a wall behind");
        assert!((back - 0.45).abs() < 1e-3, "{back}");
        for side in [Vec3::X, Vec3::NEG_X] {
            assert!(hit(&mesh, 0, side).is_some(), "{side}");
        }
        // Still nothing in view.
        assert_view_open(&mesh, &cam, 5);
        // Lamp sites: a grid under the ceiling, each with the ceiling
        // straight above it at the room's height times the drop, over the
        // room from the wall behind the camera to the wall seen.
        assert_eq!(c.lamp_sites.len(), LAMP_GRID * LAMP_GRID);
        assert!(
            (c.room_height - (up + 0.9)).abs() < 1e-3,
            "{}",
            c.room_height
        );
        for &q in &c.lamp_sites {
            let over = hit_from(&mesh, q, Vec3::Y).expect("the ceiling above");
            assert!(
                (over - LAMP_DROP * c.room_height).abs() < 1e-3,
                "{q}: {over}"
            );
            // Cell centres of [−0.45, 8.045] (the wall behind, the wall
            // seen plus the margin) in thirds.
            let cells = [0.966f32, 3.798, 6.629];
            assert!(cells.iter().any(|d| (q.z + d).abs() < 1e-3), "{q}");
        }
        // With the default typical window in each assumed wall, light
        // comes in straight from behind at the camera's height, not from
        // low down nor through the ceiling.
        let mut open = TriMesh::default();
        complete_beyond_frame(
            &mut open,
            &z,
            &cam,
            &CompleteParams {
                close: true,
                ..CompleteParams::default()
            },
        );
        assert!(hit(&open, 0, Vec3::Z).is_none());
        assert!(hit(&open, 0, Vec3::new(0.0, -1.0, 0.3).normalize()).is_some());
        assert!(hit(&open, 0, Vec3::Y).is_some());
        // Each window is a portal: a rectangle on its assumed wall over
        // the window band, facing the camera; the ray to its centre
        // leaves the room, rays just beyond its edges meet the wall.
        assert!(mesh.portals.is_empty(), "no windows, no portals");
        let open_c = complete_beyond_frame(
            &mut TriMesh::default(),
            &z,
            &cam,
            &CompleteParams {
                close: true,
                ..CompleteParams::default()
            },
        );
        assert_eq!(open.portals.len(), 3, "behind and either side");
        assert_eq!(open_c.portals, 3);
        let floor_y = -0.9;
        for p in &open.portals {
            assert!(p.is_valid(), "{p:?}");
            let centre = p.corner + (p.u + p.v) * 0.5;
            assert!(p.normal().dot(-centre) > 0.0, "{p:?} faces away");
            // Upright, over [0.3, 0.85] of the room's height.
            let corners = [
                p.corner,
                p.corner + p.u,
                p.corner + p.v,
                p.corner + p.u + p.v,
            ];
            let (lo, hi) = extent_along(&corners, Vec3::Y);
            let h = c.room_height;
            assert!((lo - floor_y - 0.3 * h).abs() < 1e-3, "{lo}");
            assert!((hi - floor_y - 0.85 * h).abs() < 1e-3, "{hi}");
            assert!(hit(&open, 0, centre.normalize()).is_none(), "{p:?}");
            for outside in [
                p.corner + p.u * 0.5 - p.v * 0.05,
                p.corner + p.u * 0.5 + p.v * 1.05,
                p.corner - p.u * 0.05 + p.v * 0.5,
                p.corner + p.u * 1.05 + p.v * 0.5,
            ] {
                let t = hit(&open, 0, outside.normalize()).expect("the wall around it");
                assert!((t - outside.length()).abs() < 1e-3, "{outside}: {t}");
            }
        }
    }

    #[test]
    fn a_window_s_reveal_does_not_stop_its_wall_bounding_the_room() {
        let cam = Camera::new(96, 72);
        // The wall 8 ahead with a window (no depth) and, around it, a
        // 2-pixel ring `deeper` times as far: the reveal, the wall's
        // own thickness (3 %), or something well behind it (30 %).
        let with_ring = |deeper: f32| {
            let mut z = render_planes(&cam, &FLOOR_AND_WALL);
            for y in 8..24 {
                for x in 28..64 {
                    let i = y * 96 + x;
                    if (10..22).contains(&y) && (30..62).contains(&x) {
                        z.data[i] = 0.0;
                    } else {
                        z.data[i] *= deeper;
                    }
                }
            }
            z
        };
        let wall_extended = |z: &GrayImage| {
            extensions(z, &cam, &CompleteParams::default())
                .planes
                .iter()
                .any(|e| e.fit.kind == PlaneKind::Wall && (e.fit.plane.d - 8.0).abs() < 0.05)
        };
        assert!(wall_extended(&render_planes(&cam, &FLOOR_AND_WALL)));
        assert!(wall_extended(&with_ring(1.03)), "a reveal");
        assert!(
            !wall_extended(&with_ring(1.3)),
            "a wall with things behind it"
        );
    }

    /// The completion of `base`'s room in view `z` with the assumed planes
    /// (and raised walls) of `mask`, no window.
    fn walled(z: &GrayImage, cam: &Camera, base: &CompleteParams, mask: u32) -> TriMesh {
        let mut m = TriMesh::default();
        complete_beyond_frame(
            &mut m,
            z,
            cam,
            &CompleteParams {
                assumed: Some(mask),
                windows: Some(0),
                ..*base
            },
        );
        m
    }

    #[test]
    fn assumed_walls_and_the_ceiling_are_kept_one_by_one() {
        let cam = Camera::new(96, 72);
        let z = render_planes(&cam, &FLOOR_AND_WALL);
        let base = CompleteParams::for_mode("room").unwrap();
        let planes = assumed_planes(&z, &cam, &base);
        // The ceiling, the walls left, behind and right, and the walls
        // raised two ways (no ceiling in view).
        let names: Vec<String> = planes.iter().map(|p| p.describe()).collect();
        assert_eq!(planes.len(), 6, "{names:?}");
        for n in ["ceiling", "wall left", "wall behind", "wall right"] {
            assert!(names.iter().any(|x| x == n), "{n} in {names:?}");
        }
        assert!(names[4].starts_with("the walls seen raised"));
        assert!(names[5].starts_with("every wall raised"));
        let bit = |n: &str| 1u32 << planes.iter().find(|p| p.describe() == n).unwrap().bit;
        let build = |mask: u32| walled(&z, &cam, &base, mask);
        // Nothing assumed: open behind and above.
        let open = build(0);
        assert!(hit(&open, 0, Vec3::Z).is_none());
        assert!(hit(&open, 0, Vec3::Y).is_none());
        // The wall behind alone: half a camera height behind, solid, as
        // high as the ceiling would be; still open above.
        let behind = build(bit("wall behind"));
        let t = hit(&behind, 0, Vec3::Z).expect("the wall behind");
        assert!((t - 0.45).abs() < 1e-3, "{t}");
        assert!(hit(&behind, 0, Vec3::Y).is_none());
        let (all, _) = closed_without_windows(&z, &cam);
        let top = hit(&all, 0, Vec3::Y).expect("the closed room's ceiling");
        let up_behind = Vec3::new(0.0, top - 0.01, 0.45).normalize();
        assert!(
            hit(&behind, 0, up_behind).is_some(),
            "up to the ceiling's height"
        );
        let over = Vec3::new(0.0, top + 0.05, 0.45).normalize();
        assert!(hit(&behind, 0, over).is_none(), "not above it");
        // The ceiling alone closes above.
        assert!(hit(&build(bit("ceiling")), 0, Vec3::Y).is_some());
        // The wall seen stops at the highest point seen on it, unless
        // raised to the room's height.
        let above_frame = Vec3::new(0.0, top - 0.01, -8.0).normalize();
        assert!(hit(&open, 0, above_frame).is_none());
        let raised = build(RAISE_SEEN_WALLS);
        let t = hit(&raised, 0, above_frame).expect("the wall seen, raised");
        assert!((t * -above_frame.z - 8.0).abs() < 1e-2, "{t}");
        // Raised high (a near wall: the room's assumed height, 1.8 camera
        // heights, is under three): the wall seen and the assumed wall
        // behind reach 2.7 above the floor, 1.8 above the camera.
        let near = render_planes(&cam, &[(Vec3::Y, 0.9), (Vec3::Z, 4.0)]);
        let near_planes = assumed_planes(&near, &cam, &base);
        let behind_bit = near_planes
            .iter()
            .find(|p| p.describe() == "wall behind")
            .map(|p| 1u32 << p.bit)
            .expect("a wall behind");
        let build_near = |mask: u32| walled(&near, &cam, &base, mask);
        let high = build_near(RAISE_WALLS_HIGH | behind_bit);
        let low = build_near(RAISE_SEEN_WALLS | behind_bit);
        let ahead = Vec3::new(0.0, 1.7, -4.0).normalize();
        let t = hit(&high, 0, ahead).expect("the wall seen, high");
        assert!((t * -ahead.z - 4.0).abs() < 1e-2, "{t}");
        assert!(hit(&low, 0, ahead).is_none(), "the room's height is lower");
        assert!(hit(&high, 0, Vec3::new(0.0, 1.7, 0.45).normalize()).is_some());
        assert!(hit(&high, 0, Vec3::new(0.0, 1.9, 0.45).normalize()).is_none());
        // Every plane kept is the closed room.
        let every = build(
            planes
                .iter()
                .filter(|p| p.kind == PlaneKind::Ceiling || p.bit < 30)
                .fold(0, |m, p| m | 1 << p.bit),
        );
        assert_eq!(every.indices.len(), all.indices.len());
    }

    #[test]
    fn windows_open_one_slot_at_a_time_where_the_mask_says() {
        let cam = Camera::new(96, 72);
        let z = render_planes(&cam, &FLOOR_AND_WALL);
        let base = CompleteParams::for_mode("room").unwrap();
        let slots = window_slots(&z, &cam, &base);
        // The wall seen runs past the frame, as do the ceiling and the
        // three assumed walls: five parts each (thirds, the band, all of
        // it), bits in order.
        assert_eq!(slots.len(), 25, "{slots:?}");
        for (k, s) in slots.iter().enumerate() {
            assert_eq!(s.bit as usize, k);
            assert_eq!(s.part, k as u32 % SLOT_PARTS);
        }
        assert_eq!(
            slots
                .iter()
                .filter(|s| s.kind == PlaneKind::Ceiling)
                .count(),
            5
        );
        assert!(slots
            .iter()
            .any(|s| !s.assumed && s.describe().starts_with("wall ahead (seen)")));
        assert!(slots
            .iter()
            .any(|s| s.describe().starts_with("wall behind (assumed)")));
        // No window: the closed room exactly.
        let (closed, _) = closed_without_windows(&z, &cam);
        let mut none = TriMesh::default();
        let c = complete_beyond_frame(
            &mut none,
            &z,
            &cam,
            &CompleteParams {
                windows: Some(0),
                ..base
            },
        );
        assert_eq!(c.portals, 0);
        assert_eq!(none.positions, closed.positions);
        assert_eq!(none.indices, closed.indices);
        // Each slot alone: one portal, on its plane, whose centre the
        // camera sees the sky through; the room stays closed elsewhere.
        for s in &slots {
            let mut m = TriMesh::default();
            let c = complete_beyond_frame(
                &mut m,
                &z,
                &cam,
                &CompleteParams {
                    windows: Some(1 << s.bit),
                    ..base
                },
            );
            assert_eq!(c.portals, 1, "{}", s.describe());
            let p = m.portals[0];
            let centre = p.corner + (p.u + p.v) * 0.5;
            assert!(p.normal().dot(s.normal) > 0.99, "{}", s.describe());
            assert!(p.normal().dot(-centre) > 0.0, "{} faces away", s.describe());
            // (What the view shows is the depth mesh's, not the
            // completion's.)
            let in_view = |q: Vec3| {
                cam.project(q)
                    .is_some_and(|f| f.x >= -1.0 && f.y >= -1.0 && f.x <= 97.0 && f.y <= 73.0)
            };
            if !in_view(centre) {
                assert!(hit(&m, 0, centre.normalize()).is_none(), "{}", s.describe());
            }
            // Just beside the window, its plane (but for a plane missing
            // altogether).
            let beside = p.corner - p.u * 0.05 + p.v * 0.5;
            if !in_view(beside) && s.part != SLOT_ALL {
                assert!(hit(&m, 0, beside.normalize()).is_some(), "{}", s.describe());
            }
            assert!(hit(&m, 0, Vec3::new(0.0, -1.0, 0.3).normalize()).is_some());
        }
        // Two thirds of one wall: two windows, the wall between them kept.
        let behind: Vec<&WindowSlot> = slots
            .iter()
            .filter(|s| s.describe().starts_with("wall behind"))
            .collect();
        let complete_with = |mask: u32| {
            let mut m = TriMesh::default();
            complete_beyond_frame(
                &mut m,
                &z,
                &cam,
                &CompleteParams {
                    windows: Some(mask),
                    ..base
                },
            );
            m
        };
        let m = complete_with(1 << behind[0].bit | 1 << behind[2].bit);
        assert_eq!(m.portals.len(), 2);
        let centre = |p: &Portal| p.corner + (p.u + p.v) * 0.5;
        let mid = (centre(&m.portals[0]) + centre(&m.portals[1])) * 0.5;
        assert!(hit(&m, 0, mid.normalize()).is_some(), "the wall between");
        // Its band: one window over the middle of the wall, wider than a
        // third; all of it: no wall behind at all.
        let band = complete_with(1 << (behind[0].bit - behind[0].part + SLOT_BAND));
        assert_eq!(band.portals.len(), 1);
        assert!(
            band.portals[0].u.length().max(band.portals[0].v.length())
                > 2.0 * m.portals[0].u.length().max(m.portals[0].v.length())
        );
        assert!(hit(&band, 0, mid.normalize()).is_none(), "no wall between");
        let all = complete_with(1 << (behind[0].bit - behind[0].part + SLOT_ALL));
        assert!(
            hit(&all, 0, Vec3::Z).is_none()
                && hit(&all, 0, Vec3::new(0.0, -0.5, 1.0).normalize()).is_none()
        );
        let (closed, _) = closed_without_windows(&z, &cam);
        assert!(hit(&closed, 0, Vec3::new(0.0, -0.5, 1.0).normalize()).is_some());
    }

    /// [`complete_beyond_frame`] with nothing continued past the border.
    fn without_margin(mesh: &mut TriMesh, z: &GrayImage, cam: &Camera) -> Completion {
        let p = CompleteParams {
            border_margin: 0.0,
            ..CompleteParams::default()
        };
        complete_beyond_frame(mesh, z, cam, &p)
    }

    #[test]
    fn an_object_cut_by_the_border_continues_past_it_on_its_own_surface() {
        let cam = Camera::new(96, 72);
        let mut z = render_planes(&cam, &ROOM);
        // A slanted cabinet front (normal turned 25° to the right) at
        // about depth 3, over the left border in rows 30..50.
        let (n, d) = (Vec3::new(0.42, 0.0, 0.9).normalize(), 3.0);
        let (rows, cols) = (30..50, 0..20);
        for y in rows.clone() {
            for x in cols.clone() {
                let dir = cam.backproject(x as f32, y as f32, 1.0);
                z.data[y * 96 + x] = -d / n.dot(dir);
            }
        }
        let mut mesh = TriMesh::default();
        let c = complete_beyond_frame(&mut mesh, &z, &cam, &CompleteParams::default());
        assert!(c.border_triangles > 0, "{c:?}");
        let first = c.triangles - c.border_triangles;
        let added = &mesh.indices[first..];
        let mut beyond = 0;
        for (t, tri) in added.iter().enumerate() {
            for &k in tri {
                // At most the margin past the left border, within the
                // cabinet's rows; on the cabinet's plane (room planes are
                // continued by their own extensions) but in its edge rows,
                // which the mesher pushes back to the wall behind, in view
                // and beyond alike.
                let q = mesh.positions[k as usize];
                let f = cam.project(q).unwrap();
                if f.y > 32.0 && f.y < 48.0 {
                    assert!((n.dot(q) + d).abs() < 2e-3 * q.length(), "{q} at {f}");
                }
                assert!(f.x > -10.0 - 1e-2 && f.x < 1.0, "{f}");
                assert!(f.y > 29.0 && f.y < 51.0, "{f}");
                beyond += (f.x < 0.0) as usize;
            }
            // It takes the material of the cabinet's border pixel.
            let px = mesh.material_pixel[first + t] as usize;
            assert!(px.is_multiple_of(96) && rows.contains(&(px / 96)), "{px}");
        }
        assert!(beyond > 0);
        // Off, nothing of the kind is added.
        let mut plain = TriMesh::default();
        let off = without_margin(&mut plain, &z, &cam);
        assert_eq!(off.border_triangles, 0);
        assert_eq!(off.triangles, c.triangles - c.border_triangles);
        // The room alone has nothing cut by the border but its planes.
        let room = render_planes(&cam, &ROOM);
        let c = complete_beyond_frame(
            &mut TriMesh::default(),
            &room,
            &cam,
            &CompleteParams::default(),
        );
        assert_eq!(c.border_triangles, 0, "{c:?}");
    }

    #[test]
    fn a_view_without_planes_still_continues_past_the_border() {
        let cam = Camera::new(64, 64);
        // A smooth, curved surface: hills and dales with no plane in them.
        let mut z = GrayImage::new(64, 64, 0.0);
        for y in 0..64 {
            for x in 0..64 {
                let (u, v) = (x as f32 / 64.0, y as f32 / 64.0);
                z.data[y * 64 + x] = 3.0 + 1.2 * (u * 4.0).cos() * (v * 3.5 + 0.5).cos();
            }
        }
        let mut mesh = TriMesh::default();
        mesh.add_box(Vec3::splat(-1.0), Vec3::splat(1.0));
        let before = mesh.clone();
        let c = complete_beyond_frame(&mut mesh, &z, &cam, &CompleteParams::default());
        // No plane is extended, but the surface the border cuts goes on
        // past it on every side: the rays through the outer half of the
        // border pixels (outside the depth mesh's pixel-centre grid) meet
        // it at about the border pixels' depth, not the sky.
        assert!(c.extended.is_empty(), "{c:?}");
        assert!(
            c.border_triangles > 0 && c.triangles == c.border_triangles,
            "{c:?}"
        );
        assert_eq!(mesh.indices[..before.indices.len()], before.indices[..]);
        let added = TriMesh {
            positions: mesh.positions.clone(),
            indices: mesh.indices[before.indices.len()..].to_vec(),
            ..TriMesh::default()
        };
        // Film positions (pixel i spans [i, i + 1); off the pixel-centre
        // lines, the mesh's edges) and their border pixel.
        let rays = [
            (0.25, 32.3, (0, 32)),
            (63.75, 20.3, (63, 20)),
            (40.3, 0.25, (40, 0)),
            (10.3, 63.75, (10, 63)),
        ];
        for (fx, fy, px) in rays {
            let dir = cam.film_to_dir(Vec2::new(fx, fy));
            let t = hit(&added, 0, dir)
                .unwrap_or_else(|| panic!("the ray through ({fx}, {fy}) leaves"));
            let want = z.data[px.1 * 64 + px.0];
            let got = -(dir * t).z;
            assert!(
                (got - want).abs() < 0.15 * want,
                "({fx}, {fy}): depth {got}, the border pixel's {want}"
            );
        }
        // Without the margin, a view without planes is unchanged.
        let mut plain = before.clone();
        let off = without_margin(&mut plain, &z, &cam);
        assert_eq!((off.triangles, plain == before), (0, true));
        let mut mesh = before.clone();
        // Nor is an empty one.
        let c = complete_beyond_frame(
            &mut mesh,
            &GrayImage::new(64, 64, 0.0),
            &cam,
            &CompleteParams::default(),
        );
        assert_eq!((c.triangles, mesh == before), (0, true));
    }

    /// Two walls meeting in a corner 2.8 ahead fill the view; the floor,
    /// 3 below, is out of it.
    fn corner() -> (Camera, GrayImage) {
        let cam = Camera::new(96, 72);
        let walls = [
            (Vec3::new(1.0, 0.0, 1.0).normalize(), 2.0),
            (Vec3::new(-1.0, 0.0, 1.0).normalize(), 2.0),
        ];
        let z = render_planes(&cam, &walls);
        (cam, z)
    }

    #[test]
    fn a_corner_of_two_walls_is_closed_over_a_floor_under_the_lowest_point_seen() {
        let (cam, z) = corner();
        assert!(z.data.iter().all(|&d| d > 0.0));
        let (mesh, c) = closed_without_windows(&z, &cam);
        // Two walls seen; a floor, a ceiling and the two walls behind
        // assumed.
        assert_eq!(c.extended.len(), 6, "{c:?}");
        // The floor lies just under the lowest point seen (a bottom
        // corner of the view), straight down from the camera.
        let low = (0..z.data.len())
            .map(|i| {
                let q = cam.backproject((i % 96) as f32, (i / 96) as f32, z.data[i]);
                -q.y
            })
            .fold(f32::NEG_INFINITY, f32::max);
        let down = hit(&mesh, 0, Vec3::NEG_Y).expect("a floor");
        assert!(
            (down - low * (1.0 + FLOOR_MARGIN)).abs() < 1e-3 * low,
            "{down} vs {low}"
        );
        assert!(hit(&mesh, 0, Vec3::Y).is_some(), "a ceiling");
        for behind in [Vec3::Z, Vec3::X + Vec3::Z, Vec3::Z - Vec3::X] {
            assert!(hit(&mesh, 0, behind.normalize()).is_some(), "{behind}");
        }
        // Nothing in view is covered.
        assert_view_open(&mesh, &cam, 5);
    }

    #[test]
    fn only_assumed_walls_and_ceilings_are_partly_open() {
        // The box room without its ceiling: one is assumed.
        let cam = Camera::new(96, 72);
        let seen: Vec<(Vec3, f32)> = ROOM
            .iter()
            .copied()
            .filter(|p| p.0 != Vec3::NEG_Y)
            .collect();
        let z = render_planes(&cam, &seen);
        let (solid, _) = closed_without_windows(&z, &cam);
        assert!(solid.openness.is_empty());
        let p = CompleteParams {
            close: true,
            assumed_opening: 0.0,
            assumed_openness: 0.25,
            ..CompleteParams::default()
        };
        let mut mesh = TriMesh::default();
        complete_beyond_frame(&mut mesh, &z, &cam, &p);
        // The same triangles, now with a share per triangle.
        assert_eq!(mesh.positions, solid.positions);
        assert_eq!(mesh.openness.len(), mesh.triangle_count());
        // Behind the camera and above: an assumed wall and ceiling, partly
        // open; below (the floor seen) and the side walls seen: solid.
        let prim = |dir: Vec3| {
            let t = hit(&mesh, 0, dir).expect("a hit");
            (0..mesh.triangle_count())
                .find(|&k| {
                    let one = TriMesh {
                        positions: mesh.positions.clone(),
                        indices: vec![mesh.indices[k]],
                        ..TriMesh::default()
                    };
                    hit(&one, 0, dir).is_some_and(|u| (u - t).abs() < 1e-5)
                })
                .expect("the triangle hit")
        };
        for dir in [Vec3::Z, Vec3::Y] {
            assert_eq!(mesh.openness_of(prim(dir)), 0.25, "{dir}");
        }
        for dir in [Vec3::NEG_Y, Vec3::X, Vec3::NEG_X] {
            assert_eq!(mesh.openness_of(prim(dir)), 0.0, "{dir}");
        }
    }

    #[test]
    fn a_floor_alone_is_not_closed() {
        let cam = Camera::new(96, 72);
        let p = CompleteParams {
            close: true,
            ..CompleteParams::default()
        };
        // Ground without walls: the scene may be outdoors.
        let z = render_planes(&cam, &[(Vec3::Y, 0.9)]);
        let mut mesh = TriMesh::default();
        let c = complete_beyond_frame(&mut mesh, &z, &cam, &p);
        assert_eq!(c.extended.len(), 1, "{c:?}");
        assert!(c.lamp_sites.is_empty());
        for dir in [Vec3::Y, Vec3::Z, Vec3::X, Vec3::NEG_X, Vec3::NEG_Z] {
            assert!(hit(&mesh, 0, dir).is_none(), "{dir}");
        }
    }

    #[test]
    fn a_floor_with_a_strip_of_wall_is_a_room_and_is_closed() {
        // A camera pitched 30° down sees mostly floor and its room's back
        // wall only as a strip along the top, under the plane fit's own
        // threshold: an upright wall bounding the scene still shows the
        // floor is a room's.
        let cam = Camera::new(96, 72);
        let pitch = 30f32.to_radians();
        let up = Vec3::new(0.0, pitch.cos(), pitch.sin());
        let back = Vec3::new(0.0, -pitch.sin(), pitch.cos());
        let z = render_planes(&cam, &[(up, 1.2), (back, 3.5)]);
        let p = CompleteParams::default();
        let fits = crate::planes::fit_planes(&z, &cam, &p.planes);
        assert!(fits.iter().all(|f| f.kind == PlaneKind::Floor), "{fits:?}");
        let (mesh, c) = closed_without_windows(&z, &cam);
        let wall = c
            .extended
            .iter()
            .find(|f| f.kind == PlaneKind::Wall && f.fraction > 0.0)
            .expect("the strip of wall found");
        assert!(
            wall.fraction >= p.small_wall && wall.fraction < p.planes.min_fraction,
            "{wall:?}"
        );
        assert!((wall.plane.n - back).length() < 0.02, "{wall:?}");
        // The floor seen, the wall; a ceiling and three walls assumed.
        assert_eq!(c.extended.len(), 6, "{c:?}");
        assert!(hit(&mesh, 0, up).is_some(), "a ceiling");
        let fwd = -back;
        for d in [-fwd, Vec3::X, Vec3::NEG_X] {
            assert!(hit(&mesh, 0, d).is_some(), "{d}");
        }
        assert_view_open(&mesh, &cam, 5);
        // Without the lower threshold the floor alone stays open.
        let open = CompleteParams {
            close: true,
            small_wall: 0.0,
            ..CompleteParams::default()
        };
        let mut mesh = TriMesh::default();
        let c = complete_beyond_frame(&mut mesh, &z, &cam, &open);
        assert_eq!(c.extended.len(), 1, "{c:?}");
        assert!(hit(&mesh, 0, up).is_none());
    }

    #[test]
    fn a_single_wall_is_closed_upright_over_a_floor_under_the_lowest_point_seen() {
        // A wall 4 ahead fills the view of a camera pitched 10° down
        // (the wall's normal leans in camera space): walls stand upright,
        // so "up" is the camera's up made parallel to the wall.
        let cam = Camera::new(96, 72);
        let pitch = 10f32.to_radians();
        let n = Vec3::new(0.0, -pitch.sin(), pitch.cos());
        let z = render_planes(&cam, &[(n, 4.0)]);
        assert!(z.data.iter().all(|&d| d > 0.0));
        let (mesh, c) = closed_without_windows(&z, &cam);
        // The wall seen; a floor, a ceiling and three walls assumed.
        assert_eq!(c.extended.len(), 6, "{c:?}");
        let up = Vec3::new(0.0, pitch.cos(), pitch.sin());
        let low = (0..z.data.len())
            .map(|i| {
                let q = cam.backproject((i % 96) as f32, (i / 96) as f32, z.data[i]);
                -up.dot(q)
            })
            .fold(f32::NEG_INFINITY, f32::max);
        let down = hit(&mesh, 0, -up).expect("a floor");
        assert!(
            (down - low * (1.0 + FLOOR_MARGIN)).abs() < 1e-3 * low,
            "{down} vs {low}"
        );
        assert!(hit(&mesh, 0, up).is_some(), "a ceiling");
        let fwd = up.cross(Vec3::X).normalize();
        for d in [-fwd, Vec3::X, Vec3::NEG_X] {
            assert!(hit(&mesh, 0, d).is_some(), "{d}");
        }
        assert_view_open(&mesh, &cam, 5);
    }
}
