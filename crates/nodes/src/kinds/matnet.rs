//! `matnet`: the prediction stage. A photograph in; MatNet's five maps out
//! (depth, albedo, roughness, metallic, normals) through an ONNX model
//! honouring MatNet's contract (`matflow_onnx::matnet`) — the model
//! matflow trained on its own `rooms` dataset (`models/matnet_rooms.onnx`,
//! built into the binary) or a given one, e.g. an export of the official
//! network. The result is a `scene` for the stages downstream and, when
//! `output` names a folder, a bundle in the reference's layout.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use glam::Vec3;
use matflow_engine::node::{Bytes, Params};
use matflow_engine::{Node, NodeError, NodeInfo, OutputSpec, ParamSpec, ParamType, RunContext};
use matflow_onnx::matnet::{
    linear, network_input, square_of, Contract, DepthKind, Encoding, Maps, Planar, SQUARE,
};
use matflow_onnx::model_file::{
    check_memory, info_of_bytes, info_of_file, memory_available, memory_needed, ModelInfo,
};
use matflow_onnx::{Backend, Graph, Source};
use matflow_scene::bundle::{check_depth_range, disparity_to_depth};
use matflow_scene::{io, GrayImage, Image, MaterialMaps, RgbImage};

use crate::data::{backend_of, put_file, SceneData, BACKEND};
use crate::{err, failed};

/// The network matflow ships: trained by `train/matnet/train.py` on the
/// `rooms` dataset (see `models/matnet_rooms.md`).
pub const BUNDLED_MODEL: &[u8] = include_bytes!("../../../../models/matnet_rooms.onnx");
/// Its BLAKE3, checked by a test: a new model must come with a new node
/// version (the version is in every key).
pub const BUNDLED_MODEL_BLAKE3: &str =
    "007367855c80be5964d836b2459971c626507faea5d97ccf0362cc3f50167df4";

/// The shortest photo side accepted: below it there is nothing to
/// predict from (the contract resizes everything to 512²).
pub const MIN_PHOTO_SIDE: usize = 32;

/// The files of a bundle this stage writes, in order.
pub const FILES: &[&str] = &[
    "gt_image.exr",
    "gt_image.png",
    "albedoPred.exr",
    "normalPred.exr",
    "roughnessPred.png",
    "metallicPred.png",
    "depth.exr",
    "depthPred.exr",
    "prediction.json",
];

pub struct MatnetNode;

const fn file(name: &'static str, doc: &'static str) -> OutputSpec {
    OutputSpec {
        name,
        ty: "file",
        doc,
    }
}

const INFO: NodeInfo = NodeInfo {
    kind: "matnet",
    version: 3,
    doc: "MatNet's prediction stage: a photo (PNG/JPEG of 8 or 16 bits, grey or colour, or a \
         linear EXR; any size and aspect) is centre-cropped, resized to 512² and run through an \
         ONNX model under MatNet's contract (input size and output layout read from the model); \
         out come depth, albedo, roughness, metallic and normals at 512², as a scene and (with \
         output) a bundle in the reference's layout. ONNX through ort: tract (pure Rust) or \
         onnxruntime (the Python wheel's library).",
    params: &[
        ParamSpec {
            name: "photo",
            ty: ParamType::InPath,
            default: None,
            unit: "",
            doc: "the photograph: PNG or JPEG (8 or 16 bits, grey or colour) or a linear EXR, \
                  any size and aspect (centre-cropped to a square)",
        },
        ParamSpec {
            name: "model",
            ty: ParamType::InPath,
            default: Some("~"),
            unit: "",
            doc: "an ONNX model honouring MatNet's contract (default: the bundled one, trained \
                  here on matflow's generated scenes)",
        },
        BACKEND,
        ParamSpec {
            name: "output",
            ty: ParamType::OutPath,
            default: Some("~"),
            unit: "",
            doc: "a folder to write the bundle to (gt_image, *Pred maps, depth, prediction.json)",
        },
    ],
    outputs: &[
        OutputSpec {
            name: "scene",
            ty: "scene",
            doc: "depth (camera-space z), the photo (linear, 512²) and the predicted materials \
                  (clamped as the reference does: albedo [0, 1], roughness [0.07, 1], metallic \
                  [0, 1])",
        },
        file(
            "gt_image.exr",
            "the photo as the network saw it before its resize: linear, 512²",
        ),
        file("gt_image.png", "the same, 8-bit, power 1/2.2"),
        file(
            "albedoPred.exr",
            "albedo, linear, unclamped (as the reference writes it)",
        ),
        file(
            "normalPred.exr",
            "normals, camera space, +z towards the camera",
        ),
        file(
            "roughnessPred.png",
            "roughness, 8-bit through the sRGB curve",
        ),
        file("metallicPred.png", "metallic, 8-bit through the sRGB curve"),
        file(
            "depth.exr",
            "camera-space z, for a model whose metadata says matflow.depth = z",
        ),
        file(
            "depthPred.exr",
            "the raw disparity-like depth of a MatNet-style model",
        ),
        file(
            "prediction.json",
            "provenance: photo, conversions, model digest, contract, backend",
        ),
        OutputSpec {
            name: "note",
            ty: "note",
            doc: "the backend and the model's digest, for the run report",
        },
    ],
};

/// A model ready to run, with what is known about it.
pub struct Loaded {
    pub graph: Graph,
    pub contract: Contract,
    pub info: ModelInfo,
    pub what: String,
}

/// What is known of the stage's model (the given file or the bundled one)
/// before loading it: its digest, size and metadata (a corrupt or
/// truncated file fails here), and that the machine has the memory to run
/// it. Also names it for messages.
fn model_info(model: Option<&Path>) -> Result<(ModelInfo, String), NodeError> {
    let (info, what) = match model {
        Some(path) => (
            info_of_file(path)
                .map_err(|e| err(format!("{}: not an ONNX model: {e}", path.display())))?,
            path.display().to_string(),
        ),
        None => (
            info_of_bytes(BUNDLED_MODEL).map_err(err)?,
            "the bundled MatNet-contract model (models/matnet_rooms.onnx)".to_string(),
        ),
    };
    // The input side is only known after loading; assume MatNet's 518²
    // for the activations.
    check_memory(
        &what,
        memory_needed(info.bytes, 3 * 518 * 518),
        memory_available(),
    )
    .map_err(err)?;
    Ok((info, what))
}

/// Loads the stage's model and checks its contract.
pub fn load_model(model: Option<&Path>, backend: Backend) -> Result<Loaded, NodeError> {
    let (info, what) = model_info(model)?;
    let graph = match model {
        Some(path) => Graph::load(Source::File(path), &what, backend),
        None => Graph::load(Source::Bytes(BUNDLED_MODEL), &what, backend),
    }
    .map_err(failed)?;
    let contract = Contract::of(&graph.inputs, &graph.outputs, &info.metadata)
        .map_err(|e| err(format!("{what}: not a MatNet-contract model: {e}")))?;
    Ok(Loaded {
        graph,
        contract,
        info,
        what,
    })
}

/// What one prediction gives.
pub struct Prediction {
    /// The photo's centred square at 512², linear.
    pub photo: RgbImage,
    pub maps: Maps,
    pub depth_kind: DepthKind,
    /// Camera-space z from the depth output.
    pub z: GrayImage,
}

fn rgb(p: &Planar) -> RgbImage {
    let n = p.h * p.w;
    Image::from_fn(p.w, p.h, |x, y| {
        let i = y * p.w + x;
        Vec3::new(p.data[i], p.data[n + i], p.data[2 * n + i])
    })
}

fn gray(p: &Planar) -> GrayImage {
    Image::from_vec(p.w, p.h, p.data.clone())
}

fn check_photo_size(path: &Path, w: usize, h: usize) -> Result<(), String> {
    if w.min(h) < MIN_PHOTO_SIDE {
        return Err(format!(
            "{}: the photo is {w}x{h}: too small to predict from (its shorter side must be at \
             least {MIN_PHOTO_SIDE} pixels)",
            path.display()
        ));
    }
    Ok(())
}

/// Reads a photo, refusing what cannot be predicted from.
pub fn read_photo(path: &Path) -> Result<io::Photo, NodeError> {
    let photo = io::read_photo(path).map_err(failed)?;
    check_photo_size(path, photo.width, photo.height).map_err(err)?;
    Ok(photo)
}

/// The photo's centred square at 512², linear (the contract's first
/// steps; the network's input is this resized to its side).
pub fn linear_square(photo: &io::Photo) -> Planar {
    let square = square_of(
        photo.height,
        photo.width,
        |c, y, x| photo.at(c, y, x),
        SQUARE,
    );
    let enc = if photo.is_linear() {
        Encoding::Linear
    } else {
        Encoding::Display
    };
    linear(square, enc)
}

/// Runs the contract on one photo: square, network input, inference,
/// maps at 512².
pub fn predict(photo: &io::Photo, m: &Loaded) -> Result<Prediction, NodeError> {
    let lin = linear_square(photo);
    let x = network_input(&lin, m.contract.input);
    let n = m.contract.input;
    let outs = m.graph.run(&[1, 3, n, n], x.data).map_err(failed)?;
    let maps =
        Maps::from_outputs(&outs, &m.contract).map_err(|e| err(format!("{}: {e}", m.what)))?;
    let raw = gray(&maps.depth);
    let z = match m.contract.depth {
        DepthKind::Z => raw,
        DepthKind::Disparity => disparity_to_depth(&raw),
    };
    check_depth_range(Path::new(&m.what), &z).map_err(|e| {
        err(format!(
            "{e} (the model's depth output is unusable for this photo)"
        ))
    })?;
    Ok(Prediction {
        photo: rgb(&lin),
        maps,
        depth_kind: m.contract.depth,
        z,
    })
}

impl Prediction {
    /// The materials as the reference holds them in memory (clamped).
    pub fn materials(&self) -> MaterialMaps {
        MaterialMaps {
            albedo: rgb(&self.maps.albedo).map(|v| v.clamp(Vec3::ZERO, Vec3::ONE)),
            roughness: gray(&self.maps.roughness).map(|v| v.clamp(0.07, 1.0)),
            metallic: gray(&self.maps.metallic).map(|v| v.clamp(0.0, 1.0)),
            normal: Some(rgb(&self.maps.normal)),
            transparency: None,
        }
    }

    /// The network's depth output as it gave it (z or disparity: see
    /// [`Prediction::depth_kind`]), at the maps' size.
    pub fn depth_raw(&self) -> GrayImage {
        gray(&self.maps.depth)
    }
}

impl Node for MatnetNode {
    fn info(&self) -> &'static NodeInfo {
        &INFO
    }
    fn film_size(&self, _p: &Params) -> Option<(usize, usize)> {
        Some((SQUARE, SQUARE))
    }
    /// Checks what can be checked without decoding the photo or loading
    /// the model (both done once, when the stage runs): the photo's size
    /// from its header, the model file, the memory, the onnxruntime library.
    fn preflight(&self, p: &Params) -> Result<(), String> {
        if let Some(photo) = p.path("photo") {
            let (w, h) = io::photo_size(&photo).map_err(|e| e.to_string())?;
            check_photo_size(&photo, w, h)?;
        }
        if p.is_set("model") {
            model_info(p.path("model").as_deref()).map_err(|e| e.0)?;
        }
        if backend_of(p) == Backend::OnnxRuntime {
            matflow_onnx::runtime::find_onnxruntime().map_err(|e| e.to_string())?;
        }
        Ok(())
    }
    fn output_files(&self, p: &Params) -> Vec<PathBuf> {
        crate::files::in_output(p, FILES)
    }
    fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
        let p = ctx.params;
        let photo_path = p.path("photo").unwrap_or_default();
        let photo = read_photo(&photo_path)?;
        let backend = backend_of(p);
        let m = load_model(p.path("model").as_deref(), backend)?;
        let pred = predict(&photo, &m)?;
        let mut out = BTreeMap::new();
        let scene = SceneData {
            depth: pred.z.clone(),
            target: Some(pred.photo.clone()),
            pred: pred.materials(),
        };
        out.insert("scene".to_string(), scene.encode());
        put_file(&mut out, "gt_image.exr", |p| {
            io::encode_exr_rgb(p, &pred.photo)
        })?;
        put_file(&mut out, "gt_image.png", |p| {
            io::encode_png_gamma(p, &pred.photo)
        })?;
        put_file(&mut out, "albedoPred.exr", |p| {
            io::encode_exr_rgb(p, &rgb(&pred.maps.albedo))
        })?;
        put_file(&mut out, "normalPred.exr", |p| {
            io::encode_exr_rgb(p, &rgb(&pred.maps.normal))
        })?;
        put_file(&mut out, "roughnessPred.png", |_| {
            io::png_srgb_bytes(&gray(&pred.maps.roughness).to_rgb())
        })?;
        put_file(&mut out, "metallicPred.png", |_| {
            io::png_srgb_bytes(&gray(&pred.maps.metallic).to_rgb())
        })?;
        match pred.depth_kind {
            DepthKind::Z => put_file(&mut out, "depth.exr", |p| io::encode_exr_gray(p, &pred.z))?,
            DepthKind::Disparity => put_file(&mut out, "depthPred.exr", |p| {
                io::encode_exr_gray(p, &gray(&pred.maps.depth))
            })?,
        }
        let s = photo.width.min(photo.height);
        let record = serde_json::json!({
            "photo": photo_path.file_name().map(|n| n.to_string_lossy().into_owned()),
            "photo_size": [photo.width, photo.height],
            "crop": {"x": (photo.width - s) / 2, "y": (photo.height - s) / 2, "side": s},
            "conversions": photo.conversions(),
            "encoding": if photo.is_linear() { "linear" } else { "display: /255, ^2.2" },
            "model": {
                "file": p.path("model").map(|p| p.display().to_string()),
                "blake3": m.info.blake3,
                "bytes": m.info.bytes,
                "producer": m.info.producer,
                "metadata": m.info.metadata,
            },
            "contract": m.contract.describe(),
            "backend": backend.name(),
        });
        out.insert(
            "prediction.json".into(),
            serde_json::to_vec_pretty(&record).map_err(failed)?,
        );
        out.insert(
            "note".into(),
            format!(
                "{} backend; model blake3 {} ({:.1} MB; {})",
                backend.name(),
                m.info.blake3,
                m.info.bytes as f64 / 1e6,
                m.contract.describe()
            )
            .into_bytes(),
        );
        Ok(out)
    }
    fn materialize(
        &self,
        params: &Params,
        outputs: &BTreeMap<String, Bytes>,
    ) -> Result<Vec<PathBuf>, NodeError> {
        let Some(dir) = params.path("output") else {
            return Ok(vec![]);
        };
        // The other depth file of an earlier prediction would win over (or
        // contradict) this one: what this run does not write is removed.
        crate::files::write_folder(&dir, FILES, |f| outputs.get(f).map(|b| &b[..]))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn repo(rel: &str) -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../..")
            .join(rel)
    }

    #[test]
    fn the_bundled_model_is_the_committed_one() {
        assert_eq!(
            blake3::hash(BUNDLED_MODEL).to_hex().as_str(),
            BUNDLED_MODEL_BLAKE3,
            "a new model needs a new BUNDLED_MODEL_BLAKE3 and a new node version"
        );
        let on_disk = std::fs::read(repo("models/matnet_rooms.onnx")).unwrap();
        assert_eq!(on_disk, BUNDLED_MODEL);
    }

    /// The whole chain in Rust (photo decoding, crop, resizes,
    /// linearisation, tract) gives what PyTorch gave for the same photo
    /// when the model was exported (`train/matnet/train.py` wrote the
    /// outputs at every 4th pixel). Tolerance 1e-3 absolute on maps of
    /// order 1 (depth: a few units): the pre-processing agrees with
    /// PyTorch's to ~1e-6 and the network carries that through.
    #[test]
    fn the_bundled_model_matches_pytorch_on_the_fixture_photo() {
        let photo = read_photo(&repo("tests/data/matnet_photo.png")).unwrap();
        let m = load_model(None, Backend::Tract).unwrap();
        assert_eq!(m.contract.input, 256);
        assert_eq!(m.contract.depth, DepthKind::Z);
        let x = network_input(&linear_square(&photo), 256);
        let outs = m.graph.run(&[1, 3, 256, 256], x.data).unwrap();
        let want = matflow_scene::npy::decode(
            &std::fs::read(repo("models/matnet_rooms.fixture_output.npy")).unwrap(),
        )
        .unwrap();
        assert_eq!(want.shape, vec![9, 64, 64]);
        let mut got = Vec::new();
        for o in &outs {
            let c = o.shape[1];
            for ch in 0..c {
                for y in (0..256).step_by(4) {
                    for x in (0..256).step_by(4) {
                        got.push(o.data[(ch * 256 + y) * 256 + x]);
                    }
                }
            }
        }
        let worst = got
            .iter()
            .zip(&want.values)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        eprintln!("max |rust - torch| = {worst:e}");
        assert!(worst < 1e-3, "max |rust - torch| = {worst}");
    }

    #[test]
    fn a_prediction_is_a_usable_scene() {
        let photo = read_photo(&repo("tests/data/matnet_photo.png")).unwrap();
        let m = load_model(None, Backend::Tract).unwrap();
        let p = predict(&photo, &m).unwrap();
        let mats = p.materials();
        assert_eq!((p.z.width, p.z.height), (SQUARE, SQUARE));
        assert!(p.z.data.iter().all(|&z| z > 0.0 && z.is_finite()));
        assert!(mats
            .roughness
            .data
            .iter()
            .all(|&r| (0.07..=1.0).contains(&r)));
        let n = mats.normal.unwrap();
        assert!(n.data.iter().all(|v| (v.length() - 1.0).abs() < 1e-4));
        // The photo the scene carries is the 512² square, linear.
        assert_eq!(p.photo.width, SQUARE);
    }
}
