//! The refraction-length dataset's two per-sample kinds (the paper's
//! supplement §10), which `matflow dataset` generates one of each per
//! sample:
//!
//! - `refraction_labels`: what the object is, seen from a viewpoint — its
//!   mask, camera-space depth and outward normals, the eq. 24 refraction
//!   length (normalised by the object's size) and the transparency edit's
//!   d1 and d2 (scene units);
//! - `refraction_render`: the photograph — the object (opaque, a random
//!   material) standing on an optional ground plane under an environment
//!   map, and the same view without it (the background), both path-traced
//!   by matflow's renderer and exposed alike.
//!
//! The object is scaled so its bounding sphere has diameter `object_size`
//! and centred at the world origin; the camera stands `distance` away at
//! (`azimuth`, `elevation`) and looks at the centre. matflow's camera
//! always looks down −z from the origin, so the object is moved into the
//! camera's frame and the environment map turned with it.

use std::collections::BTreeMap;

use glam::{Mat3, Vec2, Vec3};
use matflow_engine::node::Params;
use matflow_engine::{Node, NodeError, NodeInfo, OutputSpec, ParamSpec, ParamType, RunContext};
use matflow_geom::refraction::object_labels;
use matflow_geom::shapes::refraction_objects;
use matflow_geom::TriMesh;
use matflow_render::envmap::{rotate_and_expose, rotated};
use matflow_render::scene::{SceneObject, Surface};
use matflow_render::{render, EnvMap, Material, RenderOptions, RenderScene};
use matflow_scene::envgen::{procedural_envmap, EnvKind};
use matflow_scene::npy::{self, Dtype};
use matflow_scene::{io, Camera, Image, MaterialMaps, RgbImage};

use crate::{err, failed};

/// The names of the built-in objects (`refraction_objects`), in order.
pub use matflow_geom::shapes::REFRACTION_OBJECT_NAMES as OBJECT_NAMES;

macro_rules! common_params {
    () => {
        [
            ParamSpec {
                name: "object",
                ty: ParamType::Choice(OBJECT_NAMES),
                default: Some("~"),
                unit: "",
                doc: "a built-in object (hollow: cup, jug, bottle, vase; solid: the others)",
            },
            ParamSpec {
                name: "object_file",
                ty: ParamType::InPath,
                default: Some("~"),
                unit: "",
                doc: "an OBJ or PLY mesh (closed, outward-facing), in place of `object`",
            },
            ParamSpec {
                name: "hollow",
                ty: ParamType::Bool,
                default: Some("false"),
                unit: "",
                doc: "whether `object_file` is hollow (eq. 24's rule; built-ins know their own)",
            },
            ParamSpec {
                name: "object_size",
                ty: ParamType::Float {
                    min: 1e-3,
                    max: 1e4,
                },
                default: Some("1"),
                unit: "scene units",
                doc: "diameter of the object's bounding sphere (also the lengths' normaliser)",
            },
            ParamSpec {
                name: "azimuth",
                ty: ParamType::Float {
                    min: -360.0,
                    max: 360.0,
                },
                default: Some("0"),
                unit: "degrees",
                doc: "the camera's direction about the vertical, from +z",
            },
            ParamSpec {
                name: "elevation",
                ty: ParamType::Float {
                    min: -89.0,
                    max: 89.0,
                },
                default: Some("20"),
                unit: "degrees",
                doc: "the camera's height angle above the object's centre",
            },
            ParamSpec {
                name: "distance",
                ty: ParamType::Float {
                    min: 1e-3,
                    max: 1e6,
                },
                default: Some("2.5"),
                unit: "scene units",
                doc: "from the camera to the object's centre (beyond its bounding sphere)",
            },
            ParamSpec {
                name: "size",
                ty: ParamType::Int { min: 8, max: 4096 },
                default: Some("128"),
                unit: "px",
                doc: "image side",
            },
            ParamSpec {
                name: "ground",
                ty: ParamType::Bool,
                default: Some("true"),
                unit: "",
                doc: "a ground plane under the object (seen behind it: d2, the background)",
            },
        ]
    };
}

const COMMON: [ParamSpec; 9] = common_params!();

const fn concat<const A: usize, const B: usize, const C: usize>(
    a: [ParamSpec; A],
    b: [ParamSpec; B],
) -> [ParamSpec; C] {
    let mut out = [a[0]; C];
    let mut i = 0;
    while i < A {
        out[i] = a[i];
        i += 1;
    }
    while i < C {
        out[i] = b[i - A];
        i += 1;
    }
    out
}

const RENDER_ONLY: [ParamSpec; 14] = [
    ParamSpec {
        name: "envmap",
        ty: ParamType::InPath,
        default: Some("~"),
        unit: "",
        doc: "an environment map (HDR or EXR), in place of `envmap_kind`",
    },
    ParamSpec {
        name: "envmap_kind",
        ty: ParamType::Choice(EnvKind::NAMES),
        default: Some("~"),
        unit: "",
        doc: "a procedural environment map: an outdoor sky or a room",
    },
    ParamSpec {
        name: "envmap_seed",
        ty: ParamType::Int {
            min: 0,
            max: i64::MAX,
        },
        default: Some("0"),
        unit: "",
        doc: "the procedural map's seed",
    },
    ParamSpec {
        name: "envmap_width",
        ty: ParamType::Int { min: 8, max: 8192 },
        default: Some("256"),
        unit: "px",
        doc: "the procedural map's width (height: half)",
    },
    ParamSpec {
        name: "envmap_rotation",
        ty: ParamType::Float {
            min: -360.0,
            max: 360.0,
        },
        default: Some("0"),
        unit: "degrees",
        doc: "the map turned about the vertical",
    },
    ParamSpec {
        name: "exposure",
        ty: ParamType::Float {
            min: -20.0,
            max: 20.0,
        },
        default: Some("0"),
        unit: "EV",
        doc: "on top of the automatic exposure (the background's log-average to 0.18)",
    },
    ParamSpec {
        name: "albedo",
        ty: ParamType::FloatOrFloats {
            len: 3,
            min: 0.0,
            max: 1.0,
        },
        default: Some("0.8"),
        unit: "",
        doc: "the object's albedo",
    },
    ParamSpec {
        name: "roughness",
        ty: ParamType::Float { min: 0.0, max: 1.0 },
        default: Some("0.5"),
        unit: "",
        doc: "the object's roughness",
    },
    ParamSpec {
        name: "metallic",
        ty: ParamType::Float { min: 0.0, max: 1.0 },
        default: Some("0"),
        unit: "",
        doc: "the object's metallic",
    },
    ParamSpec {
        name: "ground_albedo",
        ty: ParamType::FloatOrFloats {
            len: 3,
            min: 0.0,
            max: 1.0,
        },
        default: Some("0.5"),
        unit: "",
        doc: "the ground's albedo",
    },
    ParamSpec {
        name: "ground_roughness",
        ty: ParamType::Float { min: 0.0, max: 1.0 },
        default: Some("0.7"),
        unit: "",
        doc: "the ground's roughness",
    },
    ParamSpec {
        name: "ground_checker",
        ty: ParamType::Float { min: 0.0, max: 1.0 },
        default: Some("0"),
        unit: "",
        doc: "contrast of a checkerboard on the ground (0: plain)",
    },
    ParamSpec {
        name: "ground_tile",
        ty: ParamType::Float {
            min: 1e-3,
            max: 1e3,
        },
        default: Some("0.25"),
        unit: "scene units",
        doc: "the checkerboard's square",
    },
    ParamSpec {
        name: "spp",
        ty: ParamType::Int { min: 1, max: 65536 },
        default: Some("32"),
        unit: "samples/px",
        doc: "samples per pixel of both renders",
    },
];

const RENDER_PARAMS: [ParamSpec; 23] = concat(COMMON, RENDER_ONLY);

/// The object and the ground in the camera's frame.
struct View {
    camera: Camera,
    object: TriMesh,
    normals: Vec<Vec3>,
    hollow: bool,
    /// The ground square (world y = the object's lowest point), when on.
    ground: Option<(TriMesh, Vec<Vec2>)>,
    /// Camera frame → world (turns the environment map).
    to_world: Mat3,
}

fn check_object(p: &Params) -> Result<(), String> {
    match (p.is_set("object"), p.is_set("object_file")) {
        (true, true) => Err("give `object` or `object_file`, not both".into()),
        (false, false) => Err("give `object` (a built-in) or `object_file`".into()),
        _ => Ok(()),
    }
}

fn view(p: &Params) -> Result<View, NodeError> {
    let (mut mesh, mut normals, hollow) = if let Some(path) = p.path("object_file") {
        let parts = io_mesh(&path)?;
        (parts.0, parts.1, p.bool("hollow"))
    } else {
        let name = p.str("object");
        let (_, shape, hollow) = refraction_objects()
            .into_iter()
            .find(|(n, ..)| *n == name)
            .ok_or_else(|| err(format!("no built-in object `{name}`")))?;
        (shape.mesh, shape.normals, hollow)
    };
    // Bounding sphere about the box's centre, scaled to `object_size`.
    let (lo, hi) = mesh.positions.iter().fold(
        (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
        |(lo, hi), &q| (lo.min(q), hi.max(q)),
    );
    let centre = (lo + hi) * 0.5;
    let radius = mesh
        .positions
        .iter()
        .map(|&q| (q - centre).length())
        .fold(0.0f32, f32::max);
    if radius.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) || !radius.is_finite() {
        return Err(err("the object has no extent"));
    }
    let size = p.f32("object_size");
    let k = 0.5 * size / radius;
    let distance = p.f32("distance");
    if distance <= 0.5 * size * 1.05 {
        return Err(err(format!(
            "`distance` {distance} puts the camera inside the object's bounding sphere \
             (radius {}): give more than {}",
            0.5 * size,
            0.5 * size * 1.05
        )));
    }
    let (az, el) = (
        p.f32("azimuth").to_radians(),
        p.f32("elevation").to_radians(),
    );
    let eye = distance * Vec3::new(el.cos() * az.sin(), el.sin(), el.cos() * az.cos());
    // Camera frame: +z from the centre towards the eye, +y up-ish.
    let z = eye.normalize();
    let x = Vec3::Y.cross(z).normalize_or(Vec3::X);
    let y = z.cross(x);
    let to_world = Mat3::from_cols(x, y, z);
    let to_cam = to_world.transpose();
    let place = |q: Vec3| to_cam * ((q - centre) * k - eye);
    let floor = (lo.y - centre.y) * k;
    for q in &mut mesh.positions {
        *q = place(*q);
    }
    for n in &mut normals {
        *n = (to_cam * *n).normalize_or(Vec3::Z);
    }
    let n = p.i64("size") as usize;
    let ground = p.bool("ground").then(|| {
        let half = 50.0 * size;
        let mut g = TriMesh::default();
        let corners = [(-half, -half), (-half, half), (half, half), (half, -half)];
        let mut uvs = Vec::new();
        for (cx, cz) in corners {
            g.positions.push(to_cam * (Vec3::new(cx, floor, cz) - eye));
            uvs.push(Vec2::new(cx, cz));
        }
        // Counter-clockwise seen from above: the normal is +y.
        g.indices = vec![[0, 1, 2], [0, 2, 3]];
        (g, uvs)
    });
    Ok(View {
        camera: Camera::new(n, n),
        object: mesh,
        normals,
        hollow,
        ground,
        to_world,
    })
}

/// The triangles of a mesh file (all parts) and its normals when every
/// part has them.
fn io_mesh(path: &std::path::Path) -> Result<(TriMesh, Vec<Vec3>), NodeError> {
    let parts = matflow_scene::meshfile::read_mesh(path).map_err(failed)?;
    let mut m = TriMesh::default();
    let mut normals = Vec::new();
    let all_normals = parts.iter().all(|p| p.normals.len() == p.positions.len());
    for part in parts {
        let base = m.positions.len() as u32;
        m.positions.extend_from_slice(&part.positions);
        m.indices
            .extend(part.indices.iter().map(|t| t.map(|i| base + i)));
        if all_normals {
            normals.extend_from_slice(&part.normals);
        }
    }
    if m.indices.is_empty() {
        return Err(err(format!(
            "{}: the mesh has no triangles",
            path.display()
        )));
    }
    Ok((m, normals))
}

pub struct RefractionLabelsNode;

pub(crate) const LABELS_INFO: NodeInfo = NodeInfo {
    kind: "refraction_labels",
    version: 1,
    doc: "One sample's labels for the refraction-length network: the object's mask, depth, \
         normals, eq. 24 refraction length (by the object's size, in [0, 1]) and the \
         transparency edit's d1, d2, per pixel centre (`matflow dataset` makes these).",
    params: &COMMON,
    outputs: &[
        OutputSpec {
            name: "mask.png",
            ty: "file",
            doc: "8-bit: 255 where the object is seen",
        },
        OutputSpec {
            name: "depth.npy",
            ty: "file",
            doc: "f16 H×W: camera-space depth of the object (0 elsewhere)",
        },
        OutputSpec {
            name: "normal.npy",
            ty: "file",
            doc: "f16 H×W×3: outward normal in camera space (+z to the camera)",
        },
        OutputSpec {
            name: "length.npy",
            ty: "file",
            doc: "f16 H×W: eq. 24 length / object_size, clamped to [0, 1]",
        },
        OutputSpec {
            name: "d1.npy",
            ty: "file",
            doc: "f16 H×W: from entering the object to finally leaving it (scene units)",
        },
        OutputSpec {
            name: "d2.npy",
            ty: "file",
            doc: "f16 H×W: from leaving the object to the ground behind (0: nothing behind)",
        },
    ],
};

impl Node for RefractionLabelsNode {
    fn info(&self) -> &'static NodeInfo {
        &LABELS_INFO
    }
    fn check(&self, p: &Params) -> Result<(), String> {
        check_object(p)
    }
    fn film_size(&self, p: &Params) -> Option<(usize, usize)> {
        let n = p.i64("size") as usize;
        Some((n, n))
    }
    fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
        let p = ctx.params;
        let v = view(p)?;
        let l = object_labels(
            &v.camera,
            &v.object,
            v.hollow,
            v.ground.as_ref().map(|g| &g.0),
        );
        let (w, h) = (v.camera.width, v.camera.height);
        let size = p.f32("object_size");
        let finite = |x: f32| if x.is_finite() { x } else { 0.0 };
        let gray = |img: &matflow_scene::GrayImage, f: &dyn Fn(f32) -> f32| {
            let vals: Vec<f32> = img.data.iter().map(|&x| f(finite(x))).collect();
            npy::encode(&vals, &[h, w], Dtype::F16)
        };
        let normals: Vec<f32> = l
            .normal
            .data
            .iter()
            .flat_map(|n| [finite(n.x), finite(n.y), finite(n.z)])
            .collect();
        let mut out = BTreeMap::new();
        out.insert(
            "mask.png".into(),
            io::png_mask_bytes(&l.mask).map_err(failed)?,
        );
        out.insert("depth.npy".into(), gray(&l.depth, &|x| x));
        out.insert(
            "normal.npy".into(),
            npy::encode(&normals, &[h, w, 3], Dtype::F16),
        );
        out.insert(
            "length.npy".into(),
            gray(&l.length, &|x| (x / size).clamp(0.0, 1.0)),
        );
        out.insert("d1.npy".into(), gray(&l.d1, &|x| x.max(0.0)));
        out.insert("d2.npy".into(), gray(&l.d2, &|x| x.max(0.0)));
        Ok(out)
    }
}

pub struct RefractionRenderNode;

pub(crate) const RENDER_INFO: NodeInfo = NodeInfo {
    kind: "refraction_render",
    version: 1,
    doc: "One sample's photographs for the refraction-length network: the object (opaque, its \
         material given) on an optional ground under an environment map, and the same view \
         without the object, path-traced and exposed alike (`matflow dataset` makes these).",
    params: &RENDER_PARAMS,
    outputs: &[
        OutputSpec {
            name: "image.png",
            ty: "file",
            doc: "8-bit sRGB: the object in its surroundings",
        },
        OutputSpec {
            name: "background.png",
            ty: "file",
            doc: "8-bit sRGB: the same view without the object",
        },
        OutputSpec {
            name: "render.json",
            ty: "file",
            doc: "the exposure applied (linear scale) and the samples taken",
        },
    ],
};

impl RefractionRenderNode {
    fn envmap(p: &Params) -> Result<RgbImage, NodeError> {
        let env = if let Some(path) = p.path("envmap") {
            io::read_envmap(&path).map_err(failed)?
        } else {
            let kind = EnvKind::from_name(p.str("envmap_kind"))
                .ok_or_else(|| err("`envmap_kind` is sky or room"))?;
            let w = p.i64("envmap_width") as usize;
            procedural_envmap(kind, p.i64("envmap_seed") as u64, w, (w / 2).max(2))
        };
        Ok(rotate_and_expose(&env, p.f64("envmap_rotation"), 0.0))
    }
}

/// A checkerboard texture of two squares per side, `contrast` apart (16
/// texels a square, so bilinear lookups keep the edges sharp).
fn checker(contrast: f32) -> RgbImage {
    Image::from_fn(32, 32, |x, y| {
        Vec3::splat(if (x / 16 + y / 16) % 2 == 0 {
            1.0
        } else {
            1.0 - contrast
        })
    })
}

impl Node for RefractionRenderNode {
    fn info(&self) -> &'static NodeInfo {
        &RENDER_INFO
    }
    fn check(&self, p: &Params) -> Result<(), String> {
        check_object(p)?;
        match (p.is_set("envmap"), p.is_set("envmap_kind")) {
            (true, true) => Err("give `envmap` or `envmap_kind`, not both".into()),
            (false, false) => Err("give `envmap` (a file) or `envmap_kind` (sky or room)".into()),
            _ => Ok(()),
        }
    }
    /// Only the envmap's format here: a dataset has thousands of these
    /// stages sharing a few files, which its generator reads once each;
    /// a damaged file fails its stage with the file's name.
    fn preflight(&self, p: &Params) -> Result<(), String> {
        if let Some(path) = p.path("envmap") {
            let ext = path
                .extension()
                .map(|e| e.to_string_lossy().to_lowercase())
                .unwrap_or_default();
            if ext != "hdr" && ext != "exr" {
                return Err(format!(
                    "{}: an environment map must be Radiance HDR (.hdr) or linear OpenEXR (.exr)",
                    path.display()
                ));
            }
        }
        Ok(())
    }
    fn film_size(&self, p: &Params) -> Option<(usize, usize)> {
        let n = p.i64("size") as usize;
        Some((n, n))
    }
    fn estimate_seconds(&self, p: &Params, film: Option<(usize, usize)>) -> f64 {
        2.0 * crate::data::render_seconds(film, p.i64("spp"), 4)
    }
    fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
        let p = ctx.params;
        let v = view(p)?;
        let env_world = Self::envmap(p)?;
        let env = EnvMap::new(&rotated(&env_world, v.to_world)).map_err(failed)?;
        let (w, h) = (v.camera.width, v.camera.height);
        let rgb = |name: &str| -> Vec3 {
            let f = p.floats(name).unwrap_or_else(|| vec![0.5; 3]);
            Vec3::new(f[0] as f32, f[1] as f32, f[2] as f32)
        };
        let maps = MaterialMaps::uniform(w, h, Vec3::splat(0.5), 0.5, 0.0);
        let mut objects = Vec::new();
        if let Some((g, uvs)) = &v.ground {
            let tile = p.f32("ground_tile");
            let contrast = p.f32("ground_checker");
            objects.push(SceneObject {
                mesh: g.clone(),
                normals: Vec::new(),
                surface: Surface::Principled(Material {
                    albedo: rgb("ground_albedo"),
                    roughness: p.f32("ground_roughness"),
                    metallic: 0.0,
                }),
                // Two texels per square: u = x / (2·tile).
                uvs: uvs.iter().map(|uv| *uv / (2.0 * tile)).collect(),
                texture: (contrast > 0.0).then(|| std::sync::Arc::new(checker(contrast))),
            });
        }
        let object = SceneObject {
            mesh: v.object.clone(),
            normals: v.normals.clone(),
            surface: Surface::Principled(Material {
                albedo: rgb("albedo"),
                roughness: p.f32("roughness"),
                metallic: p.f32("metallic"),
            }),
            uvs: Vec::new(),
            texture: None,
        };
        let opts = RenderOptions {
            spp: p.i64("spp") as u32,
            seed: ctx.seed,
            ..RenderOptions::default()
        };
        let draw = |objs: &[SceneObject], half: usize| -> Result<RgbImage, NodeError> {
            let scene =
                RenderScene::with_objects(v.camera, TriMesh::default(), &maps, env.clone(), objs)
                    .map_err(failed)?;
            let total = 2 * w * h;
            Ok(render(&scene, &opts, &|d, _| {
                (ctx.progress)((half * w * h + d) as u64, total as u64)
            })
            .image)
        };
        let background = draw(&objects, 0)?;
        objects.push(object);
        let image = draw(&objects, 1)?;
        // Exposure: the background's log-average luminance to 0.18.
        let scale =
            matflow_scene::color::exposure_to_key(&background, 0.18) * 2f64.powf(p.f64("exposure"));
        let expose = |img: &RgbImage| img.map(|c| c * scale as f32);
        let mut out = BTreeMap::new();
        out.insert(
            "image.png".into(),
            io::png_srgb_bytes(&expose(&image)).map_err(failed)?,
        );
        out.insert(
            "background.png".into(),
            io::png_srgb_bytes(&expose(&background)).map_err(failed)?,
        );
        let json = serde_json::json!({
            "exposure_scale": scale,
            "spp": opts.spp,
        });
        out.insert("render.json".into(), json.to_string().into_bytes());
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    use crate::testutil::params_of;
    use matflow_engine::Value;

    fn run(node: &dyn Node, p: &Params) -> BTreeMap<String, Vec<u8>> {
        node.run(&RunContext {
            stage: "s",
            params: p,
            inputs: BTreeMap::new(),
            seed: 5,
            progress: &|_, _| {},
        })
        .unwrap()
    }

    #[test]
    fn a_ball_on_the_ground_is_labelled_and_photographed() {
        let n = 32;
        let common = [
            ("object", Value::Str("ball".into())),
            ("size", Value::Int(n as i64)),
            ("elevation", Value::Float(25.0)),
        ];
        let lp = params_of(&LABELS_INFO, &common);
        let l = run(&RefractionLabelsNode, &lp);
        let mask = image_gray(&l["mask.png"]);
        let len = npy::decode(&l["length.npy"]).unwrap();
        let d2 = npy::decode(&l["d2.npy"]).unwrap();
        assert_eq!(len.shape, vec![n, n]);
        assert_eq!(npy::decode(&l["normal.npy"]).unwrap().shape, vec![n, n, 3]);
        let c = (n / 2) * n + n / 2;
        assert_eq!(mask[c], 255);
        // Through the centre: the chord is the diameter, normalised to 1;
        // beyond the ball, the ray meets the ground.
        assert!((len.values[c] - 1.0).abs() < 0.02, "{}", len.values[c]);
        assert!(d2.values[c] > 0.1, "{}", d2.values[c]);
        assert_eq!((mask[0], len.values[0]), (0, 0.0));
        let seen = mask.iter().filter(|&&m| m == 255).count();
        assert!(seen > n * n / 20 && seen < n * n / 2, "{seen}");

        let mut rp: Vec<(&str, Value)> = common.to_vec();
        rp.push(("envmap_kind", Value::Str("room".into())));
        rp.push(("spp", Value::Int(8)));
        rp.push(("albedo", Value::Float(0.9)));
        let rp = params_of(&RENDER_INFO, &rp);
        let r = run(&RefractionRenderNode, &rp);
        assert_eq!(r, run(&RefractionRenderNode, &rp), "not deterministic");
        let (img, bg) = (image_rgb(&r["image.png"]), image_rgb(&r["background.png"]));
        // The object changes the pixels it covers, not the far corners.
        let diff = |k: usize| {
            (0..3)
                .map(|ch| img[3 * k + ch].abs_diff(bg[3 * k + ch]) as u32)
                .sum::<u32>()
        };
        let inside: u32 = (0..n * n).filter(|&k| mask[k] == 255).map(diff).sum();
        assert!(inside as usize > 10 * seen, "{inside}");
        assert!(
            diff(0) <= 3 && diff(n * n - 1) <= 30,
            "{} {}",
            diff(0),
            diff(n * n - 1)
        );
    }

    fn image_gray(png: &[u8]) -> Vec<u8> {
        image::load_from_memory(png).unwrap().to_luma8().into_raw()
    }
    fn image_rgb(png: &[u8]) -> Vec<u8> {
        image::load_from_memory(png).unwrap().to_rgb8().into_raw()
    }
}
