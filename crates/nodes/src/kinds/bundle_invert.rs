//! `bundle_invert`: `matflow invert` as a stage: the envmap and materials
//! of a bundle folder recovered (completed past the frame as the bundle
//! or its photo says), written as a bundle in the reference's layout with
//! `best_results/`, `geometry.json` and `summary.json`.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use glam::Vec3;
use matflow_engine::node::{Bytes, Params};
use matflow_engine::{Node, NodeError, NodeInfo, OutputSpec, ParamSpec, ParamType, RunContext};
use matflow_geom::MeshParams;
use matflow_inverse::invert::{materials_to_maps, InvertOptions, InvertResult};
use matflow_inverse::routes::Side;
use matflow_render::{scene_from_depth, EnvMap};
use matflow_scene::metrics::{mse_gamma, psnr_gamma, ssim_gamma};
use matflow_scene::{Bundle, GrayImage, Image, MaterialMaps, MaterialSource, RgbImage};

use crate::completion::{
    declared_completion, hypotheses, CompleteArg, CompleteMode, CompletionDecision, Evidence,
    GEOMETRY_FILE, HYPOTHESES,
};
use crate::kinds::bundle_mesh::{complete_arg, on_off, silhouettes, BUNDLE};
use crate::recovery::{
    budget_options, env_route, mat_route, material_options, run_invert, with_route_params,
    ALBEDO_LEVEL, ALBEDO_LEVEL_BAND, ALBEDO_STRUCTURE, BUDGET, DELTA, ENV_ROUTE, LOOPS, MAT_ROUTE,
    TRUST,
};
use crate::{err, Context};

pub struct BundleInvertNode;

/// An optional count (default: from the budget).
const fn count(name: &'static str, max: i64, doc: &'static str) -> ParamSpec {
    ParamSpec {
        name,
        ty: ParamType::Int { min: 1, max },
        default: Some("~"),
        unit: "",
        doc,
    }
}

const OWN: &[ParamSpec] = &[
    BUNDLE,
    ParamSpec {
        name: "output",
        ty: ParamType::OutPath,
        default: None,
        unit: "",
        doc: "the output bundle folder: best_results/, the geometry inputs, geometry.json and \
              summary.json",
    },
    BUDGET,
    ENV_ROUTE,
    MAT_ROUTE,
    TRUST,
    DELTA,
    LOOPS,
    ALBEDO_LEVEL,
    ALBEDO_LEVEL_BAND,
    ALBEDO_STRUCTURE,
    ParamSpec {
        name: "materials",
        ty: ParamType::Choice(&["pred", "ground_truth", "best_results"]),
        default: Some("pred"),
        unit: "",
        doc: "where the starting materials come from: the predictions (pred) or, on \
              synthetic bundles, ground_truth",
    },
    ParamSpec {
        name: "env_only",
        ty: ParamType::Bool,
        default: Some("false"),
        unit: "",
        doc: "recover only the envmap; materials stay at `materials` as given",
    },
    count(
        "spp",
        65536,
        "paths per pixel of the frozen cache (default: from the budget)",
    ),
    count(
        "final_spp",
        65536,
        "samples per pixel of the final re-render (default: from the budget)",
    ),
    count(
        "steps",
        1_000_000,
        "maximum steps per optimisation stage (default: from the budget)",
    ),
    crate::kinds::render::DEPTH,
    crate::kinds::bundle_mesh::SEED,
    ParamSpec {
        name: "mesh_angle",
        ..crate::kinds::mesh::ANGLE
    },
    crate::kinds::mesh::SILHOUETTES,
    ParamSpec {
        name: "complete",
        ty: ParamType::Choice(&CompleteArg::NAMES),
        default: Some("~"),
        unit: "",
        doc: "geometry past the frame (see `bundle_render`'s): auto, room, closed, planes, or \
              none (the depth mesh alone). Auto tests each with the predicted maps under the \
              sky the photo shows, and takes room where it shows none open (only through \
              openings: under a lintel, or framed by one wall) or where the least assuming \
              needs ten times the light of that sky (measured per kind of scene in \
              docs/results/completion.md). Default: the completion the bundle declares for its \
              own geometry (geometry.json, which `matflow synth` writes), otherwise auto. A \
              render of the result uses the same unless told otherwise",
    },
    ParamSpec {
        name: "denoise",
        ty: ParamType::Int { min: 0, max: 64 },
        default: Some("3"),
        unit: "passes",
        doc: "à-trous denoising passes over the per-pixel tables (0: off)",
    },
    on_off(
        "denoise_render",
        "on",
        "denoise the independent re-render (best_results/rendered_img): two halves of its \
         samples, albedo-demodulated, edge-aware à-trous filtered (on); off writes the render \
         as it comes. With on, rendered_raw.exr is the same samples unfiltered",
    ),
    ParamSpec {
        name: "no_rescale",
        ty: ParamType::Bool,
        default: Some("false"),
        unit: "",
        doc: "do not normalise the render's mean in material stages",
    },
    on_off(
        "light_guide",
        "on",
        "guide light samples by what each region of the scene sees of the sky (on), or sample \
         the envmap by radiance alone (off)",
    ),
    on_off(
        "portals",
        "on",
        "aim light samples at the windows of a closed room's assumed walls too (portals; on), \
         or follow the envmap's density alone (off)",
    ),
    on_off(
        "rm_search",
        "off",
        "search roughness and metallic per segment (one albedo per segment under a grid of R \
         and M) before the per-pixel solve, moving the anchor where that explains the photo \
         clearly better (on); off keeps the prediction's anchor. Only when R and M are not \
         trusted",
    ),
    ParamSpec {
        name: "rm_margin",
        ty: ParamType::Float {
            min: 0.0,
            max: 0.999,
        },
        default: Some("0.1"),
        unit: "",
        doc: "how much better (relative loss) a segment's best (R, M) must explain it than the \
              prediction's for the anchor to move",
    },
    on_off(
        "lamps",
        "off",
        "lamps the view does not show, in a room the completion closed (complete room or \
         closed): on fits point lights at a grid of sites under its ceiling with the envmap \
         (texel route; a sparsity prior keeps the ones the photo does not need dark), written \
         to best_results/lamps.json; off lights the room by the envmap alone",
    ),
    ParamSpec {
        name: "lamp_sparsity",
        ty: ParamType::Float { min: 0.0, max: 1e6 },
        default: Some("0.003"),
        unit: "",
        doc: "with lamps on: weight of the lamps' sparsity prior (their entries' sum over the \
              envmap's mean texel); 0 lets the photo alone decide",
    },
    on_off(
        "sun",
        "off",
        "the sun: on searches the photo's light and shadow, after the scout, for a sun \
         direction that explains them and, where one does, fits it as a distant light beside \
         the texels (texel route); written to best_results/lamps.json. Scenes where none does \
         are recovered as with off",
    ),
    ParamSpec {
        name: "no_early_stop",
        ty: ParamType::Bool,
        default: Some("false"),
        unit: "",
        doc: "disable early stopping (run every stage for its full step count)",
    },
];

/// Every file the output bundle may hold; those a run does not write
/// (lamps, the raw re-render, normals) are removed, as the bundle writer
/// removes an earlier run's.
const FILES: &[&str] = &[
    "depth.exr",
    "albedoPred.exr",
    "roughnessPred.png",
    "metallicPred.png",
    "normalPred.exr",
    "gt_image.exr",
    "gt_image.png",
    "best_results/albedo.exr",
    "best_results/roughness.exr",
    "best_results/metallic.exr",
    "best_results/normal.exr",
    "best_results/envmap.hdr",
    "best_results/lamps.json",
    "best_results/rendered_img.exr",
    "best_results/rendered_img.png",
    "best_results/rendered_raw.exr",
    "best_results/fit_img.exr",
    "best_results/fit_img.png",
    "best_results/albedo.png",
    GEOMETRY_FILE,
    "summary.json",
];

const OUTPUTS: &[OutputSpec] = &[
    OutputSpec {
        name: "bundle",
        ty: "file",
        doc: "the output bundle's files (a folder's files by their paths in it)",
    },
    OutputSpec {
        name: "note",
        ty: "note",
        doc: "the completion taken and why, and how well the result explains the photo",
    },
];

impl Node for BundleInvertNode {
    fn info(&self) -> &'static NodeInfo {
        static INFO: OnceLock<NodeInfo> = OnceLock::new();
        static ALL_PARAMS: OnceLock<Vec<ParamSpec>> = OnceLock::new();
        INFO.get_or_init(|| NodeInfo {
            kind: "bundle_invert",
            version: 4,
            doc: "`matflow invert` as a stage: the envmap and the albedo, roughness and \
                  metallic of a bundle folder recovered (the paper's alternation on frozen \
                  paths, on the bundle's depth completed past the frame), written as a bundle \
                  in the reference's layout: best_results/, the geometry inputs, geometry.json \
                  (the completion recovered with) and summary.json (options, plan, per-stage \
                  steps and losses, rerender and fit PSNR/SSIM; no timings: the run's report \
                  has them).",
            params: with_route_params(&ALL_PARAMS, OWN, &[Side::Env, Side::Mat]),
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

    fn preflight(&self, p: &Params) -> Result<(), String> {
        crate::kinds::bundle_mesh::bundle_preflight(p)
    }

    fn film_size(&self, p: &Params) -> Option<(usize, usize)> {
        crate::kinds::bundle_mesh::bundle_film_size(p)
    }

    fn output_files(&self, p: &Params) -> Vec<PathBuf> {
        crate::files::in_output(p, FILES)
    }

    fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
        let p = ctx.params;
        let dir = p.path("bundle").unwrap_or_default();
        let materials: MaterialSource = p.parse("materials")?;
        let mesh = MeshParams {
            min_angle_deg: p.f64("mesh_angle"),
            silhouettes: silhouettes(p)?,
        };
        let InvertInput {
            depth,
            maps,
            target,
        } = load_input(&dir, materials)?;
        let decision = invert_completion(&dir, p, (&depth, &maps, &target), materials, mesh)?;
        let mut lines = decision.lines();
        // The scene under a flat placeholder envmap, completed as decided.
        let flat = Image::new(32, 16, Vec3::ONE);
        let env = EnvMap::new(&flat).node_err()?;
        let complete = decision.mode.params();
        let (scene, _, completion) = scene_from_depth(&depth, &maps, env, mesh, complete.as_ref())
            .context(|| format!("{}: building the scene", dir.display()))?;
        let mut opts = options(p)?;
        if p.str("lamps") == "on" && !completion.lamp_sites.is_empty() {
            opts.lamp_sites = completion.lamp_sites.clone();
            opts.lamp_scale = completion.room_height;
            opts.lamp_sparsity = p.f32("lamp_sparsity");
        }
        // Whether the frozen paths' light samples are guided by visibility
        // (asked for, and the scene enclosed enough).
        let light_guided = opts.light_guide && scene.light_visibility.is_some();
        let portals = if opts.portals { scene.portals.len() } else { 0 };
        let pred = matflow_render::scene::materials_from_maps(&maps);
        let res = run_invert(ctx, scene, &target, &pred, &opts)?;
        let (rerender, (fit, rerender_raw)) = rayon::join(
            || image_metrics(&res.rendered, &target),
            || {
                rayon::join(
                    || image_metrics(&res.fit_image, &target),
                    || {
                        res.rendered_raw
                            .as_ref()
                            .map(|im| image_metrics(im, &target))
                    },
                )
            },
        );
        let summary = serde_json::json!({
            "options": {
                "budget_seconds": opts.budget_seconds,
                "env_route": format!("{:?}", opts.env_route),
                "mat_route": format!("{:?}", opts.mat_route),
                "trust_rm": opts.trust_rm,
                "materials": format!("{:?}", materials),
                "env_only": opts.env_only,
                "delta": opts.delta,
                "zeta": opts.zeta,
                "max_depth": opts.max_depth,
                "seed": opts.seed,
                "pixel_filter": matflow_inverse::invert::FIT_FILTER.name(),
                "complete": decision.mode.name(),
                "silhouettes": mesh.silhouettes.name(),
                "light_guide": opts.light_guide,
                "portals": opts.portals,
                "rm_search": opts.rm_search,
                "rm_margin": opts.rm_margin,
                "albedo_level": if opts.level_from_pred { "pred" } else { "free" },
                "albedo_level_band": opts.level_band,
                "lamps": p.str("lamps") == "on",
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
            "stages": res.report.stages,
            "cache_bytes": res.report.cache_bytes,
            "cache_rays": res.report.cache_rays,
            "rerender": rerender,
            "rerender_raw": rerender_raw,
            "fit": fit,
        });
        lines.push(format!(
            "inverted (completion {} ({})): rerender PSNR {:.2} dB{}, SSIM {:.4}, MSE {:.5} (sRGB, gamma 2.2; frozen-path fit {:.2} dB)",
            decision.mode.name(),
            decision.why,
            rerender.psnr,
            rerender_raw
                .map(|r| format!(" denoised ({:.2} dB as rendered)", r.psnr))
                .unwrap_or_default(),
            rerender.ssim,
            rerender.mse,
            fit.psnr,
        ));
        lines.extend(crate::bundle_scene::photo_psnr_lines(
            "the recovered scene's re-render",
            rerender.psnr,
        ));
        let files = bundle_files(&res, &depth, &maps, &target, &summary)?;
        Ok([
            ("bundle".to_string(), files),
            ("note".to_string(), lines.join("\n").into_bytes()),
        ]
        .into())
    }

    fn materialize(
        &self,
        params: &Params,
        outputs: &BTreeMap<String, Bytes>,
    ) -> Result<Vec<PathBuf>, NodeError> {
        let Some(dir) = params.path("output") else {
            return Ok(vec![]);
        };
        let b = outputs
            .get("bundle")
            .ok_or_else(|| err("the stage made no bundle"))?;
        let files = unpack(b)?;
        crate::files::write_folder(&dir, FILES, |name| files.get(name).copied())
    }
}

/// Image error of `a` against `b`, in sRGB (γ 2.2, clipped).
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

/// What `invert` reads from a bundle: its photo, depth and starting maps.
pub struct InvertInput {
    pub depth: GrayImage,
    pub maps: MaterialMaps,
    pub target: RgbImage,
}

/// The photo, depth and starting maps of bundle `dir`, which must agree
/// in size.
pub fn load_input(dir: &Path, source: MaterialSource) -> Result<InvertInput, NodeError> {
    let bundle = Bundle::open(dir).node_err()?;
    let target = bundle.load_gt_image().node_err()?;
    let depth = bundle.load_depth().node_err()?;
    let maps = bundle.load_materials(source).node_err()?;
    if !target.same_size(&depth) || maps.width() != depth.width || maps.height() != depth.height {
        return Err(err(format!(
            "{}: gt_image is {}x{}, depth {}x{}, predictions {}x{}; they must agree",
            dir.display(),
            target.width,
            target.height,
            depth.width,
            depth.height,
            maps.width(),
            maps.height()
        )));
    }
    Ok(InvertInput {
        depth,
        maps,
        target,
    })
}

/// The recovery's options from the stage's parameters.
fn options(p: &Params) -> Result<InvertOptions, NodeError> {
    let o = InvertOptions {
        env_route: env_route(p)?,
        mat_route: mat_route(p)?,
        max_depth: p.i64("depth") as u32,
        seed: p.i64("seed") as u64,
        spp: p.opt_i64("spp").map(|v| v as u32),
        final_spp: p.opt_i64("final_spp").map(|v| v as u32),
        env_steps: p.opt_i64("steps").map(|v| v as usize),
        mat_steps: p.opt_i64("steps").map(|v| v as usize),
        early_stop: !p.bool("no_early_stop"),
        denoise: p.i64("denoise") as usize,
        denoise_render: p.str("denoise_render") == "on",
        rescale: !p.bool("no_rescale"),
        env_only: p.bool("env_only"),
        light_guide: p.str("light_guide") == "on",
        portals: p.str("portals") == "on",
        rm_search: p.str("rm_search") == "on",
        rm_margin: p.f64("rm_margin"),
        sun: p.str("sun") == "on",
        ..Default::default()
    };
    Ok(material_options(p, budget_options(p, o)))
}

/// Why `invert --complete auto` keeps `room` on a photo without sky.
pub const NO_SKY: &str = "auto: the photo shows no unclipped open sky (none, or only through \
     openings: under geometry, or framed by one surface: a room's windows, which let in more \
     light than the sky they show), so nothing weighs the light each completion needs (every one explains the photo \
     with a light of its own); room, which closes a room only where the view shows one";

/// The completion `invert` recovers with: the one asked for; else the one
/// the bundle declares (geometry.json); else (and asked for auto) the one
/// the photo supports: where the photo shows the sky unclipped, each
/// completion is rendered with the predicted maps under that sky (extended
/// alike past what the view shows,
/// [`matflow_render::evidence::seen_sky_light`]) and tested against the
/// photo as `render --complete auto` tests them under a known light. Where
/// it shows none, every completion explains the photo with a light of its
/// own (fitted, each re-renders it alike), so nothing weighs them: `room`,
/// which closes a room only where the view shows one; so too where the one
/// the test takes needs far more light than the sky gives
/// ([`matflow_render::evidence::UNSEEN_LIGHT_GAIN`]).
fn invert_completion(
    dir: &Path,
    p: &Params,
    (depth, maps, photo): (&GrayImage, &MaterialMaps, &RgbImage),
    materials: MaterialSource,
    mesh: MeshParams,
) -> Result<CompletionDecision, NodeError> {
    let asked = complete_arg(p)?;
    if let Some(m) = asked.and_then(CompleteArg::forced) {
        return Ok(CompletionDecision::given(m, "as asked"));
    }
    if asked.is_none() {
        if let Some(m) = declared_completion(dir)? {
            return Ok(CompletionDecision::given(
                m,
                "the bundle's own geometry, geometry.json",
            ));
        }
    }
    let opts = matflow_render::evidence::EvidenceOptions {
        filter: matflow_inverse::invert::FIT_FILTER,
        max_depth: p.i64("depth") as u32,
        ..Default::default()
    };
    let tested = matflow_render::evidence::choose_under_seen_sky(
        depth,
        maps,
        mesh,
        photo,
        &hypotheses(),
        &opts,
    )
    .context(|| format!("{}: testing the geometry past the frame", dir.display()))?;
    let Some((choice, sky)) = tested else {
        return Ok(CompletionDecision::given(CompleteMode::Room, NO_SKY));
    };
    Ok(CompletionDecision {
        mode: HYPOTHESES[choice.chosen],
        why: format!("auto: {}", choice.reason),
        evidence: Some(Evidence {
            choice,
            light: sky.describe(),
            materials,
            windows: None,
            walls: None,
        }),
    })
}

/// The output bundle's files, packed: the geometry inputs and predictions
/// (so that a render of the result re-renders it; geometry.json declaring
/// the completion recovered with), `best_results/` and `summary.json`, as
/// the bundle writer writes them (into a scratch folder, read back).
fn bundle_files(
    res: &InvertResult,
    depth: &GrayImage,
    pred: &MaterialMaps,
    target: &RgbImage,
    summary: &serde_json::Value,
) -> Result<Vec<u8>, NodeError> {
    // Failing to make one is the machine's failure, whatever the cause.
    let scratch = tempfile::Builder::new()
        .prefix("matflow-invert-")
        .tempdir()
        .map_err(|e| NodeError::machine(format!("making a scratch folder: {e}")))?;
    let out = scratch.path().join("bundle");
    let b = Bundle::create(&out).node_err()?;
    let mut maps = materials_to_maps(target.width, target.height, &res.materials);
    maps.normal = pred.normal.clone();
    let b = &b;
    let maps = &maps;
    matflow_scene::bundle::write_all(vec![
        Box::new(|| b.write_depth(depth)),
        Box::new(|| b.write_predictions(pred)),
        Box::new(|| b.write_gt_image(target)),
        Box::new(|| {
            b.write_best_results(&matflow_scene::BestResults {
                maps,
                envmap: &res.envmap,
                lamps: &res.lamps,
                rendered: &res.rendered,
                rendered_raw: res.rendered_raw.as_ref(),
                fit_image: &res.fit_image,
            })
        }),
    ])
    .node_err()?;
    // The result holds the input's depth and was recovered on one
    // completion of it: geometry.json declares that one (and, when the
    // photo chose it, the evidence), so `mesh` on the result builds what
    // `invert` built; `render` reads the summary first.
    let json = |v: &serde_json::Value| serde_json::to_string_pretty(v).node_err();
    matflow_scene::io::write_atomic(
        &b.path(GEOMETRY_FILE),
        json(&summary["completion"])?.as_bytes(),
    )
    .node_err()?;
    matflow_scene::io::write_atomic(&b.path("summary.json"), json(summary)?.as_bytes())
        .node_err()?;
    let mut files = BTreeMap::new();
    for name in FILES {
        let path = out.join(name);
        if path.is_file() {
            let bytes = std::fs::read(&path).context(|| format!("reading {}", path.display()))?;
            files.insert(name.to_string(), bytes);
        }
    }
    Ok(pack(&files))
}

/// Files by name as one blob: for each, the name's and the contents'
/// lengths (u64, little-endian) and bytes.
fn pack(files: &BTreeMap<String, Vec<u8>>) -> Vec<u8> {
    let mut out = Vec::new();
    for (name, bytes) in files {
        for part in [name.as_bytes(), bytes] {
            out.extend_from_slice(&(part.len() as u64).to_le_bytes());
            out.extend_from_slice(part);
        }
    }
    out
}

/// The files [`pack`] packed; a truncated blob is an error.
fn unpack(b: &[u8]) -> Result<BTreeMap<String, &[u8]>, NodeError> {
    let mut files = BTreeMap::new();
    let mut at = 0usize;
    let take = |at: &mut usize| -> Result<&[u8], NodeError> {
        let bad = || err("the packed bundle is truncated");
        let len_end = at
            .checked_add(8)
            .filter(|&e| e <= b.len())
            .ok_or_else(bad)?;
        let n = u64::from_le_bytes(b[*at..len_end].try_into().map_err(|_| bad())?);
        let end = usize::try_from(n)
            .ok()
            .and_then(|n| len_end.checked_add(n))
            .filter(|&e| e <= b.len())
            .ok_or_else(bad)?;
        *at = end;
        Ok(&b[len_end..end])
    };
    while at < b.len() {
        let name = String::from_utf8(take(&mut at)?.to_vec())
            .map_err(|_| err("a packed file's name is not UTF-8"))?;
        let bytes = take(&mut at)?;
        files.insert(name, bytes);
    }
    Ok(files)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn packed_files_unpack_to_themselves_and_truncation_is_an_error() {
        let files: BTreeMap<String, Vec<u8>> = [
            ("a.json".to_string(), b"{}".to_vec()),
            ("best_results/e.hdr".to_string(), vec![0u8; 300]),
            ("empty".to_string(), vec![]),
        ]
        .into();
        let b = pack(&files);
        let back = unpack(&b).unwrap();
        assert_eq!(back.len(), 3);
        for (k, v) in &files {
            assert_eq!(back[k.as_str()], &v[..]);
        }
        for cut in [1, 8, 9, b.len() - 1] {
            assert!(unpack(&b[..cut]).is_err(), "cut at {cut}");
        }
    }
}
