//! `material_opt`: albedo, roughness and metallic recovered together with
//! the envmap.

use std::collections::BTreeMap;
use std::sync::OnceLock;

use matflow_engine::node::Params;
use matflow_engine::{Node, NodeError, NodeInfo, OutputSpec, ParamSpec, ParamType, RunContext};
use matflow_inverse::invert::{materials_to_maps, InvertOptions};
use matflow_inverse::routes::Side;

use crate::data::{encode_image, encode_materials, envmap_from, MESH, SCENE};
use crate::recovery::{
    base_options, mat_route, material_options, prepare, run_invert, summary, with_route_params,
};
use crate::recovery::{
    ALBEDO_LEVEL, ALBEDO_LEVEL_BAND, BUDGET, DELTA, ENV_ROUTE, LOOPS, MAT_ROUTE, REPORT, TRUST,
};

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
    DELTA,
    LOOPS,
    ALBEDO_LEVEL,
    ALBEDO_LEVEL_BAND,
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
                  frozen paths. The albedo's mean per channel stays near the prediction's \
                  (albedo_level); the light takes the rest.",
            params: with_route_params(&ALL_PARAMS, PARAMS, &[Side::Env, Side::Mat]),
            outputs: OUTPUTS,
        })
    }
    fn estimate_seconds(&self, p: &Params, _film: Option<(usize, usize)>) -> f64 {
        p.f64("budget_seconds")
    }
    /// A bad route option fails validation, before anything runs.
    fn check(&self, p: &Params) -> Result<(), String> {
        crate::recovery::check_routes(p)
    }
    fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
        let pr = prepare(ctx, None)?;
        let p = ctx.params;
        let init_env = match ctx.opt_input("envmap") {
            Some(b) => Some(envmap_from(b)?),
            None => None,
        };
        let opts = material_options(
            p,
            InvertOptions {
                mat_route: mat_route(p)?,
                init_env,
                ..base_options(p, ctx.seed)?
            },
        );
        let (w, h) = (pr.target.width, pr.target.height);
        let res = run_invert(ctx, pr.scene, &pr.target, &pr.start, &opts)?;
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::artifact::Artifact;
    use crate::data::{encode_mesh, SceneData};
    use crate::testutil::{params_of, small_room};
    use matflow_engine::Value;
    use matflow_render::{render, EnvMap, RenderOptions, RenderScene};
    use std::sync::Arc;

    /// The stage's inputs: the procedural room at 24², photographed at half
    /// its brightness (the fit must trade light for albedo), and its mesh.
    fn inputs() -> [(String, Arc<Vec<u8>>); 2] {
        let n = 24;
        let (s, cam, tri) = small_room(n);
        let env = EnvMap::new(&s.envmap).unwrap();
        let scene = RenderScene::new(cam, tri.clone(), &s.maps, env).unwrap();
        let opts = RenderOptions {
            spp: 4,
            ..Default::default()
        };
        let mut target = render(&scene, &opts, &|_, _| {}).image;
        target.data.iter_mut().for_each(|v| *v *= 0.5);
        let data = SceneData {
            depth: s.depth.clone(),
            target: Some(target),
            pred: s.maps.clone(),
        }
        .encode();
        [
            ("scene".to_string(), Arc::new(data)),
            ("mesh".to_string(), Arc::new(encode_mesh(n, n, &tri))),
        ]
    }

    /// The report of the stage on `inputs` with `albedo_level` set, or at
    /// its default.
    fn report_with(inputs: &[(String, Arc<Vec<u8>>); 2], level: Option<&str>) -> serde_json::Value {
        // A 30 s budget: what the test was sized for at 24².
        let mut given = vec![("budget_seconds", Value::Float(30.0))];
        given.extend(level.map(|l| ("albedo_level", Value::Str(l.into()))));
        let p = params_of(MaterialOptNode.info(), &given);
        let out = MaterialOptNode
            .run(&RunContext {
                stage: "opt",
                params: &p,
                inputs: inputs.iter().cloned().collect(),
                seed: 1,
                progress: &|_, _| {},
                metric: &|_, _| {},
                cancelled: &matflow_engine::node::never_cancelled,
                image: None,
            })
            .unwrap();
        let a = Artifact::decode(&out["report"], "report").unwrap();
        serde_json::from_slice(a.bytes("json").unwrap()).unwrap()
    }

    #[test]
    fn the_albedo_level_is_held_near_the_prediction_unless_freed() {
        // Held by default: the report names the gain the light took.
        let inputs = inputs();
        let held = report_with(&inputs, None);
        let gain = held["invert"]["level_gain"].as_array().expect("a gain");
        assert_eq!(gain.len(), 3);
        assert!(gain.iter().all(|g| g.as_f64().is_some_and(|g| g > 0.0)));
        assert_eq!(report_with(&inputs, Some("pred")), held);
        // The stage's default band is the library's.
        let p = params_of(MaterialOptNode.info(), &[]);
        assert_eq!(
            p.f32("albedo_level_band"),
            matflow_inverse::invert::LEVEL_BAND
        );
        // Free: the fit settles the level alone.
        assert!(report_with(&inputs, Some("free"))["invert"]["level_gain"].is_null());
    }
}
