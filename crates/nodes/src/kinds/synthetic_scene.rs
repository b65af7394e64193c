//! `synthetic_scene`: a procedural room with its true materials and
//! lighting, rendered as the input image.

use std::collections::BTreeMap;

use matflow_engine::node::Params;
use matflow_engine::{Node, NodeError, NodeInfo, OutputSpec, ParamSpec, ParamType, RunContext};
use matflow_render::{render, scene_from_depth, EnvMap, RenderOptions};

use crate::data::{encode_image, encode_materials, SceneData};
use crate::failed;

pub struct SyntheticSceneNode;

const SYNTHETIC_SCENE_INFO: NodeInfo = NodeInfo {
    kind: "synthetic_scene",
    version: 6,
    doc: "A procedural room (floor, walls, a few objects with varied albedo, roughness and \
         metallic) under a procedural sky, its input image rendered by matflow's path tracer \
         on its depth mesh alone (so its `mesh` stage takes `complete: none`), and predictions \
         made by degrading the truth (blur, noise, bias, wrong R/M).",
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
    fn estimate_seconds(&self, p: &Params, film: Option<(usize, usize)>) -> f64 {
        crate::data::render_seconds(film, p.i64("spp"), 4)
    }
    fn film_size(&self, p: &Params) -> Option<(usize, usize)> {
        let s = p.i64("size") as usize;
        Some((s, s))
    }
    fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
        let p = ctx.params;
        let seed = p.i64("seed") as u64;
        let size = p.i64("size") as usize;
        let s = matflow_procgen::synthetic::generate(seed, size, size);
        let pred = if p.bool("degrade") {
            matflow_procgen::synthetic::degrade(&s.maps, seed)
        } else {
            s.maps.clone()
        };
        let env = EnvMap::new(&s.envmap).map_err(failed)?;
        let (scene, _, _) = scene_from_depth(
            &s.depth,
            &s.maps,
            env,
            matflow_geom::MeshParams::default(),
            None,
        )
        .map_err(failed)?;
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
