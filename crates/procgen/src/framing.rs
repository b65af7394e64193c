//! Where the camera stands. As drawn, each kind's camera stands where its
//! builder put it (at the origin of the layout, a few metres before the
//! furniture, at eye height). Photographs are often taken nearer: a
//! photographer walks up to a thing and frames it, from lower or higher,
//! so that objects fill much of the frame and the floor under them runs
//! up the picture. [`frame_near`] re-places the camera so: it picks one
//! of the scene's objects, stands 0.9–2.6 m (plus the object's size) from
//! it, 0.5–1.8 m above the ground, where the layout allows a camera
//! ([`Stand`]), and looks at it, a little off centre. Before a stage it
//! stands, half the time, in the front row instead: 0.6–4 m from the
//! platform's front, the eye 0.1–1.3 m above its top, looking over it,
//! so that the front face fills the bottom of the frame. The scene itself
//! (objects, lamps, windows, sky, exposure) is unchanged: only its frame
//! turns and moves. A placement that would put the camera within 0.35 m
//! of a surface, or with something between it and the object, is
//! redrawn; a scene without a free placement keeps its drawn camera.

use glam::{Mat3, Vec3};
use matflow_geom::{Bvh, TriMesh};
use matflow_scene::lamps::LampAt;

use crate::rooms::Room;
use crate::synthetic::Rng;

/// How the camera is placed in a scene.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Framing {
    /// Where the kind's builder put it.
    Drawn,
    /// Near one of the scene's objects, looking at it ([`frame_near`]).
    Near,
}

impl Framing {
    pub const NAMES: &'static [&'static str] = &["drawn", "near"];

    pub fn name(self) -> &'static str {
        match self {
            Framing::Drawn => "drawn",
            Framing::Near => "near",
        }
    }

    pub fn from_name(s: &str) -> Option<Framing> {
        [Framing::Drawn, Framing::Near]
            .into_iter()
            .find(|f| f.name() == s)
    }
}

/// Where in a scene a camera may stand (world frame, the drawn camera at
/// the origin, +y up): x and z ranges (inside the walls, off the stage),
/// and the height of the ground there; for a stage, its platform's
/// front, which a camera may stand close before.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Stand {
    pub xs: (f32, f32),
    pub zs: (f32, f32),
    pub ground: f32,
    pub front: Option<Front>,
}

/// A raised platform's front edge (world frame, as [`Stand`]): the
/// front face's z (the platform lies at smaller z), its top's height and
/// the face's x extent.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Front {
    pub z: f32,
    pub top: f32,
    pub xs: (f32, f32),
}

/// Nearest a placed camera may be to any surface (m).
const CLEARANCE: f32 = 0.35;

/// Directions to probe a placement's clearance with: the cube's faces,
/// edges and corners.
fn probes() -> Vec<Vec3> {
    let mut v = Vec::new();
    for x in -1..=1 {
        for y in -1..=1 {
            for z in -1..=1 {
                if (x, y, z) != (0, 0, 0) {
                    v.push(Vec3::new(x as f32, y as f32, z as f32).normalize());
                }
            }
        }
    }
    v
}

/// Yaw and pitch (radians) of a camera looking along `v` (unit, world):
/// the inverse of `Ry(yaw)·Rx(pitch)·(0, 0, −1)`.
fn yaw_pitch(v: Vec3) -> (f32, f32) {
    ((-v.x).atan2(-v.z), v.y.clamp(-1.0, 1.0).asin())
}

/// `room` seen from a camera near one of its objects (the module's doc);
/// `seed` draws the object and the placement. Pure: the same room and
/// seed give the same frame.
pub fn frame_near(mut room: Room, seed: u64) -> Room {
    let mut r = Rng(seed.wrapping_mul(0x94d0_49bb_1331_11eb) ^ 0x0000_f4a3_0000);
    let world = room.to_world;
    // The objects (not the walls, floors and façades, which are planes
    // without shading normals) at least 0.15 m across, as boxes in the
    // world frame: the things to walk up to.
    let mut targets: Vec<(Vec3, Vec3)> = Vec::new();
    let mut all = TriMesh::default();
    for o in &room.objects {
        let base = all.positions.len() as u32;
        all.positions.extend(o.mesh.positions.iter().copied());
        all.indices.extend(
            o.mesh
                .indices
                .iter()
                .map(|t| [t[0] + base, t[1] + base, t[2] + base]),
        );
        if o.normals.is_empty() || o.mesh.positions.is_empty() {
            continue;
        }
        let (mut lo, mut hi) = (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN));
        for &p in &o.mesh.positions {
            let w = world * p;
            lo = lo.min(w);
            hi = hi.max(w);
        }
        let size = hi - lo;
        if size.x.max(size.z) >= 0.15 && size.is_finite() {
            targets.push((lo, hi));
        }
    }
    if targets.is_empty() || all.indices.is_empty() {
        return room;
    }
    // Placements are checked in the drawn camera's frame, where the
    // geometry is.
    let bvh = Bvh::build(&all);
    let turn = world.transpose();
    let probes = probes();
    let fwd = world * Vec3::NEG_Z;
    let heading = (-fwd.x).atan2(-fwd.z);
    let stand = room.stand;
    let inside = |c: Vec3| {
        (stand.xs.0..=stand.xs.1).contains(&c.x) && (stand.zs.0..=stand.zs.1).contains(&c.z)
    };
    let clear = |at: Vec3| {
        probes
            .iter()
            .all(|&dir| bvh.intersect(at, turn * dir, 0.0, CLEARANCE).is_none())
    };
    // Before a stage, half the time: the front row, close to the
    // platform's front, the eye a little above its top, looking over it
    // (the front face fills the bottom of the frame, no ground before it).
    if let Some(f) = stand.front {
        if r.chance(0.5) {
            for _ in 0..8 {
                let x = f.xs.0 + (f.xs.1 - f.xs.0) * r.range(0.2, 0.8);
                let z = f.z + r.range(0.6, 4.0);
                let y = (f.top + r.range(0.1, 1.3)).max(stand.ground + 0.6);
                let yaw = heading + r.range(-15.0, 15.0).to_radians();
                let pitch = r.range(-15.0, 2.0).to_radians();
                let c = Vec3::new(x, y, z);
                if inside(c) && clear(turn * c) {
                    let to_world = Mat3::from_rotation_y(yaw) * Mat3::from_rotation_x(pitch);
                    reframe(&mut room, c, to_world);
                    return room;
                }
            }
        }
    }
    for _ in 0..16 {
        let (lo, hi) = targets[r.below(targets.len() as u64) as usize];
        let centre = (lo + hi) * 0.5;
        let radius = 0.5 * (hi - lo).length();
        let phi = heading + r.range(-50.0, 50.0).to_radians();
        let away = Vec3::new(phi.sin(), 0.0, phi.cos());
        let d = r.range(0.9, 2.6) + radius;
        let height = r.range(0.5, 1.8);
        let c = Vec3::new(centre.x, stand.ground + height, centre.z) + away * d;
        let look = (centre - c).normalize_or(Vec3::NEG_Z);
        let (yaw, pitch) = yaw_pitch(look);
        let yaw = yaw + r.range(-7.0, 7.0).to_radians();
        let pitch = (pitch + r.range(-6.0, 6.0).to_radians())
            .clamp(-55f32.to_radians(), 10f32.to_radians());
        if !inside(c) {
            continue;
        }
        let at = turn * c;
        let to_target = turn * (centre - c);
        let dist = to_target.length();
        let seen = match bvh.intersect(at, to_target / dist.max(1e-6), 0.0, dist) {
            None => true,
            Some(h) => h.t >= dist - radius - 0.05,
        };
        if !clear(at) || !seen {
            continue;
        }
        let to_world = Mat3::from_rotation_y(yaw) * Mat3::from_rotation_x(pitch);
        reframe(&mut room, c, to_world);
        return room;
    }
    room
}

/// Moves `room`'s camera to `c` (world frame) and turns it to `to_world`:
/// every position and direction re-expressed in the new camera's frame.
fn reframe(room: &mut Room, c: Vec3, to_world: Mat3) {
    let new_turn = to_world.transpose();
    let dir = new_turn * room.to_world;
    let shift = new_turn * c;
    let pos = |p: Vec3| dir * p - shift;
    for o in &mut room.objects {
        for p in &mut o.mesh.positions {
            *p = pos(*p);
        }
        for n in &mut o.normals {
            *n = (dir * *n).normalize_or(*n);
        }
    }
    for l in &mut room.lamps {
        l.at = match l.at {
            LampAt::Point(p) => LampAt::Point(pos(p)),
            LampAt::Distant(d) => LampAt::Distant((dir * d).normalize_or(d)),
        };
    }
    for p in &mut room.portals {
        p.corner = pos(p.corner);
        p.u = dir * p.u;
        p.v = dir * p.v;
    }
    room.to_world = to_world;
    room.stand = Stand {
        xs: (room.stand.xs.0 - c.x, room.stand.xs.1 - c.x),
        zs: (room.stand.zs.0 - c.z, room.stand.zs.1 - c.z),
        ground: room.stand.ground - c.y,
        front: room.stand.front.map(|f| Front {
            z: f.z - c.z,
            top: f.top - c.y,
            xs: (f.xs.0 - c.x, f.xs.1 - c.x),
        }),
    };
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rooms::test_support::{surface_depths, truth_of};
    use crate::rooms::{scene, SceneKind};

    fn median_depth(gt: &crate::rooms::GroundTruth) -> f32 {
        let mut z = surface_depths(gt);
        z.sort_by(f32::total_cmp);
        z.get(z.len() / 2).copied().unwrap_or(f32::INFINITY)
    }

    #[test]
    fn the_yaw_and_pitch_of_a_direction_turn_the_camera_onto_it() {
        for v in [
            Vec3::new(0.3, -0.4, -0.8),
            Vec3::new(-0.9, 0.1, 0.2),
            Vec3::new(0.0, -0.99, 0.1),
        ] {
            let v = v.normalize();
            let (yaw, pitch) = yaw_pitch(v);
            let f = Mat3::from_rotation_y(yaw) * Mat3::from_rotation_x(pitch) * Vec3::NEG_Z;
            assert!((f - v).length() < 1e-5, "{v} -> {f}");
        }
    }

    #[test]
    fn reframing_moves_the_camera_not_the_scene() {
        // The distances between any two points and the light's positions
        // relative to the geometry are kept; the new frame's origin is
        // where the camera was placed.
        let drawn = scene(SceneKind::Closed, 4);
        let mut moved = scene(SceneKind::Closed, 4);
        let c = Vec3::new(0.3, -0.2, -1.0);
        let to_world = Mat3::from_rotation_y(0.4) * Mat3::from_rotation_x(-0.3);
        reframe(&mut moved, c, to_world);
        let (a, b) = (
            &drawn.objects[0].mesh.positions,
            &moved.objects[0].mesh.positions,
        );
        for i in 1..a.len() {
            assert!(((a[i] - a[0]).length() - (b[i] - b[0]).length()).abs() < 1e-4);
        }
        // A point's world position is the same through both frames.
        let w0 = drawn.to_world * a[2];
        let w1 = to_world * b[2] + c;
        assert!((w0 - w1).length() < 1e-4, "{w0} vs {w1}");
        for (p, q) in drawn.portals.iter().zip(&moved.portals) {
            assert!((drawn.to_world * p.normal() - to_world * q.normal()).length() < 1e-5);
        }
    }

    #[test]
    fn near_framing_brings_the_camera_nearer_and_stays_valid() {
        let mut nearer = 0;
        let mut total = 0;
        for kind in SceneKind::ALL {
            for seed in 0..6 {
                let drawn = scene(kind, seed);
                let near = frame_near(scene(kind, seed), seed);
                // Pure.
                let again = frame_near(scene(kind, seed), seed);
                assert_eq!(near.to_world, again.to_world);
                assert_eq!(
                    near.objects[0].mesh.positions,
                    again.objects[0].mesh.positions
                );
                // Still a camera inside the scene's rules: a closed room
                // without windows shows no sky, no surface within reach.
                let gt = truth_of(&near, 24);
                if kind == SceneKind::Closed && near.portals.is_empty() {
                    assert!(gt.sky.data.iter().all(|&s| !s), "{kind:?} {seed}");
                }
                let zmin = surface_depths(&gt)
                    .into_iter()
                    .fold(f32::INFINITY, f32::min);
                assert!(zmin > 0.2, "{kind:?} {seed}: a surface at {zmin} m");
                assert!(near.portals.iter().all(|p| p.is_valid()));
                let (a, b) = (median_depth(&truth_of(&drawn, 24)), median_depth(&gt));
                total += 1;
                if b < a {
                    nearer += 1;
                }
            }
        }
        assert!(nearer * 4 >= total * 3, "{nearer} of {total} nearer");
    }

    /// The shares of the frame that see a stage's platform's front face
    /// and the ground before it.
    fn front_and_ground(room: &Room, n: usize) -> (f32, f32) {
        let Some(f) = room.stand.front else {
            return (0.0, 0.0);
        };
        let gt = truth_of(room, n);
        let cam = matflow_scene::Camera::new(n, n);
        let (mut front, mut ground) = (0, 0);
        for k in 0..n * n {
            if gt.sky.data[k] {
                continue;
            }
            let film = glam::Vec2::new((k % n) as f32 + 0.5, (k / n) as f32 + 0.5);
            let d = cam.film_to_dir(film);
            let p = room.to_world * (d * (gt.depth.data[k] / -d.z));
            if (p.z - f.z).abs() < 0.02 && p.y < f.top - 0.01 {
                front += 1;
            } else if (p.y - room.stand.ground).abs() < 0.02 && p.z > f.z {
                ground += 1;
            }
        }
        let all = (n * n) as f32;
        (front as f32 / all, ground as f32 / all)
    }

    #[test]
    fn near_stages_include_the_front_row() {
        // Drawn stages show the ground between the camera and the
        // platform; near-framed ones at times stand in the front row, the
        // platform's front face across the bottom of the frame and little
        // or no ground before it.
        let front_row = |(front, ground): (f32, f32)| front >= 0.25 && ground < 0.01;
        let (mut drawn, mut near) = (0, 0);
        for seed in 0..16 {
            drawn += usize::from(front_row(front_and_ground(
                &scene(SceneKind::Stage, seed),
                24,
            )));
            let framed = frame_near(scene(SceneKind::Stage, seed), seed);
            near += usize::from(front_row(front_and_ground(&framed, 24)));
        }
        assert!(drawn <= 1, "{drawn} drawn stages in the front row");
        assert!(
            (drawn + 3..=12).contains(&near),
            "{near} of 16 in the front row"
        );
    }
}
