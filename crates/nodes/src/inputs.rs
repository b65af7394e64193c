//! Inputs: photos and EXR/HDR files, reference bundles, procedural scenes,
//! and the mesh built from a scene's depth.

use std::collections::BTreeMap;
use std::path::Path;

use glam::{Vec2, Vec3};
use matflow_engine::node::Params;
use matflow_engine::{Node, NodeError, NodeInfo, OutputSpec, ParamSpec, ParamType, RunContext};
use matflow_geom::{mesh_from_depth, MeshParams, TriMesh};
use matflow_render::{render, EnvMap, RenderOptions, RenderScene};
use matflow_scene::{io, Bundle, Camera, GrayImage, MaterialMaps, MaterialSource, RgbImage};

use crate::artifact::Artifact;
use crate::err;

pub(crate) const SCENE: ParamSpec = ParamSpec {
    name: "scene",
    ty: ParamType::Ref(&["scene"]),
    default: None,
    unit: "",
    doc: "the scene (input image, starting materials)",
};
pub(crate) const MESH: ParamSpec = ParamSpec {
    name: "mesh",
    ty: ParamType::Ref(&["mesh"]),
    default: None,
    unit: "",
    doc: "geometry and camera",
};

/// What a `scene` artifact holds.
pub struct SceneData {
    /// Camera-space depth z (0: sky).
    pub depth: GrayImage,
    /// The linear input image, when there is one.
    pub target: Option<RgbImage>,
    /// Predicted (starting) materials.
    pub pred: MaterialMaps,
}

impl SceneData {
    pub fn encode(&self) -> Vec<u8> {
        let mut a = Artifact::new("scene");
        a.put_gray("depth", &self.depth);
        if let Some(t) = &self.target {
            a.put_rgb("target", t);
        }
        a.put_materials("pred_", &self.pred);
        a.encode()
    }
    pub fn decode(b: &[u8]) -> Result<SceneData, NodeError> {
        let a = Artifact::decode(b, "scene")?;
        Ok(SceneData {
            depth: a.gray("depth")?,
            target: if a.has("target") {
                Some(a.rgb("target")?)
            } else {
                None
            },
            pred: a.materials("pred_")?,
        })
    }
}

pub fn encode_image(ty: &str, name: &str, img: &RgbImage) -> Vec<u8> {
    let mut a = Artifact::new(ty);
    a.put_rgb(name, img);
    a.encode()
}

pub fn encode_materials(m: &MaterialMaps) -> Vec<u8> {
    let mut a = Artifact::new("materials");
    a.put_materials("", m);
    a.encode()
}

/// Materials from a reference that may name a `materials` or a `scene`
/// artifact (then its predictions).
pub fn materials_from(b: &[u8]) -> Result<MaterialMaps, NodeError> {
    match Artifact::decode(b, "materials") {
        Ok(a) => a.materials(""),
        Err(_) => Ok(SceneData::decode(b)?.pred),
    }
}

pub fn envmap_from(b: &[u8]) -> Result<RgbImage, NodeError> {
    Artifact::decode(b, "envmap")?.rgb("envmap")
}

pub fn encode_mesh(width: usize, height: usize, m: &TriMesh) -> Vec<u8> {
    let mut a = Artifact::new("mesh");
    a.put_u32("camera", 2, 1, vec![width as u32, height as u32]);
    a.put_f32(
        "positions",
        m.positions.len() as u32,
        3,
        m.positions.iter().flat_map(|p| [p.x, p.y, p.z]).collect(),
    );
    a.put_u32(
        "indices",
        m.indices.len() as u32,
        3,
        m.indices.iter().flatten().copied().collect(),
    );
    a.put_f32(
        "film",
        m.film.len() as u32,
        2,
        m.film.iter().flat_map(|p| [p.x, p.y]).collect(),
    );
    a.encode()
}

pub fn decode_mesh(b: &[u8]) -> Result<(Camera, TriMesh), NodeError> {
    let a = Artifact::decode(b, "mesh")?;
    let cam = a.u32_list("camera", 1)?;
    if cam.len() != 2 {
        return Err(err("mesh artifact: bad camera"));
    }
    let positions: Vec<Vec3> = a
        .f32_list("positions", 3)?
        .chunks_exact(3)
        .map(|c| Vec3::new(c[0], c[1], c[2]))
        .collect();
    let indices: Vec<[u32; 3]> = a
        .u32_list("indices", 3)?
        .chunks_exact(3)
        .map(|c| [c[0], c[1], c[2]])
        .collect();
    if indices
        .iter()
        .flatten()
        .any(|&i| i as usize >= positions.len())
    {
        return Err(err("mesh artifact: index out of range"));
    }
    let film = a
        .f32_list("film", 2)?
        .chunks_exact(2)
        .map(|c| Vec2::new(c[0], c[1]))
        .collect();
    Ok((
        Camera::new(cam[0] as usize, cam[1] as usize),
        TriMesh {
            positions,
            indices,
            film,
        },
    ))
}

/// A renderable scene from a mesh artifact, materials and an envmap.
pub fn render_scene(
    mesh: &[u8],
    maps: &MaterialMaps,
    env: &RgbImage,
) -> Result<RenderScene, NodeError> {
    let (cam, tri) = decode_mesh(mesh)?;
    if maps.width() != cam.width || maps.height() != cam.height {
        return Err(err(format!(
            "materials are {}x{} but the mesh's camera is {}x{}",
            maps.width(),
            maps.height(),
            cam.width,
            cam.height
        )));
    }
    RenderScene::new(cam, tri, maps, EnvMap::new(env).map_err(err)?).map_err(err)
}

fn mesh_of(depth: &GrayImage, angle: f64) -> Result<TriMesh, NodeError> {
    let cam = Camera::new(depth.width, depth.height);
    Ok(mesh_from_depth(
        depth,
        &cam,
        &MeshParams {
            min_angle_deg: angle,
        },
    )
    .map_err(|e| err(format!("meshing the depth map: {e}")))?
    .mesh)
}

/// Reads a photo (PNG/JPEG: centre-cropped, resized, linearised with
/// power 2.2), or a linear EXR / Radiance HDR as is; rejects NaN/Inf.
pub fn read_image(path: &Path, size: usize) -> Result<RgbImage, NodeError> {
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_lowercase())
        .unwrap_or_default();
    let img = match ext.as_str() {
        "exr" => io::read_exr_rgb(path).map_err(err)?,
        "hdr" => io::read_hdr(path).map_err(err)?,
        "png" | "jpg" | "jpeg" => {
            let raw = io::read_ldr_raw(path).map_err(err)?;
            let s = if size == 0 {
                raw.width.min(raw.height)
            } else {
                size
            };
            io::load_photo(path, s).map_err(err)?
        }
        _ => {
            return Err(err(format!(
                "{}: unknown image type (use .png, .jpg, .exr or .hdr)",
                path.display()
            )))
        }
    };
    io::ensure_finite_rgb(path, &img).map_err(err)?;
    if img.width == 0 || img.height == 0 {
        return Err(err(format!("{}: the image is empty", path.display())));
    }
    Ok(img)
}

const IMAGE_OUT: &[OutputSpec] = &[OutputSpec {
    name: "image",
    ty: "image",
    doc: "linear RGB",
}];

pub struct ImageNode;

const IMAGE_INFO: NodeInfo = NodeInfo {
    kind: "image",
    version: 1,
    doc: "An image file: a photo (PNG/JPEG; centre-cropped to a square, resized, linearised \
         with power 2.2 as the reference does) or a linear EXR / Radiance HDR (as is).",
    params: &[
        ParamSpec {
            name: "path",
            ty: ParamType::InPath,
            default: None,
            unit: "",
            doc: "the file (relative to the pipeline file)",
        },
        ParamSpec {
            name: "size",
            ty: ParamType::Int { min: 0, max: 8192 },
            default: Some("512"),
            unit: "px",
            doc: "photos: side of the square they are resized to (0: the shorter side)",
        },
    ],
    outputs: IMAGE_OUT,
};

impl Node for ImageNode {
    fn info(&self) -> &'static NodeInfo {
        &IMAGE_INFO
    }
    fn preflight(&self, p: &Params) -> Result<(), String> {
        read_image(&p.path("path").unwrap_or_default(), p.i64("size") as usize)
            .map(|_| ())
            .map_err(|e| e.0)
    }
    fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
        let p = ctx.params;
        let img = read_image(&p.path("path").unwrap_or_default(), p.i64("size") as usize)?;
        Ok([("image".to_string(), encode_image("image", "image", &img))].into())
    }
}

pub struct BundleNode;

fn material_source(s: &str) -> MaterialSource {
    match s {
        "ground_truth" => MaterialSource::GroundTruth,
        "best_results" => MaterialSource::BestResults,
        _ => MaterialSource::Pred,
    }
}

impl BundleNode {
    fn load(&self, p: &Params) -> Result<(SceneData, Bundle), NodeError> {
        let dir = p.path("path").unwrap_or_default();
        let b = Bundle::open(&dir).map_err(err)?;
        let depth = b.load_depth().map_err(err)?;
        let pred = b
            .load_materials(material_source(p.str("materials")))
            .map_err(err)?;
        let target = if b.path("gt_image.exr").exists() || b.path("gt_image.png").exists() {
            Some(b.load_gt_image().map_err(err)?)
        } else {
            None
        };
        let sized = |w: usize, h: usize, what: &str| {
            if w != depth.width || h != depth.height {
                Err(err(format!(
                    "{}: {what} is {w}x{h} but the depth is {}x{}",
                    dir.display(),
                    depth.width,
                    depth.height
                )))
            } else {
                Ok(())
            }
        };
        sized(pred.width(), pred.height(), "the material set")?;
        if let Some(t) = &target {
            sized(t.width, t.height, "gt_image")?;
        }
        Ok((
            SceneData {
                depth,
                target,
                pred,
            },
            b,
        ))
    }
}

const BUNDLE_INFO: NodeInfo = NodeInfo {
    kind: "bundle",
    version: 1,
    doc: "A folder in the reference's layout: depth (depth.exr or depthPred.exr), the input \
         image (gt_image.exr/.png, optional), predictions (albedoPred.exr, roughnessPred, \
         metallicPred) and/or results (best_results/).",
    params: &[
        ParamSpec {
            name: "path",
            ty: ParamType::InPath,
            default: None,
            unit: "",
            doc: "the bundle folder",
        },
        ParamSpec {
            name: "materials",
            ty: ParamType::Choice(&["pred", "best_results", "ground_truth"]),
            default: Some("pred"),
            unit: "",
            doc: "which material set becomes the scene's starting materials",
        },
        ParamSpec {
            name: "image",
            ty: ParamType::Ref(&["image"]),
            default: Some("~"),
            unit: "",
            doc: "an `image` stage replacing the bundle's gt_image",
        },
    ],
    outputs: &[
        OutputSpec {
            name: "scene",
            ty: "scene",
            doc: "depth, input image, starting materials",
        },
        OutputSpec {
            name: "results",
            ty: "materials",
            doc: "best_results/ materials, when present",
        },
        OutputSpec {
            name: "envmap",
            ty: "envmap",
            doc: "best_results/envmap.hdr (or ground_truth/), when present",
        },
    ],
};

impl Node for BundleNode {
    fn info(&self) -> &'static NodeInfo {
        &BUNDLE_INFO
    }
    fn preflight(&self, p: &Params) -> Result<(), String> {
        self.load(p).map(|_| ()).map_err(|e| e.0)
    }
    fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
        let (mut scene, b) = self.load(ctx.params)?;
        if let Some(img) = ctx.opt_input("image") {
            let img = Artifact::decode(img, "image")?.rgb("image")?;
            if !img.same_size(&scene.depth) {
                return Err(err(format!(
                    "the image is {}x{} but the bundle's depth is {}x{}",
                    img.width, img.height, scene.depth.width, scene.depth.height
                )));
            }
            scene.target = Some(img);
        }
        let mut out: BTreeMap<String, Vec<u8>> = BTreeMap::new();
        out.insert("scene".into(), scene.encode());
        if b.path("best_results/albedo.exr").exists() {
            let m = b.load_materials(MaterialSource::BestResults).map_err(err)?;
            out.insert("results".into(), encode_materials(&m));
        }
        if let Some(p) = b.envmap_path() {
            let env = io::read_hdr(&p).map_err(err)?;
            io::ensure_finite_rgb(&p, &env).map_err(err)?;
            out.insert("envmap".into(), encode_image("envmap", "envmap", &env));
        }
        Ok(out)
    }
}

pub struct SyntheticSceneNode;

const SYNTHETIC_SCENE_INFO: NodeInfo = NodeInfo {
    kind: "synthetic_scene",
    version: 1,
    doc: "A procedural room (floor, walls, a few objects with varied albedo, roughness and \
         metallic) under a procedural sky, its input image rendered by matflow's path tracer, \
         and predictions made by degrading the truth (blur, noise, bias, wrong R/M).",
    params: &[
        ParamSpec {
            name: "seed",
            ty: ParamType::Int {
                min: 0,
                max: i64::MAX,
            },
            default: Some("1"),
            unit: "",
            doc: "layout, objects, materials and sky",
        },
        ParamSpec {
            name: "size",
            ty: ParamType::Int { min: 16, max: 4096 },
            default: Some("256"),
            unit: "px",
            doc: "image side",
        },
        ParamSpec {
            name: "spp",
            ty: ParamType::Int { min: 1, max: 65536 },
            default: Some("128"),
            unit: "samples/px",
            doc: "samples of the input image",
        },
        ParamSpec {
            name: "degrade",
            ty: ParamType::Bool,
            default: Some("true"),
            unit: "",
            doc: "predictions degraded from the truth (false: the truth itself)",
        },
    ],
    outputs: &[
        OutputSpec {
            name: "scene",
            ty: "scene",
            doc: "depth, rendered input image, predictions",
        },
        OutputSpec {
            name: "truth",
            ty: "materials",
            doc: "true materials",
        },
        OutputSpec {
            name: "truth_envmap",
            ty: "envmap",
            doc: "true lighting (32×16)",
        },
    ],
};

impl Node for SyntheticSceneNode {
    fn info(&self) -> &'static NodeInfo {
        &SYNTHETIC_SCENE_INFO
    }
    fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
        let p = ctx.params;
        let seed = p.i64("seed") as u64;
        let size = p.i64("size") as usize;
        let s = matflow_scene::synthetic::generate(seed, size, size);
        let pred = if p.bool("degrade") {
            matflow_scene::synthetic::degrade(&s.maps, seed)
        } else {
            s.maps.clone()
        };
        let tri = mesh_of(&s.depth, 6.0)?;
        let cam = Camera::new(size, size);
        let scene = RenderScene::new(cam, tri, &s.maps, EnvMap::new(&s.envmap).map_err(err)?)
            .map_err(err)?;
        let opts = RenderOptions {
            spp: p.i64("spp") as u32,
            seed,
            ..Default::default()
        };
        let img = render(&scene, &opts, &|d, t| (ctx.progress)(d as u64, t as u64)).image;
        let data = SceneData {
            depth: s.depth,
            target: Some(img),
            pred,
        };
        Ok([
            ("scene".to_string(), data.encode()),
            ("truth".to_string(), encode_materials(&s.maps)),
            (
                "truth_envmap".to_string(),
                encode_image("envmap", "envmap", &s.envmap),
            ),
        ]
        .into())
    }
}

pub struct MeshNode;

const MESH_INFO: NodeInfo = NodeInfo {
    kind: "mesh",
    version: 1,
    doc: "The triangle mesh of a scene's depth map (one vertex per pixel, cut at depth \
         discontinuities found by the reference's angle test).",
    params: &[
        ParamSpec {
            name: "scene",
            ty: ParamType::Ref(&["scene"]),
            default: None,
            unit: "",
            doc: "the scene whose depth is meshed",
        },
        ParamSpec {
            name: "angle",
            ty: ParamType::Float {
                min: 0.0,
                max: 90.0,
            },
            default: Some("6"),
            unit: "degrees",
            doc: "boundary threshold: triangles seen more obliquely than this are cut",
        },
    ],
    outputs: &[OutputSpec {
        name: "mesh",
        ty: "mesh",
        doc: "vertices, triangles, film positions",
    }],
};

impl Node for MeshNode {
    fn info(&self) -> &'static NodeInfo {
        &MESH_INFO
    }
    fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
        let s = SceneData::decode(ctx.input("scene")?)?;
        let tri = mesh_of(&s.depth, ctx.params.f64("angle"))?;
        Ok([(
            "mesh".to_string(),
            encode_mesh(s.depth.width, s.depth.height, &tri),
        )]
        .into())
    }
}
