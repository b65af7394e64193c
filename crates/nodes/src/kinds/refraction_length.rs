//! `refraction_length`: the refraction-length network (the paper's
//! supplement §10) run on a photograph's object through ONNX — the model
//! matflow trained on its own refraction dataset (`models/`, built into
//! the binary) or a given one. Its output, d1 and d2 per pixel of the
//! object in scene units, is what `transparency` takes as `refraction`.

use std::collections::BTreeMap;
#[cfg(test)]
use std::path::Path;

use matflow_engine::node::Params;
use matflow_engine::{Node, NodeError, NodeInfo, OutputSpec, ParamSpec, ParamType, RunContext};
use matflow_onnx::refraction::{expand, normals_from_depth, prepare, CROP, IN_CH, OUT_CH};
use matflow_onnx::Model;
use matflow_scene::{Camera, Image};

use crate::data::{backend_of, encode_image, SceneData, BACKEND};
use crate::err;
use crate::kinds::edit::{
    check_mask_choice, check_mask_film, preflight_mask, EditNode, FLOOD_TOLERANCE, MASKS,
    MASK_FLOOD, MASK_PNG, MASK_RECT,
};

/// The network matflow ships: trained by `train/refraction/train.py` on
/// the refraction dataset (see `models/refraction_length.md`).
pub const BUNDLED_MODEL: &[u8] = include_bytes!("../../../../models/refraction_length.onnx");
/// Its BLAKE3, checked by a test: a new model must come with a new node
/// version (the version is in every key).
pub const BUNDLED_MODEL_BLAKE3: &str =
    "3fc3605b2eb79b8756cdd3bef1a12b8eb91199bd88015a42daab6475edcc9bd0";

pub struct RefractionLengthNode;

const INFO: NodeInfo = NodeInfo {
    kind: "refraction_length",
    version: 1,
    doc: "The refraction-length network on an object of the photograph (exactly one of \
         mask_png, mask_rect, mask_flood): from the image, depth and normals of a crop around \
         it, d1 and d2 per pixel (scene units) for `transparency`'s `refraction`, and eq. 24's \
         length. ONNX through ort: tract (pure Rust) or onnxruntime (the Python wheel's library).",
    params: &[
        ParamSpec {
            name: "scene",
            ty: ParamType::Ref(&["scene"]),
            default: None,
            unit: "",
            doc: "the photograph, its depth and predicted normals",
        },
        MASK_PNG,
        MASK_RECT,
        MASK_FLOOD,
        FLOOD_TOLERANCE,
        ParamSpec {
            name: "model",
            ty: ParamType::InPath,
            default: Some("~"),
            unit: "",
            doc: "an ONNX model with the same input and output (default: the bundled one)",
        },
        BACKEND,
    ],
    outputs: &[OutputSpec {
        name: "distances",
        ty: "image",
        doc: "d1 in R, d2 in G, the eq. 24 length in B (scene units; 0 outside the mask)",
    }],
};

/// Loads the model of a stage: the given file or the bundled one.
fn model(p: &Params) -> Result<Model, String> {
    let backend = backend_of(p);
    let (bytes, what) = match p.path("model") {
        Some(path) => (
            std::fs::read(&path).map_err(|e| format!("{}: {e}", path.display()))?,
            path.display().to_string(),
        ),
        None => (
            BUNDLED_MODEL.to_vec(),
            "the bundled refraction-length model".into(),
        ),
    };
    Model::load(
        &bytes,
        &what,
        backend,
        [IN_CH, CROP, CROP],
        [OUT_CH, CROP, CROP],
    )
    .map_err(|e| e.to_string())
}

impl Node for RefractionLengthNode {
    fn info(&self) -> &'static NodeInfo {
        &INFO
    }
    fn check(&self, p: &Params) -> Result<(), String> {
        check_mask_choice(p, &MASKS[..3])
    }
    fn check_film(&self, p: &Params, size: (usize, usize)) -> Result<(), String> {
        check_mask_film(p, size)
    }
    fn preflight(&self, p: &Params) -> Result<(), String> {
        preflight_mask(p)?;
        if p.is_set("model") || p.str("backend") != "tract" {
            model(p)?;
        }
        Ok(())
    }
    fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
        let p = ctx.params;
        let scene = SceneData::decode(ctx.input("scene")?)?;
        let (w, h) = (scene.depth.width, scene.depth.height);
        let mask = EditNode::mask(p, &scene.pred, None)?;
        let image = scene
            .target
            .as_ref()
            .ok_or_else(|| err("the scene has no input image to look at"))?;
        let camera = Camera::new(w, h);
        // The normals of the surface the depth map describes (the scene
        // artifact carries depth, not the predicted normal map).
        let normals = match &scene.pred.normal {
            Some(n) => n.clone(),
            None => normals_from_depth(&scene.depth, &mask, &camera),
        };
        let focal = camera.focal();
        let prep = prepare(image, &mask, &scene.depth, &normals, focal)
            .map_err(|e| err(format!("the masked object: {e}")))?;
        let m = model(p).map_err(err)?;
        let out = m
            .run(1, prep.input.clone())
            .map_err(|e| err(e.to_string()))?;
        let [length, d1, d2] = expand(&out, &prep, &mask);
        let img = Image::from_fn(w, h, |x, y| {
            glam::Vec3::new(d1.get(x, y), d2.get(x, y), length.get(x, y))
        });
        Ok([(
            "distances".to_string(),
            encode_image("image", "image", &img),
        )]
        .into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinds::refraction::{
        RefractionLabelsNode, RefractionRenderNode, LABELS_INFO, RENDER_INFO,
    };
    use crate::testutil::params_of;
    use glam::Vec3;
    use matflow_engine::Value;
    use matflow_scene::npy;
    use matflow_scene::{GrayImage, MaterialMaps};

    fn run(
        node: &dyn Node,
        p: &Params,
        inputs: BTreeMap<String, matflow_engine::node::Bytes>,
    ) -> BTreeMap<String, Vec<u8>> {
        node.run(&RunContext {
            stage: "s",
            params: p,
            inputs,
            seed: 3,
            progress: &|_, _| {},
            metric: &|_, _| {},
            cancelled: &matflow_engine::node::never_cancelled,
            image: None,
        })
        .unwrap()
    }

    #[test]
    fn the_bundled_model_is_the_one_the_version_names() {
        assert_eq!(
            blake3::hash(BUNDLED_MODEL).to_hex().as_str(),
            BUNDLED_MODEL_BLAKE3
        );
    }

    /// On views, materials and lighting the training data did not draw,
    /// the network's d1 is far closer to the truth than the constant
    /// baseline (the training data's mean, in units of the object's
    /// extent) and than the round-object thickness rule.
    #[test]
    fn the_network_beats_the_baselines_on_unseen_views() {
        let card: serde_json::Value = serde_json::from_slice(
            &std::fs::read(
                Path::new(env!("CARGO_MANIFEST_DIR"))
                    .join("../../models/refraction_length.train.json"),
            )
            .unwrap(),
        )
        .unwrap();
        let constant_d1 = card["constant"]["d1"].as_f64().unwrap() as f32;
        let dir = tempfile::tempdir().unwrap();
        let n = 128;
        let (mut net, mut cst, mut rule) = (0.0f64, 0.0f64, 0.0f64);
        for (k, (object, az, el)) in [
            ("cup", 33.0, 25.0),
            ("lemon", 200.0, 8.0),
            ("torus", 95.0, 40.0),
        ]
        .into_iter()
        .enumerate()
        {
            let common = [
                ("object", Value::Str(object.into())),
                ("size", Value::Int(n as i64)),
                ("azimuth", Value::Float(az)),
                ("elevation", Value::Float(el)),
                ("distance", Value::Float(2.3)),
            ];
            let l = run(
                &RefractionLabelsNode,
                &params_of(&LABELS_INFO, &common),
                BTreeMap::new(),
            );
            let mut rp = common.to_vec();
            rp.push(("envmap_kind", Value::Str("room".into())));
            rp.push(("envmap_seed", Value::Int(987_654 + k as i64)));
            rp.push(("spp", Value::Int(16)));
            rp.push(("albedo", Value::Float(0.35)));
            let r = run(
                &RefractionRenderNode,
                &params_of(&RENDER_INFO, &rp),
                BTreeMap::new(),
            );
            let gray = |m: &str| {
                let a = npy::decode(&l[m]).unwrap();
                GrayImage::from_vec(n, n, a.values)
            };
            let normal = npy::decode(&l["normal.npy"]).unwrap();
            let normals = Image::from_fn(n, n, |x, y| {
                let i = 3 * (y * n + x);
                Vec3::new(normal.values[i], normal.values[i + 1], normal.values[i + 2])
            });
            let png = image::load_from_memory(&r["image.png"]).unwrap().to_rgb8();
            let photo = Image::from_fn(n, n, |x, y| {
                let p = png.get_pixel(x as u32, y as u32).0;
                Vec3::from_array(p.map(|c| matflow_scene::color::srgb_to_linear(c as f32 / 255.0)))
            });
            let mask_path = dir.path().join(format!("mask{k}.png"));
            std::fs::write(&mask_path, &l["mask.png"]).unwrap();
            let mask = matflow_scene::io::read_mask(&mask_path).unwrap();
            let depth = gray("depth.npy");
            let truth = gray("d1.npy");
            let scene = SceneData {
                depth: depth.clone(),
                target: Some(photo.clone()),
                pred: MaterialMaps {
                    albedo: Image::new(n, n, Vec3::splat(0.5)),
                    roughness: Image::new(n, n, 0.5),
                    metallic: Image::new(n, n, 0.0),
                    normal: Some(normals.clone()),
                    transparency: None,
                },
            };
            let p = params_of(
                &INFO,
                &[("mask_png", Value::Str(mask_path.to_string_lossy().into()))],
            );
            let out = run(
                &RefractionLengthNode,
                &p,
                [("scene".to_string(), std::sync::Arc::new(scene.encode()))].into(),
            );
            let d = crate::artifact::Artifact::decode(&out["distances"], "image")
                .unwrap()
                .rgb("image")
                .unwrap();
            let focal = Camera::new(n, n).focal();
            let s = prepare(&photo, &mask, &depth, &normals, focal)
                .unwrap()
                .scale;
            let thick = matflow_scene::transparency::thickness_rule(&mask, &depth, focal, 1.0);
            let (mut a, mut b, mut c, mut cnt) = (0.0f64, 0.0f64, 0.0f64, 0usize);
            for q in 0..n * n {
                if mask.data[q] {
                    let t = truth.data[q] as f64;
                    a += (d.data[q].x as f64 - t).abs();
                    b += (constant_d1 as f64 * s as f64 - t).abs();
                    c += (thick.data[q] as f64 - t).abs();
                    cnt += 1;
                }
                assert!(d.data[q].is_finite() && d.data[q].min_element() >= 0.0);
                if !mask.data[q] {
                    assert_eq!(d.data[q], Vec3::ZERO);
                }
            }
            let m = cnt.max(1) as f64;
            eprintln!(
                "{object}: d1 MAE network {:.4}, constant {:.4}, thickness rule {:.4}",
                a / m,
                b / m,
                c / m
            );
            net += a / m;
            cst += b / m;
            rule += c / m;
        }
        assert!(net < 0.6 * cst, "network {net} vs constant {cst}");
        assert!(net < rule, "network {net} vs thickness rule {rule}");
    }
}
