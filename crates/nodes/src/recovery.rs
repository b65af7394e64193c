//! What the two recovery kinds (`envmap_opt`, `material_opt`) share: the
//! route parameters built from the inverse route registry, the options
//! common to both, loading the scene and the deterministic report.

use std::sync::OnceLock;

use matflow_engine::node::Params;
use matflow_engine::{NodeError, OutputSpec, ParamSpec, ParamType, RunContext};
use matflow_inverse::invert::{
    invert_until, Event, InvertError, InvertOptions, InvertReport, InvertResult, MAX_LEVEL_BAND,
};
use matflow_inverse::routes::{
    self, all_options, Chosen, EnvRoute, MatRoute, OptionKind, Side, ENV_ROUTE_NAMES,
    MAT_ROUTE_NAMES,
};
use matflow_inverse::structure::StructureParams;
use matflow_scene::metrics::{psnr_gamma, ssim_gamma};
use matflow_scene::{Image, RgbImage};

use crate::artifact::Artifact;
use crate::data::{materials_from, render_scene, SceneData};
use crate::err;

/// The deterministic report both kinds output (see [`summary`]).
pub(crate) const REPORT: OutputSpec = OutputSpec {
    name: "report",
    ty: "report",
    doc: "plan, per-stage steps and losses, rerender PSNR/SSIM",
};
pub(crate) const BUDGET: ParamSpec = ParamSpec {
    name: "budget_seconds",
    ty: ParamType::Float {
        min: 1.0,
        max: 86400.0,
    },
    default: Some("60"),
    unit: "s",
    doc: "time budget on the reference 2-core machine; sets sample and step counts through \
          a fixed cost model (results never depend on the clock)",
};
pub(crate) const TRUST: ParamSpec = ParamSpec {
    name: "trust_rm",
    ty: ParamType::Bool,
    default: Some("false"),
    unit: "",
    doc: "trust predicted roughness/metallic (synthetic data); photos start them at 0.7/0.05",
};
pub(crate) const ENV_ROUTE: ParamSpec = ParamSpec {
    name: "env_route",
    ty: ParamType::Choice(&ENV_ROUTE_NAMES),
    default: Some(ENV_ROUTE_NAMES[0]),
    unit: "",
    doc: "how envmap stages fit (each route's options: env_ROUTE_OPTION)",
};
pub(crate) const MAT_ROUTE: ParamSpec = ParamSpec {
    name: "mat_route",
    ty: ParamType::Choice(&MAT_ROUTE_NAMES),
    default: Some(MAT_ROUTE_NAMES[0]),
    unit: "",
    doc: "how material stages fit (each route's options: mat_ROUTE_OPTION)",
};

pub(crate) const DELTA: ParamSpec = ParamSpec {
    name: "delta",
    ty: ParamType::Float {
        min: 0.0,
        max: 100.0,
    },
    default: Some("0.1"),
    unit: "",
    doc: "consistency weight δ (pull towards the predictions)",
};
pub(crate) const LOOPS: ParamSpec = ParamSpec {
    name: "loops",
    ty: ParamType::Int { min: 1, max: 64 },
    default: Some("~"),
    unit: "",
    doc: "envmap/material alternations (default: from the budget)",
};
pub(crate) const ALBEDO_LEVEL: ParamSpec = ParamSpec {
    name: "albedo_level",
    ty: ParamType::Choice(&["pred", "free"]),
    default: Some("pred"),
    unit: "",
    doc: "who sets the albedo's mean level and colour: the prediction (within \
          albedo_level_band; the light takes the gain, since one image cannot tell a \
          brighter light from a brighter albedo) or the fit",
};
pub(crate) const ALBEDO_LEVEL_BAND: ParamSpec = ParamSpec {
    name: "albedo_level_band",
    ty: ParamType::Float {
        min: 0.0,
        max: MAX_LEVEL_BAND,
    },
    default: Some("0.25"),
    unit: "share",
    doc: "with albedo_level pred: how far the albedo's mean per channel may move from the \
          prediction's before it is held (0: held exactly)",
};

pub(crate) const ALBEDO_STRUCTURE: ParamSpec = ParamSpec {
    name: "albedo_structure",
    ty: ParamType::Choice(&["photo", "free"]),
    default: Some("free"),
    unit: "",
    doc: "where the recovered albedo's structure comes from: free (the per-pixel solve's \
          albedo as it is, the paper's method) or photo (the prediction's coarse structure, \
          the photo's fine detail, and the solve's level and colour per surface; roughness \
          and metallic per surface too). photo keeps shading the geometry gets wrong out of \
          the albedo, and so shows it in the re-render (docs/results/prediction.md)",
};

fn leak(s: String) -> &'static str {
    Box::leak(s.into_boxed_str())
}

/// One optional parameter per route option of `side`
/// (`env_mlp_width`, …), from the registry.
fn route_option_params(side: Side) -> Vec<ParamSpec> {
    let doc_of = |side: Side, route: &str| -> &'static str {
        match side {
            Side::Env => routes::ENV_ROUTES
                .iter()
                .find(|e| e.name == route)
                .map(|e| e.doc),
            Side::Mat => routes::MAT_ROUTES
                .iter()
                .find(|e| e.name == route)
                .map(|e| e.doc),
        }
        .unwrap_or("")
    };
    all_options(side)
        .into_iter()
        .map(|(q, route, o)| ParamSpec {
            name: leak(q),
            ty: match o.kind {
                OptionKind::Int { min, max } => ParamType::Int { min, max },
                OptionKind::Float { min, max } => ParamType::Float { min, max },
            },
            default: Some("~"),
            unit: "",
            doc: leak(format!(
                "{} route `{route}` ({}): {}{}",
                side.prefix(),
                doc_of(side, route),
                o.doc,
                o.default
                    .map(|d| format!("; default {d}"))
                    .unwrap_or_default()
            )),
        })
        .collect()
}

/// A node kind's parameter list: its own, then the route options of the
/// given sides. Built once per kind.
pub(crate) fn with_route_params(
    cell: &'static OnceLock<Vec<ParamSpec>>,
    own: &[ParamSpec],
    sides: &[Side],
) -> &'static [ParamSpec] {
    cell.get_or_init(|| {
        let mut v = own.to_vec();
        for &s in sides {
            v.extend(route_option_params(s));
        }
        v
    })
}

/// The chosen envmap route and its options (`env_ROUTE_OPTION`).
pub(crate) fn env_route(p: &Params) -> Result<Chosen<dyn EnvRoute>, NodeError> {
    routes::env_route_given(p.str("env_route"), &|q| p.opt_f64(q)).map_err(err)
}

/// The chosen material route and its options (`mat_ROUTE_OPTION`).
pub(crate) fn mat_route(p: &Params) -> Result<Chosen<dyn MatRoute>, NodeError> {
    routes::mat_route_given(p.str("mat_route"), &|q| p.opt_f64(q)).map_err(err)
}

/// A stage's route options checked against its routes (an option of a
/// route not chosen, a value out of the route's range): before anything
/// runs.
pub(crate) fn check_routes(p: &Params) -> Result<(), String> {
    env_route(p).map_err(|e| e.0)?;
    mat_route(p).map_err(|e| e.0)?;
    Ok(())
}

/// The options both kinds set.
pub(crate) fn base_options(p: &Params, seed: u64) -> Result<InvertOptions, NodeError> {
    Ok(InvertOptions {
        env_route: env_route(p)?,
        seed,
        ..budget_options(p, InvertOptions::default())
    })
}

/// What `budget_seconds` and `trust_rm` set, over `o`. `matflow invert`
/// reads its flags of the same names (built from these specs) through
/// this too.
pub fn budget_options(p: &Params, o: InvertOptions) -> InvertOptions {
    InvertOptions {
        budget_seconds: p.f64("budget_seconds"),
        trust_rm: p.bool("trust_rm"),
        ..o
    }
}

/// What `material_opt`'s own numeric and choice parameters set (`delta`,
/// `loops`, `albedo_level`, `albedo_level_band`, `albedo_structure`),
/// over `o`; shared with `matflow invert` as [`budget_options`] is.
pub fn material_options(p: &Params, o: InvertOptions) -> InvertOptions {
    InvertOptions {
        delta: p.f32("delta"),
        loops: p.opt_i64("loops").map(|l| l as usize),
        level_from_pred: p.str("albedo_level") == "pred",
        level_band: p.f32("albedo_level_band"),
        albedo_structure: (p.str("albedo_structure") == "photo").then(StructureParams::default),
        ..o
    }
}

/// A deterministic summary (the report holds no timings: the blob must
/// not depend on the clock) with the rerender error against the input.
pub(crate) fn summary(report: &InvertReport, rendered: &RgbImage, target: &RgbImage) -> Vec<u8> {
    let s = serde_json::json!({
        "rerender": {"psnr": psnr_gamma(rendered, target), "ssim": ssim_gamma(rendered, target)},
        "invert": report,
    });
    let mut a = Artifact::new("report");
    a.put_bytes("json", serde_json::to_vec_pretty(&s).unwrap_or_default());
    a.encode()
}

pub(crate) struct Prepared {
    pub scene: matflow_render::RenderScene,
    pub target: RgbImage,
    pub start: Vec<matflow_render::Material>,
}

/// The scene to recover: geometry from the mesh stage, the input image and
/// starting materials from the scene (or the `materials_param` stage).
pub(crate) fn prepare(
    ctx: &RunContext,
    materials_param: Option<&str>,
) -> Result<Prepared, NodeError> {
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

/// Progress: the optimisation steps of the current stage, each step's
/// loss as the metric `loss`, and, where someone watches, the current
/// re-render after each fitting stage as the image `current`.
pub(crate) fn on_event(ctx: &RunContext, e: Event) {
    match e {
        Event::Step { step, loss } => {
            (ctx.progress)(step as u64, 0);
            if loss.is_finite() {
                (ctx.metric)("loss", loss);
            }
        }
        Event::Current {
            width,
            height,
            image,
            ..
        } => {
            if let Some(show) = ctx.image {
                let rgb: Vec<f32> = image()
                    .iter()
                    .flat_map(|v| v.to_array())
                    .map(|x| if x.is_finite() { x.max(0.0) } else { 0.0 })
                    .collect();
                show("current", width, height, &rgb);
            }
        }
        _ => {}
    }
}

/// Logs each stage's wall time (`MATFLOW_LOG=info`): where a recovery's
/// time goes, for tuning the budget plan's cost model. The clock is read
/// for the log only; nothing computed depends on it.
fn stage_clock(clock: &std::sync::Mutex<Option<(String, std::time::Instant)>>, e: &Event) {
    let mut c = clock.lock().unwrap_or_else(|p| p.into_inner());
    match e {
        Event::Stage { name, steps } => {
            tracing::debug!(target: "matflow::stages", "{name}: {steps} steps");
            *c = Some((name.to_string(), std::time::Instant::now()));
        }
        Event::Step { step, .. } => {
            if let Some((name, t0)) = c.as_ref() {
                tracing::trace!(
                    target: "matflow::stages",
                    "{name}: step {step} at {:.3} s",
                    t0.elapsed().as_secs_f64()
                );
            }
        }
        Event::StageDone => {
            if let Some((name, t0)) = c.take() {
                tracing::info!(
                    target: "matflow::stages",
                    "{name}: {:.3} s",
                    t0.elapsed().as_secs_f64()
                );
            }
        }
        _ => {}
    }
}

/// The recovery for a stage: [`invert_until`] with the stage's progress
/// ([`on_event`]), stopped when its run no longer wants it.
pub(crate) fn run_invert(
    ctx: &RunContext,
    scene: matflow_render::RenderScene,
    target: &RgbImage,
    start: &[matflow_render::Material],
    opts: &InvertOptions,
) -> Result<InvertResult, NodeError> {
    let clock = std::sync::Mutex::new(None);
    invert_until(
        scene,
        target,
        start,
        opts,
        &|e| {
            stage_clock(&clock, &e);
            on_event(ctx, e)
        },
        ctx.cancelled,
    )
    .map_err(|e| match e {
        InvertError::Stopped => NodeError::cancelled(),
        e => err(e),
    })
}
