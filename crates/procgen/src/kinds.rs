//! The scene kinds besides the open room ([`crate::rooms`]): closed rooms
//! (the camera inside four walls and a ceiling, lit through windows and
//! by lamps), stages (a raised platform with a backdrop seen from the
//! ground in front, the sky beyond) and outdoor scenes (objects on a wide
//! ground, buildings far off, the sky). They share the open room's
//! furniture, objects and materials, so that what tells the kinds apart
//! is their layout and their light, and each is a pure function of its
//! seed.

use glam::{Mat3, Vec3};
use matflow_geom::Portal;
use matflow_render::bsdf::Material;
use matflow_scene::lamps::Lamp;
use matflow_scene::{Image, RgbImage};

use crate::envgen::EnvKind;
use crate::framing::{Front, Stand};
use crate::rooms::{
    floor_material, floor_quad, floor_texture, object_material, scatter, Objects, Room, SceneKind,
};
use crate::synthetic::{hsv, Rng};

/// A texture for walls and façades: none, wallpaper stripes, bricks,
/// or a mottled finish (smooth noise on a coarse grid, wrapping).
fn wall_texture(r: &mut Rng) -> Option<RgbImage> {
    match r.below(4) {
        0 | 1 => None,
        2 => {
            let k = r.range(0.6, 0.9);
            let w = [4usize, 8, 16][r.below(3) as usize];
            Some(Image::from_fn(64, 64, |x, _| {
                Vec3::splat(if (x / w).is_multiple_of(2) { 1.0 } else { k })
            }))
        }
        _ => {
            let amount = r.range(0.08, 0.25);
            Some(mottled(r, amount))
        }
    }
}

/// Smooth multiplicative noise 1 ± `amount` on an 8×8 grid, bilinear and
/// wrapping, 64² texels.
fn mottled(r: &mut Rng, amount: f32) -> RgbImage {
    let grid: Vec<f32> = (0..64).map(|_| 1.0 + amount * r.signed()).collect();
    Image::from_fn(64, 64, |x, y| {
        let (fx, fy) = (x as f32 / 8.0, y as f32 / 8.0);
        let (ix, iy) = (fx as usize, fy as usize);
        let (tx, ty) = (fx - ix as f32, fy - iy as f32);
        let g = |i: usize, j: usize| grid[(j % 8) * 8 + (i % 8)];
        let top = g(ix, iy) * (1.0 - tx) + g(ix + 1, iy) * tx;
        let bottom = g(ix, iy + 1) * (1.0 - tx) + g(ix + 1, iy + 1) * tx;
        Vec3::splat((top * (1.0 - ty) + bottom * ty).clamp(0.0, 1.0))
    })
}

/// Bricks: courses of 8 texels, each brick its own shade, mortar lines.
fn bricks(r: &mut Rng) -> RgbImage {
    let shades: Vec<f32> = (0..64).map(|_| r.range(0.75, 1.0)).collect();
    let mortar = r.range(0.5, 1.2).min(1.0);
    Image::from_fn(64, 64, |x, y| {
        let row = y / 8;
        let xs = x + if row % 2 == 0 { 0 } else { 8 };
        if y % 8 == 0 || xs % 16 == 0 {
            Vec3::splat(mortar)
        } else {
            Vec3::splat(shades[(row * 4 + (xs / 16) % 4) % 64])
        }
    })
}

/// A façade: a grid of darker windows on a wall, 64² texels per storey
/// and bay.
fn facade(r: &mut Rng) -> RgbImage {
    let glass = r.range(0.1, 0.35);
    let (w0, w1) = (r.range(10.0, 20.0) as usize, r.range(44.0, 54.0) as usize);
    let (h0, h1) = (r.range(12.0, 22.0) as usize, r.range(42.0, 52.0) as usize);
    Image::from_fn(64, 64, |x, y| {
        Vec3::splat(if (w0..w1).contains(&x) && (h0..h1).contains(&y) {
            glass
        } else {
            1.0
        })
    })
}

/// A wall or floor material: mostly matte, of muted colour.
fn wall_material(r: &mut Rng) -> Material {
    Material {
        albedo: hsv(r.f(), r.range(0.0, 0.45), r.range(0.3, 0.9)),
        roughness: r.range(0.5, 1.0),
        metallic: 0.0,
    }
}

/// A rectangle in world space: corner, and the two edges along it.
#[derive(Clone, Copy)]
struct Rect {
    corner: Vec3,
    along: Vec3,
    up: Vec3,
}

impl Rect {
    fn corners(&self) -> [Vec3; 4] {
        let c = self.corner;
        [c, c + self.along, c + self.along + self.up, c + self.up]
    }
    /// The part [a0, a1] × [b0, b1] of it, in fractions of its edges.
    fn part(&self, a0: f32, a1: f32, b0: f32, b1: f32) -> Rect {
        Rect {
            corner: self.corner + self.along * a0 + self.up * b0,
            along: self.along * (a1 - a0),
            up: self.up * (b1 - b0),
        }
    }
}

/// A wall `wall` with, if `window` is given (fractions of its edges: a0,
/// a1 along, b0, b1 up), an opening there: four quads around it. Returns
/// the opening as a portal facing `inward`, in the camera's frame.
fn wall(
    o: &mut Objects,
    wall: Rect,
    window: Option<[f32; 4]>,
    m: Material,
    tex: Option<&RgbImage>,
    inward: Vec3,
) -> Option<Portal> {
    let Some([a0, a1, b0, b1]) = window else {
        o.plane(wall.corners(), 1.0, m, tex.cloned());
        return None;
    };
    for part in [
        wall.part(0.0, a0, 0.0, 1.0),
        wall.part(a1, 1.0, 0.0, 1.0),
        wall.part(a0, a1, 0.0, b0),
        wall.part(a0, a1, b1, 1.0),
    ] {
        o.plane(part.corners(), 1.0, m, tex.cloned());
    }
    let hole = wall.part(a0, a1, b0, b1);
    // u × v must point into the room.
    let (u, v) = if hole.along.cross(hole.up).dot(inward) > 0.0 {
        (hole.along, hole.up)
    } else {
        (hole.up, hole.along)
    };
    Some(Portal {
        corner: o.turn * hole.corner,
        u: o.turn * u,
        v: o.turn * v,
    })
}

/// A lamp's colour: white to warm, a coloured one now and then.
fn lamp_colour(r: &mut Rng, coloured: f32) -> Vec3 {
    if r.chance(coloured) {
        hsv(r.f(), r.range(0.3, 0.7), 1.0)
    } else {
        hsv(r.range(0.05, 0.12), r.range(0.0, 0.45), 1.0)
    }
}

/// The camera's turn: yaw (degrees, either way up to `yaw`) and a tilt
/// between `pitch.0` and `pitch.1` degrees (negative: down).
fn camera_turn(r: &mut Rng, yaw: f32, pitch: (f32, f32)) -> Mat3 {
    let yaw = r.range(-yaw, yaw).to_radians();
    let pitch = r.range(pitch.0, pitch.1).to_radians();
    Mat3::from_rotation_y(yaw) * Mat3::from_rotation_x(pitch)
}

/// A scene of `kind` made of `o`'s objects, lit by a sky (its seed drawn
/// here, then the photograph's exposure in EV about the log-average), the
/// lamps and the portals; a camera may stand on `stand`.
fn under_the_sky(
    kind: SceneKind,
    o: Objects,
    r: &mut Rng,
    to_world: Mat3,
    lamps: Vec<Lamp>,
    portals: Vec<Portal>,
    stand: Stand,
) -> Room {
    Room {
        kind,
        objects: o.list,
        env_kind: EnvKind::Sky,
        env_seed: r.next_u64() >> 1,
        to_world,
        exposure: r.range(-0.7, 0.7),
        lamps,
        portals,
        stand,
    }
}

/// A closed room: floor, four walls (one behind the camera) and a
/// ceiling; windows onto the sky in up to three walls (the light's
/// portals), lamps under the ceiling (at least one where there is no
/// window), furniture on the floor.
pub fn closed(seed: u64) -> Room {
    let mut r = Rng(seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) ^ 0x00c1_05ed_0000);
    let floor = -r.range(1.1, 1.7);
    let ceil = floor + r.range(2.4, 3.4);
    let (x0, x1) = (-r.range(1.6, 4.0), r.range(1.6, 4.0));
    let (z0, z1) = (-r.range(3.5, 9.0), r.range(0.4, 2.5));
    let to_world = camera_turn(&mut r, 30.0, (-20.0, 5.0));
    let mut o = Objects::new(to_world);
    let tile = r.range(0.3, 0.9);
    o.plane(
        floor_quad((x0, x1), (z0, z1), floor),
        1.0 / tile,
        floor_material(&mut r),
        floor_texture(&mut r),
    );
    let h = ceil - floor;
    // Back, left, right, front (behind the camera), each with its inward
    // direction.
    let walls = [
        (
            Rect {
                corner: Vec3::new(x0, floor, z0),
                along: Vec3::new(x1 - x0, 0.0, 0.0),
                up: Vec3::new(0.0, h, 0.0),
            },
            Vec3::Z,
        ),
        (
            Rect {
                corner: Vec3::new(x0, floor, z1),
                along: Vec3::new(0.0, 0.0, z0 - z1),
                up: Vec3::new(0.0, h, 0.0),
            },
            Vec3::X,
        ),
        (
            Rect {
                corner: Vec3::new(x1, floor, z0),
                along: Vec3::new(0.0, 0.0, z1 - z0),
                up: Vec3::new(0.0, h, 0.0),
            },
            -Vec3::X,
        ),
        (
            Rect {
                corner: Vec3::new(x1, floor, z1),
                along: Vec3::new(x0 - x1, 0.0, 0.0),
                up: Vec3::new(0.0, h, 0.0),
            },
            -Vec3::Z,
        ),
    ];
    // One wall material for the room, now and then one wall of its own.
    let m = wall_material(&mut r);
    let tex = wall_texture(&mut r);
    let accent = r.below(6);
    let mut portals = Vec::new();
    let n_windows = r.below(4);
    let first = r.below(4);
    for (k, (rect, inward)) in walls.into_iter().enumerate() {
        let len = rect.along.length();
        let window = (((k as u64 + 4 - first) % 4) < n_windows && len > 1.4).then(|| {
            let w = r.range(0.7, (len - 0.4).min(2.6)) / len;
            let a0 = r.range(0.1, 0.9 - w).max(0.05);
            let sill = r.range(0.3, 1.0) / h;
            let top = r.range(0.7, 0.9).max(sill + 0.25);
            [a0, a0 + w, sill, top.min(0.95)]
        });
        let (mk, tk) = if accent as usize == k {
            (wall_material(&mut r), wall_texture(&mut r))
        } else {
            (m, tex.clone())
        };
        portals.extend(wall(&mut o, rect, window, mk, tk.as_ref(), inward));
    }
    let ceiling_m = Material {
        albedo: hsv(r.f(), r.range(0.0, 0.1), r.range(0.7, 0.95)),
        roughness: r.range(0.7, 1.0),
        metallic: 0.0,
    };
    o.plane(
        [
            Vec3::new(x0, ceil, z0),
            Vec3::new(x1, ceil, z0),
            Vec3::new(x1, ceil, z1),
            Vec3::new(x0, ceil, z1),
        ],
        1.0,
        ceiling_m,
        None,
    );
    let n_items = 2 + r.below(5);
    scatter(&mut r, n_items, (x0, x1), (z0, -1.5), floor, &mut o);
    // Pendant lamps, well below the ceiling (a lamp close to a surface
    // makes a small, very bright spot that only fireflies would find).
    let n_lamps = if portals.is_empty() {
        1 + r.below(3)
    } else {
        r.below(3)
    };
    let mut lamps = Vec::new();
    for _ in 0..n_lamps {
        let p = Vec3::new(
            r.range(x0 + 0.5, x1 - 0.5),
            ceil - r.range(0.6, 1.0),
            r.range(z0 + 0.5, z1 - 0.3),
        );
        let power = r.range(0.6, 3.0) * h * h / 9.0;
        lamps.push(Lamp::point(o.turn * p, lamp_colour(&mut r, 0.1) * power));
    }
    let stand = Stand {
        xs: (x0 + 0.4, x1 - 0.4),
        zs: (z0 + 0.6, z1 - 0.4),
        ground: floor,
        front: None,
    };
    under_the_sky(
        SceneKind::Closed,
        o,
        &mut r,
        to_world,
        lamps,
        portals,
        stand,
    )
}

/// A ground material for outdoor scenes and the ground before a stage:
/// grass, asphalt, sand or paving (tiled), with its texture.
fn ground(r: &mut Rng) -> (Material, Option<RgbImage>, f32) {
    let (albedo, tex) = match r.below(4) {
        0 => (
            hsv(r.range(0.2, 0.33), r.range(0.35, 0.7), r.range(0.12, 0.35)),
            Some(mottled(r, 0.3)),
        ),
        1 => (Vec3::splat(r.range(0.06, 0.2)), Some(mottled(r, 0.15))),
        2 => (
            hsv(r.range(0.07, 0.12), r.range(0.25, 0.5), r.range(0.4, 0.7)),
            Some(mottled(r, 0.2)),
        ),
        _ => (
            hsv(r.range(0.0, 0.15), r.range(0.0, 0.3), r.range(0.3, 0.65)),
            floor_texture(r),
        ),
    };
    let m = Material {
        albedo,
        roughness: r.range(0.6, 1.0),
        metallic: 0.0,
    };
    (m, tex, r.range(0.2, 0.6))
}

/// A ground ([`ground`]'s) at height `y`, `half_width` to either side and
/// over z ∈ `zs`.
fn ground_plane(r: &mut Rng, o: &mut Objects, y: f32, half_width: f32, zs: (f32, f32)) {
    let (m, tex, tile) = ground(r);
    o.plane(
        floor_quad((-half_width, half_width), zs, y),
        1.0 / tile,
        m,
        tex,
    );
}

/// The faces of the box `lo`..`hi` but its bottom, each counter-clockwise
/// seen from outside: front (+z), back, left (−x), right, top.
fn box_faces(lo: Vec3, hi: Vec3) -> [[Vec3; 4]; 5] {
    let c = |x: f32, y: f32, z: f32| Vec3::new(x, y, z);
    [
        [
            c(lo.x, lo.y, hi.z),
            c(hi.x, lo.y, hi.z),
            c(hi.x, hi.y, hi.z),
            c(lo.x, hi.y, hi.z),
        ],
        [
            c(hi.x, lo.y, lo.z),
            c(lo.x, lo.y, lo.z),
            c(lo.x, hi.y, lo.z),
            c(hi.x, hi.y, lo.z),
        ],
        [
            c(lo.x, lo.y, lo.z),
            c(lo.x, lo.y, hi.z),
            c(lo.x, hi.y, hi.z),
            c(lo.x, hi.y, lo.z),
        ],
        [
            c(hi.x, lo.y, hi.z),
            c(hi.x, lo.y, lo.z),
            c(hi.x, hi.y, lo.z),
            c(hi.x, hi.y, hi.z),
        ],
        [
            c(lo.x, hi.y, hi.z),
            c(hi.x, hi.y, hi.z),
            c(hi.x, hi.y, lo.z),
            c(lo.x, hi.y, lo.z),
        ],
    ]
}

/// A box of size `size` (x, y, z) standing at `at` with its faces as
/// textured planes (the texture's repeat is `uv_scale` per unit), its
/// bottom left out.
fn textured_box(
    o: &mut Objects,
    at: Vec3,
    size: Vec3,
    m: Material,
    tex: Option<&RgbImage>,
    uv: f32,
) {
    let (lo, hi) = (
        at - Vec3::new(size.x, 0.0, size.z) * 0.5,
        at + Vec3::new(size.x * 0.5, size.y, size.z * 0.5),
    );
    for f in box_faces(lo, hi) {
        o.plane(f, uv, m, tex.cloned());
    }
}

/// A stage: a raised platform (planked or plain) with a backdrop and,
/// now and then, wings at its sides, seen from the ground in front;
/// objects on it and a few before it; stage lights above the front; the
/// sky beyond and above.
pub fn stage(seed: u64) -> Room {
    let mut r = Rng(seed.wrapping_mul(0xd1b5_4a32_d192_ed03) ^ 0x0057_a6e0_0000);
    let g = -r.range(1.2, 1.8);
    let top = g + r.range(0.3, 1.1);
    let zf = -r.range(4.0, 9.0);
    let zb = zf - r.range(3.0, 6.0);
    let (cx, wx) = (r.range(-1.0, 1.0), r.range(2.5, 5.5));
    let to_world = camera_turn(&mut r, 20.0, (-12.0, 8.0));
    let mut o = Objects::new(to_world);
    ground_plane(&mut r, &mut o, g, 60.0, (-120.0, 6.0));
    // The platform: its top (planked or plain), its front and sides.
    let deck = floor_material(&mut r);
    let deck_tex = floor_texture(&mut r);
    let (x0, x1) = (cx - wx, cx + wx);
    o.plane(
        floor_quad((x0, x1), (zb, zf), top),
        1.0 / r.range(0.3, 0.9),
        deck,
        deck_tex,
    );
    let skirt = wall_material(&mut r);
    let [front, _, left, right, _] = box_faces(Vec3::new(x0, g, zb), Vec3::new(x1, top, zf));
    for f in [front, left, right] {
        o.plane(f, 1.0, skirt, None);
    }
    // The backdrop (a curtain, a painted wall or bricks) and the wings.
    let back_h = r.range(2.5, 5.0);
    let back = wall_material(&mut r);
    let back_tex = match r.below(3) {
        0 => Some(bricks(&mut r)),
        _ => wall_texture(&mut r),
    };
    let bw = wx * r.range(0.8, 1.0);
    o.plane(
        [
            Vec3::new(cx - bw, top, zb),
            Vec3::new(cx + bw, top, zb),
            Vec3::new(cx + bw, top + back_h, zb),
            Vec3::new(cx - bw, top + back_h, zb),
        ],
        1.0,
        back,
        back_tex.clone(),
    );
    if r.chance(0.5) {
        let reach = (zf - zb) * r.range(0.3, 0.7);
        for (x, s) in [(x0, 1.0), (x1, -1.0)] {
            let (a, b) = (Vec3::new(x, top, zb), Vec3::new(x, top, zb + reach));
            let up = Vec3::new(0.0, back_h, 0.0);
            let quad = if s > 0.0 {
                [b, a, a + up, b + up]
            } else {
                [a, b, b + up, a + up]
            };
            o.plane(quad, 1.0, back, back_tex.clone());
        }
    }
    // Objects on the platform and before it.
    let on = 1 + r.below(4);
    scatter(&mut r, on, (x0, x1), (zb + 0.3, zf), top, &mut o);
    let before = r.below(3);
    scatter(&mut r, before, (-3.5, 3.5), (zf + 0.3, -1.2), g, &mut o);
    // Stage lights above the front edge.
    let mut lamps = Vec::new();
    for _ in 0..1 + r.below(4) {
        let p = Vec3::new(
            r.range(x0, x1),
            top + r.range(2.0, 4.0),
            zf + r.range(0.5, 3.0),
        );
        let power = r.range(1.0, 6.0);
        lamps.push(Lamp::point(o.turn * p, lamp_colour(&mut r, 0.3) * power));
    }
    // On the ground before the platform.
    let stand = Stand {
        xs: (-4.0, 4.0),
        zs: (zf + 0.6, 4.0),
        ground: g,
        front: Some(Front {
            z: zf,
            top,
            xs: (x0, x1),
        }),
    };
    under_the_sky(
        SceneKind::Stage,
        o,
        &mut r,
        to_world,
        lamps,
        Vec::new(),
        stand,
    )
}

/// An outdoor scene: a wide ground (grass, asphalt, sand or paving),
/// objects and blocks on it near and far, buildings in the distance, the
/// sky.
pub fn outdoor(seed: u64) -> Room {
    let mut r = Rng(seed.wrapping_mul(0xa076_1d64_78bd_642f) ^ 0x0000_0d00_0000);
    let g = -r.range(1.2, 1.9);
    let to_world = camera_turn(&mut r, 30.0, (-25.0, 6.0));
    let mut o = Objects::new(to_world);
    ground_plane(&mut r, &mut o, g, 150.0, (-250.0, 10.0));
    // Objects near the camera, then blocks (walls, planters, crates)
    // further off.
    let near = 2 + r.below(5);
    scatter(&mut r, near, (-5.0, 5.0), (-12.0, -2.0), g, &mut o);
    for _ in 0..r.below(4) {
        let at = Vec3::new(r.range(-10.0, 10.0), g, -r.range(5.0, 25.0));
        let size = Vec3::new(r.range(0.5, 4.0), r.range(0.4, 2.5), r.range(0.4, 2.0));
        let m = if r.chance(0.7) {
            wall_material(&mut r)
        } else {
            object_material(&mut r)
        };
        let tex = match r.below(3) {
            0 => Some(bricks(&mut r)),
            _ => wall_texture(&mut r),
        };
        textured_box(&mut o, at, size, m, tex.as_ref(), 1.0 / r.range(0.5, 1.5));
    }
    // Buildings far off.
    for _ in 0..r.below(6) {
        let at = Vec3::new(r.range(-60.0, 60.0), g, -r.range(25.0, 90.0));
        let size = Vec3::new(r.range(6.0, 25.0), r.range(4.0, 30.0), r.range(6.0, 20.0));
        let m = wall_material(&mut r);
        let tex = facade(&mut r);
        textured_box(&mut o, at, size, m, Some(&tex), 1.0 / r.range(2.5, 4.0));
    }
    under_the_sky(
        SceneKind::Outdoor,
        o,
        &mut r,
        to_world,
        Vec::new(),
        Vec::new(),
        Stand {
            xs: (-12.0, 12.0),
            zs: (-25.0, 8.0),
            ground: g,
            front: None,
        },
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rooms::scene;
    use crate::rooms::test_support::truth_of;

    fn sky_share(gt: &crate::rooms::GroundTruth) -> f32 {
        gt.sky.data.iter().filter(|&&s| s).count() as f32 / gt.sky.data.len() as f32
    }

    #[test]
    fn each_kind_has_its_layout() {
        for seed in 0..12 {
            // A closed room: nothing seen is sky but through a window, and
            // it has light (a window or a lamp) and its portals face in.
            let c = closed(seed);
            assert!(!c.lamps.is_empty() || !c.portals.is_empty(), "seed {seed}");
            for p in &c.portals {
                assert!(p.is_valid());
                // The camera (origin) is inside: on the inward side.
                assert!(
                    p.normal().dot(-p.corner) > 0.0,
                    "seed {seed}: portal faces out"
                );
            }
            let gt = truth_of(&c, 24);
            if c.portals.is_empty() {
                assert_eq!(sky_share(&gt), 0.0, "seed {seed}: a closed room shows sky");
            }
            // Outdoors: sky above, ground below, depth reaching far.
            let o = outdoor(seed);
            let gt = truth_of(&o, 24);
            assert!((0..24).all(|x| !gt.sky.get(x, 23)), "seed {seed}");
            let far = gt.depth.data.iter().cloned().fold(0.0, f32::max);
            assert!(far > 15.0, "seed {seed}: outdoor depth reaches only {far}");
            // A stage: ground below, the platform and backdrop in view.
            let s = stage(seed);
            assert!(!s.lamps.is_empty());
            let gt = truth_of(&s, 24);
            assert!((0..24).all(|x| !gt.sky.get(x, 23)), "seed {seed}");
        }
    }

    #[test]
    fn kinds_are_pure_functions_of_the_seed_and_differ() {
        for kind in SceneKind::ALL {
            assert_eq!(SceneKind::from_name(kind.name()), Some(kind));
            let (a, b) = (scene(kind, 5), scene(kind, 5));
            assert_eq!(a.kind, kind);
            assert_eq!(a.objects.len(), b.objects.len());
            let pa: Vec<Vec3> = a
                .objects
                .iter()
                .flat_map(|o| o.mesh.positions.clone())
                .collect();
            let pb: Vec<Vec3> = b
                .objects
                .iter()
                .flat_map(|o| o.mesh.positions.clone())
                .collect();
            assert_eq!(pa, pb);
            assert_eq!(a.lamps, b.lamps);
        }
        // Open rooms show sky far more often than closed ones.
        let share = |k| {
            (0..16)
                .map(|s| sky_share(&truth_of(&scene(k, s), 16)))
                .sum::<f32>()
        };
        assert!(share(SceneKind::Closed) < share(SceneKind::Outdoor));
    }
}
