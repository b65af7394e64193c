//! The whole recovery: envmap and materials from one image, alternating
//! stages on frozen light paths, then an independent re-render.
//!
//! Schedule (following the reference's alternation, `opt_order = rm, a`):
//!
//! 1. scout: a few paths per pixel, envmap fitted from a constant start
//!    (gives the main trace a sensible envmap to importance-sample);
//! 2. main trace with the scout envmap and the starting materials;
//! 3. `loops` × [envmap stage, roughness+metallic stage, albedo stage],
//!    each material stage on freshly built per-pixel tables (the light
//!    reaching primary vertices from deeper bounces is refreshed there);
//! 4. a last envmap stage for the final materials;
//! 5. an independent render (new random numbers) of the recovered scene.
//!
//! Everything is a pure function of the inputs and options: the time
//! budget picks step counts and sample counts through a fixed cost model
//! ([`Plan::from_budget`]), never through the clock.

use std::time::Instant;

use glam::Vec3;
use matflow_render::{EnvMap, Material, PixelFilter, RenderOptions, RenderScene};
use matflow_scene::{Image, MaterialMaps, RgbImage};

use crate::cache::{CacheOptions, PathCache};
use crate::denoise::{denoise_tables, Guide};
use crate::envfit::{
    exposure_scale, fit_texels, strided_pixels, EnvFitOptions, EnvMlp, EnvMlpOptions, EnvTransport,
    FitTrace,
};
use crate::loss::{loss_and_grad, Target};
use crate::matfit::{fit_pixels, MatFitOptions, MatMlp, MatMlpOptions, Parts};
use crate::solve::{solve_pixels, SolveOptions};
use crate::tables::build_tables_with_variance;
use crate::transport;

#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub enum EnvRoute {
    /// Free texels in log space, Adam on the frozen linear transport.
    Texel,
    /// The paper's positional-encoding MLP with a Softplus head
    /// ([`EnvMlp`]), Adam on the same transport.
    Mlp,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub enum MatRoute {
    /// Free ζ·tanh(z) offsets per pixel, Adam on the per-pixel tables.
    Pixel,
    /// Per-pixel exact minimisation on the tables ([`crate::solve`]).
    Solve,
    /// The paper's positional-encoding MLP ([`MatMlp`]), AdamW on
    /// stratified minibatches of the tables.
    Mlp,
}

#[derive(Clone, Debug)]
pub struct InvertOptions {
    pub budget_seconds: f64,
    pub env_route: EnvRoute,
    pub mat_route: MatRoute,
    /// Use the predicted roughness and metallic (synthetic data). When
    /// false (real photos, the reference's `opt_src = a`), they start at,
    /// and are held near, 0.7 and 0.05.
    pub trust_rm: bool,
    pub max_depth: u32,
    pub delta: f32,
    pub zeta: f32,
    pub seed: u64,
    pub env_width: usize,
    pub env_height: usize,
    /// Overrides of the budget plan.
    pub spp: Option<u32>,
    pub final_spp: Option<u32>,
    pub loops: Option<usize>,
    pub env_steps: Option<usize>,
    pub mat_steps: Option<usize>,
    pub early_stop: bool,
    /// Normalise the render's mean in material stages (see
    /// [`MatFitOptions::rescale`]).
    pub rescale: bool,
    /// À-trous passes over the per-pixel tables before each material
    /// stage (0: fit the raw Monte Carlo tables).
    pub denoise: usize,
    /// Network of the MLP envmap route.
    pub env_mlp: EnvMlpOptions,
    /// Network of the MLP material route.
    pub mat_mlp: MatMlpOptions,
    /// Recover only the envmap, materials held at the given ones (which
    /// are trusted as they are: the paper's Table 3 setting with ground
    /// truth or MatNet materials).
    pub env_only: bool,
}

impl Default for InvertOptions {
    fn default() -> Self {
        InvertOptions {
            budget_seconds: 60.0,
            env_route: EnvRoute::Texel,
            mat_route: MatRoute::Solve,
            trust_rm: false,
            max_depth: 4,
            delta: 0.1,
            zeta: 1.3,
            seed: 0,
            env_width: 32,
            env_height: 16,
            spp: None,
            final_spp: None,
            loops: None,
            env_steps: None,
            mat_steps: None,
            early_stop: true,
            rescale: true,
            denoise: 3,
            env_mlp: EnvMlpOptions::default(),
            mat_mlp: MatMlpOptions::default(),
            env_only: false,
        }
    }
}

/// Sample and step counts derived from the budget.
#[derive(Clone, Copy, Debug, serde::Serialize)]
pub struct Plan {
    pub scout_spp: u32,
    pub spp: u32,
    pub final_spp: u32,
    pub loops: usize,
    pub env_steps: usize,
    pub mat_steps: usize,
    /// Rounds of the per-pixel solve per material stage.
    pub solve_rounds: usize,
    pub env_stride: usize,
}

/// Cost model of the reference 2-core machine, used only to turn a budget
/// into counts, so results never depend on the clock. Seconds per pixel
/// (per sample, pass or round where stated), measured on indoor 512².
pub mod cost {
    /// Tracing and recording one 4-segment path.
    pub const TRACE_PER_SAMPLE: f64 = 1.1e-6;
    /// Rendering one sample in the final re-render.
    pub const RENDER_PER_SAMPLE: f64 = 0.9e-6;
    /// Building a pixel's table, per cached path.
    pub const TABLE_PER_SAMPLE: f64 = 2.0e-7;
    /// One à-trous pass over a pixel's table.
    pub const DENOISE_PER_PASS: f64 = 1.4e-6;
    /// One round of the per-pixel solve.
    pub const SOLVE_PER_ROUND: f64 = 6.5e-6;
    /// Loading, meshing, BVH, guide, scout trace and the envmap stages.
    pub const FIXED: f64 = 1.6e-5;
}

impl Plan {
    pub fn from_budget(budget: f64, npix: usize, opts: &InvertOptions) -> Plan {
        use cost::*;
        let n = npix as f64;
        let b = budget.max(1.0);
        let loops = if b < 30.0 { 1 } else { 2 };
        let rounds = if b >= 30.0 {
            3
        } else if b >= 12.0 {
            2
        } else {
            1
        };
        let passes = opts.denoise as f64;
        // What is left after the fixed work and the material stages'
        // per-pixel work; below the minimum plan (≈ 8 s at 512²) the
        // counts bottom out and the run takes longer than the budget.
        let fixed = FIXED * n
            + loops as f64 * (passes * DENOISE_PER_PASS + rounds as f64 * SOLVE_PER_ROUND) * n;
        // Plan for 85 % of the budget: the model is a median, not a bound.
        let rest = (0.85 * b - fixed).max(0.0);
        let per_spp = (TRACE_PER_SAMPLE + loops as f64 * TABLE_PER_SAMPLE) * n;
        // ~45 % of the rest tracing the cache (memory caps it at 32 paths
        // per pixel), the remainder rendering the result.
        let spp = ((0.45 * rest / per_spp) as u32).clamp(2, 32);
        let final_spp =
            (((rest - spp as f64 * per_spp) / (RENDER_PER_SAMPLE * n)) as u32).clamp(2, 256);
        let scout_spp = (spp / 8).clamp(1, 4);
        let steps = ((b * 10.0) as usize).clamp(60, 400);
        // Envmap stages see about 64k pixels.
        let env_stride = ((n / 65536.0).sqrt().ceil() as usize).max(1);
        Plan {
            scout_spp: opts.spp.map(|s| (s / 8).clamp(1, 4)).unwrap_or(scout_spp),
            spp: opts.spp.unwrap_or(spp),
            final_spp: opts.final_spp.unwrap_or(final_spp),
            loops: opts.loops.unwrap_or(loops),
            env_steps: opts.env_steps.unwrap_or(steps),
            mat_steps: opts.mat_steps.unwrap_or(steps),
            solve_rounds: rounds,
            env_stride,
        }
    }
}

/// What one stage did, for `summary.json`.
#[derive(Clone, Debug, serde::Serialize)]
pub struct StageReport {
    pub name: String,
    pub steps: usize,
    pub seconds: f64,
    pub loss_start: f64,
    pub loss_end: f64,
    pub stopped_early: bool,
}

#[derive(Clone, Debug, serde::Serialize)]
pub struct InvertReport {
    pub plan: Plan,
    pub stages: Vec<StageReport>,
    pub cache_bytes: u64,
    pub cache_rays: u64,
    /// Loss of the frozen estimator's image for the final parameters.
    pub fit_loss: f64,
    pub seconds: f64,
}

pub struct InvertResult {
    pub materials: Vec<Material>,
    pub envmap: RgbImage,
    /// The frozen estimator's image for the final parameters.
    pub fit_image: RgbImage,
    /// Independent re-render (new random numbers, box filter).
    pub rendered: RgbImage,
    pub report: InvertReport,
}

/// Progress events for a front end.
pub enum Event<'a> {
    Stage { name: &'a str, steps: usize },
    Step { step: usize, loss: f64 },
    Trace { done: usize, total: usize },
}

#[derive(Debug, thiserror::Error)]
pub enum InvertError {
    #[error("{0}")]
    Invalid(String),
    #[error(transparent)]
    Cache(#[from] crate::cache::CacheError),
    #[error("{0}")]
    Render(String),
}

fn to_maps(w: usize, h: usize, mats: &[Material]) -> MaterialMaps {
    MaterialMaps {
        albedo: Image::from_vec(w, h, mats.iter().map(|m| m.albedo).collect()),
        roughness: Image::from_vec(w, h, mats.iter().map(|m| m.roughness).collect()),
        metallic: Image::from_vec(w, h, mats.iter().map(|m| m.metallic).collect()),
        normal: None,
    }
}

fn env_image(w: usize, h: usize, tex: &[Vec3]) -> RgbImage {
    Image::from_vec(w, h, tex.to_vec())
}

/// Recovers envmap and materials. `scene` carries camera and geometry (its
/// materials and envmap are replaced); `target` is the linear input image;
/// `pred` the predicted materials.
pub fn invert(
    mut scene: RenderScene,
    target_linear: &RgbImage,
    pred: &[Material],
    opts: &InvertOptions,
    events: &(dyn Fn(Event) + Sync),
) -> Result<InvertResult, InvertError> {
    let t0 = Instant::now();
    let (w, h) = (scene.camera.width, scene.camera.height);
    let npix = w * h;
    if target_linear.width != w || target_linear.height != h || pred.len() != npix {
        return Err(InvertError::Invalid(format!(
            "input image is {}x{} and predictions have {} pixels, but the camera is {w}x{h}",
            target_linear.width,
            target_linear.height,
            pred.len()
        )));
    }
    let plan = Plan::from_budget(opts.budget_seconds, npix, opts);
    let (ew, eh) = (opts.env_width, opts.env_height);
    let ntex = ew * eh;
    let target = Target::new(w, h, &target_linear.data);
    // Starting materials and the consistency anchor.
    let pred: Vec<Material> = pred
        .iter()
        .map(|m| {
            let m = m.sanitized();
            if opts.trust_rm || opts.env_only {
                m
            } else {
                Material {
                    roughness: 0.7,
                    metallic: 0.05,
                    ..m
                }
            }
        })
        .collect();
    let mut mats = pred.clone();
    let mut stages = Vec::new();
    let env_opts = EnvFitOptions {
        steps: plan.env_steps,
        lr: 0.05,
        early_stop: opts.early_stop,
    };
    let pixels = strided_pixels(w, h, plan.env_stride);

    let set_scene =
        |scene: &mut RenderScene, mats: &[Material], env: &[Vec3]| -> Result<(), InvertError> {
            scene.materials = mats.iter().map(|m| m.sanitized()).collect();
            scene.env = EnvMap::new(&env_image(ew, eh, env))
                .map_err(|e| InvertError::Render(e.to_string()))?;
            Ok(())
        };
    let run_env = |name: &str,
                   cache: &PathCache,
                   mats: &[Material],
                   init: &[Vec3],
                   steps: usize,
                   mlp: &mut Option<EnvMlp>,
                   stages: &mut Vec<StageReport>|
     -> Vec<Vec3> {
        let ts = Instant::now();
        events(Event::Stage { name, steps });
        let tr = EnvTransport::build(cache, mats, pixels.clone());
        let progress = |step, loss| events(Event::Step { step, loss });
        let (env, trace) = match mlp {
            Some(net) => net.fit(
                &tr,
                &target,
                &EnvFitOptions {
                    steps,
                    lr: opts.env_mlp.lr,
                    ..env_opts
                },
                &progress,
            ),
            None => fit_texels(
                &tr,
                &target,
                init,
                &EnvFitOptions { steps, ..env_opts },
                &progress,
            ),
        };
        stages.push(report(name, &trace, ts));
        env
    };

    // 1. Scout.
    let flat = vec![Vec3::ONE; ntex];
    set_scene(&mut scene, &mats, &flat)?;
    events(Event::Stage {
        name: "trace scout",
        steps: h,
    });
    let ts = Instant::now();
    let scout = PathCache::build(
        &scene,
        &CacheOptions {
            spp: plan.scout_spp,
            max_depth: opts.max_depth,
            seed: opts.seed ^ 0x5c0u64,
            env_width: ew,
            env_height: eh,
        },
        &|d, t| events(Event::Trace { done: d, total: t }),
    )?;
    stages.push(timed("trace scout", plan.scout_spp as usize, ts));
    let tr0 = EnvTransport::build(&scout, &mats, pixels.clone());
    let s = exposure_scale(&tr0, &target_linear.data, &flat);
    drop(tr0);
    let init: Vec<Vec3> = flat.iter().map(|e| *e * s).collect();
    let mut mlp = match opts.env_route {
        EnvRoute::Texel => None,
        EnvRoute::Mlp => Some(EnvMlp::new(
            ew,
            eh,
            s,
            &EnvMlpOptions {
                seed: opts.seed,
                ..opts.env_mlp
            },
        )),
    };
    let mut env = run_env(
        "envmap (scout)",
        &scout,
        &mats,
        &init,
        plan.env_steps,
        &mut mlp,
        &mut stages,
    );
    drop(scout);

    // 2. Main trace.
    set_scene(&mut scene, &mats, &env)?;
    events(Event::Stage {
        name: "trace",
        steps: h,
    });
    let ts = Instant::now();
    let cache = PathCache::build(
        &scene,
        &CacheOptions {
            spp: plan.spp,
            max_depth: opts.max_depth,
            seed: opts.seed,
            env_width: ew,
            env_height: eh,
        },
        &|d, t| events(Event::Trace { done: d, total: t }),
    )?;
    stages.push(timed("trace", plan.spp as usize, ts));

    // 3. Alternation.
    let guide = Guide::build(&scene);
    let mat_mlp_opts = MatMlpOptions {
        seed: opts.seed,
        ..opts.mat_mlp
    };
    let mut mat_mlp: Option<MatMlp> = None;
    let fit_opts = |parts| MatFitOptions {
        steps: plan.mat_steps,
        lr: 0.05,
        delta: opts.delta,
        zeta: opts.zeta,
        parts,
        early_stop: opts.early_stop,
        rescale: opts.rescale,
    };
    for l in 0..plan.loops {
        env = run_env(
            &format!("envmap {}", l + 1),
            &cache,
            &mats,
            &env,
            plan.env_steps,
            &mut mlp,
            &mut stages,
        );
        let stages_parts: &[Parts] = match opts.mat_route {
            _ if opts.env_only => &[],
            // The per-pixel solve searches A, R and M jointly.
            MatRoute::Solve => &[Parts::ARM],
            MatRoute::Pixel | MatRoute::Mlp => &[Parts::RM, Parts::A],
        };
        for &parts in stages_parts {
            let name = format!("materials {} {}", parts.name(), l + 1);
            let ts = Instant::now();
            events(Event::Stage {
                name: &name,
                steps: plan.mat_steps,
            });
            let (mut tabs, var, valid) = build_tables_with_variance(&cache, &mats, &env);
            if opts.denoise > 0 {
                denoise_tables(&mut tabs, &var, &valid, &guide, opts.denoise);
            }
            drop(var);
            let fit = match opts.mat_route {
                MatRoute::Pixel => fit_pixels(
                    &tabs,
                    &target,
                    &pred,
                    &mats,
                    &fit_opts(parts),
                    &|step, loss| events(Event::Step { step, loss }),
                ),
                MatRoute::Mlp => mat_mlp
                    .get_or_insert_with(|| MatMlp::new(w, h, &pred, &mat_mlp_opts))
                    .fit(
                        &tabs,
                        &target,
                        &pred,
                        &mats,
                        &fit_opts(parts),
                        &mat_mlp_opts,
                        &|step, loss| events(Event::Step { step, loss }),
                    ),
                MatRoute::Solve => solve_pixels(
                    &tabs,
                    &target,
                    &pred,
                    &mats,
                    &SolveOptions {
                        delta: opts.delta,
                        zeta: opts.zeta,
                        parts,
                        rounds: plan.solve_rounds,
                        rescale: opts.rescale,
                        reference_weighting: true,
                        min_roughness: resolvable_roughness(ew, eh),
                    },
                    &|step, loss| events(Event::Step { step, loss }),
                ),
            };
            mats = fit.materials;
            for e in env.iter_mut() {
                *e *= fit.scale;
            }
            if let Some(net) = mlp.as_mut() {
                net.scale *= fit.scale;
            }
            stages.push(report(&name, &fit.trace, ts));
        }
    }
    // 4. Final envmap for the final materials.
    env = run_env(
        "envmap final",
        &cache,
        &mats,
        &env,
        plan.env_steps,
        &mut mlp,
        &mut stages,
    );

    let fit = transport::render(&cache, &mats, &env);
    let (fit_loss, _) = loss_and_grad(&fit, &target, None);
    let report_bytes = cache.stats.bytes;
    let report_rays = cache.stats.rays;
    drop(cache);

    // 5. Independent re-render.
    set_scene(&mut scene, &mats, &env)?;
    events(Event::Stage {
        name: "render",
        steps: h,
    });
    let ts = Instant::now();
    let out = matflow_render::render(
        &scene,
        &RenderOptions {
            spp: plan.final_spp,
            max_depth: opts.max_depth,
            seed: opts.seed ^ 0xf1_4a1,
            filter: PixelFilter::Box,
            reference_compat: false,
            tile_size: 16,
        },
        &|d, t| events(Event::Trace { done: d, total: t }),
    );
    stages.push(timed("render", plan.final_spp as usize, ts));
    Ok(InvertResult {
        materials: mats,
        envmap: env_image(ew, eh, &env),
        fit_image: Image::from_vec(w, h, fit),
        rendered: out.image,
        report: InvertReport {
            plan,
            stages,
            cache_bytes: report_bytes,
            cache_rays: report_rays,
            fit_loss: fit_loss.total(),
            seconds: t0.elapsed().as_secs_f64(),
        },
    })
}

/// The roughness whose reflection lobe (solid angle ≈ 4π·α², α = R²)
/// covers one average envmap texel (4π / (W·H)): R = (W·H)^(-1/4), 0.21
/// at 32×16. Sharper lobes see detail the envmap does not have, and their
/// per-pixel estimates rest on a few frozen directions, so the solve does
/// not go below it unless the prediction does.
pub fn resolvable_roughness(env_width: usize, env_height: usize) -> f32 {
    ((env_width * env_height).max(1) as f32).powf(-0.25)
}

/// A stage without a loss (tracing, rendering): its name, size and time.
fn timed(name: &str, steps: usize, ts: Instant) -> StageReport {
    StageReport {
        name: name.to_string(),
        steps,
        seconds: ts.elapsed().as_secs_f64(),
        loss_start: f64::NAN,
        loss_end: f64::NAN,
        stopped_early: false,
    }
}

fn report(name: &str, trace: &FitTrace, ts: Instant) -> StageReport {
    StageReport {
        name: name.to_string(),
        steps: trace.steps,
        seconds: ts.elapsed().as_secs_f64(),
        loss_start: trace.losses.first().copied().unwrap_or(f64::NAN),
        loss_end: trace.losses.last().copied().unwrap_or(f64::NAN),
        stopped_early: trace.stopped_early,
    }
}

/// Materials as maps (for writing).
pub fn materials_to_maps(w: usize, h: usize, mats: &[Material]) -> MaterialMaps {
    to_maps(w, h, mats)
}
