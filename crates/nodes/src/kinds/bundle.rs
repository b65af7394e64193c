//! `bundle`: a scene from a reference-layout bundle folder (depth, input
//! image, predicted or other materials).

use std::collections::BTreeMap;

use matflow_engine::node::Params;
use matflow_engine::{Node, NodeError, NodeInfo, OutputSpec, ParamSpec, ParamType, RunContext};
use matflow_scene::{io, Bundle, MaterialSource};

use crate::artifact::Artifact;
use crate::data::{encode_image, encode_materials, SceneData};
use crate::err;

pub struct BundleNode;

impl BundleNode {
    fn load(&self, p: &Params) -> Result<(SceneData, Bundle), NodeError> {
        let dir = p.path("path").unwrap_or_default();
        let b = Bundle::open(&dir).map_err(err)?;
        let depth = b.load_depth().map_err(err)?;
        let pred = b
            .load_materials(p.parse::<MaterialSource>("materials")?)
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
    version: 2,
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
    fn film_size(&self, p: &Params) -> Option<(usize, usize)> {
        // The depth map's size, from its header (a bundle that cannot be
        // read fails its preflight with the reason).
        Bundle::open(p.path("path")?).ok()?.depth_size().ok()
    }
    fn preflight(&self, p: &Params) -> Result<(), String> {
        let (_, b) = self.load(p).map_err(|e| e.0)?;
        if let Some(env) = b.envmap_path() {
            io::read_envmap(&env).map_err(|e| e.to_string())?;
        }
        Ok(())
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
            let env = io::read_envmap(&p).map_err(err)?;
            out.insert("envmap".into(), encode_image("envmap", "envmap", &env));
        }
        Ok(out)
    }
}
