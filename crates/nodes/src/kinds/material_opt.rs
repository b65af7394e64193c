//! `material_opt`: albedo, roughness and metallic recovered together with
//! the envmap.

use std::collections::BTreeMap;
use std::sync::OnceLock;

use matflow_engine::node::Params;
use matflow_engine::{Node, NodeError, NodeInfo, OutputSpec, ParamSpec, ParamType, RunContext};
use matflow_inverse::invert::{invert, materials_to_maps, InvertOptions};
use matflow_inverse::routes::Side;

use crate::data::{encode_image, encode_materials, envmap_from, MESH, SCENE};
use crate::err;
use crate::recovery::{
    base_options, env_route, mat_route, on_event, prepare, summary, with_route_params,
};
use crate::recovery::{BUDGET, ENV_ROUTE, MAT_ROUTE, REPORT, TRUST};

pub struct MaterialOptNode;

const PARAMS: &[ParamSpec] = &[
    SCENE,
    MESH,
    ParamSpec {
        name: "envmap",
        ty: ParamType::Ref(&["envmap"]),
        default: Some("~"),
        unit: "",
        doc: "starting envmap (e.g. an envmap_opt stage; for routes that take one)",
    },
    BUDGET,
    ENV_ROUTE,
    MAT_ROUTE,
    TRUST,
    ParamSpec {
        name: "delta",
        ty: ParamType::Float {
            min: 0.0,
            max: 100.0,
        },
        default: Some("0.1"),
        unit: "",
        doc: "consistency weight δ (pull towards the predictions)",
    },
    ParamSpec {
        name: "loops",
        ty: ParamType::Int { min: 1, max: 64 },
        default: Some("~"),
        unit: "",
        doc: "envmap/material alternations (default: from the budget)",
    },
];

const OUTPUTS: &[OutputSpec] = &[
    OutputSpec {
        name: "materials",
        ty: "materials",
        doc: "recovered albedo, roughness, metallic",
    },
    OutputSpec {
        name: "envmap",
        ty: "envmap",
        doc: "recovered lighting",
    },
    OutputSpec {
        name: "rendered",
        ty: "image",
        doc: "independent re-render of the result (denoised)",
    },
    REPORT,
];

impl Node for MaterialOptNode {
    fn info(&self) -> &'static NodeInfo {
        static INFO: OnceLock<NodeInfo> = OnceLock::new();
        static ALL_PARAMS: OnceLock<Vec<ParamSpec>> = OnceLock::new();
        INFO.get_or_init(|| NodeInfo {
            kind: "material_opt",
            version: 6,
            doc: "Recovers albedo, roughness and metallic together with the envmap: the \
                  reference's alternation of envmap and material stages (paper §3.2), on \
                  frozen paths. The albedo's mean per channel stays within 25 % of the \
                  prediction's (one image cannot tell a brighter light from a brighter \
                  albedo); the light takes the rest.",
            params: with_route_params(&ALL_PARAMS, PARAMS, &[Side::Env, Side::Mat]),
            outputs: OUTPUTS,
        })
    }
    fn estimate_seconds(&self, p: &Params, _film: Option<(usize, usize)>) -> f64 {
        p.f64("budget_seconds")
    }
    /// A bad route option fails validation, before anything runs.
    fn check(&self, p: &Params) -> Result<(), String> {
        env_route(p).map_err(|e| e.0)?;
        mat_route(p).map_err(|e| e.0)?;
        Ok(())
    }
    fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
        let pr = prepare(ctx, None)?;
        let p = ctx.params;
        let init_env = match ctx.opt_input("envmap") {
            Some(b) => Some(envmap_from(b)?),
            None => None,
        };
        let opts = InvertOptions {
            mat_route: mat_route(p)?,
            delta: p.f32("delta"),
            loops: p.opt_i64("loops").map(|l| l as usize),
            init_env,
            ..base_options(p, ctx.seed)?
        };
        let (w, h) = (pr.target.width, pr.target.height);
        let res = invert(pr.scene, &pr.target, &pr.start, &opts, &|e| {
            on_event(ctx, e)
        })
        .map_err(err)?;
        let maps = materials_to_maps(w, h, &res.materials);
        Ok([
            ("materials".to_string(), encode_materials(&maps)),
            (
                "envmap".to_string(),
                encode_image("envmap", "envmap", &res.envmap),
            ),
            (
                "rendered".to_string(),
                encode_image("image", "image", &res.rendered),
            ),
            (
                "report".to_string(),
                summary(&res.report, &res.rendered, &pr.target),
            ),
        ]
        .into())
    }
}
