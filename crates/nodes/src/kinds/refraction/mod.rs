//! The refraction-length dataset's two per-sample kinds (the paper's
//! supplement §10), which `matflow dataset` generates one of each per
//! sample, each in its own file; what they share (the object, the view,
//! their common parameters) is here:
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
use matflow_geom::TriMesh;
use matflow_procgen::envgen::{procedural_envmap, EnvKind};
use matflow_procgen::refraction::object_labels;
use matflow_procgen::shapes::refraction_objects;
use matflow_render::envmap::{rotate_and_expose, rotated};
use matflow_render::scene::{SceneObject, Surface};
use matflow_render::{render, EnvMap, Material, RenderOptions, RenderScene};
use matflow_scene::npy::{self, Dtype};
use matflow_scene::{io, Camera, Image, MaterialMaps, RgbImage};

use crate::{err, failed};

/// The names of the built-in objects (`refraction_objects`), in order.
pub use matflow_procgen::shapes::REFRACTION_OBJECT_NAMES as OBJECT_NAMES;

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

mod labels;
mod render;

pub use labels::RefractionLabelsNode;
#[cfg(test)]
pub(crate) use labels::LABELS_INFO;
pub use render::RefractionRenderNode;
#[cfg(test)]
pub(crate) use render::RENDER_INFO;

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
            metric: &|_, _| {},
            cancelled: &matflow_engine::node::never_cancelled,
            image: None,
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
