//! Inverse rendering stages: the envmap with materials held fixed, and the
//! full alternation of envmap and material stages (`matflow invert`).

use std::collections::BTreeMap;

use matflow_engine::node::Params;
use matflow_engine::{Node, NodeError, NodeInfo, OutputSpec, ParamSpec, ParamType, RunContext};
use matflow_inverse::invert::{invert, materials_to_maps, EnvRoute, InvertOptions, MatRoute};
use matflow_scene::metrics::{psnr_gamma, ssim_gamma};
use matflow_scene::{Image, RgbImage};

use crate::artifact::Artifact;
use crate::err;
use crate::inputs::{
    encode_image, encode_materials, envmap_from, materials_from, render_scene, SceneData, MESH,
    SCENE,
};

const BUDGET: ParamSpec = ParamSpec {
    name: "budget_seconds",
    ty: ParamType::Float {
        min: 1.0,
        max: 86400.0,
    },
    default: Some("30"),
    unit: "s",
    doc: "time budget on the reference 2-core machine; sets sample and step counts through \
          a fixed cost model (results never depend on the clock)",
};
const TRUST: ParamSpec = ParamSpec {
    name: "trust_rm",
    ty: ParamType::Bool,
    default: Some("false"),
    unit: "",
    doc: "trust predicted roughness/metallic (synthetic data); photos start them at 0.7/0.05",
};
const ENV_ROUTE: ParamSpec = ParamSpec {
    name: "env_route",
    ty: ParamType::Choice(&["texel", "mlp"]),
    default: Some("texel"),
    unit: "",
    doc: "free log texels (fast) or the paper's positional-encoding MLP",
};
const SMOOTH: ParamSpec = ParamSpec {
    name: "env_smooth",
    ty: ParamType::Float {
        min: 0.0,
        max: 100.0,
    },
    default: Some("~"),
    unit: "",
    doc: "texel smoothness prior weight (default: 0.01 with trust_rm, else 0)",
};
fn base_options(p: &Params, seed: u64) -> InvertOptions {
    InvertOptions {
        budget_seconds: p.f64("budget_seconds"),
        env_route: if p.str("env_route") == "mlp" {
            EnvRoute::Mlp
        } else {
            EnvRoute::Texel
        },
        trust_rm: p.bool("trust_rm"),
        env_smooth: p.opt_f64("env_smooth").map(|x| x as f32),
        seed,
        ..Default::default()
    }
}

/// A deterministic summary (no timings: the blob must not depend on the
/// clock) with the rerender error against the input.
fn summary(
    report: &matflow_inverse::invert::InvertReport,
    rendered: &RgbImage,
    target: &RgbImage,
) -> Vec<u8> {
    let mut v = serde_json::to_value(report).unwrap_or_default();
    strip_seconds(&mut v);
    let s = serde_json::json!({
        "rerender": {"psnr": psnr_gamma(rendered, target), "ssim": ssim_gamma(rendered, target)},
        "invert": v,
    });
    let mut a = Artifact::new("report");
    a.put_bytes("json", serde_json::to_vec_pretty(&s).unwrap_or_default());
    a.encode()
}

fn strip_seconds(v: &mut serde_json::Value) {
    match v {
        serde_json::Value::Object(m) => {
            m.remove("seconds");
            for x in m.values_mut() {
                strip_seconds(x);
            }
        }
        serde_json::Value::Array(a) => a.iter_mut().for_each(strip_seconds),
        _ => {}
    }
}

struct Prepared {
    scene: matflow_render::RenderScene,
    target: RgbImage,
    start: Vec<matflow_render::Material>,
}

fn prepare(ctx: &RunContext, materials_param: Option<&str>) -> Result<Prepared, NodeError> {
    let s = SceneData::decode(ctx.input("scene")?)?;
    let target = s
        .target
        .ok_or_else(|| err("the scene has no input image to fit (give the bundle an image)"))?;
    let maps = match materials_param.and_then(|m| ctx.opt_input(m)) {
        Some(b) => materials_from(b)?,
        None => s.pred,
    };
    let flat = Image::new(32, 16, glam::Vec3::ONE);
    let scene = render_scene(ctx.input("mesh")?, &maps, &flat)?;
    if !target.same_size(&maps.albedo) {
        return Err(err("the input image and the materials differ in size"));
    }
    let start = matflow_render::scene::materials_from_maps(&maps);
    Ok(Prepared {
        scene,
        target,
        start,
    })
}

fn on_event(ctx: &RunContext, e: matflow_inverse::invert::Event) {
    if let matflow_inverse::invert::Event::Step { step, .. } = e {
        (ctx.progress)(step as u64, 0)
    }
}

pub struct EnvmapOptNode;

const ENVMAP_OPT_INFO: NodeInfo = NodeInfo {
    kind: "envmap_opt",
    version: 1,
    doc: "Recovers the 32×16 HDR environment map with the materials held fixed (the paper's \
         envmap stage; L1 + L2 on γ-encoded images over frozen paths).",
    params: &[
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
        SMOOTH,
    ],
    outputs: &[
        OutputSpec {
            name: "envmap",
            ty: "envmap",
            doc: "the recovered lighting",
        },
        OutputSpec {
            name: "report",
            ty: "report",
            doc: "plan, per-stage steps and losses, rerender PSNR/SSIM",
        },
    ],
};

impl Node for EnvmapOptNode {
    fn info(&self) -> &'static NodeInfo {
        &ENVMAP_OPT_INFO
    }
    fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
        let pr = prepare(ctx, Some("materials"))?;
        let opts = InvertOptions {
            env_only: true,
            ..base_options(ctx.params, ctx.seed)
        };
        let res = invert(pr.scene, &pr.target, &pr.start, &opts, &|e| {
            on_event(ctx, e)
        })
        .map_err(err)?;
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

pub struct MaterialOptNode;

const MATERIAL_OPT_INFO: NodeInfo = NodeInfo {
    kind: "material_opt",
    version: 1,
    doc: "Recovers albedo, roughness and metallic together with the envmap: the reference's \
         alternation of envmap and material stages (paper §3.2), on frozen paths.",
    params: &[
        SCENE,
        MESH,
        ParamSpec {
            name: "envmap",
            ty: ParamType::Ref(&["envmap"]),
            default: Some("~"),
            unit: "",
            doc: "starting envmap (e.g. an envmap_opt stage; texel route only)",
        },
        BUDGET,
        ENV_ROUTE,
        ParamSpec {
            name: "mat_route",
            ty: ParamType::Choice(&["solve", "pixel", "mlp"]),
            default: Some("solve"),
            unit: "",
            doc: "per-pixel exact solves (fast), per-pixel Adam, or the paper's MLP",
        },
        TRUST,
        SMOOTH,
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
    ],
    outputs: &[
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
            doc: "independent re-render of the result",
        },
        OutputSpec {
            name: "report",
            ty: "report",
            doc: "plan, per-stage steps and losses, rerender PSNR/SSIM",
        },
    ],
};

impl Node for MaterialOptNode {
    fn info(&self) -> &'static NodeInfo {
        &MATERIAL_OPT_INFO
    }
    fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
        let pr = prepare(ctx, None)?;
        let p = ctx.params;
        let init_env = match ctx.opt_input("envmap") {
            Some(b) => Some(envmap_from(b)?),
            None => None,
        };
        let opts = InvertOptions {
            mat_route: match p.str("mat_route") {
                "pixel" => MatRoute::Pixel,
                "mlp" => MatRoute::Mlp,
                _ => MatRoute::Solve,
            },
            delta: p.f32("delta"),
            loops: p.opt_i64("loops").map(|l| l as usize),
            init_env,
            ..base_options(p, ctx.seed)
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
