//! Synthetic interiors with ground truth, for training and validating the
//! prediction stage: a room of varied shape (a back wall, side walls and a
//! ceiling present or not, an opening behind the camera), a floor plain,
//! tiled or planked and sometimes glossy, furniture built of boxes
//! (tables, cabinets, shelves) and primitives (balls, cylinders, tori,
//! jugs) on the floor and on tables, matte, glossy and metal materials, a
//! camera at a varied height, turned and tilted, and a procedural sky or
//! room environment map. Unlike [`crate::synthetic`] (a depth map
//! of the visible surfaces), the geometry is whole: it casts shadows
//! from outside the view. Everything is a pure function of the seed.

use std::sync::Arc;

use crate::envgen::EnvKind;
use crate::framing::{frame_near, Framing, Stand};
use crate::shapes::{cuboid, jug, revolve, sphere, torus, Shape};
use crate::synthetic::{hsv, Rng};
use glam::{Mat3, Vec2, Vec3};
use matflow_geom::{Portal, TriMesh};
use matflow_scene::lamps::Lamp;
use matflow_scene::{Camera, GrayImage, Image, RgbImage};

use matflow_render::bsdf::Material;
use matflow_render::scene::{RenderScene, SceneObject, Surface};

/// A generated scene: objects in the camera's frame (the camera at the
/// origin looking down −z), the environment map's kind and seed, how the
/// camera is turned (camera frame → world, for turning the map), the
/// exposure (EV) a photograph of it should get, and, for the kinds that
/// have them, lamps and the windows light comes in through (both in the
/// camera's frame), and where else a camera may stand in it.
pub struct Room {
    pub kind: SceneKind,
    pub objects: Vec<SceneObject>,
    pub env_kind: EnvKind,
    pub env_seed: u64,
    pub to_world: Mat3,
    pub exposure: f32,
    pub lamps: Vec<Lamp>,
    pub portals: Vec<Portal>,
    pub stand: Stand,
}

/// The kinds of scene the generator draws (`crate::kinds` has all but
/// the open room, this module's own).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum SceneKind {
    /// A room open to the sky: a back wall, side walls and a ceiling
    /// present or not, nothing behind the camera.
    Open,
    /// A room closed on every side, the camera inside: windows onto the
    /// sky and lamps light it.
    Closed,
    /// A raised platform with a backdrop, seen from the lower ground in
    /// front, the sky beyond and above.
    Stage,
    /// Objects on a wide ground under the sky, buildings far off.
    Outdoor,
}

impl SceneKind {
    pub const ALL: [SceneKind; 4] = [
        SceneKind::Closed,
        SceneKind::Open,
        SceneKind::Stage,
        SceneKind::Outdoor,
    ];
    pub const NAMES: &'static [&'static str] = &["closed", "open", "stage", "outdoor"];

    pub fn name(self) -> &'static str {
        match self {
            SceneKind::Closed => "closed",
            SceneKind::Open => "open",
            SceneKind::Stage => "stage",
            SceneKind::Outdoor => "outdoor",
        }
    }

    pub fn from_name(s: &str) -> Option<SceneKind> {
        SceneKind::ALL.into_iter().find(|k| k.name() == s)
    }
}

/// A material for furniture and objects: a quarter metal (gold, silver,
/// copper-like, rough or polished), the rest dielectric of any colour,
/// from matte to glossy.
pub(crate) fn object_material(r: &mut Rng) -> Material {
    if r.chance(0.25) {
        let tints = [
            Vec3::new(1.0, 0.78, 0.34),
            Vec3::new(0.95, 0.93, 0.88),
            Vec3::new(0.95, 0.64, 0.54),
            Vec3::new(0.56, 0.57, 0.58),
        ];
        Material {
            albedo: tints[r.below(tints.len() as u64) as usize] * r.range(0.8, 1.0),
            roughness: r.range(0.07, 0.5),
            metallic: 1.0,
        }
    } else {
        Material {
            albedo: hsv(r.f(), r.range(0.0, 0.85), r.range(0.1, 0.9)),
            roughness: r.range(0.1, 0.95),
            metallic: 0.0,
        }
    }
}

/// A quad (a, b, c, d counter-clockwise seen from its front) with texture
/// coordinates `uv` scaled from its corners.
fn quad(p: [Vec3; 4], uv: [Vec2; 4]) -> (TriMesh, Vec<Vec2>) {
    let m = TriMesh {
        positions: p.to_vec(),
        indices: vec![[0, 1, 2], [0, 2, 3]],
        ..Default::default()
    };
    (m, uv.to_vec())
}

/// A pattern texture: tiles (a grid of `n`×`n` squares with grout),
/// planks (stripes of varied shade) or none.
pub(crate) fn floor_texture(r: &mut Rng) -> Option<RgbImage> {
    match r.below(3) {
        0 => None,
        1 => {
            let grout = r.range(0.5, 0.8);
            Some(Image::from_fn(64, 64, |x, y| {
                if x % 32 < 2 || y % 32 < 2 {
                    Vec3::splat(grout)
                } else {
                    Vec3::ONE
                }
            }))
        }
        _ => {
            let shades: Vec<f32> = (0..8).map(|_| r.range(0.7, 1.0)).collect();
            Some(Image::from_fn(64, 64, |x, y| {
                let s = shades[y / 8];
                if y % 8 == 0 || (x + 16 * (y / 8)) % 64 == 0 {
                    Vec3::splat(0.55)
                } else {
                    Vec3::splat(s)
                }
            }))
        }
    }
}

fn shape_object(s: Shape, to_cam: &dyn Fn(Vec3) -> Vec3, turn: Mat3, m: Material) -> SceneObject {
    let mesh = TriMesh {
        positions: s.mesh.positions.iter().map(|&p| to_cam(p)).collect(),
        indices: s.mesh.indices,
        ..Default::default()
    };
    SceneObject {
        mesh,
        normals: s
            .normals
            .iter()
            .map(|&n| (turn * n).normalize_or(n))
            .collect(),
        surface: Surface::Principled(m),
        uvs: Vec::new(),
        texture: None,
    }
}

/// Where a room's surfaces stand (world space, the camera at the origin,
/// the floor below) and which of them are there.
struct Shell {
    floor: f32,
    ceil: f32,
    /// Left and right walls (x), back wall and the opening behind the
    /// camera (z).
    x0: f32,
    x1: f32,
    z0: f32,
    z1: f32,
    has_left: bool,
    has_right: bool,
    has_ceiling: bool,
}

fn shell(r: &mut Rng) -> Shell {
    let floor = -r.range(1.0, 1.8);
    let height = r.range(2.4, 3.4);
    let back = -r.range(5.0, 10.0);
    let left = -r.range(1.8, 4.0);
    let right = r.range(1.8, 4.0);
    let front = r.range(1.0, 3.0);
    Shell {
        floor,
        ceil: floor + height,
        x0: left,
        x1: right,
        z0: back,
        z1: front,
        has_left: r.chance(0.8),
        has_right: r.chance(0.6),
        has_ceiling: r.chance(0.25),
    }
}

/// A room's objects in the camera's frame, added one by one.
pub(crate) struct Objects {
    /// World → camera.
    pub turn: Mat3,
    pub list: Vec<SceneObject>,
}

impl Objects {
    /// No objects yet, for a camera turned by `to_world` (camera → world).
    pub fn new(to_world: Mat3) -> Objects {
        Objects {
            turn: to_world.transpose(),
            list: Vec::new(),
        }
    }

    /// A textured quad given in world space.
    pub fn plane(&mut self, corners: [Vec3; 4], uv_scale: f32, m: Material, tex: Option<RgbImage>) {
        let uv = corners.map(|c| {
            // Texture coordinates from the plane's two long axes.
            let n = (corners[1] - corners[0]).cross(corners[2] - corners[0]);
            let a = n.abs();
            let (s, t) = if a.y >= a.x && a.y >= a.z {
                (c.x, c.z)
            } else if a.x >= a.z {
                (c.z, c.y)
            } else {
                (c.x, c.y)
            };
            Vec2::new(s, t) * uv_scale
        });
        let (mesh, uvs) = quad(corners.map(|c| self.turn * c), uv);
        self.list.push(SceneObject {
            mesh,
            normals: Vec::new(),
            surface: Surface::Principled(m),
            uvs,
            texture: tex.map(Arc::new),
        });
    }

    /// A shape standing at `at` (world space).
    pub fn shape(&mut self, s: Shape, at: Vec3, m: Material) {
        let turn = self.turn;
        self.list
            .push(shape_object(s, &|p| turn * (p + at), turn, m));
    }
}

/// A floor material: warm and muted, glossy now and then.
pub(crate) fn floor_material(r: &mut Rng) -> Material {
    Material {
        albedo: hsv(r.range(0.0, 0.15), r.range(0.05, 0.6), r.range(0.2, 0.85)),
        roughness: if r.chance(0.4) {
            r.range(0.07, 0.25)
        } else {
            r.range(0.35, 0.9)
        },
        metallic: 0.0,
    }
}

/// A horizontal quad at height `y` over x ∈ `xs`, z ∈ `zs` (world space),
/// facing up.
pub(crate) fn floor_quad(xs: (f32, f32), zs: (f32, f32), y: f32) -> [Vec3; 4] {
    [
        Vec3::new(xs.0, y, zs.1),
        Vec3::new(xs.1, y, zs.1),
        Vec3::new(xs.1, y, zs.0),
        Vec3::new(xs.0, y, zs.0),
    ]
}

/// The floor (plain, tiled or planked; a glossy finish now and then), the
/// walls there are and the ceiling if there is one.
fn floor_and_walls(r: &mut Rng, s: &Shell, o: &mut Objects) {
    let floor_mat = floor_material(r);
    let tex = floor_texture(r);
    let tile = r.range(0.3, 0.9);
    let (x0, x1, z0, z1, floor, ceil) = (s.x0, s.x1, s.z0, s.z1, s.floor, s.ceil);
    // Where a side is open the floor runs on (a bigger hall).
    let (fx0, fx1) = (
        if s.has_left { x0 } else { x0 - 20.0 },
        if s.has_right { x1 } else { x1 + 20.0 },
    );
    o.plane(
        floor_quad((fx0, fx1), (z0, z1), floor),
        1.0 / tile,
        floor_mat,
        tex,
    );
    // Back wall (facing +z), side walls facing inwards, the ceiling down;
    // each draws its material whether it is there or not.
    let walls = [
        (
            true,
            [
                Vec3::new(x0, floor, z0),
                Vec3::new(x1, floor, z0),
                Vec3::new(x1, ceil, z0),
                Vec3::new(x0, ceil, z0),
            ],
        ),
        (
            s.has_left,
            [
                Vec3::new(x0, floor, z1),
                Vec3::new(x0, floor, z0),
                Vec3::new(x0, ceil, z0),
                Vec3::new(x0, ceil, z1),
            ],
        ),
        (
            s.has_right,
            [
                Vec3::new(x1, floor, z0),
                Vec3::new(x1, floor, z1),
                Vec3::new(x1, ceil, z1),
                Vec3::new(x1, ceil, z0),
            ],
        ),
        (
            s.has_ceiling,
            [
                Vec3::new(x0, ceil, z0),
                Vec3::new(x1, ceil, z0),
                Vec3::new(x1, ceil, z1),
                Vec3::new(x0, ceil, z1),
            ],
        ),
    ];
    for (there, corners) in walls {
        let m = Material {
            albedo: hsv(r.f(), r.range(0.0, 0.45), r.range(0.3, 0.9)),
            roughness: r.range(0.5, 1.0),
            metallic: 0.0,
        };
        if there {
            o.plane(corners, 1.0, m, None);
        }
    }
}

/// Furniture and objects on the floor, in front of the camera, apart: two
/// to six, each at the first of 12 tries that keeps clear of the others.
fn furniture(r: &mut Rng, s: &Shell, o: &mut Objects) {
    let n_items = 2 + r.below(5);
    scatter(r, n_items, (s.x0, s.x1), (s.z0, -1.5), s.floor, o);
}

/// `n_items` pieces of furniture or objects standing at height `y` within
/// x ∈ `xs`, z ∈ `zs` (world space), apart: each at the first of 12 tries
/// that keeps clear of the others, or left out.
pub(crate) fn scatter(
    r: &mut Rng,
    n_items: u64,
    xs: (f32, f32),
    zs: (f32, f32),
    y: f32,
    o: &mut Objects,
) {
    let mut taken: Vec<(Vec2, f32)> = Vec::new();
    for _ in 0..n_items {
        let kind = r.below(7);
        let radius = match kind {
            0 => r.range(0.5, 0.9),  // table
            1 => r.range(0.35, 0.6), // cabinet
            2 => r.range(0.4, 0.7),  // shelf
            _ => r.range(0.15, 0.45),
        };
        let mut spot = None;
        for _ in 0..12 {
            let c = Vec2::new(
                r.range(xs.0 + radius, xs.1 - radius),
                r.range(zs.0 + radius, zs.1 - radius),
            );
            if taken.iter().all(|(p, q)| (*p - c).length() > q + radius) {
                spot = Some(c);
                break;
            }
        }
        let Some(c) = spot else {
            continue;
        };
        taken.push((c, radius));
        let m = object_material(r);
        item(r, kind, radius, Vec3::new(c.x, y, c.y), m, o);
    }
}

/// One piece of furniture or object of `kind` and size `radius`, standing
/// at `at`.
pub(crate) fn item(r: &mut Rng, kind: u64, radius: f32, at: Vec3, m: Material, o: &mut Objects) {
    match kind {
        0 => {
            // A table: a top on four legs, sometimes with a thing on it.
            let top_h = r.range(0.65, 0.85);
            let (hx, hz) = (radius, radius * r.range(0.55, 0.9));
            let t = 0.04;
            let mut parts = vec![cuboid(
                Vec3::new(-hx, top_h - t, -hz),
                Vec3::new(hx, top_h, hz),
            )];
            let l = 0.04;
            for (sx, sz) in [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)] {
                let (px, pz) = (sx * (hx - 2.0 * l), sz * (hz - 2.0 * l));
                parts.push(cuboid(
                    Vec3::new(px - l, 0.0, pz - l),
                    Vec3::new(px + l, top_h - t, pz + l),
                ));
            }
            for p in parts {
                o.shape(p, at, m);
            }
            if r.chance(0.7) {
                let s = r.range(0.1, 0.2);
                let m2 = object_material(r);
                let thing = if r.chance(0.5) {
                    sphere(s, 16, 32).transformed(1.0, Vec3::new(0.0, top_h + s, 0.0))
                } else {
                    jug(32).transformed(2.0 * s, Vec3::new(0.0, top_h, 0.0))
                };
                o.shape(thing, at, m2);
            }
        }
        1 | 2 => {
            // A cabinet (a block) or a shelf (a tall, shallow block).
            let h = if kind == 1 {
                r.range(0.6, 1.2)
            } else {
                r.range(1.3, 2.0)
            };
            let d = if kind == 1 {
                radius * 0.8
            } else {
                radius * 0.4
            };
            o.shape(
                cuboid(Vec3::new(-radius, 0.0, -d), Vec3::new(radius, h, d)),
                at,
                m,
            );
        }
        3 => o.shape(
            sphere(radius, 24, 48).transformed(1.0, Vec3::new(0.0, radius, 0.0)),
            at,
            m,
        ),
        4 => {
            let h = r.range(0.3, 1.0);
            let cyl = revolve(
                &[
                    Vec2::new(0.0, 0.0),
                    Vec2::new(radius, 0.0),
                    Vec2::new(radius, h),
                    Vec2::new(0.0, h),
                ],
                Some(&[
                    Vec2::new(0.0, -1.0),
                    Vec2::new(1.0, 0.0),
                    Vec2::new(1.0, 0.0),
                    Vec2::new(0.0, 1.0),
                ]),
                48,
            );
            o.shape(cyl, at, m);
        }
        5 => {
            let tube = radius * 0.3;
            o.shape(
                torus(radius - tube, tube, 16, 48).transformed(1.0, Vec3::new(0.0, tube, 0.0)),
                at,
                m,
            )
        }
        _ => o.shape(jug(40).transformed(2.0 * radius, Vec3::ZERO), at, m),
    }
}

/// The scene of `kind` and `seed`.
/// The scene of `kind` drawn from `seed`, its camera placed as `framing`
/// says (near: [`frame_near`], drawing from the same seed).
pub fn scene_framed(kind: SceneKind, seed: u64, framing: Framing) -> Room {
    let r = scene(kind, seed);
    match framing {
        Framing::Drawn => r,
        Framing::Near => frame_near(r, seed),
    }
}

pub fn scene(kind: SceneKind, seed: u64) -> Room {
    match kind {
        SceneKind::Open => room(seed),
        SceneKind::Closed => crate::kinds::closed(seed),
        SceneKind::Stage => crate::kinds::stage(seed),
        SceneKind::Outdoor => crate::kinds::outdoor(seed),
    }
}

/// The open room of `seed`: its shell, the camera's yaw and tilt, floor
/// and walls, furniture, then the lighting's kind and seed and the
/// exposure.
pub fn room(seed: u64) -> Room {
    let mut r = Rng(seed.wrapping_mul(0x2545_f491_4f6c_dd1d) ^ 0x0005_eed0_0f00);
    let shell = shell(&mut r);
    // The camera: yaw and a downward tilt.
    let yaw = r.range(-25.0, 25.0).to_radians();
    let pitch = r.range(-22.0, 4.0).to_radians();
    let to_world = Mat3::from_rotation_y(yaw) * Mat3::from_rotation_x(pitch);
    let mut objects = Objects::new(to_world);
    floor_and_walls(&mut r, &shell, &mut objects);
    furniture(&mut r, &shell, &mut objects);
    let env_kind = if r.chance(0.5) {
        EnvKind::Sky
    } else {
        EnvKind::Room
    };
    Room {
        kind: SceneKind::Open,
        objects: objects.list,
        env_kind,
        env_seed: r.next_u64() >> 1,
        to_world,
        exposure: r.range(-0.7, 0.7),
        lamps: Vec::new(),
        portals: Vec::new(),
        // On the floor, inside the walls there are (0.4 m off them), off
        // the back wall; the floor runs 20 m on where a side is open.
        stand: Stand {
            xs: (
                if shell.has_left {
                    shell.x0 + 0.4
                } else {
                    shell.x0 - 6.0
                },
                if shell.has_right {
                    shell.x1 - 0.4
                } else {
                    shell.x1 + 6.0
                },
            ),
            zs: (shell.z0 + 0.6, shell.z1 - 0.2),
            ground: shell.floor,
            front: None,
        },
    }
}

/// A scene's ground truth per pixel centre: camera-space depth z (0 where
/// the ray leaves the scene), albedo (texture included), roughness and
/// metallic as rendered, the shading normal in camera space turned to
/// face the camera, and which pixels see nothing.
pub struct GroundTruth {
    pub depth: GrayImage,
    pub albedo: RgbImage,
    pub roughness: GrayImage,
    pub metallic: GrayImage,
    pub normal: RgbImage,
    pub sky: Image<bool>,
}

/// [`GroundTruth`] of a scene made of objects only (no depth mesh).
pub fn ground_truth(scene: &RenderScene, camera: &Camera) -> GroundTruth {
    use rayon::prelude::*;
    let (w, h) = (camera.width, camera.height);
    let px: Vec<(f32, Vec3, f32, f32, Vec3, bool)> = (0..w * h)
        .into_par_iter()
        .map(|k| {
            let film = Vec2::new((k % w) as f32 + 0.5, (k / w) as f32 + 0.5);
            let d = camera.film_to_dir(film).normalize_or(-Vec3::Z);
            let Some(hit) = scene.bvh.intersect(Vec3::ZERO, d, 0.0, f32::INFINITY) else {
                return (0.0, Vec3::ZERO, 0.0, 0.0, Vec3::Z, true);
            };
            let obj = hit
                .prim
                .checked_sub(scene.screen_prims as u32)
                .and_then(|q| scene.prim_object.get(q as usize))
                .copied();
            let (albedo, rough, metal) = match obj.and_then(|o| scene.objects.get(o as usize)) {
                Some(Surface::Principled(m)) => {
                    let tex =
                        scene.object_texture(obj.unwrap_or(0) as usize, hit.prim, hit.u, hit.v);
                    (m.albedo * tex, m.roughness, m.metallic)
                }
                Some(Surface::Diffuse(a)) => (*a, 1.0, 0.0),
                _ => (Vec3::ZERO, 0.0, 0.0),
            };
            let mut n = scene.shading_normal(hit.prim, hit.u, hit.v);
            if n.dot(d) > 0.0 {
                n = -n;
            }
            let z = -(d * hit.t).z;
            (z.max(0.0), albedo, rough, metal, n, false)
        })
        .collect();
    GroundTruth {
        depth: Image::from_vec(w, h, px.iter().map(|p| p.0).collect()),
        albedo: Image::from_vec(w, h, px.iter().map(|p| p.1).collect()),
        roughness: Image::from_vec(w, h, px.iter().map(|p| p.2).collect()),
        metallic: Image::from_vec(w, h, px.iter().map(|p| p.3).collect()),
        normal: Image::from_vec(w, h, px.iter().map(|p| p.4).collect()),
        sky: Image::from_vec(w, h, px.iter().map(|p| p.5).collect()),
    }
}

/// What the generators' tests look at: a scene's objects seen by an
/// n x n camera, and their ground truth.
#[cfg(test)]
pub(crate) mod test_support {
    use super::*;
    use matflow_render::EnvMap;
    use matflow_scene::MaterialMaps;

    pub(crate) fn scene_of(room: &Room, n: usize) -> (RenderScene, Camera) {
        let cam = Camera::new(n, n);
        let maps = MaterialMaps::uniform(n, n, Vec3::splat(0.5), 0.5, 0.0);
        let env = EnvMap::new(&Image::new(8, 4, Vec3::ONE)).unwrap();
        let s =
            RenderScene::with_objects(cam, TriMesh::default(), &maps, env, &room.objects).unwrap();
        (s, cam)
    }

    pub(crate) fn truth_of(room: &Room, n: usize) -> GroundTruth {
        let (s, cam) = scene_of(room, n);
        ground_truth(&s, &cam)
    }

    /// The depths of the pixels that see a surface.
    pub(crate) fn surface_depths(gt: &GroundTruth) -> Vec<f32> {
        let seen = gt.depth.data.iter().zip(&gt.sky.data);
        seen.filter(|(_, &s)| !s).map(|(&z, _)| z).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::test_support::scene_of;
    use super::*;

    #[test]
    fn rooms_vary_and_their_ground_truth_is_valid() {
        let mut metals = 0;
        let mut glossy_floors = 0;
        let mut layouts = std::collections::BTreeSet::new();
        for seed in 0..24 {
            let room = room(seed);
            layouts.insert(room.objects.len());
            let (s, cam) = scene_of(&room, 24);
            let gt = ground_truth(&s, &cam);
            // The floor fills the bottom row; everything seen is in front.
            assert!((0..24).all(|x| !gt.sky.get(x, 23)), "seed {seed}");
            for k in 0..24 * 24 {
                assert!(gt.depth.data[k].is_finite() && gt.depth.data[k] >= 0.0);
                assert!((gt.normal.data[k].length() - 1.0).abs() < 1e-3);
                assert!(gt.albedo.data[k].max_element() <= 1.0);
                if !gt.sky.data[k] {
                    let d = s
                        .camera
                        .film_to_dir(Vec2::new((k % 24) as f32 + 0.5, (k / 24) as f32 + 0.5));
                    assert!(
                        gt.normal.data[k].dot(d) <= 1e-4,
                        "seed {seed}: normal faces away"
                    );
                }
            }
            metals += gt.metallic.data.iter().filter(|&&m| m > 0.5).count().min(1);
            glossy_floors += usize::from(gt.roughness.get(12, 23) < 0.3);
        }
        assert!(metals >= 3, "{metals} rooms show metal");
        assert!(glossy_floors >= 3, "{glossy_floors} glossy floors");
        assert!(layouts.len() >= 4, "{layouts:?}");
    }
}
