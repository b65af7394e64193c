//! The whole recovery: envmap and materials from one image, alternating
//! stages on frozen light paths, then an independent re-render.
//!
//! Schedule (following the reference's alternation, `opt_order = rm, a`):
//!
//! 1. scout: a few paths per pixel, envmap fitted from a constant start
//!    (gives the main trace a sensible envmap to importance-sample); then,
//!    when asked, the search for a sun ([`crate::sun`]), which joins the
//!    light vector as a distant lamp where the photo shows one;
//! 2. main trace with the scout envmap and the starting materials; then,
//!    when asked and R and M are not trusted, roughness and metallic per segment
//!    ([`crate::segments`]): where one albedo under another (R, M) explains
//!    a segment clearly better, the anchor of the per-pixel solve moves;
//! 3. `loops` × [envmap stage, the material route's stages (e.g.
//!    roughness+metallic, then albedo)], each material stage on freshly
//!    built per-pixel tables (the light reaching primary vertices from
//!    deeper bounces is refreshed there);
//! 4. a last envmap stage for the final materials;
//! 5. an independent render (new random numbers) of the recovered scene.
//!
//! How envmap and material stages fit is the routes' business
//! ([`crate::routes`]); this file only orders the stages. Everything is a
//! pure function of the inputs and options: the time budget picks step
//! and sample counts through a fixed cost model ([`Plan::from_budget`]),
//! never through the clock. Durations are the observer's to measure: each
//! stage is announced ([`Event::Stage`]) and closed ([`Event::StageDone`]).

use glam::Vec3;
use matflow_render::{
    EnvMap, Lamp, Material, PixelFilter, RenderError, RenderOptions, RenderScene,
};
use matflow_scene::{Image, MaterialMaps, RgbImage};

use crate::denoise::{denoise_tables, Guide};
use crate::envfit::{exposure_scale, strided_pixels, EnvTransport, FitTrace};
use crate::loss::{loss_and_grad, Target};
use crate::paths::{check_lamps, light_len, sun_scale, CacheError, CacheOptions, PathCache};

/// The pixel filter the inversion fits and re-renders with (each sample in
/// its own pixel, as the frozen paths are kept); `summary.json` records
/// it so that a re-render of the result uses it too.
pub const FIT_FILTER: PixelFilter = PixelFilter::Box;

use crate::matfit::Parts;
pub use crate::plan::{Plan, SceneCost};
use crate::routes::mat_solve::resolvable_roughness;
use crate::routes::{
    self, Chosen, EnvFitter, EnvRoute, EnvStage, EnvStart, MatRoute, MatStage, MatStart,
};
use crate::segments::{apply, search_rm, segment, SearchParams, SegmentParams};
use crate::structure::{photo_structured, rm_per_surface, StructureParams, Surfaces};
use crate::sun::{self, SearchPixel, SunFit, SunParams};
use crate::tables::{build_tables_with_variance, PixelTable};
use crate::transport;

#[derive(Clone, Debug)]
pub struct InvertOptions {
    pub budget_seconds: f64,
    /// How envmap stages fit ([`routes::ENV_ROUTES`]).
    pub env_route: Chosen<dyn EnvRoute>,
    /// How material stages fit ([`routes::MAT_ROUTES`]).
    pub mat_route: Chosen<dyn MatRoute>,
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
    /// [`crate::matfit::MatFitOptions::rescale`]).
    pub rescale: bool,
    /// À-trous passes over the per-pixel tables before each material
    /// stage (0: fit the raw Monte Carlo tables).
    pub denoise: usize,
    /// Denoise the independent re-render: it is rendered as two halves of
    /// its samples with their own random numbers, and filtered by
    /// [`matflow_render::denoise::denoise_render`] (albedo-demodulated,
    /// edge-aware à-trous, the halves' difference giving its noise).
    /// Off: one render, as it comes.
    pub denoise_render: bool,
    /// Recover only the envmap, materials held at the given ones (which
    /// are trusted as they are: the paper's Table 3 setting with ground
    /// truth or MatNet materials).
    pub env_only: bool,
    /// A starting envmap (`env_width`×`env_height`, e.g. from an earlier
    /// envmap-only recovery); it replaces the scout's envmap stage.
    pub init_env: Option<RgbImage>,
    /// Guide the frozen paths' light samples by what each region of the
    /// scene sees of the sky ([`matflow_render::guide`]); off samples the
    /// envmap by radiance alone.
    pub light_guide: bool,
    /// Aim the light samples at the scene's portals too (a completed
    /// room's windows, [`matflow_render::portal`]); off samples the
    /// envmap's density alone.
    pub portals: bool,
    /// Search roughness and metallic per segment before the first
    /// material stage ([`crate::segments`]; only when R and M are not
    /// trusted and materials are recovered). Off by default: on the
    /// validation set's tuning half it recovers metals but does not
    /// improve relighting (docs/notes/2026-11-relighting-log.md).
    pub rm_search: bool,
    /// How much better (relative loss) a segment's best (R, M) must
    /// explain it than its anchor for the anchor to move.
    pub rm_margin: f64,
    /// Hold the albedo's level and colour (its mean per channel over the
    /// surfaces in view) near the prediction's, the light taking the
    /// inverse gain ([`level_gain`]). One image cannot tell a brighter
    /// light from a brighter albedo; free, the fit settles that trade
    /// wherever its path ends. On by default, with [`LEVEL_BAND`].
    pub level_from_pred: bool,
    /// With the level held: how far (a share, per channel) the albedo's
    /// mean may move from the prediction's before it is held; 0 holds it
    /// exactly.
    pub level_band: f32,
    /// Where lamps may hang (camera space; e.g. under the ceiling of a
    /// closed room, [`matflow_geom::complete`]'s `lamp_sites`): each is a
    /// point light whose intensity is fitted with the envmap (texel route
    /// only; at most one per envmap column), under a sparsity prior. None:
    /// the envmap alone lights the scene.
    pub lamp_sites: Vec<Vec3>,
    /// A length of the scene's (e.g. the room's height): a lamp's fitted
    /// entry is its intensity over it squared ([`CacheOptions::lamp_scale`]).
    pub lamp_scale: f32,
    /// Weight of the lamps' sparsity prior
    /// ([`crate::envfit::EnvFitOptions::lamp_sparsity`]).
    pub lamp_sparsity: f32,
    /// After the scout, search the photo's light and shadow for a sun and,
    /// where one explains them, fit it as a distant lamp beside the texels
    /// ([`crate::sun`]; texel route only).
    pub sun: bool,
    /// How the sun is searched for, and when the best direction is one.
    pub sun_params: SunParams,
    /// After each stage that fits albedo, rebuild it from the prediction's
    /// coarse structure, the photo's fine detail and the solve's level per
    /// surface ([`crate::structure`]), so that shading the frozen paths
    /// get wrong does not stay in it. None: the solve's albedo as it is
    /// (the paper's method).
    pub albedo_structure: Option<StructureParams>,
}

impl InvertOptions {
    /// Whether roughness and metallic are searched per segment: asked
    /// for, and materials recovered with R and M not trusted.
    pub fn searches_rm(&self) -> bool {
        self.rm_search && !self.env_only && !self.trust_rm
    }
}

/// The per-pixel tables of the frozen paths for materials `mats` under
/// `env`, denoised by `passes` à-trous passes guided by `guide`.
fn fresh_tables(
    cache: &PathCache,
    mats: &[Material],
    env: &[Vec3],
    guide: &Guide,
    passes: usize,
) -> Vec<PixelTable> {
    let (mut tabs, var, valid) = build_tables_with_variance(cache, mats, env);
    if passes > 0 {
        denoise_tables(&mut tabs, &var, &valid, guide, passes);
    }
    tabs
}

/// The default band of the albedo's level ([`InvertOptions::level_band`]):
/// the fit may move the mean albedo per channel by up to 25 % from the
/// prediction's, about a material network's own error in level and
/// colour; past it the light takes the gain. Measured on the validation
/// set's tuning half (docs/notes/2026-11-relighting-log.md): rooms whose
/// fit stays inside are recovered bit for bit as with the level free, and
/// the one that drifted (a dimmed sky, a 1.5× albedo) relights 0.8 /
/// 2.5 dB better.
pub const LEVEL_BAND: f32 = 0.25;

/// The widest band of the albedo's level (a wider one is taken as this).
pub const MAX_LEVEL_BAND: f64 = 0.95;

/// Per pixel, whether it sees a surface (a finite distance of
/// [`RenderScene::primary_distances`]) rather than the sky.
pub fn surface_pixels(dist: &[f32]) -> Vec<bool> {
    dist.iter().map(|d| d.is_finite()).collect()
}

/// Per channel, the mean albedo of `mats` over the pixels where `surface`
/// holds, against that of `pred`: the gain that light and albedo trade
/// freely (the envmap times g and the albedo divided by g leave every
/// path of one bounce unchanged). `None` where it is not defined (no
/// surface, a black prediction); each channel within [1/20, 20].
pub fn level_gain(mats: &[Material], pred: &[Material], surface: &[bool]) -> Option<Vec3> {
    let (mut a, mut p) = ([0f64; 3], [0f64; 3]);
    let mut n = 0usize;
    for ((m, q), _) in mats.iter().zip(pred).zip(surface).filter(|(_, s)| **s) {
        for c in 0..3 {
            a[c] += f64::from(m.albedo[c].max(0.0));
            p[c] += f64::from(q.albedo[c].max(0.0));
        }
        n += 1;
    }
    let floor = 1e-4 * n as f64;
    if n == 0 || p.iter().chain(&a).any(|v| !(*v > floor)) {
        return None;
    }
    let g = |c: usize| ((a[c] / p[c]) as f32).clamp(0.05, 20.0);
    Some(Vec3::new(g(0), g(1), g(2)))
}

impl Default for InvertOptions {
    fn default() -> Self {
        InvertOptions {
            budget_seconds: 60.0,
            env_route: Chosen {
                entry: &routes::ENV_ROUTES[0],
                settings: Default::default(),
            },
            mat_route: Chosen {
                entry: &routes::MAT_ROUTES[0],
                settings: Default::default(),
            },
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
            denoise_render: true,
            env_only: false,
            light_guide: true,
            portals: true,
            rm_search: false,
            rm_margin: 0.1,
            level_from_pred: true,
            level_band: LEVEL_BAND,
            init_env: None,
            lamp_sites: Vec::new(),
            lamp_scale: 1.0,
            lamp_sparsity: 0.003,
            sun: false,
            sun_params: SunParams::default(),
            albedo_structure: None,
        }
    }
}

/// What one stage did, for `summary.json`.
#[derive(Clone, Debug, serde::Serialize)]
pub struct StageReport {
    pub name: String,
    pub steps: usize,
    pub loss_start: f64,
    pub loss_end: f64,
    pub stopped_early: bool,
}

impl StageReport {
    /// A stage without a loss (tracing, rendering): its name and size.
    fn plain(name: &str, steps: usize) -> StageReport {
        StageReport {
            name: name.to_string(),
            steps,
            loss_start: f64::NAN,
            loss_end: f64::NAN,
            stopped_early: false,
        }
    }

    fn fit(name: &str, trace: &FitTrace) -> StageReport {
        StageReport {
            name: name.to_string(),
            steps: trace.steps,
            loss_start: trace.losses.first().copied().unwrap_or(f64::NAN),
            loss_end: trace.losses.last().copied().unwrap_or(f64::NAN),
            stopped_early: trace.stopped_early,
        }
    }
}

#[derive(Clone, Debug, serde::Serialize)]
pub struct InvertReport {
    pub plan: Plan,
    /// In the order they ran (and were announced by [`Event::Stage`]).
    pub stages: Vec<StageReport>,
    pub cache_bytes: u64,
    pub cache_rays: u64,
    /// Loss of the frozen estimator's image for the final parameters.
    pub fit_loss: f64,
    /// What the search of R and M per segment did, when it ran.
    pub rm_search: Option<RmSearchReport>,
    /// With the level held at the prediction's: the gain per channel the
    /// light took from the albedo over the whole recovery.
    pub level_gain: Option<[f32; 3]>,
    /// The search for a sun, when it ran.
    pub sun: Option<SunReport>,
}

/// The search for a sun ([`crate::sun`]).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct SunReport {
    /// Whether the best direction explained enough to be taken for the
    /// sun.
    pub found: bool,
    /// The best direction (camera space, towards the sun).
    pub direction: [f32; 3],
    /// Share of what the ambient terms leave of the photo's light that
    /// it explained.
    pub explained: f64,
    /// The irradiance it started from (the search's) and the one fitted
    /// (found: zero), per channel.
    pub start_irradiance: [f32; 3],
    pub irradiance: [f32; 3],
}

/// The search of roughness and metallic per segment ([`crate::segments`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct RmSearchReport {
    pub segments: usize,
    /// Segments large enough to be scored.
    pub scored: usize,
    /// Segments whose anchor moved, and their pixels.
    pub moved: usize,
    pub moved_pixels: usize,
    /// Of the moved pixels, those anchored as metal.
    pub metal_pixels: usize,
}

pub struct InvertResult {
    pub materials: Vec<Material>,
    pub envmap: RgbImage,
    /// The lamps fitted at [`InvertOptions::lamp_sites`] (one per site,
    /// some possibly dark; none without sites), then the sun when one was
    /// found ([`InvertOptions::sun`]).
    pub lamps: Vec<Lamp>,
    /// The frozen estimator's image for the final parameters.
    pub fit_image: RgbImage,
    /// Independent re-render (new random numbers, box filter), denoised
    /// with [`InvertOptions::denoise_render`].
    pub rendered: RgbImage,
    /// With [`InvertOptions::denoise_render`]: the same re-render before
    /// denoising (the mean of its two halves).
    pub rendered_raw: Option<RgbImage>,
    pub report: InvertReport,
}

/// Progress events for a front end.
pub enum Event<'a> {
    /// A stage starts (`steps`: its planned size).
    Stage {
        name: &'a str,
        steps: usize,
    },
    /// The stage last announced has ended; its report is the next entry
    /// of [`InvertReport::stages`].
    StageDone,
    Step {
        step: usize,
        loss: f64,
    },
    Trace {
        done: usize,
        total: usize,
    },
    /// A fitting stage has ended: what the scene looks like now (the
    /// frozen paths under the current materials and light, `width ×
    /// height` linear RGB, filtered for viewing by
    /// [`crate::denoise::viewable`]), computed only when `image()` is
    /// called (it costs one evaluation of the paths and the filter);
    /// `after` names the stage.
    Current {
        after: &'a str,
        width: usize,
        height: usize,
        image: &'a (dyn Fn() -> Vec<Vec3> + Sync),
    },
}

#[derive(Debug, thiserror::Error)]
pub enum InvertError {
    #[error(
        "input image is {image_width}x{image_height} and predictions have {pred_pixels} pixels, \
         but the camera is {width}x{height}"
    )]
    SizeMismatch {
        image_width: usize,
        image_height: usize,
        pred_pixels: usize,
        width: usize,
        height: usize,
    },
    #[error("a starting envmap needs an envmap route that takes one; `{route}` does not")]
    StartEnvmapNotTaken { route: &'static str },
    #[error("the starting envmap is {got_width}x{got_height}; expected {width}x{height}")]
    StartEnvmapSize {
        got_width: usize,
        got_height: usize,
        width: usize,
        height: usize,
    },
    #[error("{sites} lamp sites: the `{route}` envmap route fits no lamps")]
    LampsNotFitted { sites: usize, route: &'static str },
    #[error("{sites} lamp sites for a {width}-texel-wide envmap: at most one per column")]
    TooManyLamps { sites: usize, width: usize },
    #[error("lamp scale {0} is not a positive finite length")]
    LampScale(f32),
    #[error("a sun was asked for: the `{route}` envmap route fits no lamps or suns")]
    SunNotFitted { route: &'static str },
    #[error("lamp site {index} is not a finite point")]
    LampSite { index: usize },
    #[error("tracing the frozen light paths")]
    Cache(#[from] CacheError),
    /// The caller's `stop` said so ([`invert_until`]).
    #[error("stopped: the recovery is no longer wanted")]
    Stopped,
    #[error("building the {what}")]
    Render {
        what: &'static str,
        #[source]
        source: RenderError,
    },
}

/// Materials as maps (for writing).
pub fn materials_to_maps(w: usize, h: usize, mats: &[Material]) -> MaterialMaps {
    MaterialMaps {
        albedo: Image::from_vec(w, h, mats.iter().map(|m| m.albedo).collect()),
        roughness: Image::from_vec(w, h, mats.iter().map(|m| m.roughness).collect()),
        metallic: Image::from_vec(w, h, mats.iter().map(|m| m.metallic).collect()),
        normal: None,
        transparency: None,
    }
}

/// The starting materials: the predictions, with R and M at 0.7 / 0.05
/// unless they are trusted.
fn starting_materials(pred: &[Material], opts: &InvertOptions) -> Vec<Material> {
    pred.iter()
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
        .collect()
}

/// A given starting envmap, checked and made finite and positive.
fn start_envmap(e: &RgbImage, opts: &InvertOptions) -> Result<Vec<Vec3>, InvertError> {
    let (ew, eh) = (opts.env_width, opts.env_height);
    if e.width != ew || e.height != eh {
        return Err(InvertError::StartEnvmapSize {
            got_width: e.width,
            got_height: e.height,
            width: ew,
            height: eh,
        });
    }
    Ok(e.data
        .iter()
        .map(|v| {
            let v = if v.is_finite() { *v } else { Vec3::ZERO };
            v.clamp(Vec3::splat(1e-6), Vec3::splat(1e6))
        })
        .collect())
}

/// The lamps at [`InvertOptions::lamp_sites`] lit as the light vector
/// `env` says (its entries after the envmap's texels, times the lamp
/// scale squared), then the sun in direction `sun` (the next entry, times
/// [`sun_scale`]).
fn lamps_of(env: &[Vec3], opts: &InvertOptions, sun: Option<Vec3>) -> Vec<Lamp> {
    let base = opts.env_width * opts.env_height;
    let area = opts.lamp_scale * opts.lamp_scale;
    let entry = |k: usize| env.get(base + k).copied().unwrap_or(Vec3::ZERO);
    let sites = opts.lamp_sites.len();
    opts.lamp_sites
        .iter()
        .enumerate()
        .map(|(k, &position)| Lamp::point(position, entry(k) * area))
        .chain(sun.map(|d| Lamp::sun(d, entry(sites) * sun_scale(opts.env_width, opts.env_height))))
        .collect()
}

/// The state the stages share.
struct Run<'a> {
    scene: RenderScene,
    opts: &'a InvertOptions,
    /// The sun's direction, once found.
    sun: Option<Vec3>,
    target: Target,
    pixels: Vec<u32>,
    stages: Vec<StageReport>,
    events: &'a (dyn Fn(Event) + Sync),
    stop: &'a (dyn Fn() -> bool + Sync),
    /// What each pixel sees first (geometry only: it never changes).
    guide: &'a Guide,
}

impl Run<'_> {
    /// Announces a stage, unless the caller has asked to stop.
    fn begin(&self, name: &str, steps: usize) -> Result<(), InvertError> {
        if (self.stop)() {
            return Err(InvertError::Stopped);
        }
        (self.events)(Event::Stage { name, steps });
        Ok(())
    }

    /// Shows the scene as `cache` renders it under `mats` and `env`,
    /// filtered for viewing ([`Event::Current`]).
    fn current(&self, after: &str, cache: &PathCache, mats: &[Material], env: &[Vec3]) {
        let image = || {
            let raw = transport::render(cache, mats, env);
            let albedo: Vec<Vec3> = mats.iter().map(|m| m.albedo).collect();
            let passes = matflow_render::denoise::RENDER_PASSES;
            crate::denoise::viewable(&raw, &albedo, self.guide, passes)
        };
        (self.events)(Event::Current {
            after,
            width: cache.width,
            height: cache.height,
            image: &image,
        });
    }

    fn end(&mut self, report: StageReport) {
        self.stages.push(report);
        (self.events)(Event::StageDone);
    }

    /// Lights the scene with the light vector `env` (the envmap's texels,
    /// then the lamps' entries) and shades it with `mats`.
    fn set_scene(&mut self, mats: &[Material], env: &[Vec3]) -> Result<(), InvertError> {
        let (ew, eh) = (self.opts.env_width, self.opts.env_height);
        self.scene.materials = mats.iter().map(|m| m.sanitized()).collect();
        let map =
            EnvMap::new(&Image::from_vec(ew, eh, env[..ew * eh].to_vec())).map_err(|source| {
                InvertError::Render {
                    what: "envmap",
                    source,
                }
            })?;
        self.scene.set_env(map);
        self.scene
            .set_lamps(lamps_of(env, self.opts, self.sun))
            .map_err(|source| InvertError::Render {
                what: "lamps",
                source,
            })
    }

    /// Traces `spp` frozen paths per pixel through the current scene.
    fn trace(&mut self, name: &str, spp: u32, seed: u64) -> Result<PathCache, InvertError> {
        self.begin(name, self.scene.camera.height)?;
        let events = self.events;
        let cache = PathCache::build(
            &self.scene,
            &CacheOptions {
                spp,
                max_depth: self.opts.max_depth,
                seed,
                env_width: self.opts.env_width,
                env_height: self.opts.env_height,
                lamp_scale: self.opts.lamp_scale,
            },
            &|d, t| events(Event::Trace { done: d, total: t }),
        )?;
        self.end(StageReport::plain(name, spp as usize));
        Ok(cache)
    }

    /// The best sun direction the photo shows ([`crate::sun`]), searched
    /// at up to [`SunParams::pixels`] of the envmap stages' pixels (those
    /// with a saturated channel left out), and whether it is taken for
    /// the sun.
    fn find_sun(&self, mats: &[Material], guide: &Guide) -> Option<(SunFit, bool)> {
        let (ew, eh) = (self.opts.env_width, self.opts.env_height);
        let params = &self.opts.sun_params;
        let step = self.pixels.len().div_ceil(params.pixels.max(1)).max(1);
        let pixels: Vec<SearchPixel> = self
            .pixels
            .iter()
            .step_by(step)
            .filter_map(|&i| {
                let i = i as usize;
                let (point, normal, _) = guide.hits.get(i).copied().flatten()?;
                if self.target.saturated[i].iter().any(|&s| s) {
                    return None;
                }
                let m = &mats[i];
                Some(SearchPixel {
                    point,
                    normal,
                    albedo: m.albedo * (1.0 - m.metallic) / std::f32::consts::PI,
                    light: self.target.linear[i],
                })
            })
            .collect();
        let fit = sun::search(&self.scene, &pixels, ew, eh, params)?;
        Some((fit, fit.is_sun(params)))
    }

    fn fit_env(
        &mut self,
        name: &str,
        fitter: &mut dyn EnvFitter,
        cache: &PathCache,
        mats: &[Material],
        current: &[Vec3],
        steps: usize,
    ) -> Result<Vec<Vec3>, InvertError> {
        self.begin(name, steps)?;
        let tr = EnvTransport::build(cache, mats, self.pixels.clone());
        let events = self.events;
        let (env, trace) = fitter.fit(
            &tr,
            &self.target,
            current,
            &EnvStage {
                steps,
                early_stop: self.opts.early_stop,
                lamp_sparsity: self.opts.lamp_sparsity,
            },
            &|step, loss| events(Event::Step { step, loss }),
        );
        self.end(StageReport::fit(name, &trace));
        self.current(name, cache, mats, &env);
        Ok(env)
    }
}

/// What the options ask of the envmap route (a start envmap, lamps, a
/// sun) it can do, and the lamps fit the frozen paths' limits; checked
/// before anything runs.
fn check_options(opts: &InvertOptions, env_route: &dyn EnvRoute) -> Result<(), InvertError> {
    if opts.init_env.is_some() && !env_route.takes_start_envmap() {
        return Err(InvertError::StartEnvmapNotTaken {
            route: opts.env_route.name(),
        });
    }
    let (ew, eh) = (opts.env_width, opts.env_height);
    let sites = opts.lamp_sites.len();
    if opts.sun && !env_route.fits_lamps() {
        return Err(InvertError::SunNotFitted {
            route: opts.env_route.name(),
        });
    }
    if sites > 0 || opts.sun {
        if !env_route.fits_lamps() {
            return Err(InvertError::LampsNotFitted {
                sites,
                route: opts.env_route.name(),
            });
        }
        // The frozen paths' own limits (a sun takes the entry after the
        // sites').
        let slots = sites + opts.sun as usize;
        check_lamps(slots, ew, eh, opts.lamp_scale).map_err(|e| match e {
            CacheError::Lamps { .. } => InvertError::TooManyLamps {
                sites: slots,
                width: ew,
            },
            CacheError::LampScale(s) => InvertError::LampScale(s),
            e => InvertError::Cache(e),
        })?;
        if let Some(index) = opts.lamp_sites.iter().position(|p| !p.is_finite()) {
            return Err(InvertError::LampSite { index });
        }
    }
    Ok(())
}

/// R and M per segment (`--rm-search`): segments that one albedo under
/// another (R, M) explains clearly better move their anchor in `pred` and
/// their start in `mats`.
fn rm_per_segment(
    run: &mut Run,
    (cache, env, guide): (&PathCache, &[Vec3], &Guide),
    dist: &[f32],
    pred: &mut [Material],
    mats: &mut [Material],
) -> Result<RmSearchReport, InvertError> {
    let opts = run.opts;
    let (w, h) = (run.scene.camera.width, run.scene.camera.height);
    let name = "R/M per segment";
    run.begin(name, 1)?;
    let tabs = fresh_tables(cache, mats, env, guide, opts.denoise);
    let tabs = &tabs;
    let albedo: Vec<Vec3> = pred.iter().map(|m| m.albedo).collect();
    let (labels, count) = segment(&albedo, dist, w, h, &SegmentParams::default());
    let choices = search_rm(
        tabs,
        &run.target,
        &labels,
        count,
        pred,
        1.0,
        &SearchParams {
            margin: opts.rm_margin,
            ..SearchParams::new(resolvable_roughness(opts.env_width, opts.env_height))
        },
    );
    let moved_pixels = apply(&choices, &labels, pred, mats);
    let metal = choices
        .iter()
        .filter(|c| c.moved && c.metallic > 0.5)
        .map(|c| c.pixels)
        .sum();
    run.end(StageReport::plain(name, choices.len()));
    Ok(RmSearchReport {
        segments: count,
        scored: choices.len(),
        moved: choices.iter().filter(|c| c.moved).count(),
        moved_pixels,
        metal_pixels: metal,
    })
}

/// With the albedo's level held: after a stage that fits albedo, its mean
/// per channel over `surface` goes back to within `band` of `pred`'s and
/// the light (`env`, the envmap fit's state) takes the gain, which
/// accumulates in `total`.
fn hold_level(
    mats: &mut [Material],
    pred: &[Material],
    surface: &[bool],
    band: f32,
    env: &mut [Vec3],
    env_fit: &mut dyn EnvFitter,
    total: &mut Vec3,
) {
    let over = level_gain(mats, pred, surface)
        .map(|g| g / g.clamp(Vec3::splat(1.0 - band), Vec3::splat(1.0 + band)))
        .filter(|g| *g != Vec3::ONE);
    if let Some(g) = over {
        for m in mats.iter_mut() {
            m.albedo = (m.albedo / g).clamp(Vec3::ZERO, Vec3::ONE);
        }
        for e in env.iter_mut() {
            *e *= g;
        }
        env_fit.rescale(g);
        *total *= g;
    }
}

/// After a material stage fitting `parts`: the albedo of `mats` rebuilt
/// by [`photo_structured`] from the prediction `pred` and the linear
/// photo, and roughness and metallic moved per surface
/// ([`rm_per_surface`], down to the renderer's floor).
fn restructure(
    mats: &mut [Material],
    pred: &[Material],
    photo: &[Vec3],
    (surfaces, p): (&Surfaces, &StructureParams),
    parts: Parts,
    (w, h): (usize, usize),
) {
    if parts.albedo {
        let solved: Vec<Vec3> = mats.iter().map(|m| m.albedo).collect();
        let predicted: Vec<Vec3> = pred.iter().map(|m| m.albedo).collect();
        let rebuilt = photo_structured(&solved, &predicted, photo, surfaces, (w, h), p);
        for (m, a) in mats.iter_mut().zip(rebuilt) {
            m.albedo = a;
        }
    }
    if parts.roughness || parts.metallic {
        rm_per_surface(mats, pred, surfaces, matflow_render::bsdf::MIN_ROUGHNESS);
    }
}

/// The independent re-render of the recovered scene (fresh random
/// numbers), denoised when asked: the image and, denoised, the same
/// samples unfiltered.
fn final_render(
    run: &mut Run,
    guide: &Guide,
    final_spp: u32,
) -> Result<(RgbImage, Option<RgbImage>), InvertError> {
    let (opts, events) = (run.opts, run.events);
    run.begin("render", run.scene.camera.height)?;
    let render_opts = RenderOptions {
        spp: final_spp,
        max_depth: opts.max_depth,
        glass_depth: matflow_render::integrator::DEFAULT_GLASS_DEPTH,
        seed: opts.seed ^ 0xf1_4a1,
        filter: FIT_FILTER,
        reference_compat: false,
        tile_size: 16,
        crop: None,
    };
    let trace = |d: usize, t: usize| events(Event::Trace { done: d, total: t });
    let denoised = opts
        .denoise_render
        .then(|| {
            let passes = matflow_render::denoise::RENDER_PASSES;
            matflow_render::denoise::render_denoised(
                &run.scene,
                guide,
                &render_opts,
                passes,
                &trace,
            )
        })
        .flatten();
    let out = match denoised {
        Some(d) => (d.image, Some(d.raw)),
        None => (
            matflow_render::render_until(&run.scene, &render_opts, &trace, run.stop)
                .ok_or(InvertError::Stopped)?
                .image,
            None,
        ),
    };
    if (run.stop)() {
        return Err(InvertError::Stopped);
    }
    run.end(StageReport::plain("render", final_spp as usize));
    Ok(out)
}

/// The sun stage: searches the photo's light and shadow for a sun the
/// scout's envmap `env` shows and, where one is taken, moves its power
/// from the texels into a distant lamp (the entry after the sites'). Its
/// report, and the shadow rays per path it adds (to re-plan with).
fn sun_stage(
    run: &mut Run,
    mats: &[Material],
    guide: &Guide,
    env: &mut Vec<Vec3>,
    scout: &PathCache,
) -> Result<(Option<SunReport>, Option<f64>), InvertError> {
    let opts = run.opts;
    let (ew, eh, sites) = (opts.env_width, opts.env_height, opts.lamp_sites.len());
    run.begin("sun", 1)?;
    let found = run.find_sun(mats, guide);
    let report = found.as_ref().map(|(fit, taken)| SunReport {
        found: *taken,
        direction: fit.direction.to_array(),
        explained: fit.explained,
        start_irradiance: fit.irradiance.to_array(),
        irradiance: [0.0; 3],
    });
    let mut extra_rays = None;
    if let Some((fit, true)) = found {
        // The scout had spread the sun into the brightest texels.
        let mut lit = sun::baseline(env, ew, eh, opts.sun_params.quantile);
        lit.extend_from_slice(&env[ew * eh..ew * eh + sites]);
        lit.push(fit.irradiance / sun_scale(ew, eh));
        lit.resize(light_len(ew, eh, sites + 1), Vec3::ZERO);
        *env = lit;
        run.sun = Some(fit.direction);
        // One more shadow ray per vertex.
        let n = (scout.width * scout.height * scout.spp.max(1) as usize).max(1) as f64;
        extra_rays = Some(scout.stats.vertices as f64 / n);
    }
    run.end(StageReport::plain("sun", run.sun.is_some() as usize));
    Ok((report, extra_rays))
}

/// Recovers envmap and materials. `scene` carries camera and geometry (its
/// materials and envmap are replaced); `target` is the linear input image;
/// `pred` the predicted materials.
pub fn invert(
    scene: RenderScene,
    target_linear: &RgbImage,
    pred: &[Material],
    opts: &InvertOptions,
    events: &(dyn Fn(Event) + Sync),
) -> Result<InvertResult, InvertError> {
    invert_until(scene, target_linear, pred, opts, events, &|| false)
}

/// [`invert`], asking `stop()` before each of its stages and the final
/// render's tiles: once it says yes, the recovery ends with
/// [`InvertError::Stopped`]. Never stopped, the result is [`invert`]'s.
pub fn invert_until(
    mut scene: RenderScene,
    target_linear: &RgbImage,
    pred: &[Material],
    opts: &InvertOptions,
    events: &(dyn Fn(Event) + Sync),
    stop: &(dyn Fn() -> bool + Sync),
) -> Result<InvertResult, InvertError> {
    let (w, h) = (scene.camera.width, scene.camera.height);
    let npix = w * h;
    if target_linear.width != w || target_linear.height != h || pred.len() != npix {
        return Err(InvertError::SizeMismatch {
            image_width: target_linear.width,
            image_height: target_linear.height,
            pred_pixels: pred.len(),
            width: w,
            height: h,
        });
    }
    // Every scene is built guided where it gains from it.
    if !opts.light_guide {
        scene.set_light_guide(None);
    }
    if !opts.portals {
        scene.portals = Default::default();
    }
    let env_route = opts.env_route.build();
    let mat_route = opts.mat_route.build();
    check_options(opts, &*env_route)?;
    let (ew, eh) = (opts.env_width, opts.env_height);
    let sites = opts.lamp_sites.len();
    // The light vector: the envmap's texels, then (with lamp sites) the
    // lamps' entries and their padding (zero).
    let lights = light_len(ew, eh, sites);
    let with_lamps = |mut texels: Vec<Vec3>, lamp: Vec3| {
        texels.resize(ew * eh, Vec3::ZERO);
        texels.extend((0..lights - ew * eh).map(|k| if k < sites { lamp } else { Vec3::ZERO }));
        texels
    };
    let given_env = opts
        .init_env
        .as_ref()
        .map(|e| start_envmap(e, opts))
        .transpose()?;
    let plan_for = |scene| {
        Plan::from_budget(
            opts.budget_seconds,
            npix,
            scene,
            opts,
            &*env_route,
            &*mat_route,
        )
    };
    // Counts before the scout has measured the scene's rays per path;
    // only the scout's sample count and the envmap stages' settings
    // (which do not depend on the scene's rays) are taken from it.
    let guided = scene.light_visibility.is_some();
    let portals = !scene.portals.is_empty();
    let first = plan_for(SceneCost::default().guided(guided).with_portals(portals));
    let pred = starting_materials(pred, opts);
    let mut mats = pred.clone();
    // What each pixel sees first (geometry only: it never changes).
    let guide = Guide::build(&scene);
    let mut run = Run {
        scene,
        opts,
        sun: None,
        target: Target::new(w, h, &target_linear.data),
        pixels: strided_pixels(w, h, first.env_stride),
        stages: Vec::new(),
        events,
        stop,
        guide: &guide,
    };

    // 1. Scout.
    let flat = with_lamps(vec![Vec3::ONE; ew * eh], Vec3::ONE);
    run.set_scene(&mats, &flat)?;
    let scout = run.trace("trace scout", first.scout_spp, opts.seed ^ 0x5c0u64)?;
    let scout_cost = SceneCost::of(&scout).guided(guided).with_portals(portals);
    let mut plan = Plan {
        scout_spp: first.scout_spp,
        ..plan_for(scout_cost)
    };
    let exposure = {
        let tr = EnvTransport::build(&scout, &mats, run.pixels.clone());
        exposure_scale(&tr, &target_linear.data, &flat)
    };
    let mut env_fit = env_route.start(&EnvStart {
        width: ew,
        height: eh,
        exposure,
        seed: opts.seed,
        trust_rm: opts.trust_rm,
    });
    let mut env = match given_env {
        Some(e) => with_lamps(e, Vec3::splat(exposure)),
        None => {
            let init: Vec<Vec3> = flat.iter().map(|e| *e * exposure).collect();
            let steps = plan.env_steps;
            run.fit_env("envmap (scout)", &mut *env_fit, &scout, &mats, &init, steps)?
        }
    };
    // The sun, where the scout's envmap shows one: a distant lamp in the
    // entry after the sites', its power taken out of the texels; found,
    // it costs one more shadow ray per vertex.
    let mut sun_report = None;
    if opts.sun {
        let (report, extra_rays) = sun_stage(&mut run, &mats, &guide, &mut env, &scout)?;
        sun_report = report;
        if let Some(x) = extra_rays {
            plan = Plan {
                scout_spp: first.scout_spp,
                ..plan_for(scout_cost.with_extra_rays(x))
            };
        }
    }
    drop(scout);

    // 2. Main trace.
    run.set_scene(&mats, &env)?;
    let cache = run.trace("trace", plan.spp, opts.seed)?;

    // R and M per segment: moves the anchor (and the start) of segments
    // that one albedo under another (R, M) explains clearly better.
    // With the level held (below), the light takes the albedo's gain.
    let mut level_total = (opts.level_from_pred && !opts.env_only).then_some(Vec3::ONE);
    // What each pixel sees first, for the segments, the level and the
    // albedo's structure (traced once, only when one of them runs).
    let structure = opts.albedo_structure.filter(|_| !opts.env_only);
    let dist = if opts.searches_rm() || level_total.is_some() || structure.is_some() {
        run.scene.primary_distances()
    } else {
        Vec::new()
    };
    let mut pred = pred;
    let structure = structure.map(|sp| {
        let albedo: Vec<Vec3> = pred.iter().map(|m| m.albedo).collect();
        (sp, Surfaces::new(&albedo, &dist, w, h, &sp))
    });
    let rm_search = opts.searches_rm().then(|| {
        rm_per_segment(
            &mut run,
            (&cache, &env, &guide),
            &dist,
            &mut pred,
            &mut mats,
        )
    });
    let rm_search = rm_search.transpose()?;

    // 3. Alternation. With the level held, after each stage that fits
    // albedo its mean per channel goes back to the prediction's (past the
    // band) and the light takes the gain.
    let surface = surface_pixels(&dist);
    let band = opts.level_band.clamp(0.0, MAX_LEVEL_BAND as f32);
    let mut mat_fit = (!opts.env_only).then(|| {
        mat_route.start(&MatStart {
            width: w,
            height: h,
            pred: &pred,
            seed: opts.seed,
            budget_seconds: opts.budget_seconds,
            env_width: ew,
            env_height: eh,
        })
    });
    for l in 0..plan.loops {
        let name = format!("envmap {}", l + 1);
        env = run.fit_env(&name, &mut *env_fit, &cache, &mats, &env, plan.env_steps)?;
        let Some(mat_fit) = mat_fit.as_mut() else {
            continue;
        };
        for &parts in mat_route.stages() {
            let name = format!("materials {} {}", parts.name(), l + 1);
            run.begin(&name, plan.mat_steps)?;
            let tabs = fresh_tables(&cache, &mats, &env, &guide, opts.denoise);
            let fit = mat_fit.fit(
                &tabs,
                &run.target,
                &pred,
                &mats,
                &MatStage {
                    parts,
                    steps: plan.mat_steps,
                    loop_index: l,
                    delta: opts.delta,
                    zeta: opts.zeta,
                    early_stop: opts.early_stop,
                    rescale: opts.rescale,
                },
                &|step, loss| events(Event::Step { step, loss }),
            );
            mats = fit.materials;
            if let Some((sp, surfaces)) = structure.as_ref() {
                let photo = &run.target.linear;
                restructure(&mut mats, &pred, photo, (surfaces, sp), parts, (w, h));
            }
            for e in env.iter_mut() {
                *e *= fit.scale;
            }
            env_fit.rescale(Vec3::splat(fit.scale));
            if let Some(total) = level_total.as_mut().filter(|_| parts.albedo) {
                hold_level(
                    &mut mats,
                    &pred,
                    &surface,
                    band,
                    &mut env,
                    &mut *env_fit,
                    total,
                );
            }
            run.end(StageReport::fit(&name, &fit.trace));
            run.current(&name, &cache, &mats, &env);
        }
    }
    // 4. Final envmap for the final materials.
    env = run.fit_env(
        "envmap final",
        &mut *env_fit,
        &cache,
        &mats,
        &env,
        plan.env_steps,
    )?;

    let fit = transport::render(&cache, &mats, &env);
    let (fit_loss, _) = loss_and_grad(&fit, &run.target, None);
    let (cache_bytes, cache_rays) = (cache.stats.bytes, cache.stats.rays);
    drop(cache);

    // 5. Independent re-render.
    run.set_scene(&mats, &env)?;
    let (rendered, rendered_raw) = final_render(&mut run, &guide, plan.final_spp)?;
    let lamps = lamps_of(&env, opts, run.sun);
    if let (Some(r), Some(sun)) = (sun_report.as_mut(), lamps.last()) {
        if r.found {
            r.irradiance = sun.intensity.to_array();
        }
    }
    env.truncate(ew * eh);
    Ok(InvertResult {
        materials: mats,
        envmap: Image::from_vec(ew, eh, env),
        lamps,
        fit_image: Image::from_vec(w, h, fit),
        rendered,
        rendered_raw,
        report: InvertReport {
            plan,
            stages: run.stages,
            cache_bytes,
            cache_rays,
            fit_loss: fit_loss.total(),
            rm_search,
            level_gain: level_total.map(|g| g.to_array()),
            sun: sun_report,
        },
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::routes::{env_route, mat_route};
    use crate::testutil::{materials_of, room};

    fn with_albedo(m: &Material, a: Vec3) -> Material {
        Material { albedo: a, ..*m }
    }

    #[test]
    fn level_gain_is_the_ratio_of_channel_means_over_surfaces() {
        let base = Material {
            albedo: Vec3::splat(0.4),
            roughness: 0.5,
            metallic: 0.0,
        };
        let pred = vec![base; 4];
        let mut mats: Vec<Material> = pred
            .iter()
            .map(|m| with_albedo(m, m.albedo * Vec3::new(2.0, 1.0, 0.5)))
            .collect();
        // A pixel without a surface (a window's sky) does not count.
        mats[3].albedo = Vec3::ONE;
        let surface = [true, true, true, false];
        let g = level_gain(&mats, &pred, &surface).expect("defined");
        assert!(
            (g - Vec3::new(2.0, 1.0, 0.5)).abs().max_element() < 1e-6,
            "{g}"
        );
        // Undefined without surfaces or with a black channel.
        assert_eq!(level_gain(&mats, &pred, &[false; 4]), None);
        let black: Vec<Material> = pred
            .iter()
            .map(|m| with_albedo(m, Vec3::new(0.4, 0.0, 0.4)))
            .collect();
        assert_eq!(level_gain(&mats, &black, &surface), None);
    }

    /// With the level held, the recovered albedo keeps the prediction's
    /// mean per channel and the light takes the gain. The photo has a
    /// shadow the mesh cannot cast (its left half at 30 % of the light, as
    /// from an occluder out of view), which a free fit paints into the
    /// albedo, darkening its level; held, the level stays the
    /// prediction's and the photo is explained about as well. Within a
    /// band wider than that drift, nothing is held.
    #[test]
    fn a_held_level_moves_the_gain_into_the_light() {
        let n = 24;
        let t = room(3, n);
        let mut target = matflow_render::render(
            &t.scene,
            &RenderOptions {
                spp: 16,
                ..Default::default()
            },
            &|_, _| {},
        )
        .image;
        for (p, v) in target.data.iter_mut().enumerate() {
            if p % n < n / 2 {
                *v *= 0.3;
            }
        }
        let pred = materials_of(&t.maps);
        let opts = |held, band| InvertOptions {
            budget_seconds: 2.0,
            env_route: env_route("texel", &[]).expect("env route"),
            mat_route: mat_route("solve", &[]).expect("mat route"),
            spp: Some(8),
            final_spp: Some(8),
            loops: Some(2),
            env_steps: Some(60),
            mat_steps: Some(60),
            level_from_pred: held,
            level_band: band,
            ..Default::default()
        };
        let run = |held, band| {
            invert(room(3, n).scene, &target, &pred, &opts(held, band), &|_| {}).expect("invert")
        };
        let (free, held) = (run(false, 0.0), run(true, 0.0));
        assert_eq!(free.report.level_gain, None);
        let g = Vec3::from(held.report.level_gain.expect("reported"));
        assert!(g.is_finite() && g.min_element() > 0.0, "{g}");
        let surface = surface_pixels(&t.scene.primary_distances());
        let left = level_gain(&held.materials, &pred, &surface).expect("defined");
        let drift = level_gain(&free.materials, &pred, &surface).expect("defined");
        // Free, the fit darkens the level (else this test could not fail).
        assert!(drift.max_element() < 0.93, "{drift}");
        // Only albedos clamped at 1 keep it from being exactly 1.
        assert!((left - Vec3::ONE).abs().max_element() < 0.02, "{left}");
        // Within a band wider than the drift nothing is held: the same
        // recovery as free, bit for bit.
        let banded = run(true, 0.5);
        assert_eq!(banded.materials, free.materials);
        assert_eq!(banded.envmap.data, free.envmap.data);
        assert!(
            held.report.fit_loss < 1.25 * free.report.fit_loss,
            "held {} free {}",
            held.report.fit_loss,
            free.report.fit_loss
        );
    }

    /// A watched recovery: after each fitting stage it offers the fit so
    /// far, the frozen paths' image filtered for viewing (closer to the
    /// photo at the end than after the scout; the last is the result's
    /// `fit_image`, filtered);
    /// watching changes
    /// nothing of the result; asked to stop, it ends before its next stage.
    #[test]
    fn a_recovery_shows_its_fit_and_stops_when_asked() {
        let n = 16;
        let t = room(3, n);
        let target = matflow_render::render(
            &t.scene,
            &RenderOptions {
                spp: 8,
                ..Default::default()
            },
            &|_, _| {},
        )
        .image;
        let pred = materials_of(&t.maps);
        let opts = InvertOptions {
            budget_seconds: 1.0,
            env_route: env_route("texel", &[]).expect("env route"),
            mat_route: mat_route("solve", &[]).expect("mat route"),
            spp: Some(4),
            final_spp: Some(4),
            loops: Some(1),
            env_steps: Some(30),
            mat_steps: Some(20),
            ..Default::default()
        };
        let shots = std::sync::Mutex::new(Vec::<(String, Vec<Vec3>)>::new());
        let watched = invert(room(3, n).scene, &target, &pred, &opts, &|e| {
            if let Event::Current {
                after,
                width,
                height,
                image,
            } = e
            {
                assert_eq!((width, height), (n, n));
                shots.lock().unwrap().push((after.to_string(), image()));
            }
        })
        .expect("invert");
        let shots = shots.into_inner().unwrap();
        let names: Vec<&str> = shots.iter().map(|(a, _)| a.as_str()).collect();
        assert_eq!(names.first(), Some(&"envmap (scout)"));
        assert_eq!(names.last(), Some(&"envmap final"));
        assert!(
            names.iter().any(|a| a.starts_with("materials")),
            "{names:?}"
        );
        // The last is the result's fit, filtered for viewing.
        let albedo: Vec<Vec3> = watched.materials.iter().map(|m| m.albedo).collect();
        let guide = Guide::build(&room(3, n).scene);
        let passes = matflow_render::denoise::RENDER_PASSES;
        let viewed = crate::denoise::viewable(&watched.fit_image.data, &albedo, &guide, passes);
        assert_eq!(shots.last().unwrap().1, viewed);
        let err = |img: &[Vec3]| -> f64 {
            img.iter()
                .zip(&target.data)
                .map(|(a, b)| (*a - *b).length_squared() as f64)
                .sum()
        };
        let (first, last) = (err(&shots[0].1), err(&shots.last().unwrap().1));
        assert!(last < first, "first {first} last {last}");
        let plain = invert(room(3, n).scene, &target, &pred, &opts, &|_| {}).expect("invert");
        assert_eq!(plain.materials, watched.materials);
        assert_eq!(plain.rendered.data, watched.rendered.data);
        // Stopped once the first fit was shown: nothing more runs.
        let stages = std::sync::Mutex::new(Vec::<String>::new());
        let shown = std::sync::atomic::AtomicBool::new(false);
        let r = invert_until(
            room(3, n).scene,
            &target,
            &pred,
            &opts,
            &|e| match e {
                Event::Stage { name, .. } => stages.lock().unwrap().push(name.into()),
                Event::Current { .. } => shown.store(true, std::sync::atomic::Ordering::SeqCst),
                _ => {}
            },
            &|| shown.load(std::sync::atomic::Ordering::SeqCst),
        );
        assert!(matches!(r, Err(InvertError::Stopped)), "{:?}", r.err());
        assert_eq!(
            stages.into_inner().unwrap(),
            ["trace scout", "envmap (scout)"]
        );
    }

    /// A quick fit of the light alone (envmap only, the texel route, the
    /// materials trusted), as the light tests run it.
    fn light_fit() -> InvertOptions {
        InvertOptions {
            budget_seconds: 2.0,
            env_route: env_route("texel", &[]).expect("env route"),
            mat_route: mat_route("solve", &[]).expect("mat route"),
            trust_rm: true,
            env_only: true,
            spp: Some(16),
            final_spp: Some(8),
            loops: Some(2),
            env_steps: Some(150),
            mat_steps: Some(10),
            ..Default::default()
        }
    }

    /// The sun is found and fitted: a room lit by a dim uniform sky and a
    /// sun is recovered (materials known) with a sun within 10°
    /// of the true one at about its irradiance, explaining the image
    /// better than the texels alone; lit by the sky alone, no sun is
    /// found; a route that fits no lamps refuses to look for one.
    #[test]
    fn a_sun_is_found_where_the_sky_has_one() {
        let n = 64;
        let sky = Image::from_vec(32, 16, vec![Vec3::new(0.25, 0.3, 0.4); 32 * 16]);
        let scene = || {
            let mut s = room(5, n).scene;
            s.set_env(EnvMap::new(&sky).unwrap());
            s
        };
        let truth = Vec3::new(-0.6, 0.7, 0.2).normalize();
        let irradiance = Vec3::new(3.0, 2.7, 2.2);
        let pred = materials_of(&room(5, n).maps);
        let target_with = |sun: bool| {
            let mut s = scene();
            if sun {
                s.set_lamps(vec![Lamp::sun(truth, irradiance)]).unwrap();
            }
            matflow_render::render(
                &s,
                &RenderOptions {
                    spp: 64,
                    ..Default::default()
                },
                &|_, _| {},
            )
            .image
        };
        let opts = |sun: bool| InvertOptions { sun, ..light_fit() };
        let run = |target: &RgbImage, sun: bool| {
            invert(scene(), target, &pred, &opts(sun), &|_| {}).expect("invert")
        };
        let lit = target_with(true);
        let with = run(&lit, true);
        let without = run(&lit, false);
        let found = with.report.sun.expect("a sun");
        assert!(found.found, "{found:?}");
        let d = Vec3::from(found.direction);
        assert!(
            d.dot(truth) > 10f32.to_radians().cos(),
            "found {d} ({found:?}) for {truth}"
        );
        let sun = with.lamps.last().expect("the sun is a lamp");
        assert!(sun.is_distant() && with.lamps.len() == 1);
        let ratio = sun.intensity / irradiance;
        assert!(
            ratio.min_element() > 0.6 && ratio.max_element() < 1.5,
            "fitted {} for {irradiance}",
            sun.intensity
        );
        assert!(without.report.sun.is_none() && without.lamps.is_empty());
        assert!(
            with.report.fit_loss < 0.8 * without.report.fit_loss,
            "with the sun {} without {}",
            with.report.fit_loss,
            without.report.fit_loss
        );
        // The sky alone: nothing to find.
        let overcast = run(&target_with(false), true);
        assert!(
            overcast.report.sun.is_none_or(|s| !s.found),
            "{:?}",
            overcast.report.sun
        );
        assert!(overcast.lamps.is_empty());
        // Looking for a sun needs a route that fits lamps.
        let mlp = InvertOptions {
            env_route: env_route("mlp", &[]).expect("env route"),
            ..opts(true)
        };
        assert!(matches!(
            invert(scene(), &lit, &pred, &mlp, &|_| {}),
            Err(InvertError::SunNotFitted { .. })
        ));
    }

    /// Lamps are fitted with the envmap: a room lit by its envmap and a
    /// lamp at one of two sites is recovered (materials known) with the
    /// lamp at about its intensity and the other site dark, explaining the
    /// image better than the envmap alone can; lit by its envmap alone,
    /// the sparsity prior keeps both sites dark.
    #[test]
    fn a_lamp_is_found_at_its_site_and_nowhere_else() {
        let n = 24;
        let t = room(3, n);
        let depth = t.scene.mesh.positions.iter().map(|p| -p.z).sum::<f32>()
            / t.scene.mesh.positions.len() as f32;
        let sites = vec![
            Vec3::new(0.3 * depth, 0.25 * depth, -0.5 * depth),
            Vec3::new(-0.3 * depth, -0.2 * depth, -0.3 * depth),
        ];
        let truth = Vec3::new(1.5, 1.2, 0.8) * depth * depth;
        let pred = materials_of(&t.maps);
        let target_with = |lamp: bool| {
            let mut scene = room(3, n).scene;
            if lamp {
                scene.set_lamps(vec![Lamp::point(sites[0], truth)]).unwrap();
            }
            matflow_render::render(
                &scene,
                &RenderOptions {
                    spp: 64,
                    ..Default::default()
                },
                &|_, _| {},
            )
            .image
        };
        let opts = |sites: Vec<Vec3>| InvertOptions {
            lamp_sites: sites,
            lamp_scale: depth,
            ..light_fit()
        };
        let run = |target: &RgbImage, sites: Vec<Vec3>| {
            invert(room(3, n).scene, target, &pred, &opts(sites), &|_| {}).expect("invert")
        };
        let lit = target_with(true);
        let with = run(&lit, sites.clone());
        let without = run(&lit, Vec::new());
        assert_eq!(with.lamps.len(), 2);
        assert!(without.lamps.is_empty());
        let ratio = with.lamps[0].intensity / truth;
        assert!(
            ratio.min_element() > 0.8 && ratio.max_element() < 1.2,
            "found {} for {truth}",
            with.lamps[0].intensity
        );
        assert!(
            with.lamps[1].intensity.element_sum() < 0.05 * truth.element_sum(),
            "the empty site lights: {}",
            with.lamps[1].intensity
        );
        assert!(
            with.report.fit_loss < 0.7 * without.report.fit_loss,
            "with lamps {} without {}",
            with.report.fit_loss,
            without.report.fit_loss
        );
        // No lamp in the room: the sites stay dark.
        let dark = run(&target_with(false), sites.clone());
        for l in &dark.lamps {
            assert!(
                l.intensity.element_sum() < 0.1 * truth.element_sum(),
                "a lamp where there is none: {}",
                l.intensity
            );
        }
        // Fitting lamps needs a route that fits them.
        let mlp = InvertOptions {
            env_route: env_route("mlp", &[]).expect("env route"),
            ..opts(sites.clone())
        };
        assert!(matches!(
            invert(room(3, n).scene, &lit, &pred, &mlp, &|_| {}),
            Err(InvertError::LampsNotFitted { .. })
        ));
        // Sites and scale are checked before anything runs.
        let bad = |o: InvertOptions| invert(room(3, n).scene, &lit, &pred, &o, &|_| {}).err();
        let mut nan = sites.clone();
        nan[1].y = f32::NAN;
        assert!(matches!(
            bad(opts(nan)),
            Some(InvertError::LampSite { index: 1 })
        ));
        assert!(matches!(
            bad(InvertOptions {
                lamp_scale: 0.0,
                ..opts(sites.clone())
            }),
            Some(InvertError::LampScale(_))
        ));
        assert!(matches!(
            bad(opts(vec![sites[0]; 33])),
            Some(InvertError::TooManyLamps {
                sites: 33,
                width: 32
            })
        ));
    }
}
