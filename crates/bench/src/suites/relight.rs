//! `matflow-bench invert --validation DIR`: relighting on scenes matflow
//! has never seen (the set `crates/bench/scripts/relight_scenes.py` renders with
//! Mitsuba 3), as the headline accuracy metric.
//!
//! Per scene and configuration, one child `matflow invert`, then child
//! `matflow render`s (Gaussian filter, as the truth's film; the same seed
//! for every render of a scene, so renders on the same mesh share their
//! random streams):
//!
//! - **relight**: the recovered scene under each of the two new envmaps
//!   against the true relit image (sRGB γ 2.2); also after the one gain
//!   that best matches the truth (the light level through openings the
//!   view does not show cannot be known from the photo);
//! - **geometry part**: the *true* maps on matflow's mesh, under the true
//!   capture light (against the input) and under the new envmaps (against
//!   the true relit images) — what the single-view mesh alone costs;
//! - **recovery part**: the recovered maps against the true maps, both on
//!   matflow's mesh under the new envmaps — what recovery alone costs;
//! - material errors on the room's pixels: albedo RMSE and chroma angle,
//!   roughness and metallic mean absolute error on metal (true metallic
//!   > 0.5) and dielectric pixels;
//! - the rerender PSNR and the wall time from the child's `summary.json`.
//!
//! Summaries are per half (tuning, held back): median and worst over the
//! (scene, envmap) pairs. The truth's own noise floor (`scene.json`) is
//! printed beside each scene.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use matflow_scene::metrics::psnr_gamma;
use matflow_scene::{io, Bundle, MaterialSource, RgbImage};

use crate::harness::median;
use crate::harness::path_arg as s;
use matflow_nodes::completion::CompleteArg;

/// The validation set's index (`validation.json`).
pub struct Validation {
    pub dir: PathBuf,
    pub tuning: Vec<String>,
    pub heldback: Vec<String>,
    /// Each scene's kind (closed, open, stage, outdoor): `kinds` in the
    /// index; a set without it is closed rooms alone.
    pub kinds: std::collections::BTreeMap<String, String>,
}

impl Validation {
    pub fn kind(&self, scene: &str) -> &str {
        self.kinds
            .get(scene)
            .map(String::as_str)
            .unwrap_or("closed")
    }
}

pub fn load_validation(dir: &Path) -> Result<Validation> {
    let p = dir.join("validation.json");
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&p).with_context(|| {
        format!(
            "reading {} (generate the set with `python3 crates/bench/scripts/relight_scenes.py --out {}`)",
            p.display(),
            dir.display()
        )
    })?)
    .with_context(|| format!("parsing {}", p.display()))?;
    let names = |k: &str| -> Result<Vec<String>> {
        v[k].as_array()
            .with_context(|| format!("{}: field `{k}` must be a list of scene names", p.display()))?
            .iter()
            .map(|s| {
                s.as_str()
                    .map(String::from)
                    .with_context(|| format!("{}: `{k}` holds a non-string", p.display()))
            })
            .collect()
    };
    let mut kinds = std::collections::BTreeMap::new();
    if let Some(k) = v.get("kinds") {
        let k = k.as_object().with_context(|| {
            format!(
                "{}: field `kinds` must map scene names to kinds",
                p.display()
            )
        })?;
        for (name, kind) in k {
            let kind = kind
                .as_str()
                .with_context(|| format!("{}: kinds.{name} is not a string", p.display()))?;
            kinds.insert(name.clone(), kind.to_string());
        }
    }
    Ok(Validation {
        dir: dir.to_path_buf(),
        tuning: names("tuning")?,
        heldback: names("heldback")?,
        kinds,
    })
}

/// What one validation run needs.
pub struct RelightRun<'a> {
    pub exe: &'a Path,
    pub budget: f64,
    /// (name, extra `invert` flags).
    pub variants: Vec<(String, Vec<String>)>,
    pub spp: u32,
    /// Geometry past the frame for `invert` and every render: each mode
    /// runs every variant.
    pub complete: Vec<CompleteArg>,
    /// Only the geometry part (the true maps rendered on each completion
    /// against the truths): no inversion.
    pub geometry_only: bool,
    pub halves: Vec<String>,
    /// Only these scenes (all of the halves when empty).
    pub only: Vec<String>,
    pub work: &'a Path,
}

#[derive(Clone, Debug, Default)]
struct SceneRow {
    scene: String,
    half: String,
    kind: String,
    /// The completion taken: the inversion's (its summary.json), or with
    /// --geometry-only the true maps' capture render's (auto decides).
    taken: String,
    /// Seconds auto's choice took in that render.
    choice_seconds: f64,
    variant: String,
    seconds: f64,
    rerender: f64,
    relight: [f64; 2],
    /// Relight PSNR after the one gain that best matches the truth.
    relight_gain: [f64; 2],
    geo_capture: f64,
    geo_relit: [f64; 2],
    recovery: [f64; 2],
    albedo_rmse: f64,
    albedo_chroma_deg: f64,
    rough_mae: [f64; 2],
    metal_mae: [f64; 2],
    noise_floor: Vec<f64>,
}

/// Renders `bundle` with `materials` under `envmap` into `out` (kept when
/// it exists: the true-map renders are shared by every configuration).
/// Whether [`render`] reuses an image there already, and lights the
/// scene with the maps' own lamps.
#[derive(Clone, Copy)]
struct RenderHow {
    reuse: bool,
    lamps: bool,
}

fn render(
    r: &RelightRun,
    complete: CompleteArg,
    bundle: &Path,
    materials: &str,
    envmap: &Path,
    out: &Path,
    how: RenderHow,
) -> Result<RgbImage> {
    let RenderHow { reuse, lamps } = how;
    if !(reuse && out.exists()) {
        let mut args: Vec<String> = [
            "render",
            "--bundle",
            &s(bundle),
            "--materials",
            materials,
            "--envmap",
            &s(envmap),
            "--spp",
            &r.spp.to_string(),
            "--seed",
            "7",
            "--filter",
            "gaussian",
            "--out",
            &s(out),
        ]
        .iter()
        .map(|x| x.to_string())
        .collect();
        args.extend(["--complete".into(), complete.name().into()]);
        // Relit truths have their lamps off: so have the recovered
        // scene's (the fitted lamps light only the rerender); the capture
        // is lit by its true lamps too (ground_truth/lamps.json).
        args.extend(["--lamps".into(), if lamps { "on" } else { "off" }.into()]);
        crate::harness::stage_child(r.exe, &args, false)?;
    }
    Ok(io::read_exr_rgb(out)?)
}

fn relight_names(j: usize) -> (String, String) {
    let suffix = if j == 0 {
        String::new()
    } else {
        format!("_{}", j + 1)
    };
    (
        format!("ground_truth/relight_envmap{suffix}.exr"),
        format!("ground_truth/relit_image{suffix}.exr"),
    )
}

/// Material errors on the room's pixels (depth > 0).
fn material_errors(scene: &Path, out: &Path, row: &mut SceneRow) -> Result<()> {
    let truth = Bundle::open(scene)?;
    let z = truth.load_depth()?;
    let t = truth.load_materials(MaterialSource::GroundTruth)?;
    let g = Bundle::open(out)?.load_materials(MaterialSource::BestResults)?;
    let (mut se, mut ang, mut n) = (0f64, 0f64, 0usize);
    let mut rough = [(0f64, 0usize); 2];
    let mut metal = [(0f64, 0usize); 2];
    for i in 0..z.data.len() {
        if z.data[i] <= 0.0 {
            continue;
        }
        let (a, b) = (g.albedo.data[i].as_dvec3(), t.albedo.data[i].as_dvec3());
        se += (a - b).length_squared() / 3.0;
        let (la, lb) = (a.length(), b.length());
        if la > 1e-6 && lb > 1e-6 {
            ang += (a.dot(b) / (la * lb)).clamp(-1.0, 1.0).acos().to_degrees();
        } else if (la > 1e-6) != (lb > 1e-6) {
            ang += 90.0;
        }
        n += 1;
        let k = usize::from(t.metallic.data[i] <= 0.5);
        rough[k].0 += (g.roughness.data[i] - t.roughness.data[i]).abs() as f64;
        rough[k].1 += 1;
        metal[k].0 += (g.metallic.data[i] - t.metallic.data[i]).abs() as f64;
        metal[k].1 += 1;
    }
    let mean = |(v, c): (f64, usize)| if c == 0 { f64::NAN } else { v / c as f64 };
    row.albedo_rmse = (se / n.max(1) as f64).sqrt();
    row.albedo_chroma_deg = ang / n.max(1) as f64;
    row.rough_mae = [mean(rough[0]), mean(rough[1])];
    row.metal_mae = [mean(metal[0]), mean(metal[1])];
    Ok(())
}

/// `a` times the gain that minimises its squared error to `b` (linear
/// values, all channels): what is left once the overall light level —
/// which light through openings the view does not show makes unknowable —
/// is set right.
fn with_best_gain(a: &RgbImage, b: &RgbImage) -> RgbImage {
    let (mut ab, mut aa) = (0f64, 0f64);
    for (p, q) in a.data.iter().zip(&b.data) {
        let (p, q) = (p.as_dvec3(), q.as_dvec3());
        ab += p.dot(q);
        aa += p.dot(p);
    }
    let g = if aa > 0.0 { (ab / aa) as f32 } else { 1.0 };
    RgbImage::from_vec(a.width, a.height, a.data.iter().map(|v| *v * g).collect())
}

fn scene_meta(scene: &Path) -> Result<serde_json::Value> {
    let p = scene.join("scene.json");
    serde_json::from_slice(&std::fs::read(&p).with_context(|| format!("reading {}", s(&p)))?)
        .with_context(|| format!("parsing {}", s(&p)))
}

#[allow(clippy::too_many_arguments)]
fn measure(
    r: &RelightRun,
    complete: CompleteArg,
    scene: &Path,
    name: &str,
    half: &str,
    kind: &str,
    variant: &(String, Vec<String>),
) -> Result<SceneRow> {
    let tag = variant.0.replace(|c: char| !c.is_ascii_alphanumeric(), "_");
    let out = r
        .work
        .join(format!("{name}-{}-{tag}-{}", r.budget, complete.name()));
    if r.geometry_only {
        let mut row = SceneRow {
            scene: name.into(),
            half: half.into(),
            kind: kind.into(),
            variant: format!("complete {}", complete.name()),
            noise_floor: noise_floor(&scene_meta(scene)?),
            ..Default::default()
        };
        geometry_part(r, complete, scene, name, &mut row)?;
        return Ok(row);
    }
    let mut args: Vec<String> = vec![
        "invert".into(),
        "--bundle".into(),
        s(scene),
        "--out".into(),
        s(&out),
        "--budget-seconds".into(),
        r.budget.to_string(),
        "--quiet".into(),
        "--complete".into(),
        complete.name().into(),
    ];
    args.extend(variant.1.iter().cloned());
    let timing = crate::harness::stage_child(r.exe, &args, false)?;
    let sp = out.join("summary.json");
    let sum: serde_json::Value = serde_json::from_slice(
        &std::fs::read(&sp).with_context(|| format!("reading {}", s(&sp)))?,
    )?;
    let meta = scene_meta(scene)?;
    let mut row = SceneRow {
        scene: name.into(),
        half: half.into(),
        variant: if r.complete.len() > 1 {
            format!("{}, complete {}", variant.0, complete.name())
        } else {
            variant.0.clone()
        },
        kind: kind.into(),
        seconds: timing.seconds,
        rerender: sum["rerender"]["psnr"].as_f64().unwrap_or(f64::NAN),
        noise_floor: noise_floor(&meta),
        ..Default::default()
    };
    let c = format!("-complete-{}", complete.name());
    let relit_truth = geometry_part(r, complete, scene, name, &mut row)?;
    row.taken = sum["options"]["complete"]
        .as_str()
        .unwrap_or("?")
        .to_string();
    for (j, (truth, t)) in relit_truth.iter().enumerate() {
        let (env, _) = relight_names(j);
        let env = scene.join(env);
        let g = render(
            r,
            complete,
            &out,
            "best_results",
            &env,
            // Beside the bundle: a stage may not write into a folder it
            // reads.
            &out.with_extension(format!("relit{j}{c}.exr")),
            RenderHow {
                reuse: false,
                lamps: false,
            },
        )?;
        row.relight[j] = psnr_gamma(&g, truth);
        row.relight_gain[j] = psnr_gamma(&with_best_gain(&g, truth), truth);
        row.recovery[j] = psnr_gamma(&g, t);
    }
    material_errors(scene, &out, &mut row)?;
    Ok(row)
}

fn noise_floor(meta: &serde_json::Value) -> Vec<f64> {
    meta["noise_floor_psnr"]
        .as_array()
        .map(|a| a.iter().filter_map(|x| x.as_f64()).collect())
        .unwrap_or_default()
}

/// The geometry part: the true maps under the true capture light and each
/// new sky, rendered on the view's completed mesh, against the truths
/// (the capture image and the relit images); the completion the capture
/// render took (auto decides it by the photo) and the seconds its choice
/// took. Returns each relit (truth, render).
fn geometry_part(
    r: &RelightRun,
    complete: CompleteArg,
    scene: &Path,
    name: &str,
    row: &mut SceneRow,
) -> Result<Vec<(RgbImage, RgbImage)>> {
    let c = format!("-complete-{}", complete.name());
    let shared = r.work.join(format!("{name}-truth-{}spp{c}", r.spp));
    std::fs::create_dir_all(&shared)?;
    let cap_path = shared.join("capture.exr");
    let cap = render(
        r,
        complete,
        scene,
        "ground_truth",
        &scene.join("ground_truth/envmap.exr"),
        &cap_path,
        RenderHow {
            reuse: true,
            lamps: true,
        },
    )?;
    row.geo_capture = psnr_gamma(&cap, &io::read_exr_rgb(&scene.join("gt_image.exr"))?);
    let report: serde_json::Value = std::fs::read(cap_path.with_extension("json"))
        .ok()
        .and_then(|b| serde_json::from_slice(&b).ok())
        .unwrap_or_default();
    row.taken = report["completion"]["complete"]
        .as_str()
        .unwrap_or("?")
        .to_string();
    // The photo's test of the completions, the window search included:
    // `matflow mesh --complete auto` on the scene runs it under the
    // scene's own light and maps (with the mesh's build, a small part).
    if complete == CompleteArg::Auto {
        let ply = shared.join("auto.ply");
        let args = [
            "mesh".to_string(),
            "--bundle".into(),
            s(scene),
            "--complete".into(),
            "auto".into(),
            "--out".into(),
            s(&ply),
        ];
        row.choice_seconds = crate::harness::stage_child(r.exe, &args, false)?.seconds;
    }
    let mut out = Vec::new();
    for j in 0..2 {
        let (env, img) = relight_names(j);
        let truth = io::read_exr_rgb(&scene.join(&img))?;
        let t = render(
            r,
            complete,
            scene,
            "ground_truth",
            &scene.join(env),
            &shared.join(format!("relit{j}.exr")),
            RenderHow {
                reuse: true,
                lamps: false,
            },
        )?;
        row.geo_relit[j] = psnr_gamma(&t, &truth);
        out.push((truth, t));
    }
    Ok(out)
}

fn print_row(r: &SceneRow) {
    let floor = r
        .noise_floor
        .iter()
        .map(|v| format!("{v:.1}"))
        .collect::<Vec<_>>()
        .join(" / ");
    outln!(
        "| {} | {} | {} | {} | {} | {:.1} | {:.2} | {:.2} / {:.2} | {:.2} / {:.2} | {:.2} | {:.2} / {:.2} | {:.2} / {:.2} | {:.3} / {:.1}° | {:.3} / {:.3} | {:.3} / {:.3} | {} |",
        r.scene,
        r.half,
        r.kind,
        r.variant,
        r.taken,
        r.seconds,
        r.rerender,
        r.relight[0],
        r.relight[1],
        r.relight_gain[0],
        r.relight_gain[1],
        r.geo_capture,
        r.geo_relit[0],
        r.geo_relit[1],
        r.recovery[0],
        r.recovery[1],
        r.albedo_rmse,
        r.albedo_chroma_deg,
        r.rough_mae[0],
        r.rough_mae[1],
        r.metal_mae[0],
        r.metal_mae[1],
        floor
    );
}

const HEADER: &str = "| scene | half | kind | configuration | completion taken (the inversion's; the true maps' with --geometry-only) | wall (s) | rerender (dB) | relight 1 / 2 (dB) | relight, best gain, 1 / 2 (dB) | geometry, capture (dB) | geometry, relit 1 / 2 (dB) | recovery 1 / 2 (dB) | albedo RMSE / chroma | R MAE metal / dielectric | M MAE metal / dielectric | truth noise floor (dB) |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|";

fn min(v: &[f64]) -> f64 {
    v.iter().cloned().fold(f64::INFINITY, f64::min)
}

fn nan_mean(v: impl Iterator<Item = f64>) -> f64 {
    let (s, n) = v
        .filter(|x| x.is_finite())
        .fold((0.0, 0usize), |(s, n), x| (s + x, n + 1));
    if n == 0 {
        f64::NAN
    } else {
        s / n as f64
    }
}

pub fn bench_relight(v: &Validation, r: &RelightRun) -> Result<()> {
    std::fs::create_dir_all(r.work)?;
    let mut scenes: Vec<(String, String)> = Vec::new();
    for half in &r.halves {
        let list = match half.as_str() {
            "tuning" => &v.tuning,
            "heldback" => &v.heldback,
            other => bail!("unknown half `{other}` (tuning or heldback)"),
        };
        scenes.extend(
            list.iter()
                .filter(|n| r.only.is_empty() || r.only.contains(n))
                .map(|n| (n.clone(), half.clone())),
        );
    }
    outln!(
        "bench invert --validation {}: {} scene(s), budget {:.0} s, {} thread(s); renders at {} spp, \
         Gaussian filter, seed 7; geometry past the frame (--complete): {}",
        s(&v.dir),
        scenes.len(),
        r.budget,
        rayon::current_num_threads(),
        r.spp,
        r.complete
            .iter()
            .map(|m| m.name())
            .collect::<Vec<_>>()
            .join(", ")
    );
    outln!("{HEADER}");
    let mut rows = Vec::new();
    let mut configs: Vec<String> = Vec::new();
    for &complete in &r.complete {
        for variant in &r.variants {
            for (name, half) in &scenes {
                let row = measure(
                    r,
                    complete,
                    &v.dir.join(name),
                    name,
                    half,
                    v.kind(name),
                    variant,
                )?;
                print_row(&row);
                if !configs.contains(&row.variant) {
                    configs.push(row.variant.clone());
                }
                rows.push(row);
            }
        }
    }
    let mut kinds: Vec<String> = Vec::new();
    for row in &rows {
        if !kinds.contains(&row.kind) {
            kinds.push(row.kind.clone());
        }
    }
    outln!();
    outln!("Per half and kind of scene: median and worst over (scene, envmap) pairs; geometry over capture and relit; material errors are means. The worst kind (by its worst relight, or geometry with --geometry-only) heads each half.");
    outln!("| half | kind | configuration | scenes | completions taken | choice (s) | wall (s) | rerender median (dB) | relight median / worst (dB) | relight, best gain, median / worst (dB) | geometry, capture median / worst (dB) | geometry median / worst (dB) | recovery median / worst (dB) | albedo RMSE / chroma | R MAE metal / dielectric | M MAE metal / dielectric |");
    outln!("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|");
    for config in &configs {
        for half in &r.halves {
            let mut lines: Vec<(f64, String)> = Vec::new();
            for kind in kinds.iter().map(Some).chain([None]) {
                let sel: Vec<&SceneRow> = rows
                    .iter()
                    .filter(|x| {
                        &x.half == half && &x.variant == config && kind.is_none_or(|k| &x.kind == k)
                    })
                    .collect();
                if sel.is_empty() {
                    continue;
                }
                let relight: Vec<f64> = sel.iter().flat_map(|x| x.relight).collect();
                let gained: Vec<f64> = sel.iter().flat_map(|x| x.relight_gain).collect();
                let recovery: Vec<f64> = sel.iter().flat_map(|x| x.recovery).collect();
                let capture: Vec<f64> = sel.iter().map(|x| x.geo_capture).collect();
                let geo: Vec<f64> = sel
                    .iter()
                    .flat_map(|x| [x.geo_capture, x.geo_relit[0], x.geo_relit[1]])
                    .collect();
                let mut taken: Vec<(String, usize)> = Vec::new();
                for x in &sel {
                    match taken.iter_mut().find(|t| t.0 == x.taken) {
                        Some(t) => t.1 += 1,
                        None => taken.push((x.taken.clone(), 1)),
                    }
                }
                let line = format!(
                    "| {} | {} | {} | {} | {} | {:.2} | {:.1} | {:.2} | {:.2} / {:.2} | {:.2} / {:.2} | {:.2} / {:.2} | {:.2} / {:.2} | {:.2} / {:.2} | {:.3} / {:.1}° | {:.3} / {:.3} | {:.3} / {:.3} |",
                    half,
                    kind.map(String::as_str).unwrap_or("all"),
                    config,
                    sel.len(),
                    taken
                        .iter()
                        .map(|(n, c)| format!("{n} {c}"))
                        .collect::<Vec<_>>()
                        .join(", "),
                    median(sel.iter().map(|x| x.choice_seconds).collect()),
                    median(sel.iter().map(|x| x.seconds).collect()),
                    median(sel.iter().map(|x| x.rerender).collect()),
                    median(relight.clone()),
                    min(&relight),
                    median(gained.clone()),
                    min(&gained),
                    median(capture.clone()),
                    min(&capture),
                    median(geo.clone()),
                    min(&geo),
                    median(recovery.clone()),
                    min(&recovery),
                    nan_mean(sel.iter().map(|x| x.albedo_rmse)),
                    nan_mean(sel.iter().map(|x| x.albedo_chroma_deg)),
                    nan_mean(sel.iter().map(|x| x.rough_mae[0])),
                    nan_mean(sel.iter().map(|x| x.rough_mae[1])),
                    nan_mean(sel.iter().map(|x| x.metal_mae[0])),
                    nan_mean(sel.iter().map(|x| x.metal_mae[1])),
                );
                let key = if r.geometry_only {
                    min(&geo)
                } else {
                    min(&relight)
                };
                lines.push((
                    if kind.is_some() {
                        key
                    } else {
                        f64::NEG_INFINITY
                    },
                    line,
                ));
            }
            // The whole half first, then its kinds from the worst up.
            lines.sort_by(|a, b| a.0.total_cmp(&b.0));
            for (_, l) in lines {
                outln!("{l}");
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn validation_index_names_its_halves_and_refuses_bad_fields() {
        let d = std::env::temp_dir().join(format!("matflow-val-{}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        std::fs::write(
            d.join("validation.json"),
            r#"{"tuning": ["scene-00"], "heldback": ["scene-01", "scene-02"]}"#,
        )
        .unwrap();
        let v = load_validation(&d).unwrap();
        assert_eq!(v.tuning, ["scene-00"]);
        assert_eq!(v.heldback, ["scene-01", "scene-02"]);
        // A set without kinds is closed rooms alone.
        assert_eq!(v.kind("scene-01"), "closed");
        std::fs::write(
            d.join("validation.json"),
            r#"{"tuning": ["scene-00"], "heldback": ["scene-01"], "kinds": {"scene-00": "stage", "scene-01": "outdoor"}}"#,
        )
        .unwrap();
        let v = load_validation(&d).unwrap();
        assert_eq!(
            (v.kind("scene-00"), v.kind("scene-01")),
            ("stage", "outdoor")
        );
        std::fs::write(
            d.join("validation.json"),
            r#"{"tuning": ["scene-00"], "heldback": [], "kinds": {"scene-00": 3}}"#,
        )
        .unwrap();
        let e = format!("{:#}", load_validation(&d).err().unwrap());
        assert!(e.contains("kinds.scene-00"), "{e}");
        std::fs::write(d.join("validation.json"), r#"{"tuning": "scene-00"}"#).unwrap();
        let e = format!("{:#}", load_validation(&d).err().unwrap());
        assert!(e.contains("tuning") && e.contains("validation.json"), "{e}");
        std::fs::remove_dir_all(&d).unwrap();
        let e = format!("{:#}", load_validation(&d).err().unwrap());
        assert!(e.contains("relight_scenes.py"), "{e}");
    }
}
