//! The budget plan: sample and step counts from a time budget through a
//! fixed cost model, so that results never depend on the clock.

use crate::invert::InvertOptions;
use crate::paths::PathCache;
use crate::routes::{env_texel, EnvRoute, MatRoute, PlanInputs};

/// With trusted R/M (synthetic data: every prediction is a degraded
/// truth) further loops only bake light the envmap misses into the
/// albedo, and texels few paths see fit noise; with photos (R/M start at
/// constants) the loops are what finds R and M. Measured at budget 60 on
/// synthetic rooms: 2 loops 40.29 dB rerender against 38.98 at 5–7 (see
/// [`env_texel::SYNTHETIC_SMOOTH`]).
pub const SYNTHETIC_MAX_LOOPS: usize = 2;

/// Samples per pixel of the final re-render that the loops leave it, at
/// least. It is the report's (denoised), not what is recovered: jinjya at
/// 20 s with 5 final samples reads 32.7 dB where an independent 256-spp
/// render of the same result reads 34.1, and 2 final samples 30.3 dB.
pub const FINAL_MIN_SPP: u32 = 4;

/// Sample and step counts derived from the budget.
#[derive(Clone, Copy, Debug, serde::Serialize)]
pub struct Plan {
    pub scout_spp: u32,
    pub spp: u32,
    pub final_spp: u32,
    pub loops: usize,
    pub env_steps: usize,
    pub mat_steps: usize,
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
    /// Cost of a ray relative to the calibration scene's: 1, times
    /// [`cost::GUIDED_RAY`] when light samples are guided by visibility
    /// and [`cost::PORTAL_RAY`] when they aim at portals.
    pub ray_cost: f64,
}

impl Default for SceneCost {
    /// The calibration scene (indoor: every pixel a surface).
    fn default() -> Self {
        SceneCost {
            rays_per_sample: cost::RAYS_PER_SAMPLE,
            surface_fraction: 1.0,
            ray_cost: 1.0,
        }
    }
}

impl SceneCost {
    pub fn of(cache: &PathCache) -> SceneCost {
        let n = (cache.width * cache.height).max(1) as f64;
        SceneCost {
            rays_per_sample: cache.stats.rays as f64 / (n * cache.spp.max(1) as f64),
            surface_fraction: cache.surface_pixels() as f64 / n,
            ray_cost: 1.0,
        }
    }

    /// The same scene with its light samples guided by visibility (or
    /// not).
    pub fn guided(self, guided: bool) -> SceneCost {
        SceneCost {
            ray_cost: if guided { cost::GUIDED_RAY } else { 1.0 },
            ..self
        }
    }

    /// The same scene with `rays` more rays per sample (e.g. a shadow ray
    /// per vertex towards a sun found after the scout counted them).
    pub fn with_extra_rays(self, rays: f64) -> SceneCost {
        SceneCost {
            rays_per_sample: self.rays_per_sample + rays.max(0.0),
            ..self
        }
    }

    /// The same scene with its light samples aiming at portals
    /// ([`matflow_render::portal`]), after [`SceneCost::guided`].
    pub fn with_portals(self, portals: bool) -> SceneCost {
        SceneCost {
            ray_cost: self.ray_cost * if portals { cost::PORTAL_RAY } else { 1.0 },
            ..self
        }
    }
}

/// Cost model of the reference 2-core machine for what every route shares,
/// used only to turn a budget into counts. Seconds per pixel (per ray or
/// pass where stated), measured on indoor and jinjya at 512²
/// (`MATFLOW_LOG=matflow::stages=trace matflow invert --budget-seconds 20`
/// logs each stage's time and each solve round's) on a 2-core AMD EPYC
/// (Zen 3) and divided by 1.8: that machine's wall time over the previous
/// model's on both photos (32.4 and 33.2 s for 18 planned), so the model
/// stays in the reference machine's seconds. Per ray the two photos
/// differ (jinjya 0.65× indoor's): the constants are their geometric
/// means. Tracing costs scale with the rays a sample needs, which the
/// scout trace counts (a deterministic number: sky pixels end at once,
/// interiors bounce), so the plan fits the scene without a clock. Each route prices its own
/// stages (`routes/*.rs`).
pub mod cost {
    /// Tracing and recording one ray of the frozen cache.
    pub const TRACE_PER_RAY: f64 = 1.9e-7;
    /// One ray of the final re-render.
    pub const RENDER_PER_RAY: f64 = 1.9e-7;
    /// Rays per sample assumed before the scout has counted them (indoor).
    pub const RAYS_PER_SAMPLE: f64 = 2.6;
    /// Building a pixel's table, per cached path: 1.0e-7 before the
    /// specular sums ran in lanes, which took the tables' build 0.75×
    /// (the trace log's "step 0" of each material stage, old and new
    /// binaries alternated three times on both photos).
    pub const TABLE_PER_SAMPLE: f64 = 0.75e-7;
    /// One à-trous pass over a pixel's table.
    pub const DENOISE_PER_PASS: f64 = 1.35e-6;
    /// A ray's cost when light samples are guided by visibility, relative
    /// to sampling by radiance (its lookups; more of its shadow rays go
    /// far): scene-00 of the validation set with the room completed,
    /// 32 cached paths 1.19×, the final render 1.11× per ray.
    pub const GUIDED_RAY: f64 = 1.2;
    /// A ray's cost, relative, when light samples also aim at portals
    /// (choosing one and mapping its spherical rectangle; more shadow
    /// rays cross the room): indoor closed as a room with three assumed
    /// windows, 32 cached paths 1.15×, the final render 1.09× per ray.
    pub const PORTAL_RAY: f64 = 1.12;
    /// The search of R and M per segment (`crate::segments`), per surface
    /// pixel, besides its tables: primary rays, segments and the scores
    /// of a grid of 13 materials.
    pub const RM_SEARCH: f64 = 4.0e-6;
    /// Loading, meshing, BVH, testing the completions, guide, scout
    /// trace, two envmap stages of the texel route, metrics and writing
    /// the bundle.
    pub const FIXED: f64 = 1.65e-5;
}

impl Plan {
    /// The plan for a budget and a scene's costs (before the scout:
    /// [`SceneCost::default`]) with the chosen routes.
    ///
    /// Split, from measurements on both reference scenes: the frozen
    /// cache gets ~40 % of the budget, up to 32 paths per pixel (memory
    /// caps it); then alternation loops take what is left but
    /// [`FINAL_MIN_SPP`] samples of the final re-render, up to their cap,
    /// and the final re-render the rest. Each loop refreshes the light
    /// reaching primary vertices and re-solves every pixel, and that is
    /// what finds the scene: at 20 s (26 cached paths on jinjya, 10 on
    /// indoor), an independent 256-spp re-render of the result went
    /// 33.27 → 33.61 → 33.91 dB for 2, 3, 4 loops on jinjya and 28.17 →
    /// 29.26 → 29.91 dB on indoor, whereas 49 → 128 final samples changed
    /// it by nothing (the final re-render is the report's; a later render
    /// re-renders the result anyway). Before, the loops took 55 % of what
    /// the cache left and the final re-render the rest.
    pub fn from_budget(
        budget: f64,
        npix: usize,
        scene: SceneCost,
        opts: &InvertOptions,
        env_route: &dyn EnvRoute,
        mat_route: &dyn MatRoute,
    ) -> Plan {
        use cost::*;
        let n = npix as f64;
        let b = budget.max(1.0);
        let finite_or = |x: f64, d: f64| if x.is_finite() { x } else { d };
        let rho = finite_or(scene.rays_per_sample, RAYS_PER_SAMPLE).clamp(1.0, 8.0);
        let ray_cost = finite_or(scene.ray_cost, 1.0).clamp(1.0, 4.0);
        // Per-pixel material work scales with the surface pixels (at
        // least a tenth: loading and sweeping the tables is not free).
        let surf = finite_or(scene.surface_fraction, 1.0).clamp(0.1, 1.0);
        let passes = opts.denoise as f64;
        // Plan for 90 % of the budget: the model is a median, not a bound.
        let avail0 = (0.9 * b - FIXED * n).max(0.0);
        // Envmap stages see about 64k pixels.
        let env_stride = ((n / 65536.0).sqrt().ceil() as usize).max(1);
        let inputs = PlanInputs {
            budget_seconds: b,
            pixels: n,
            env_pixels: n / (env_stride * env_stride) as f64,
            surface_fraction: surf,
            available: avail0,
            steps: ((b * 10.0) as usize).clamp(60, 400),
        };
        let mat_steps = opts.mat_steps.unwrap_or(mat_route.steps(&inputs));
        let env_steps = opts.env_steps.unwrap_or(env_route.steps(&inputs));
        let env_stage = env_route.stage_seconds(&inputs, env_steps);
        // The scout's and the final envmap stage (FIXED prices texel ones).
        let avail = (avail0 - 2.0 * (env_stage - env_texel::STAGE_PER_PIXEL * n)).max(0.0);
        // A loop's cost with s cached paths per pixel; the first loop
        // solves from a grid, later ones from the previous answer.
        let loop_cost = |s: f64, warm: bool| -> f64 {
            let tables = (TABLE_PER_SAMPLE * s + DENOISE_PER_PASS * passes) * surf * n;
            env_stage + mat_route.loop_seconds(&inputs, tables, mat_steps, warm)
        };
        let trace_spp = TRACE_PER_RAY * ray_cost * rho * n;
        // ~40 % of the budget tracing the cache, capped at 32 paths.
        let spp = opts.spp.unwrap_or(
            ((0.4 * avail / (trace_spp + loop_cost(0.0, false) / 32.0)) as u32).clamp(2, 32),
        );
        // The search of R and M per segment builds tables once more.
        let search = if opts.searches_rm() {
            (TABLE_PER_SAMPLE * spp as f64 + DENOISE_PER_PASS * passes + RM_SEARCH) * surf * n
        } else {
            0.0
        };
        let avail = (avail - search).max(0.0);
        let rest = (avail - spp as f64 * trace_spp - loop_cost(spp as f64, false)).max(0.0);
        let warm = loop_cost(spp as f64, true);
        let max_loops = if opts.trust_rm {
            SYNTHETIC_MAX_LOOPS
        } else {
            8
        };
        let render_spp = RENDER_PER_RAY * ray_cost * rho * n;
        let extra = (rest - FINAL_MIN_SPP as f64 * render_spp).max(0.0) / warm;
        let loops = opts.loops.unwrap_or((1 + extra as usize).min(max_loops));
        let spent = loop_cost(spp as f64, false) + (loops.max(1) - 1) as f64 * warm;
        let left = (avail - spp as f64 * trace_spp - spent).max(0.0);
        let final_spp = opts
            .final_spp
            .unwrap_or(((left / render_spp) as u32).clamp(2, 256));
        let scout_spp = (spp / 8).clamp(1, 4);
        Plan {
            scout_spp,
            spp,
            final_spp,
            loops,
            env_steps,
            mat_steps,
            env_stride,
            scene: SceneCost {
                rays_per_sample: rho,
                surface_fraction: surf,
                ray_cost,
            },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::routes::{env_route, mat_route};

    fn plan(budget: f64, scene: SceneCost, o: &InvertOptions) -> Plan {
        Plan::from_budget(
            budget,
            512 * 512,
            scene,
            o,
            &*o.env_route.build(),
            &*o.mat_route.build(),
        )
    }

    /// The plan is a pure function of budget, size and the scout's
    /// counts: a scene of cheap (sky) paths gets more samples for the
    /// same budget, a bigger budget never buys less, and trusted R/M cap
    /// the loops.
    #[test]
    fn plan_follows_budget_and_counted_scene_cost() {
        let o = InvertOptions::default();
        let base = plan(60.0, SceneCost::default(), &o);
        let cheap = plan(
            60.0,
            SceneCost {
                rays_per_sample: 1.6,
                surface_fraction: 0.5,
                ray_cost: 1.0,
            },
            &o,
        );
        assert!(cheap.final_spp > base.final_spp || cheap.loops > base.loops);
        assert!(cheap.final_spp >= base.final_spp && cheap.loops >= base.loops);
        let mut prev = plan(5.0, SceneCost::default(), &o);
        for b in [15.0, 30.0, 60.0, 240.0] {
            let p = plan(b, SceneCost::default(), &o);
            assert!(p.spp >= prev.spp && p.loops >= prev.loops, "budget {b}");
            assert!(p.loops >= 1 && p.final_spp >= 2 && p.spp >= 2);
            prev = p;
        }
        assert!(base.loops > SYNTHETIC_MAX_LOOPS);
        let trusted = InvertOptions {
            trust_rm: true,
            ..InvertOptions::default()
        };
        let t = plan(60.0, SceneCost::default(), &trusted);
        assert_eq!(t.loops, SYNTHETIC_MAX_LOOPS);
        assert!(t.final_spp > base.final_spp);
        // Nonsense counts fall back to the calibration scene.
        let nan = SceneCost {
            rays_per_sample: f64::NAN,
            surface_fraction: f64::INFINITY,
            ray_cost: f64::NAN,
        };
        let p = plan(60.0, nan, &o);
        assert_eq!(p.final_spp, base.final_spp);
        // Guided light samples cost more per ray: fewer samples.
        let guided = plan(60.0, SceneCost::default().guided(true), &o);
        assert!(guided.final_spp < base.final_spp && guided.spp <= base.spp);
        // So do light samples aimed at portals.
        let portals = plan(
            60.0,
            SceneCost::default().guided(true).with_portals(true),
            &o,
        );
        assert!(portals.final_spp < guided.final_spp && portals.spp <= guided.spp);
        let none = plan(
            60.0,
            SceneCost::default().guided(true).with_portals(false),
            &o,
        );
        assert_eq!(none.final_spp, guided.final_spp);
        // The search of R and M per segment is paid for (when it runs:
        // not with trusted R and M).
        let searched = InvertOptions {
            rm_search: true,
            ..o.clone()
        };
        let with = plan(60.0, SceneCost::default(), &searched);
        assert!(with.final_spp < base.final_spp || with.loops < base.loops);
        assert!(with.loops <= base.loops && with.spp <= base.spp);
        let t = |rm_search| InvertOptions {
            trust_rm: true,
            rm_search,
            ..o.clone()
        };
        let (a, b) = (
            plan(60.0, SceneCost::default(), &t(true)),
            plan(60.0, SceneCost::default(), &t(false)),
        );
        assert_eq!((a.spp, a.loops, a.final_spp), (b.spp, b.loops, b.final_spp));
        // Dearer routes buy fewer loops (and the MLP fewer steps) from the
        // same budget.
        let route = |m: &str, e: &str| InvertOptions {
            mat_route: mat_route(m, &[]).unwrap(),
            env_route: env_route(e, &[]).unwrap(),
            ..InvertOptions::default()
        };
        // (At 30 s: at 60 s the solve route and the pixel route both
        // reach the loops' cap.)
        let base = plan(30.0, SceneCost::default(), &o);
        let pixel = plan(30.0, SceneCost::default(), &route("pixel", "texel"));
        let mlp = plan(30.0, SceneCost::default(), &route("mlp", "texel"));
        let env_mlp = plan(30.0, SceneCost::default(), &route("solve", "mlp"));
        assert!(
            pixel.loops < base.loops && mlp.loops <= pixel.loops,
            "{base:?} {pixel:?} {mlp:?}"
        );
        assert!(env_mlp.loops < base.loops);
        // At small budgets the MLP gets fewer steps.
        let small = plan(15.0, SceneCost::default(), &route("mlp", "texel"));
        assert!(small.mat_steps < plan(15.0, SceneCost::default(), &o).mat_steps);
    }
}
