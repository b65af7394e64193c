//! `matflow invert`: recover envmap and materials from a bundle and write
//! the reference's `best_results/` layout plus `summary.json`.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::Args;
use glam::Vec3;
use indicatif::{ProgressBar, ProgressStyle};
use matflow_geom::{MeshParams, Silhouettes};
use matflow_inverse::invert::{invert, materials_to_maps, Event, InvertOptions, InvertResult};
use matflow_render::{scene_from_depth, EnvMap, RenderScene};
use matflow_scene::metrics::{mse_gamma, psnr_gamma, ssim_gamma};
use matflow_scene::{io, Bundle, Image, MaterialMaps, MaterialSource, RgbImage};

use crate::routes::RouteArgs;

#[derive(Args, Clone)]
pub struct InvertArgs {
    /// Input bundle: gt_image.exr (or .png), predictions, depth.
    #[arg(long)]
    pub bundle: PathBuf,
    /// Output bundle; gets best_results/, the geometry inputs and
    /// summary.json.
    #[arg(long)]
    pub out: PathBuf,
    /// The envmap and material routes and their options.
    #[command(flatten)]
    pub routes: RouteArgs,
    /// The options `invert` shares with the `material_opt` stage, declared
    /// by that kind (`--budget-seconds`, `--trust-rm`, `--delta`,
    /// `--loops`, `--albedo-level`, `--albedo-level-band`).
    #[command(flatten)]
    pub recovery: RecoveryFlags,
    /// Where the starting materials come from: the predictions (`pred`)
    /// or, on synthetic bundles, `ground_truth`.
    #[arg(long, default_value = "pred")]
    pub materials: MaterialSource,
    /// Recover only the envmap; materials stay at --materials as given.
    #[arg(long)]
    pub env_only: bool,
    /// Paths per pixel of the frozen cache (default: from the budget).
    #[arg(long)]
    pub spp: Option<u32>,
    /// Samples per pixel of the final re-render (default: from the budget).
    #[arg(long)]
    pub final_spp: Option<u32>,
    /// Maximum steps per optimisation stage (default: from the budget).
    #[arg(long)]
    pub steps: Option<usize>,
    /// Maximum path depth in ray segments.
    #[arg(long, default_value_t = 4)]
    pub depth: u32,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Mesh boundary angle threshold in degrees.
    #[arg(long, default_value_t = 6.0)]
    pub mesh_angle: f64,
    /// The near side of a depth discontinuity (see `mesh --silhouettes`):
    /// kept or reference.
    #[arg(long, default_value_t = Silhouettes::Kept)]
    pub silhouettes: Silhouettes,
    /// Geometry past the frame (see `render --complete`): auto, room,
    /// closed, planes, or none (the depth mesh alone). Auto tests each
    /// with the predicted maps under the sky the photo shows, and takes
    /// room where it shows none open (only through openings: under a
    /// lintel, or framed by one wall) or where the least assuming needs
    /// ten times the light of that sky (measured per kind of scene in
    /// docs/results/completion.md). Default: the completion the bundle declares
    /// for its own geometry (geometry.json, which `matflow synth`
    /// writes), otherwise auto. `render` on the result uses the same
    /// unless told otherwise.
    #[arg(long)]
    pub complete: Option<crate::commands::CompleteArg>,
    /// À-trous denoising passes over the per-pixel tables (0: off).
    #[arg(long, default_value_t = 3)]
    pub denoise: usize,
    /// Denoise the independent re-render (`best_results/rendered_img`):
    /// two halves of its samples, albedo-demodulated, edge-aware à-trous
    /// filtered (on); off writes the render as it comes. With on,
    /// `rendered_raw.exr` is the same samples unfiltered.
    #[arg(long, default_value = "on")]
    pub denoise_render: crate::commands::OnOff,
    /// Do not normalise the render's mean in material stages.
    #[arg(long)]
    pub no_rescale: bool,
    /// Guide light samples by what each region of the scene sees of the
    /// sky (on), or sample the envmap by radiance alone (off).
    #[arg(long, default_value = "on")]
    pub light_guide: crate::commands::OnOff,
    /// Aim light samples at the windows of a closed room's assumed walls
    /// too (portals; on), or follow the envmap's density alone (off).
    #[arg(long, default_value = "on")]
    pub portals: crate::commands::OnOff,
    /// Search roughness and metallic per segment (one albedo per segment
    /// under a grid of R and M) before the per-pixel solve, moving the
    /// anchor where that explains the photo clearly better (on); off (the
    /// default) keeps the prediction's anchor. Only when R and M are not
    /// trusted.
    #[arg(long, default_value = "off")]
    pub rm_search: crate::commands::OnOff,
    /// How much better (relative loss) a segment's best (R, M) must
    /// explain it than the prediction's for the anchor to move.
    #[arg(long, default_value_t = 0.1, value_parser = margin_in_range)]
    pub rm_margin: f64,
    /// Lamps the view does not show, in a room the completion closed
    /// (`--complete room` or `closed`): `on` fits point lights at a grid
    /// of sites under its ceiling with the envmap (texel route; a
    /// sparsity prior keeps the ones the photo does not need dark),
    /// written to best_results/lamps.json; `off` lights the room by the
    /// envmap alone.
    #[arg(long, default_value = "off")]
    pub lamps: crate::commands::OnOff,
    /// With `--lamps on`: weight of the lamps' sparsity prior (their
    /// entries' sum over the envmap's mean texel); 0 lets the photo alone
    /// decide.
    #[arg(long, default_value_t = 0.003)]
    pub lamp_sparsity: f32,
    /// The sun: `on` searches the photo's light and shadow, after the
    /// scout, for a sun direction that explains them and, where one does,
    /// fits it as a distant light beside the texels (texel route);
    /// written to best_results/lamps.json. Scenes where none does are
    /// recovered as with `off`.
    #[arg(long, default_value = "off")]
    pub sun: crate::commands::OnOff,
    /// Disable early stopping (run every stage for its full step count).
    #[arg(long)]
    pub no_early_stop: bool,
    /// Hide the progress bar.
    #[arg(long)]
    pub quiet: bool,
}

/// Metrics of an image against the input, in sRGB (γ 2.2, clipped).
#[derive(Clone, Copy, Debug, serde::Serialize)]
pub struct ImageMetrics {
    pub psnr: f64,
    pub ssim: f64,
    pub mse: f64,
}

pub fn image_metrics(a: &RgbImage, b: &RgbImage) -> ImageMetrics {
    ImageMetrics {
        psnr: psnr_gamma(a, b),
        ssim: ssim_gamma(a, b),
        mse: mse_gamma(a, b),
    }
}

/// Peak resident memory of this process (Linux), in bytes.
pub fn peak_memory_bytes() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

/// Everything `invert` reads from a bundle.
pub struct InvertInput {
    pub depth: matflow_scene::GrayImage,
    pub maps: MaterialMaps,
    pub target: RgbImage,
    pub scene: RenderScene,
    /// What the completion did (lamp sites, the room's height).
    pub completion: matflow_geom::Completion,
}

pub fn load_input(
    dir: &Path,
    source: MaterialSource,
    mesh: MeshParams,
    complete: Option<&matflow_geom::CompleteParams>,
) -> Result<InvertInput> {
    let bundle = Bundle::open(dir)?;
    let target = bundle.load_gt_image()?;
    let depth = bundle.load_depth()?;
    let maps = bundle.load_materials(source)?;
    if !target.same_size(&depth) || maps.width() != depth.width || maps.height() != depth.height {
        bail!(
            "{}: gt_image is {}x{}, depth {}x{}, predictions {}x{}; they must agree",
            dir.display(),
            target.width,
            target.height,
            depth.width,
            depth.height,
            maps.width(),
            maps.height()
        );
    }
    let flat = Image::new(32, 16, Vec3::ONE);
    let (scene, _, completion) =
        scene_from_depth(&depth, &maps, EnvMap::new(&flat)?, mesh, complete)
            .with_context(|| format!("{}: building the scene", dir.display()))?;
    Ok(InvertInput {
        depth,
        maps,
        target,
        scene,
        completion,
    })
}

/// A number in [0, `hi`), or a message saying it is not.
fn below(s: &str, hi: f64) -> Result<f64, String> {
    let v: f64 = s.parse().map_err(|e| format!("{e}"))?;
    if (0.0..hi).contains(&v) {
        Ok(v)
    } else {
        Err(format!("{v} is not in [0, {hi})"))
    }
}

fn margin_in_range(s: &str) -> Result<f64, String> {
    below(s, 1.0)
}

/// `material_opt`'s parameters that `invert` takes as flags.
const RECOVERY: &[&str] = &[
    "budget_seconds",
    "trust_rm",
    "delta",
    "loops",
    "albedo_level",
    "albedo_level_band",
];

/// `invert`'s flags declared by the `material_opt` kind, as the stage's
/// validated parameters.
#[derive(Clone, Debug)]
pub struct RecoveryFlags(pub matflow_engine::node::Params);

impl clap::FromArgMatches for RecoveryFlags {
    fn from_arg_matches(m: &clap::ArgMatches) -> Result<Self, clap::Error> {
        crate::stage_flags::params(m, "material_opt", RECOVERY).map(RecoveryFlags)
    }
    fn update_from_arg_matches(&mut self, m: &clap::ArgMatches) -> Result<(), clap::Error> {
        *self = Self::from_arg_matches(m)?;
        Ok(())
    }
}

impl clap::Args for RecoveryFlags {
    fn augment_args(cmd: clap::Command) -> clap::Command {
        crate::stage_flags::augment(cmd, "material_opt", RECOVERY)
    }
    fn augment_args_for_update(cmd: clap::Command) -> clap::Command {
        Self::augment_args(cmd)
    }
}

pub fn options_from(a: &InvertArgs) -> InvertOptions {
    use matflow_nodes::recovery::{budget_options, material_options};
    let p = &a.recovery.0;
    let o = InvertOptions {
        env_route: a.routes.env.clone(),
        mat_route: a.routes.mat.clone(),
        max_depth: a.depth,
        seed: a.seed,
        spp: a.spp,
        final_spp: a.final_spp,
        env_steps: a.steps,
        mat_steps: a.steps,
        early_stop: !a.no_early_stop,
        denoise: a.denoise,
        denoise_render: a.denoise_render.on(),
        rescale: !a.no_rescale,
        env_only: a.env_only,
        light_guide: a.light_guide.on(),
        portals: a.portals.on(),
        rm_search: a.rm_search.on(),
        rm_margin: a.rm_margin,
        sun: a.sun.on(),
        ..Default::default()
    };
    material_options(p, budget_options(p, o))
}

/// Runs the recovery with a progress bar; returns its result and each
/// stage's wall time in seconds (the order of the report's stages).
pub fn run_invert(
    scene: RenderScene,
    target: &RgbImage,
    maps: &MaterialMaps,
    opts: &InvertOptions,
    quiet: bool,
) -> Result<(InvertResult, Vec<f64>)> {
    let pred = matflow_render::scene::materials_from_maps(maps);
    let pb = if quiet {
        ProgressBar::hidden()
    } else {
        let pb = ProgressBar::new(1);
        pb.set_style(
            ProgressStyle::with_template("{prefix:>22} [{bar:30}] {pos}/{len} {msg} ({elapsed})")
                .unwrap()
                .progress_chars("=> "),
        );
        pb
    };
    // The clock is the front end's: stage durations are measured between
    // the events that open and close each stage.
    let timing = std::sync::Mutex::new((Instant::now(), Vec::new()));
    let res = invert(scene, target, &pred, opts, &|e| match e {
        Event::Stage { name, steps } => {
            if let Ok(mut t) = timing.lock() {
                t.0 = Instant::now();
            }
            pb.set_prefix(name.to_string());
            pb.set_length(steps as u64);
            pb.set_position(0);
            pb.set_message("");
        }
        Event::Step { step, loss } => {
            pb.set_position(step as u64);
            pb.set_message(format!("loss {loss:.5}"));
        }
        Event::Trace { done, total } => {
            pb.set_length(total as u64);
            pb.set_position(done as u64);
        }
        Event::StageDone => {
            if let Ok(mut t) = timing.lock() {
                let s = t.0.elapsed().as_secs_f64();
                t.1.push(s);
            }
        }
    })?;
    pb.finish_and_clear();
    let seconds = timing.into_inner().map(|t| t.1).unwrap_or_default();
    Ok((res, seconds))
}

/// The report's stages, each with its measured wall time.
fn stages_with_seconds(res: &InvertResult, seconds: &[f64]) -> serde_json::Value {
    let mut v = serde_json::to_value(&res.report.stages).unwrap_or_default();
    if let serde_json::Value::Array(stages) = &mut v {
        for (s, t) in stages.iter_mut().zip(seconds) {
            if let serde_json::Value::Object(m) = s {
                m.insert("seconds".into(), serde_json::json!(t));
            }
        }
    }
    v
}

/// Writes the output bundle: geometry inputs and predictions (so that
/// `matflow render --bundle OUT --materials best_results` re-renders the
/// result; geometry.json declaring the completion recovered with),
/// `best_results/` and `summary.json`.
pub fn write_bundle(
    out: &Path,
    res: &InvertResult,
    depth: &matflow_scene::GrayImage,
    pred: &MaterialMaps,
    target: &RgbImage,
    summary: &serde_json::Value,
) -> Result<()> {
    let b = Bundle::create(out)?;
    b.write_depth(depth)?;
    b.write_predictions(pred)?;
    b.write_gt_image(target)?;
    let mut maps = materials_to_maps(target.width, target.height, &res.materials);
    maps.normal = pred.normal.clone();
    b.write_best_results(&matflow_scene::BestResults {
        maps: &maps,
        envmap: &res.envmap,
        lamps: &res.lamps,
        rendered: &res.rendered,
        rendered_raw: res.rendered_raw.as_ref(),
        fit_image: &res.fit_image,
    })?;
    // The result holds the input's depth and was recovered on one
    // completion of it: geometry.json declares that one (and, when the
    // photo chose it, the evidence), so `mesh` on the result builds what
    // `invert` built; `render` reads the summary first.
    io::write_atomic(
        &b.path(crate::commands::GEOMETRY_FILE),
        serde_json::to_string_pretty(&summary["completion"])?.as_bytes(),
    )?;
    let text = serde_json::to_string_pretty(summary)?;
    io::write_atomic(&b.path("summary.json"), text.as_bytes())?;
    Ok(())
}

/// The completion `invert` recovers with: the one asked for; else the one
/// the bundle declares (geometry.json); else (and asked for auto) the one
/// the photo supports: where the photo shows the sky unclipped, each completion is rendered
/// with the predicted maps under that sky (extended alike past what the
/// view shows, [`matflow_render::evidence::seen_sky_light`]) and tested
/// against the photo as `render --complete auto` tests them under a known
/// light. Where it shows none, every completion explains the photo with
/// a light of its own (fitted, each re-renders it alike), so nothing
/// weighs them: `room`, which closes a room only where the view shows
/// one; so too where the one the test takes needs far more light than the
/// sky gives ([`matflow_render::evidence::UNSEEN_LIGHT_GAIN`]).
fn invert_completion(a: &InvertArgs) -> Result<crate::commands::CompletionDecision> {
    use crate::commands::{declared_completion, CompleteMode, CompletionDecision};
    if let Some(m) = a.complete.and_then(crate::commands::CompleteArg::forced) {
        return Ok(CompletionDecision {
            mode: m,
            why: "as asked".into(),
            evidence: None,
        });
    }
    if a.complete.is_none() {
        if let Some(m) = declared_completion(&a.bundle)? {
            return Ok(CompletionDecision {
                mode: m,
                why: "the bundle's own geometry, geometry.json".into(),
                evidence: None,
            });
        }
    }
    let bundle = Bundle::open(&a.bundle)?;
    let photo = bundle.load_gt_image()?;
    let depth = bundle.load_depth()?;
    let maps = bundle.load_materials(a.materials)?;
    let opts = matflow_render::evidence::EvidenceOptions {
        filter: matflow_inverse::invert::FIT_FILTER,
        max_depth: a.depth,
        ..Default::default()
    };
    let tested = matflow_render::evidence::choose_under_seen_sky(
        &depth,
        &maps,
        mesh_params(a),
        &photo,
        &crate::commands::hypotheses(),
        &opts,
    )
    .with_context(|| {
        format!(
            "{}: testing the geometry past the frame",
            a.bundle.display()
        )
    })?;
    let Some((choice, sky)) = tested else {
        return Ok(CompletionDecision {
            mode: CompleteMode::Room,
            why: NO_SKY.into(),
            evidence: None,
        });
    };
    Ok(CompletionDecision {
        mode: crate::commands::HYPOTHESES[choice.chosen],
        why: format!("auto: {}", choice.reason),
        evidence: Some(crate::commands::Evidence {
            choice,
            light: sky.describe(),
            materials: a.materials,
            windows: None,
            walls: None,
        }),
    })
}

/// Why `invert --complete auto` keeps `room` on a photo without sky.
pub const NO_SKY: &str = "auto: the photo shows no unclipped open sky (none, or only through \
     openings: under geometry, or framed by one surface: a room's windows, which let in more \
     light than the sky they show), so nothing weighs the light each completion needs (every one explains the photo \
     with a light of its own); room, which closes a room only where the view shows one";

/// The mesh `invert` recovers on.
fn mesh_params(a: &InvertArgs) -> MeshParams {
    MeshParams {
        min_angle_deg: a.mesh_angle,
        silhouettes: a.silhouettes,
    }
}

pub fn invert_cmd(a: InvertArgs) -> Result<()> {
    let t0 = Instant::now();
    let decision = invert_completion(&a)?;
    decision.print();
    let complete = decision.mode;
    let input = load_input(
        &a.bundle,
        a.materials,
        mesh_params(&a),
        complete.params().as_ref(),
    )?;
    let mut opts = options_from(&a);
    let InvertInput {
        depth,
        maps,
        target,
        scene,
        completion,
    } = input;
    if a.lamps.on() && !completion.lamp_sites.is_empty() {
        opts.lamp_sites = completion.lamp_sites.clone();
        opts.lamp_scale = completion.room_height;
        opts.lamp_sparsity = a.lamp_sparsity;
    }
    // Whether the frozen paths' light samples are guided by visibility
    // (asked for, and the scene enclosed enough).
    let light_guided = opts.light_guide && scene.light_visibility.is_some();
    let portals = if opts.portals { scene.portals.len() } else { 0 };
    let (res, stage_seconds) = run_invert(scene, &target, &maps, &opts, a.quiet)?;
    let (depth, pred, target) = (&depth, &maps, &target);
    let rerender = image_metrics(&res.rendered, target);
    let fit = image_metrics(&res.fit_image, target);
    let rerender_raw = res
        .rendered_raw
        .as_ref()
        .map(|im| image_metrics(im, target));
    let summary = serde_json::json!({
        "input": a.bundle.display().to_string(),
        "options": {
            "budget_seconds": opts.budget_seconds,
            "env_route": format!("{:?}", opts.env_route),
            "mat_route": format!("{:?}", opts.mat_route),
            "trust_rm": opts.trust_rm,
            "materials": format!("{:?}", a.materials),
            "env_only": opts.env_only,
            "delta": opts.delta,
            "zeta": opts.zeta,
            "max_depth": opts.max_depth,
            "seed": opts.seed,
            "pixel_filter": matflow_inverse::invert::FIT_FILTER.name(),
            "complete": complete.name(),
            "silhouettes": a.silhouettes.name(),
            "light_guide": opts.light_guide,
            "portals": opts.portals,
            "rm_search": opts.rm_search,
            "rm_margin": opts.rm_margin,
            "albedo_level": if opts.level_from_pred { "pred" } else { "free" },
            "albedo_level_band": opts.level_band,
            "lamps": a.lamps.on(),
            "lamp_sparsity": opts.lamp_sparsity,
            "sun": opts.sun,
            "denoise_render": opts.denoise_render,
        },
        "lamps": {
            "sites": opts.lamp_sites.len(),
            "room_height": completion.room_height,
            "intensity_sum": res
                .lamps
                .iter()
                .filter(|l| !l.is_distant())
                .map(|l| l.intensity)
                .sum::<Vec3>()
                .to_array(),
        },
        "sun": res.report.sun,
        "completion": decision.to_json(),
        "light_guided": light_guided,
        "portals": portals,
        "rm_search": res.report.rm_search,
        "level_gain": res.report.level_gain,
        "plan": res.report.plan,
        "stages": stages_with_seconds(&res, &stage_seconds),
        "cache_bytes": res.report.cache_bytes,
        "cache_rays": res.report.cache_rays,
        "rerender": rerender,
        "rerender_raw": rerender_raw,
        "fit": fit,
        "seconds": t0.elapsed().as_secs_f64(),
        "peak_memory_bytes": peak_memory_bytes(),
    });
    write_bundle(&a.out, &res, depth, pred, target, &summary)?;
    outln!(
        "inverted {} (completion {} ({})) in {:.1} s: rerender PSNR {:.2} dB{}, SSIM {:.4}, MSE {:.5} (sRGB, gamma 2.2; frozen-path fit {:.2} dB); peak memory {:.0} MB -> {}",
        a.bundle.display(),
        complete.name(),
        decision.why,
        t0.elapsed().as_secs_f64(),
        rerender.psnr,
        rerender_raw
            .map(|r| format!(" denoised ({:.2} dB as rendered)", r.psnr))
            .unwrap_or_default(),
        rerender.ssim,
        rerender.mse,
        fit.psnr,
        peak_memory_bytes().unwrap_or(0) as f64 / 1e6,
        a.out.display()
    );
    crate::commands::report_photo_psnr("the recovered scene's re-render", rerender.psnr);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;
    use matflow_engine::value::parse_override;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        a: InvertArgs,
    }

    fn cli(extra: &[&str]) -> InvertOptions {
        let mut args = vec!["invert", "--bundle", "b", "--out", "o"];
        args.extend_from_slice(extra);
        options_from(&Cli::try_parse_from(args).unwrap().a)
    }

    /// The `material_opt` stage's parameters as the engine fills them:
    /// the kind's defaults, then `given` (YAML text, as a pipeline says).
    fn stage(given: &[(&str, &str)]) -> InvertOptions {
        let reg = matflow_nodes::registry();
        let node = reg.get("material_opt").unwrap();
        let mut p = matflow_engine::node::Params::default();
        for s in node.params() {
            let text = given
                .iter()
                .find(|(n, _)| *n == s.name)
                .map(|(_, v)| *v)
                .or(s.default)
                .unwrap_or("~");
            let v = parse_override(text).unwrap();
            p.0.insert(s.name.into(), s.ty.normalize(&v).unwrap_or(v));
        }
        use matflow_nodes::recovery::{budget_options, material_options};
        material_options(&p, budget_options(&p, InvertOptions::default()))
    }

    /// What `invert` and a `material_opt` stage share they read the same
    /// way: the same defaults, and the same values for the same words.
    #[test]
    fn invert_and_the_material_stage_read_shared_options_alike() {
        let same = |a: &InvertOptions, b: &InvertOptions| {
            assert_eq!(a.budget_seconds, b.budget_seconds);
            assert_eq!(a.trust_rm, b.trust_rm);
            assert_eq!(a.delta.to_bits(), b.delta.to_bits());
            assert_eq!(a.loops, b.loops);
            assert_eq!(a.level_from_pred, b.level_from_pred);
            assert_eq!(a.level_band.to_bits(), b.level_band.to_bits());
        };
        same(&cli(&[]), &stage(&[]));
        same(
            &cli(&[
                "--budget-seconds",
                "7.5",
                "--trust-rm",
                "--delta",
                "0.3",
                "--loops",
                "2",
                "--albedo-level",
                "free",
                "--albedo-level-band",
                "0.4",
            ]),
            &stage(&[
                ("budget_seconds", "7.5"),
                ("trust_rm", "true"),
                ("delta", "0.3"),
                ("loops", "2"),
                ("albedo_level", "free"),
                ("albedo_level_band", "0.4"),
            ]),
        );
        // And the defaults are the library's where it has one.
        let d = cli(&[]);
        assert_eq!(d.level_band, matflow_inverse::invert::LEVEL_BAND);
        assert!(d.level_from_pred);
    }
}
