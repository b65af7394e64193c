//! `envmap_opt`: the envmap with the materials held fixed.

use std::collections::BTreeMap;
use std::sync::OnceLock;

use matflow_engine::node::Params;
use matflow_engine::{Node, NodeError, NodeInfo, OutputSpec, ParamSpec, ParamType, RunContext};
use matflow_inverse::invert::InvertOptions;
use matflow_inverse::routes::Side;

use crate::data::{encode_image, MESH, SCENE};
use crate::recovery::{base_options, env_route, prepare, run_invert, summary, with_route_params};
use crate::recovery::{BUDGET, ENV_ROUTE, REPORT, TRUST};

pub struct EnvmapOptNode;

const PARAMS: &[ParamSpec] = &[
    SCENE,
    MESH,
    ParamSpec {
        name: "materials",
        ty: ParamType::Ref(&["materials"]),
        default: Some("~"),
        unit: "",
        doc: "materials to hold fixed (default: the scene's predictions)",
    },
    BUDGET,
    ENV_ROUTE,
    TRUST,
];

const OUTPUTS: &[OutputSpec] = &[
    OutputSpec {
        name: "envmap",
        ty: "envmap",
        doc: "the recovered lighting",
    },
    REPORT,
];

impl Node for EnvmapOptNode {
    fn info(&self) -> &'static NodeInfo {
        static INFO: OnceLock<NodeInfo> = OnceLock::new();
        static ALL_PARAMS: OnceLock<Vec<ParamSpec>> = OnceLock::new();
        INFO.get_or_init(|| NodeInfo {
            kind: "envmap_opt",
            version: 5,
            doc: "Recovers the 32×16 HDR environment map with the materials held fixed (the \
                  paper's envmap stage; L1 + L2 on γ-encoded images over frozen paths).",
            params: with_route_params(&ALL_PARAMS, PARAMS, &[Side::Env]),
            outputs: OUTPUTS,
        })
    }
    fn estimate_seconds(&self, p: &Params, _film: Option<(usize, usize)>) -> f64 {
        p.f64("budget_seconds")
    }
    /// A bad route option fails validation, before anything runs.
    fn check(&self, p: &Params) -> Result<(), String> {
        env_route(p).map_err(|e| e.0)?;
        Ok(())
    }
    fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
        let pr = prepare(ctx, Some("materials"))?;
        let opts = InvertOptions {
            env_only: true,
            ..base_options(ctx.params, ctx.seed)?
        };
        let res = run_invert(ctx, pr.scene, &pr.target, &pr.start, &opts)?;
        Ok([
            (
                "envmap".to_string(),
                encode_image("envmap", "envmap", &res.envmap),
            ),
            (
                "report".to_string(),
                summary(&res.report, &res.rendered, &pr.target),
            ),
        ]
        .into())
    }
}
