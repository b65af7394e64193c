//! Objects inserted into a scene: the entry format shared by the `insert`
//! and `trace` kinds and `matflow render --insert`, reading their mesh
//! files, placing them in the camera frame, and their artifact form.
//!
//! One entry: `mesh` (an OBJ or PLY file), `translate: [x, y, z]` or
//! `anchor: [column, row]`, `rotate: [rx, ry, rz]` (degrees, about the
//! object's own origin, x then y then z), `scale` (one number or three)
//! and `material` (`type: diffuse | principled | glass` with `albedo`,
//! `roughness`, `metallic`, `ior`, `transmission`, `tint`). The transform
//! is translate · Rz·Ry·Rx · scale; with `anchor` the object's origin sits
//! on the depth mesh's surface seen through that pixel's centre and its +y
//! axis along that surface's normal (turned towards the camera). Without
//! `material`, each part of the file takes its MTL material (OBJ), else a
//! grey diffuse one.

use std::path::Path;

use glam::{Mat3, Quat, Vec2, Vec3};
use matflow_engine::{ParamSpec, ParamType, Value};
use matflow_geom::{Bvh, TriMesh};
use matflow_render::{Dielectric, Material, SceneObject, Surface};
use matflow_scene::color::srgb_to_linear;
use matflow_scene::meshfile::{read_mesh, FileMaterial, MeshPart};
use matflow_scene::{Camera, RgbImage};
use std::sync::Arc;

use crate::artifact::Artifact;
use crate::{err, NodeError};

/// Fields of an object's `material`.
pub const MATERIAL_FIELDS: &[ParamSpec] = &[
    ParamSpec {
        name: "type",
        ty: ParamType::Choice(&["diffuse", "principled", "glass"]),
        default: None,
        unit: "",
        doc: "Lambertian (albedo/π), matflow's BRDF, or a dielectric",
    },
    ParamSpec {
        name: "albedo",
        ty: ParamType::Floats {
            len: 3,
            min: 0.0,
            max: 1.0,
        },
        default: Some("[0.8, 0.8, 0.8]"),
        unit: "linear RGB",
        doc: "diffuse / base colour",
    },
    ParamSpec {
        name: "roughness",
        ty: ParamType::Float { min: 0.0, max: 1.0 },
        default: Some("~"),
        unit: "",
        doc: "GGX α = roughness² (default 0.5, glass 0: smooth)",
    },
    ParamSpec {
        name: "metallic",
        ty: ParamType::Float { min: 0.0, max: 1.0 },
        default: Some("0"),
        unit: "",
        doc: "principled only",
    },
    ParamSpec {
        name: "ior",
        ty: ParamType::Float { min: 1.0, max: 4.0 },
        default: Some("1.5"),
        unit: "",
        doc: "glass: index of refraction",
    },
    ParamSpec {
        name: "transmission",
        ty: ParamType::Float { min: 0.0, max: 1.0 },
        default: Some("1"),
        unit: "",
        doc: "glass: specular transmission T (light through the object carries T·tint)",
    },
    ParamSpec {
        name: "tint",
        ty: ParamType::Floats {
            len: 3,
            min: 0.0,
            max: 1.0,
        },
        default: Some("[1, 1, 1]"),
        unit: "linear RGB",
        doc: "glass: colour of transmitted light",
    },
];

/// Fields of one object entry.
pub const OBJECT_FIELDS: &[ParamSpec] = &[
    ParamSpec {
        name: "mesh",
        ty: ParamType::InPath,
        default: None,
        unit: "",
        doc: "OBJ (with its MTL) or PLY file",
    },
    ParamSpec {
        name: "translate",
        ty: ParamType::Floats {
            len: 3,
            min: -1e6,
            max: 1e6,
        },
        default: Some("~"),
        unit: "scene units",
        doc: "position of the object's origin in the camera frame (camera at 0 looking down −z, +y up)",
    },
    ParamSpec {
        name: "anchor",
        ty: ParamType::Floats {
            len: 2,
            min: -1e6,
            max: 1e6,
        },
        default: Some("~"),
        unit: "px",
        doc: "[column, row]: stand the object on the surface seen at this pixel's centre (instead of `translate`)",
    },
    ParamSpec {
        name: "rotate",
        ty: ParamType::Floats {
            len: 3,
            min: -3600.0,
            max: 3600.0,
        },
        default: Some("[0, 0, 0]"),
        unit: "degrees",
        doc: "about the object's own x, then y, then z axis",
    },
    ParamSpec {
        name: "scale",
        ty: ParamType::FloatOrFloats {
            len: 3,
            min: 1e-4,
            max: 1e4,
        },
        default: Some("1"),
        unit: "",
        doc: "one factor or three (x, y, z)",
    },
    ParamSpec {
        name: "material",
        ty: ParamType::Record(MATERIAL_FIELDS),
        default: Some("~"),
        unit: "",
        doc: "the surface (absent: the file's MTL materials, else grey diffuse)",
    },
];

/// The `objects` parameter: up to 64 entries.
pub const OBJECTS: ParamType = ParamType::Records {
    fields: OBJECT_FIELDS,
    max: 64,
};

/// One object entry, read from a normalised record.
#[derive(Clone, Debug, PartialEq)]
pub struct ObjectSpec {
    pub mesh: std::path::PathBuf,
    pub translate: Option<Vec3>,
    pub anchor: Option<Vec2>,
    pub rotate_deg: Vec3,
    pub scale: Vec3,
    pub material: Option<Surface>,
}

fn field<'a>(
    m: &'a [(String, matflow_engine::Loc, Value, matflow_engine::Loc)],
    k: &str,
) -> &'a Value {
    m.iter()
        .find(|(n, ..)| n == k)
        .map(|(_, _, v, _)| v)
        .unwrap_or(&Value::Null)
}

fn vec3(v: &Value) -> Option<Vec3> {
    match v {
        Value::List(xs) if xs.len() == 3 => Some(Vec3::new(
            xs[0].as_f64()? as f32,
            xs[1].as_f64()? as f32,
            xs[2].as_f64()? as f32,
        )),
        _ => None,
    }
}

fn surface_of(m: &[(String, matflow_engine::Loc, Value, matflow_engine::Loc)]) -> Surface {
    let num = |k: &str| field(m, k).as_f64().map(|x| x as f32);
    let albedo = vec3(field(m, "albedo")).unwrap_or(Vec3::splat(0.8));
    match field(m, "type") {
        Value::Str(t) if t == "glass" => Surface::Glass(Dielectric {
            eta: num("ior").unwrap_or(1.5),
            transmission: num("transmission").unwrap_or(1.0),
            tint: vec3(field(m, "tint")).unwrap_or(Vec3::ONE),
            roughness: num("roughness").unwrap_or(0.0),
        }),
        Value::Str(t) if t == "principled" => Surface::Principled(Material {
            albedo,
            roughness: num("roughness").unwrap_or(0.5),
            metallic: num("metallic").unwrap_or(0.0),
        }),
        _ => Surface::Diffuse(albedo),
    }
    .sanitized()
}

/// The entries of a normalised `objects` value (see [`OBJECTS`]).
pub fn specs(v: &Value) -> Result<Vec<ObjectSpec>, NodeError> {
    let Value::List(items) = v else {
        return Ok(Vec::new());
    };
    items
        .iter()
        .enumerate()
        .map(|(i, item)| {
            let Value::Map(m) = item else {
                return Err(err(format!("objects[{i}] is not a mapping")));
            };
            let Value::Str(mesh) = field(m, "mesh") else {
                return Err(err(format!("objects[{i}] has no mesh")));
            };
            let scale = vec3(field(m, "scale")).unwrap_or(Vec3::ONE);
            let anchor = match field(m, "anchor") {
                Value::List(xs) if xs.len() == 2 => Some(Vec2::new(
                    xs[0].as_f64().unwrap_or(0.0) as f32,
                    xs[1].as_f64().unwrap_or(0.0) as f32,
                )),
                _ => None,
            };
            Ok(ObjectSpec {
                mesh: mesh.into(),
                translate: vec3(field(m, "translate")),
                anchor,
                rotate_deg: vec3(field(m, "rotate")).unwrap_or(Vec3::ZERO),
                scale,
                material: match field(m, "material") {
                    Value::Map(mm) => Some(surface_of(mm)),
                    _ => None,
                },
            })
        })
        .collect()
}

/// Checks across an entry's fields (the engine has checked each field).
pub fn check_specs(specs: &[ObjectSpec]) -> Result<(), String> {
    for (i, s) in specs.iter().enumerate() {
        match (s.translate.is_some(), s.anchor.is_some()) {
            (true, true) => {
                return Err(format!(
                    "objects[{i}]: give `translate` or `anchor`, not both"
                ))
            }
            (false, false) => {
                return Err(format!(
                    "objects[{i}]: give `translate: [x, y, z]` (camera frame) or `anchor: [column, row]` (a pixel to stand it on)"
                ))
            }
            _ => {}
        }
    }
    Ok(())
}

/// Checks anchors against the image size.
pub fn check_anchors(specs: &[ObjectSpec], (w, h): (usize, usize)) -> Result<(), String> {
    for (i, s) in specs.iter().enumerate() {
        if let Some(a) = s.anchor {
            if !(a.x >= 0.0 && a.y >= 0.0 && a.x < w as f32 && a.y < h as f32) {
                return Err(format!(
                    "objects[{i}]: anchor [{}, {}] is outside the {w}x{h} image",
                    a.x, a.y
                ));
            }
        }
    }
    Ok(())
}

/// Reads every entry's mesh file (for checking before anything runs).
pub fn read_all(specs: &[ObjectSpec]) -> Result<Vec<Vec<MeshPart>>, String> {
    specs
        .iter()
        .enumerate()
        .map(|(i, s)| read_entry(i, s))
        .collect()
}

fn read_entry(i: usize, s: &ObjectSpec) -> Result<Vec<MeshPart>, String> {
    let parts = read_mesh(&s.mesh).map_err(|e| format!("objects[{i}]: {e}"))?;
    let tris: usize = parts.iter().map(|p| p.indices.len()).sum();
    if tris == 0 {
        return Err(format!(
            "objects[{i}]: {}: the mesh has no triangles",
            s.mesh.display()
        ));
    }
    Ok(parts)
}

/// An MTL material as a matflow surface: glass for transparent models
/// (`illum` 4, 6, 7 or 9, or `d` < 1: T = 1 − d, η = `Ni`, tint `Tf`),
/// principled where the file gives `Pr`/`Pm` or a specular colour (α from
/// the Phong exponent, α = √(2/(Ns + 2))), else Lambertian `Kd`.
pub fn surface_of_file(m: &FileMaterial) -> Surface {
    let kd = m.diffuse.unwrap_or(Vec3::splat(0.8));
    let phong_roughness = m
        .shininess
        .map(|ns| (2.0 / (ns.max(0.0) + 2.0)).sqrt().sqrt());
    let roughness = m.roughness.or(phong_roughness);
    let transparent = matches!(m.illum, Some(4 | 6 | 7 | 9)) || m.dissolve.is_some_and(|d| d < 1.0);
    let s = if transparent {
        let t = match m.dissolve {
            Some(d) if d < 1.0 => 1.0 - d,
            _ => 1.0,
        };
        Surface::Glass(Dielectric {
            eta: m.ior.filter(|&n| n >= 1.0).unwrap_or(1.5),
            transmission: t,
            tint: m.transmission_filter.unwrap_or(Vec3::ONE),
            roughness: m.roughness.unwrap_or(0.0),
        })
    } else if m.roughness.is_some()
        || m.metallic.is_some()
        || m.specular.is_some_and(|s| s.max_element() > 0.0)
    {
        Surface::Principled(Material {
            albedo: kd,
            roughness: roughness.unwrap_or(0.5),
            metallic: m.metallic.unwrap_or(0.0),
        })
    } else {
        Surface::Diffuse(kd)
    };
    s.sanitized()
}

/// The surface point and normal (towards the camera) of `mesh` seen
/// through film position `film` (pixel centre: column + ½, row + ½).
pub fn surface_at(camera: &Camera, mesh: &TriMesh, bvh: &Bvh, film: Vec2) -> Option<(Vec3, Vec3)> {
    let f = camera.focal();
    let pp = camera.principal_point();
    let dir = Vec3::new((film.x - 0.5 - pp.x) / f, -(film.y - 0.5 - pp.y) / f, -1.0).normalize();
    let hit = bvh.intersect(Vec3::ZERO, dir, 0.0, f32::INFINITY)?;
    let n = mesh.face_normal(hit.prim as usize);
    let n = if n.dot(dir) > 0.0 { -n } else { n };
    (n != Vec3::ZERO).then_some((dir * hit.t, n))
}

/// Where entry `i` goes: its origin (given, or the surface under its
/// anchor, the object's up along that surface's normal) and its linear
/// map (alignment, rotation, scale).
fn placement(
    i: usize,
    s: &ObjectSpec,
    camera: &Camera,
    depth_mesh: &TriMesh,
    bvh: Option<&Bvh>,
) -> Result<(Vec3, Mat3), NodeError> {
    let rot = Mat3::from_rotation_z(s.rotate_deg.z.to_radians())
        * Mat3::from_rotation_y(s.rotate_deg.y.to_radians())
        * Mat3::from_rotation_x(s.rotate_deg.x.to_radians());
    let (origin, align) = match (s.translate, s.anchor) {
        (Some(t), _) => (t, Mat3::IDENTITY),
        (None, Some(a)) => {
            let film = a + Vec2::splat(0.5);
            let (p, n) = bvh
                .and_then(|b| surface_at(camera, depth_mesh, b, film))
                .ok_or_else(|| {
                    err(format!(
                        "objects[{i}] ({}): anchor [{}, {}] sees no surface (sky)",
                        s.mesh.display(),
                        a.x,
                        a.y
                    ))
                })?;
            (p, Mat3::from_quat(Quat::from_rotation_arc(Vec3::Y, n)))
        }
        (None, None) => unreachable!("checked"),
    };
    Ok((origin, align * rot * Mat3::from_diagonal(s.scale)))
}

/// An MTL's diffuse texture as linear RGB, read once per file.
fn texture_of(
    path: &std::path::Path,
    textures: &mut std::collections::HashMap<std::path::PathBuf, Arc<RgbImage>>,
) -> Result<Arc<RgbImage>, matflow_scene::SceneError> {
    if let Some(t) = textures.get(path) {
        return Ok(t.clone());
    }
    let raw = matflow_scene::io::read_ldr_raw(path)?;
    let lin = Arc::new(raw.map(|c| {
        Vec3::new(
            srgb_to_linear(c.x),
            srgb_to_linear(c.y),
            srgb_to_linear(c.z),
        )
    }));
    textures.insert(path.to_path_buf(), lin.clone());
    Ok(lin)
}

/// A placed object has triangles of some area, finite vertices within
/// bounds `lo`..`hi`, something in front of the camera and a size that
/// fits a scene `scene_depth` deep.
fn check_placed(
    has_triangles: bool,
    (lo, hi): (Vec3, Vec3),
    in_front: bool,
    scene_depth: f32,
) -> Result<(), String> {
    if !has_triangles {
        return Err("every triangle is degenerate (zero area) after scaling".into());
    }
    if !lo.is_finite() || !hi.is_finite() {
        return Err("non-finite placed vertices".into());
    }
    if !in_front {
        return Err(
            "the object is entirely behind the camera (every vertex has z ≥ 0; the \
                    camera looks down −z)"
                .into(),
        );
    }
    let size = (hi - lo).length();
    if !(size >= 1e-4 * scene_depth && size <= 1e3 * scene_depth) {
        return Err(format!(
            "placed size {size:.3e} is absurd for a scene {scene_depth:.3} deep (check `scale` \
             and the file's units)"
        ));
    }
    Ok(())
}

/// The placed objects of `specs` (one per part of each file), in the
/// camera frame of `camera`, anchors found on `depth_mesh`. Errors name
/// the entry and its file: an empty or degenerate mesh, one entirely
/// behind the camera, an anchor on the sky, an object absurdly large or
/// small for the scene (its size outside 10⁻⁴..10³ times the scene's depth:
/// sub-pixel, or swallowing the scene).
pub fn place(
    specs: &[ObjectSpec],
    camera: &Camera,
    depth_mesh: &TriMesh,
) -> Result<Vec<SceneObject>, NodeError> {
    place_with(specs, camera, depth_mesh, None)
}

/// [`place`] with the depth mesh's BVH already built (`None`: built here
/// when an anchor needs it).
pub fn place_with(
    specs: &[ObjectSpec],
    camera: &Camera,
    depth_mesh: &TriMesh,
    built: Option<&Bvh>,
) -> Result<Vec<SceneObject>, NodeError> {
    check_specs(specs).map_err(err)?;
    check_anchors(specs, (camera.width, camera.height)).map_err(err)?;
    let need_bvh = built.is_none() && specs.iter().any(|s| s.anchor.is_some());
    let own = need_bvh.then(|| Bvh::build(depth_mesh));
    let bvh = built.or(own.as_ref());
    let scene_depth = depth_mesh
        .positions
        .iter()
        .map(|p| -p.z)
        .fold(0.0f32, f32::max)
        .max(1e-3);
    let mut out = Vec::new();
    let mut textures: std::collections::HashMap<std::path::PathBuf, Arc<RgbImage>> =
        std::collections::HashMap::new();
    for (i, s) in specs.iter().enumerate() {
        let name = s.mesh.display();
        let parts = read_entry(i, s).map_err(err)?;
        let (origin, linear) = placement(i, s, camera, depth_mesh, bvh)?;
        let normal_m = linear.inverse().transpose();
        let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
        let mut in_front = false;
        let first = out.len();
        for part in parts {
            let positions: Vec<Vec3> = part
                .positions
                .iter()
                .map(|p| origin + linear * *p)
                .collect();
            let indices: Vec<[u32; 3]> = part
                .indices
                .iter()
                .copied()
                .filter(|t| {
                    let [a, b, c] = t.map(|k| positions[k as usize]);
                    (b - a).cross(c - a).length_squared() > 0.0
                })
                .collect();
            for t in &indices {
                for &k in t {
                    let p = positions[k as usize];
                    lo = lo.min(p);
                    hi = hi.max(p);
                    in_front |= p.z < 0.0;
                }
            }
            if indices.is_empty() {
                continue;
            }
            let normals = if part.normals.len() == part.positions.len() {
                part.normals
                    .iter()
                    .map(|n| (normal_m * *n).normalize_or_zero())
                    .collect()
            } else {
                Vec::new()
            };
            let surface = s
                .material
                .or_else(|| part.material.as_ref().map(surface_of_file))
                .unwrap_or(Surface::Diffuse(Vec3::splat(0.8)));
            // The MTL's diffuse texture, when the entry gives no material
            // and the part has texture coordinates.
            let texture = match (
                &s.material,
                part.material
                    .as_ref()
                    .and_then(|m| m.diffuse_texture.clone()),
            ) {
                (None, Some(path)) if part.uvs.len() == part.positions.len() => {
                    Some(texture_of(&path, &mut textures).map_err(|e| {
                        err(format!("objects[{i}] ({name}): its MTL's map_Kd: {e}"))
                    })?)
                }
                _ => None,
            };
            out.push(SceneObject {
                mesh: TriMesh {
                    positions,
                    indices,
                    film: Vec::new(),
                    material_pixel: Vec::new(),
                    openness: Vec::new(),
                    portals: Vec::new(),
                    normals: Vec::new(),
                },
                normals,
                surface,
                uvs: if texture.is_some() {
                    part.uvs
                } else {
                    Vec::new()
                },
                texture,
            });
        }
        check_placed(out.len() > first, (lo, hi), in_front, scene_depth)
            .map_err(|m| err(format!("objects[{i}] ({name}): {m}")))?;
    }
    Ok(out)
}

/// Writes placed objects into an artifact (under `prefix`).
pub fn put_objects(a: &mut Artifact, prefix: &str, objects: &[SceneObject]) {
    let mut meta = Vec::new();
    let (mut pos, mut idx, mut nrm) = (Vec::new(), Vec::new(), Vec::new());
    let (mut surf, mut uvs, mut tex) = (Vec::new(), Vec::new(), Vec::new());
    for o in objects {
        let (tw, th) = o.texture.as_ref().map_or((0, 0), |t| (t.width, t.height));
        meta.extend([
            o.mesh.positions.len() as u32,
            o.mesh.indices.len() as u32,
            o.normals.len() as u32,
            o.uvs.len() as u32,
            tw as u32,
            th as u32,
        ]);
        pos.extend(o.mesh.positions.iter().flat_map(|p| p.to_array()));
        idx.extend(o.mesh.indices.iter().flatten().copied());
        nrm.extend(o.normals.iter().flat_map(|p| p.to_array()));
        surf.extend(surface_words(&o.surface));
        uvs.extend(o.uvs.iter().flat_map(|p| p.to_array()));
        if let Some(t) = &o.texture {
            tex.extend(t.data.iter().flat_map(|p| p.to_array()));
        }
    }
    let n = |v: &[f32], k: usize| (v.len() / k) as u32;
    a.put_f32(&format!("{prefix}uvs"), n(&uvs, 2), 2, uvs.clone());
    a.put_f32(&format!("{prefix}textures"), n(&tex, 3), 3, tex.clone());
    a.put_u32(&format!("{prefix}meta"), objects.len() as u32, 6, meta);
    a.put_f32(&format!("{prefix}positions"), n(&pos, 3), 3, pos.clone());
    a.put_u32(&format!("{prefix}indices"), (idx.len() / 3) as u32, 3, idx);
    a.put_f32(&format!("{prefix}normals"), n(&nrm, 3), 3, nrm.clone());
    a.put_f32(&format!("{prefix}surfaces"), objects.len() as u32, 9, surf);
}

/// A surface as 9 numbers: kind, then its parameters.
fn surface_words(s: &Surface) -> [f32; 9] {
    match *s {
        Surface::Diffuse(a) => [0.0, a.x, a.y, a.z, 0.0, 0.0, 0.0, 0.0, 0.0],
        Surface::Principled(m) => [
            1.0,
            m.albedo.x,
            m.albedo.y,
            m.albedo.z,
            m.roughness,
            m.metallic,
            0.0,
            0.0,
            0.0,
        ],
        Surface::Glass(g) => [
            2.0,
            g.tint.x,
            g.tint.y,
            g.tint.z,
            g.roughness,
            g.eta,
            g.transmission,
            0.0,
            0.0,
        ],
    }
}

fn surface_from_words(w: &[f32]) -> Result<Surface, NodeError> {
    let v = Vec3::new(w[1], w[2], w[3]);
    Ok(match w[0] as u32 {
        0 => Surface::Diffuse(v),
        1 => Surface::Principled(Material {
            albedo: v,
            roughness: w[4],
            metallic: w[5],
        }),
        2 => Surface::Glass(Dielectric {
            tint: v,
            roughness: w[4],
            eta: w[5],
            transmission: w[6],
        }),
        k => return Err(err(format!("objects artifact: unknown surface kind {k}"))),
    }
    .sanitized())
}

/// Reads objects written by [`put_objects`]; none when absent.
pub fn get_objects(a: &Artifact, prefix: &str) -> Result<Vec<SceneObject>, NodeError> {
    let key = format!("{prefix}meta");
    if !a.has(&key) {
        return Ok(Vec::new());
    }
    let meta = a.u32_list(&key, 6)?;
    let uv_all = a.f32_list(&format!("{prefix}uvs"), 2)?;
    let tex_all = a.f32_list(&format!("{prefix}textures"), 3)?;
    let (mut u0, mut t0) = (0usize, 0usize);
    let pos = a.f32_list(&format!("{prefix}positions"), 3)?;
    let idx = a.u32_list(&format!("{prefix}indices"), 3)?;
    let nrm = a.f32_list(&format!("{prefix}normals"), 3)?;
    let surf = a.f32_list(&format!("{prefix}surfaces"), 9)?;
    let bad = || err("objects artifact: sections do not match");
    if surf.len() != meta.len() / 6 * 9 {
        return Err(bad());
    }
    let (mut p0, mut i0, mut n0) = (0usize, 0usize, 0usize);
    let mut out = Vec::new();
    for (k, m) in meta.chunks_exact(6).enumerate() {
        let (np, ni, nn) = (m[0] as usize, m[1] as usize, m[2] as usize);
        let (nuv, tw, th) = (m[3] as usize, m[4] as usize, m[5] as usize);
        let uvs: Vec<Vec2> = uv_all
            .get(2 * u0..2 * (u0 + nuv))
            .ok_or_else(bad)?
            .chunks_exact(2)
            .map(|c| Vec2::new(c[0], c[1]))
            .collect();
        u0 += nuv;
        let texture = if tw * th > 0 {
            let d = tex_all
                .get(3 * t0..3 * (t0 + tw * th))
                .ok_or_else(bad)?
                .chunks_exact(3)
                .map(|c| Vec3::new(c[0], c[1], c[2]))
                .collect();
            t0 += tw * th;
            Some(Arc::new(RgbImage::from_vec(tw, th, d)))
        } else {
            None
        };
        let positions: Vec<Vec3> = pos
            .get(3 * p0..3 * (p0 + np))
            .ok_or_else(bad)?
            .chunks_exact(3)
            .map(|c| Vec3::new(c[0], c[1], c[2]))
            .collect();
        let indices: Vec<[u32; 3]> = idx
            .get(3 * i0..3 * (i0 + ni))
            .ok_or_else(bad)?
            .chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect();
        if indices.iter().flatten().any(|&i| i as usize >= np) {
            return Err(bad());
        }
        let normals: Vec<Vec3> = nrm
            .get(3 * n0..3 * (n0 + nn))
            .ok_or_else(bad)?
            .chunks_exact(3)
            .map(|c| Vec3::new(c[0], c[1], c[2]))
            .collect();
        (p0, i0, n0) = (p0 + np, i0 + ni, n0 + nn);
        out.push(SceneObject {
            mesh: TriMesh {
                positions,
                indices,
                film: Vec::new(),
                material_pixel: Vec::new(),
                openness: Vec::new(),
                portals: Vec::new(),
                normals: Vec::new(),
            },
            normals,
            surface: surface_from_words(&surf[9 * k..9 * k + 9])?,
            uvs,
            texture,
        });
    }
    Ok(out)
}

/// Whether two object lists have the same geometry (positions, triangles
/// and normals, bit for bit), whatever their surfaces.
pub fn same_geometry(a: &[SceneObject], b: &[SceneObject]) -> bool {
    a.len() == b.len()
        && a.iter()
            .zip(b)
            .all(|(x, y)| x.mesh == y.mesh && x.normals == y.normals)
}

/// An objects file (`matflow render --insert`: a YAML list of entries,
/// each as the `objects` parameter takes them, mesh paths relative to the
/// file) as the `objects` parameter's value: normalised, its
/// mesh paths resolved against the file's folder, its entries checked
/// across their fields. Errors give the file, line and column.
pub fn read_objects_value(path: &Path) -> Result<Value, NodeError> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| NodeError(format!("{}: {e}", path.display()), NodeError::kind_of(&e)))?;
    let (v, loc) = matflow_engine::value::parse_yaml(&text)
        .map_err(|e| err(format!("{}:{}: {}", path.display(), e.loc, e.message)))?;
    let base = path.parent().unwrap_or(Path::new("."));
    let mut reads = Vec::new();
    let norm = matflow_engine::spec::normalize_fields(
        &OBJECTS,
        &v,
        Some(loc),
        base,
        "the objects file",
        &mut reads,
    )
    .map_err(|(at, m)| match at {
        Some(l) => err(format!("{}:{l}: objects{m}", path.display())),
        None => err(format!("{}: objects{m}", path.display())),
    })?;
    let at = |e: &dyn std::fmt::Display| err(format!("{}: {e}", path.display()));
    check_specs(&specs(&norm).map_err(|e| at(&e))?).map_err(|e| at(&e))?;
    Ok(norm)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinds::insert::composite_differential;
    use crate::kinds::render::rerender_kept;
    use crate::testutil::{check_retrace, opts, small_room, trace_kept};
    use matflow_procgen::shapes;
    use matflow_render::{render, EnvMap, RenderScene};
    use matflow_scene::meshfile::obj_text;
    use matflow_scene::GrayImage;

    fn dir(name: &str) -> std::path::PathBuf {
        let d = std::env::temp_dir().join(format!("matflow-objects-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    fn write_shape(d: &Path, name: &str, s: &shapes::Shape) -> std::path::PathBuf {
        let f = d.join(format!("{name}.obj"));
        let part = MeshPart {
            positions: s.mesh.positions.clone(),
            indices: s.mesh.indices.clone(),
            normals: s.normals.clone(),
            ..Default::default()
        };
        std::fs::write(&f, obj_text(&part, name)).unwrap();
        f
    }

    fn spec(mesh: &Path) -> ObjectSpec {
        ObjectSpec {
            mesh: mesh.to_path_buf(),
            translate: Some(Vec3::new(0.0, 0.0, -4.0)),
            anchor: None,
            rotate_deg: Vec3::ZERO,
            scale: Vec3::ONE,
            material: Some(Surface::Diffuse(Vec3::splat(0.5))),
        }
    }

    /// A wall facing the camera at depth 5.
    fn wall(n: usize) -> (Camera, TriMesh) {
        let cam = Camera::new(n, n);
        let tri =
            matflow_geom::mesh_from_depth(&GrayImage::new(n, n, 5.0), &cam, &Default::default())
                .unwrap()
                .mesh;
        (cam, tri)
    }

    #[test]
    fn placement_is_translate_rotate_zyx_scale_and_anchors_stand_on_the_surface() {
        let d = dir("place");
        // One triangle with vertices on the axes.
        let tri = MeshPart {
            positions: vec![Vec3::X, Vec3::Y, Vec3::Z],
            indices: vec![[0, 1, 2]],
            ..Default::default()
        };
        let f = d.join("t.obj");
        std::fs::write(&f, obj_text(&tri, "t")).unwrap();
        let (cam, wall_mesh) = wall(16);
        let mut s = spec(&f);
        s.translate = Some(Vec3::new(1.0, 2.0, -6.0));
        s.rotate_deg = Vec3::new(90.0, 0.0, 90.0);
        s.scale = Vec3::new(2.0, 3.0, 4.0);
        let o = &place(&[s], &cam, &wall_mesh).unwrap()[0];
        // x̂ → scale (2,0,0) → Rx keeps → Rz(90°) turns to (0,2,0).
        // ŷ → (0,3,0) → Rx(90°) to (0,0,3) → Rz keeps.
        // ẑ → (0,0,4) → Rx(90°) to (0,−4,0) → Rz(90°) to (4,0,0).
        let want = [
            Vec3::new(1.0, 4.0, -6.0),
            Vec3::new(1.0, 2.0, -3.0),
            Vec3::new(5.0, 2.0, -6.0),
        ];
        let got: Vec<Vec3> = o.mesh.indices[0]
            .map(|k| o.mesh.positions[k as usize])
            .to_vec();
        for w in want {
            assert!(
                got.iter().any(|g| (*g - w).length() < 1e-5),
                "{got:?} lacks {w}"
            );
        }
        // Anchored at the centre pixel of a wall facing the camera: the
        // origin lands on the wall, +y along its normal (towards the camera).
        let mut s = spec(&f);
        s.translate = None;
        s.anchor = Some(Vec2::new(7.5, 7.5));
        let o = &place(&[s], &cam, &wall_mesh).unwrap()[0];
        let (surf, n) = surface_at(
            &cam,
            &wall_mesh,
            &Bvh::build(&wall_mesh),
            Vec2::new(8.0, 8.0),
        )
        .unwrap();
        assert!((n - Vec3::Z).length() < 1e-4, "{n}");
        let ys: Vec<Vec3> = o.mesh.positions.clone();
        // The file's ŷ vertex sits one unit from the surface along +z.
        assert!(
            ys.iter().any(|v| (*v - (surf + Vec3::Z)).length() < 1e-4),
            "{ys:?} {surf}"
        );
        let _ = std::fs::remove_dir_all(&d);
    }

    #[test]
    fn bad_objects_are_errors_naming_the_entry_and_file() {
        let d = dir("bad");
        let ball = write_shape(&d, "ball", &shapes::sphere(0.5, 8, 16));
        let (cam, wall_mesh) = wall(16);
        let flat = d.join("flat.obj");
        std::fs::write(&flat, "v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n").unwrap();
        let empty = d.join("empty.obj");
        std::fs::write(&empty, "v 0 0 0\n").unwrap();
        let nan = d.join("nan.obj");
        std::fs::write(&nan, "v 0 0 nan\nv 1 0 0\nv 0 1 0\nf 1 2 3\n").unwrap();
        let mut behind = spec(&ball);
        behind.translate = Some(Vec3::new(0.0, 0.0, 3.0));
        let mut huge = spec(&ball);
        huge.scale = Vec3::splat(1e4);
        let mut tiny = spec(&ball);
        tiny.scale = Vec3::splat(1e-4);
        let mut both = spec(&ball);
        both.anchor = Some(Vec2::new(1.0, 1.0));
        let mut outside = spec(&ball);
        outside.translate = None;
        outside.anchor = Some(Vec2::new(16.0, 3.0));
        let cases = [
            (spec(&d.join("missing.obj")), "missing.obj"),
            (spec(&flat), "degenerate"),
            (spec(&empty), "no triangles"),
            (spec(&nan), "non-finite"),
            (behind, "behind the camera"),
            (huge, "absurd"),
            (tiny, "absurd"),
            (both, "not both"),
            (outside, "outside the 16x16 image"),
        ];
        for (s, want) in cases {
            let e = match place(&[spec(&ball), s], &cam, &wall_mesh) {
                Ok(_) => panic!("accepted: {want}"),
                Err(e) => e.to_string(),
            };
            assert!(e.contains("objects[1]") && e.contains(want), "{want}: {e}");
        }
        // An anchor that sees the sky.
        let sky_cam = Camera::new(16, 16);
        let mut depth = GrayImage::new(16, 16, 5.0);
        for x in 0..16 {
            depth.set(x, 0, 0.0);
            depth.set(x, 1, 0.0);
        }
        let m = matflow_geom::mesh_from_depth(&depth, &sky_cam, &Default::default())
            .unwrap()
            .mesh;
        let mut s = spec(&ball);
        s.translate = None;
        s.anchor = Some(Vec2::new(5.0, 0.0));
        let e = match place(&[s], &sky_cam, &m) {
            Ok(_) => panic!("an anchor on the sky was accepted"),
            Err(e) => e.to_string(),
        };
        assert!(e.contains("objects[0]") && e.contains("sky"), "{e}");
        let _ = std::fs::remove_dir_all(&d);
    }

    #[test]
    fn object_surfaces_round_trip_and_re_edits_retrace_bit_identically() {
        let d = dir("reedit");
        let n = 24;
        let (s, cam, tri) = small_room(n);
        let ball = write_shape(&d, "ball", &shapes::sphere(0.5, 12, 24));
        let jug = write_shape(&d, "jug", &shapes::jug(16));
        let specs = vec![
            ObjectSpec {
                anchor: Some(Vec2::new(6.0, 20.0)),
                translate: None,
                ..spec(&ball)
            },
            ObjectSpec {
                anchor: Some(Vec2::new(17.0, 21.0)),
                translate: None,
                material: Some(Surface::Glass(Dielectric::default())),
                ..spec(&jug)
            },
        ];
        let objs = place(&specs, &cam, &tri).unwrap();
        // The artifact form keeps geometry and surfaces bit for bit.
        let mut a = Artifact::new("paths");
        put_objects(&mut a, "obj_", &objs);
        let back = get_objects(&Artifact::decode(&a.encode(), "paths").unwrap(), "obj_").unwrap();
        assert!(same_geometry(&objs, &back));
        assert_eq!(
            objs.iter().map(|o| o.surface).collect::<Vec<_>>(),
            back.iter().map(|o| o.surface).collect::<Vec<_>>()
        );
        let env = EnvMap::new(&s.envmap).unwrap();
        let scene = |objs: &[SceneObject]| {
            RenderScene::with_objects(cam, tri.clone(), &s.maps, env.clone(), objs).unwrap()
        };
        let opts = opts();
        let base = scene(&objs);
        let plain = render(&scene(&[]), &opts, &|_, _| {}).image;
        let kept = trace_kept(&base, &s.maps, &s.envmap, &objs, Some(plain.clone()));
        let image = kept.image.clone();
        assert!(same_geometry(&kept.objects, &objs));
        // Differential compositing changes the photo only where a path
        // met an object: elsewhere with and without are bit-identical.
        let alpha = base.object_coverage(4);
        // The matte traces only the objects' film box: the same as every
        // pixel traced.
        let every: Vec<f32> = (0..n * n)
            .map(|k| {
                let mut hits = 0;
                for j in 0..4 {
                    for i in 0..4 {
                        let film = glam::Vec2::new(
                            (k % n) as f32 + (i as f32 + 0.5) / 4.0,
                            (k / n) as f32 + (j as f32 + 0.5) / 4.0,
                        );
                        let d = base.camera_ray(film);
                        if let Some(hit) = base.bvh.intersect(Vec3::ZERO, d, 0.0, f32::INFINITY) {
                            hits += (hit.prim as usize >= base.screen_prims) as u32;
                        }
                    }
                }
                hits as f32 / 16.0
            })
            .collect();
        assert!(alpha == every, "the matte differs from tracing every pixel");
        assert!(alpha.iter().any(|&a| a > 0.0));
        let photo = &s.maps.albedo; // any image of the right size
        let comp = composite_differential(photo, &image, &plain, &alpha);
        let mut same = 0;
        for (k, a) in alpha.iter().enumerate() {
            if image.data[k] == plain.data[k] {
                assert_eq!(*a, 0.0);
                assert_eq!(comp.data[k], photo.data[k]);
                same += 1;
            }
        }
        assert!(same > n * n / 4 && same < n * n, "{same}");
        // Re-editing the glass jug's material re-traces what its kept
        // paths reach, bit-identical to a full render there.
        let mut edited = objs.clone();
        edited[1].surface = Surface::Glass(Dielectric {
            eta: 1.33,
            tint: Vec3::new(1.0, 0.5, 0.2),
            ..Default::default()
        });
        let escene = scene(&edited);
        let got = rerender_kept(&kept, &escene, &s.maps, &edited).unwrap();
        let full = render(&escene, &opts, &|_, _| {}).image;
        let mut changed = vec![false; n * n];
        changed.extend([false, true]);
        let (hit, missed) = check_retrace(&kept, &changed, &got, &full);
        assert!(hit > 0 && hit < n * n, "{hit}");
        assert!(missed * 10 < n * n, "{missed} pixels missed");
        let _ = std::fs::remove_dir_all(&d);
    }
}

#[cfg(test)]
mod texture_tests {
    use super::*;
    use matflow_render::{render, EnvMap, PixelFilter, RenderOptions, RenderScene};
    use matflow_scene::{GrayImage, MaterialMaps};

    #[test]
    fn an_mtl_diffuse_texture_colours_the_object() {
        let d = std::env::temp_dir().join(format!("matflow-objects-tex-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        // A 4x1 texture: red on the left half, blue on the right.
        let (r, b) = (Vec3::new(1.0, 0.0, 0.0), Vec3::new(0.0, 0.0, 1.0));
        let tex = RgbImage::from_vec(4, 1, vec![r, r, b, b]);
        matflow_scene::io::write_png_gamma(&d.join("t.png"), &tex).unwrap();
        std::fs::write(d.join("m.mtl"), "newmtl painted\nKd 1 1 1\nmap_Kd t.png\n").unwrap();
        std::fs::write(
            d.join("quad.obj"),
            "mtllib m.mtl\nv -1 -1 0\nv 1 -1 0\nv 1 1 0\nv -1 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n\
             usemtl painted\nf 1/1 2/2 3/3 4/4\n",
        )
        .unwrap();
        let n = 16;
        let cam = Camera::new(n, n);
        let wall =
            matflow_geom::mesh_from_depth(&GrayImage::new(n, n, 50.0), &cam, &Default::default())
                .unwrap()
                .mesh;
        let s = ObjectSpec {
            mesh: d.join("quad.obj"),
            translate: Some(Vec3::new(0.0, 0.0, -3.0)),
            anchor: None,
            rotate_deg: Vec3::ZERO,
            scale: Vec3::ONE,
            material: None,
        };
        let objs = place(&[s], &cam, &wall).unwrap();
        assert!(objs[0].texture.is_some() && objs[0].uvs.len() == objs[0].mesh.vertex_count());
        // The artifact keeps the texture.
        let mut a = Artifact::new("paths");
        put_objects(&mut a, "obj_", &objs);
        let back = get_objects(&Artifact::decode(&a.encode(), "paths").unwrap(), "obj_").unwrap();
        assert_eq!(back[0].texture, objs[0].texture);
        assert_eq!(back[0].uvs, objs[0].uvs);
        let env = EnvMap::new(&RgbImage::new(32, 16, Vec3::ONE)).unwrap();
        let maps = MaterialMaps::uniform(n, n, Vec3::splat(0.5), 1.0, 0.0);
        let scene = RenderScene::with_objects(cam, wall, &maps, env, &objs).unwrap();
        let img = render(
            &scene,
            &RenderOptions {
                spp: 16,
                max_depth: 2,
                filter: PixelFilter::Box,
                ..Default::default()
            },
            &|_, _| {},
        )
        .image;
        let (left, right) = (img.get(n / 2 - 3, n / 2), img.get(n / 2 + 2, n / 2));
        assert!(left.x > 0.5 && left.z < 0.2 * left.x, "left {left}");
        assert!(right.z > 0.5 && right.x < 0.2 * right.z, "right {right}");
        let _ = std::fs::remove_dir_all(&d);
    }
}
