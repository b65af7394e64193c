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

use crate::denoise::{denoise_tables, Guide};
use crate::envfit::{
    exposure_scale, fit_texels, strided_pixels, EnvFitOptions, EnvMlp, EnvMlpOptions, EnvTransport,
    FitTrace,
};
use crate::loss::{loss_and_grad, Target};
use crate::matfit::{fit_pixels, MatFitOptions, MatMlp, MatMlpOptions, Parts};
use crate::paths::{CacheOptions, PathCache};
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
    pub solve_rounds: Option<usize>,
    pub env_steps: Option<usize>,
    pub mat_steps: Option<usize>,
    pub early_stop: bool,
    /// Texel envmap route: weight of the smoothness prior on log texels
    /// (see [`EnvFitOptions::smooth`]); `None`: [`SYNTHETIC_ENV_SMOOTH`]
    /// with trusted R/M, off for photos.
    pub env_smooth: Option<f32>,
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
    /// A starting envmap (`env_width`×`env_height`, e.g. from an earlier
    /// envmap-only recovery); it replaces the scout's envmap stage.
    pub init_env: Option<RgbImage>,
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
            solve_rounds: None,
            env_steps: None,
            mat_steps: None,
            early_stop: true,
            env_smooth: None,
            rescale: true,
            denoise: 3,
            env_mlp: EnvMlpOptions::default(),
            mat_mlp: MatMlpOptions::default(),
            env_only: false,
            init_env: None,
        }
    }
}

/// The two settings, measured at budget 60 (2-core machine, one run per
/// cell; synthetic: means over seeds 1 and 2):
///
/// | setting | texel smoothing | loops | synthetic rerender / relight / envmap SSIM | indoor | jinjya |
/// |---|---|---|---|---|---|
/// | both off | 0 | 5–7 | 38.51 / 25.64 / 0.058 | 30.34 | 34.14 |
/// | smoothing | 0.01 | 5–7 | 38.98 / 25.73 / 0.182 | 29.40 | 34.16 |
/// | smoothing, 2 loops | 0.01 | 2 | 40.29 / 27.14 / 0.239 | — | — |
///
/// With trusted R/M (synthetic data: every prediction is a degraded truth)
/// further loops only bake light the envmap misses into the albedo, and
/// texels few paths see fit noise; with photos (R/M start at constants)
/// the loops are what finds R and M, and the indoor "envmap" stands in
/// for sharp interior lights that smoothing blurs. So trusted R/M get
/// [`SYNTHETIC_ENV_SMOOTH`] and at most [`SYNTHETIC_MAX_LOOPS`] loops.
pub const SYNTHETIC_ENV_SMOOTH: f32 = 0.01;
pub const SYNTHETIC_MAX_LOOPS: usize = 2;

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
    /// What the counts were planned for (the scout's measurements once
    /// it has run).
    pub scene: SceneCost,
}

/// What makes one scene dearer than another at the same size, counted
/// (not timed) by the scout trace.
#[derive(Clone, Copy, Debug, serde::Serialize)]
pub struct SceneCost {
    /// Rays per traced path.
    pub rays_per_sample: f64,
    /// Share of pixels whose paths start on a surface: only those have
    /// materials to solve (sky pixels cost next to nothing there).
    pub surface_fraction: f64,
}

impl Default for SceneCost {
    /// The calibration scene (indoor: every pixel a surface).
    fn default() -> Self {
        SceneCost {
            rays_per_sample: cost::RAYS_PER_SAMPLE,
            surface_fraction: 1.0,
        }
    }
}

impl SceneCost {
    pub fn of(cache: &PathCache) -> SceneCost {
        let n = (cache.width * cache.height).max(1) as f64;
        SceneCost {
            rays_per_sample: cache.stats.rays as f64 / (n * cache.spp.max(1) as f64),
            surface_fraction: cache.surface_pixels() as f64 / n,
        }
    }
}

/// Cost model of the reference 2-core machine, used only to turn a budget
/// into counts, so results never depend on the clock. Seconds per pixel
/// (per ray, pass or round where stated), measured on indoor and jinjya
/// at 512². Tracing costs scale with the rays a sample needs, which the
/// scout trace counts (a deterministic number: sky pixels end at once,
/// interiors bounce), so the plan fits the scene without a clock.
pub mod cost {
    /// Tracing and recording one ray of the frozen cache.
    pub const TRACE_PER_RAY: f64 = 3.8e-7;
    /// One ray of the final re-render.
    pub const RENDER_PER_RAY: f64 = 3.7e-7;
    /// Rays per sample assumed before the scout has counted them (indoor).
    pub const RAYS_PER_SAMPLE: f64 = 2.6;
    /// Building a pixel's table, per cached path.
    pub const TABLE_PER_SAMPLE: f64 = 8.5e-8;
    /// One à-trous pass over a pixel's table.
    pub const DENOISE_PER_PASS: f64 = 9.0e-7;
    /// One round of the per-pixel solve from a grid over (R, M).
    pub const SOLVE_COLD_ROUND: f64 = 6.5e-6;
    /// One round started from the previous answer (compass search only).
    pub const SOLVE_WARM_ROUND: f64 = 2.9e-6;
    /// One envmap stage (it stops early after a few dozen steps).
    pub const ENV_STAGE: f64 = 1.9e-6;
    /// Loading, meshing, BVH, guide, scout trace and the envmap stages.
    pub const FIXED: f64 = 1.6e-5;
    /// The pixel route's material stage (Adam on the tables, staged R+M
    /// then A, early-stopped) relative to the solve route's (measured:
    /// ~4.8 s against ~3.4 s a loop on jinjya at 512²).
    pub const PIXEL_ROUTE_FACTOR: f64 = 1.4;
    /// One step of the material MLP (forward, reverse, AdamW), per pixel.
    /// A loop's two stages take about `mat_steps` steps together (the
    /// R+M stage stops early, the albedo stage rarely).
    pub const MAT_MLP_STEP: f64 = 1.9e-7;
    /// One step of the envmap MLP, per pixel the envmap stage sees; a
    /// stage takes about half its `env_steps` before its stopping rule.
    pub const ENV_MLP_STEP: f64 = 2.4e-7;
}

impl Plan {
    /// The plan for a budget and a scene's costs (before the scout:
    /// [`SceneCost::default`]).
    ///
    /// Split, from measurements on both reference scenes: the frozen
    /// cache gets up to 32 paths per pixel (memory caps it); then about
    /// 55 % of what is left buys alternation loops (each refreshes the
    /// light reaching primary vertices and re-solves every pixel: indoor
    /// at 92 final spp went 28.9 → 30.3 → 30.8 → 31.1 dB for 2, 4, 6, 8
    /// loops) and the rest buys samples of the final re-render (92 → 200
    /// spp: +0.45 dB).
    pub fn from_budget(budget: f64, npix: usize, scene: SceneCost, opts: &InvertOptions) -> Plan {
        use cost::*;
        let n = npix as f64;
        let b = budget.max(1.0);
        let finite_or = |x: f64, d: f64| if x.is_finite() { x } else { d };
        let rho = finite_or(scene.rays_per_sample, RAYS_PER_SAMPLE).clamp(1.0, 8.0);
        // Per-pixel material work scales with the surface pixels (at
        // least a tenth: loading and sweeping the tables is not free).
        let surf = finite_or(scene.surface_fraction, 1.0).clamp(0.1, 1.0);
        let rounds = opts.solve_rounds.unwrap_or(if b >= 30.0 {
            3
        } else if b >= 12.0 {
            2
        } else {
            1
        });
        let passes = opts.denoise as f64;
        // Plan for 90 % of the budget: the model is a median, not a bound.
        let avail0 = (0.9 * b - FIXED * n).max(0.0);
        let steps = ((b * 10.0) as usize).clamp(60, 400);
        // Envmap stages see about 64k pixels.
        let env_stride = ((n / 65536.0).sqrt().ceil() as usize).max(1);
        let env_px = n / (env_stride * env_stride) as f64;
        // The MLP routes' steps are priced; when a loop at the default
        // step count would take more than half the budget, they get fewer
        // steps (the reference's thousands do not fit a CPU minute).
        let mat_steps = opts.mat_steps.unwrap_or(match opts.mat_route {
            MatRoute::Mlp => steps
                .min((0.5 * avail0 / (MAT_MLP_STEP * n)) as usize)
                .max(20),
            _ => steps,
        });
        let env_steps = opts.env_steps.unwrap_or(match opts.env_route {
            EnvRoute::Mlp => steps
                .min((0.1 * avail0 / (0.5 * ENV_MLP_STEP * env_px)) as usize)
                .max(20),
            EnvRoute::Texel => steps,
        });
        let env_stage = match opts.env_route {
            EnvRoute::Texel => ENV_STAGE * n,
            EnvRoute::Mlp => 0.5 * ENV_MLP_STEP * env_px * env_steps as f64,
        };
        // The scout's and the final envmap stage (FIXED prices texel ones).
        let avail = (avail0 - 2.0 * (env_stage - ENV_STAGE * n)).max(0.0);
        // A loop's cost with s cached paths per pixel; the first loop
        // solves from a grid, later ones from the previous answer.
        let loop_cost = |s: f64, warm: bool| -> f64 {
            let solve = if warm {
                SOLVE_WARM_ROUND * rounds as f64
            } else {
                SOLVE_COLD_ROUND + SOLVE_WARM_ROUND * (rounds - 1) as f64
            };
            let tables = (TABLE_PER_SAMPLE * s + DENOISE_PER_PASS * passes) * surf * n;
            let materials = match opts.mat_route {
                MatRoute::Solve => tables + solve * surf * n,
                MatRoute::Pixel => PIXEL_ROUTE_FACTOR * (tables + solve * surf * n),
                MatRoute::Mlp => tables + MAT_MLP_STEP * n * mat_steps as f64,
            };
            env_stage + materials
        };
        let trace_spp = TRACE_PER_RAY * rho * n;
        // ~40 % of the budget tracing the cache, capped at 32 paths.
        let spp = opts.spp.unwrap_or(
            ((0.4 * avail / (trace_spp + loop_cost(0.0, false) / 32.0)) as u32).clamp(2, 32),
        );
        let rest = (avail - spp as f64 * trace_spp - loop_cost(spp as f64, false)).max(0.0);
        let warm = loop_cost(spp as f64, true);
        let max_loops = if opts.trust_rm {
            SYNTHETIC_MAX_LOOPS
        } else {
            8
        };
        let loops = opts
            .loops
            .unwrap_or((1 + (0.55 * rest / warm) as usize).min(max_loops));
        let spent = loop_cost(spp as f64, false) + (loops.max(1) - 1) as f64 * warm;
        let left = (avail - spp as f64 * trace_spp - spent).max(0.0);
        let final_spp = opts
            .final_spp
            .unwrap_or(((left / (RENDER_PER_RAY * rho * n)) as u32).clamp(2, 256));
        let scout_spp = (spp / 8).clamp(1, 4);
        Plan {
            scout_spp,
            spp,
            final_spp,
            loops,
            env_steps,
            mat_steps,
            solve_rounds: rounds,
            env_stride,
            scene: SceneCost {
                rays_per_sample: rho,
                surface_fraction: surf,
            },
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
    Cache(#[from] crate::paths::CacheError),
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
    // Counts before the scout has measured the scene's rays per path;
    // only the scout's sample count is taken from this first plan.
    let first = Plan::from_budget(opts.budget_seconds, npix, SceneCost::default(), opts);
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
    // Envmap step counts and pixel stride do not depend on the scene's
    // rays, so the first plan's serve throughout.
    let env_opts = EnvFitOptions {
        steps: first.env_steps,
        lr: 0.05,
        early_stop: opts.early_stop,
        smooth: opts.env_smooth.unwrap_or(if opts.trust_rm {
            SYNTHETIC_ENV_SMOOTH
        } else {
            0.0
        }),
    };
    let pixels = strided_pixels(w, h, first.env_stride);

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
            spp: first.scout_spp,
            max_depth: opts.max_depth,
            seed: opts.seed ^ 0x5c0u64,
            env_width: ew,
            env_height: eh,
        },
        &|d, t| events(Event::Trace { done: d, total: t }),
    )?;
    stages.push(timed("trace scout", first.scout_spp as usize, ts));
    let plan = Plan {
        scout_spp: first.scout_spp,
        ..Plan::from_budget(opts.budget_seconds, npix, SceneCost::of(&scout), opts)
    };
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
    let mut env = match &opts.init_env {
        Some(_) if mlp.is_some() => {
            return Err(InvertError::Invalid(
                "a starting envmap needs the texel envmap route".into(),
            ))
        }
        Some(e) if e.width != ew || e.height != eh => {
            return Err(InvertError::Invalid(format!(
                "the starting envmap is {}x{}; expected {ew}x{eh}",
                e.width, e.height
            )))
        }
        Some(e) => e
            .data
            .iter()
            .map(|v| {
                let v = if v.is_finite() { *v } else { Vec3::ZERO };
                v.clamp(Vec3::splat(1e-6), Vec3::splat(1e6))
            })
            .collect(),
        None => run_env(
            "envmap (scout)",
            &scout,
            &mats,
            &init,
            plan.env_steps,
            &mut mlp,
            &mut stages,
        ),
    };
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
                        warm: l > 0,
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
            crop: None,
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

#[cfg(test)]
mod tests {
    use super::*;

    /// The plan is a pure function of budget, size and the scout's
    /// counts: a scene of cheap (sky) paths gets more samples for the
    /// same budget, a bigger budget never buys less, and trusted R/M cap
    /// the loops.
    #[test]
    fn plan_follows_budget_and_counted_scene_cost() {
        let o = InvertOptions::default();
        let n = 512 * 512;
        let base = Plan::from_budget(60.0, n, SceneCost::default(), &o);
        let cheap = Plan::from_budget(
            60.0,
            n,
            SceneCost {
                rays_per_sample: 1.6,
                surface_fraction: 0.5,
            },
            &o,
        );
        assert!(cheap.final_spp > base.final_spp || cheap.loops > base.loops);
        assert!(cheap.final_spp >= base.final_spp && cheap.loops >= base.loops);
        let mut prev = Plan::from_budget(5.0, n, SceneCost::default(), &o);
        for b in [15.0, 30.0, 60.0, 240.0] {
            let p = Plan::from_budget(b, n, SceneCost::default(), &o);
            assert!(p.spp >= prev.spp && p.loops >= prev.loops, "budget {b}");
            assert!(p.loops >= 1 && p.final_spp >= 2 && p.spp >= 2);
            prev = p;
        }
        assert!(base.loops > SYNTHETIC_MAX_LOOPS);
        let trusted = InvertOptions {
            trust_rm: true,
            ..InvertOptions::default()
        };
        let t = Plan::from_budget(60.0, n, SceneCost::default(), &trusted);
        assert_eq!(t.loops, SYNTHETIC_MAX_LOOPS);
        assert!(t.final_spp > base.final_spp);
        // Nonsense counts fall back to the calibration scene.
        let nan = SceneCost {
            rays_per_sample: f64::NAN,
            surface_fraction: f64::INFINITY,
        };
        let p = Plan::from_budget(60.0, n, nan, &o);
        assert_eq!(p.final_spp, base.final_spp);
        // Dearer routes buy fewer loops (and the MLP fewer steps) from the
        // same budget.
        let route = |mat_route, env_route| {
            Plan::from_budget(
                60.0,
                n,
                SceneCost::default(),
                &InvertOptions {
                    mat_route,
                    env_route,
                    ..InvertOptions::default()
                },
            )
        };
        let pixel = route(MatRoute::Pixel, EnvRoute::Texel);
        let mlp = route(MatRoute::Mlp, EnvRoute::Texel);
        let env_mlp = route(MatRoute::Solve, EnvRoute::Mlp);
        assert!(
            pixel.loops < base.loops && mlp.loops <= pixel.loops,
            "{pixel:?} {mlp:?}"
        );
        assert!(env_mlp.loops < base.loops);
        // At small budgets the MLP gets fewer steps.
        let small = Plan::from_budget(
            15.0,
            n,
            SceneCost::default(),
            &InvertOptions {
                mat_route: MatRoute::Mlp,
                ..InvertOptions::default()
            },
        );
        assert!(small.mat_steps < Plan::from_budget(15.0, n, SceneCost::default(), &o).mat_steps);
    }
}
