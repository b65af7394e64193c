//! `matflow-bench matnet`: the prediction stage.
//!
//! - Inference time and peak memory per 512² photo for the bundled model
//!   and, with `--extra-model`, another MatNet-contract export (e.g. the
//!   randomly initialised MatNet-architecture one), on each backend; each
//!   (model, backend) in its own process (a process has one backend, and
//!   its peak resident memory is then that model's).
//! - Accuracy of the bundled model (or `--model`) per scene and per kind
//!   of scene, on held-out generated scenes and on another renderer's,
//!   against the predictors that need no network
//!   ([`super::matnet_eval`]).
//! - On the reference bundles: the bundled model's (or `--model`'s) maps
//!   against the official MatNet's stored predictions, and
//!   (`--e2e-budget`) the re-render PSNR of `pipelines/photo.yaml` started
//!   from each.

use std::path::PathBuf;
use std::process::Command;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::Args;
use glam::Vec3;
use matflow_nodes::{load_matnet_model, matnet_linear_square, matnet_predict, read_matnet_photo};
use matflow_onnx::matnet::network_input;
use matflow_onnx::Backend;
use matflow_scene::{Bundle, GrayImage, MaterialMaps, MaterialSource, RgbImage};

use crate::harness::{bench_exe, matflow_exe, median, peak_rss_mib};

#[derive(Args)]
pub struct BenchMatnetArgs {
    /// Held-out `rooms` dataset (train/matnet/kinds-heldout.yaml) for the
    /// accuracy tables; skipped when absent.
    #[arg(long, default_value = "out/matnet/heldout")]
    pub heldout: PathBuf,
    /// Bundles of another renderer with ground truth and their kinds
    /// (crates/bench/scripts/relight_scenes.py --kinds ...) for the
    /// accuracy tables; skipped when absent.
    #[arg(long, default_value = "out/kinds")]
    pub scenes: PathBuf,
    /// The model the accuracy tables and the end-to-end runs evaluate
    /// (default: the bundled one); the timing is the bundled model's.
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Only the accuracy tables (no timing, no reference bundles).
    #[arg(long)]
    pub accuracy_only: bool,
    /// The reference's data (bundles `indoor` and `jinjya`); skipped when
    /// absent.
    #[arg(long, default_value = "../shared/data/materialist")]
    pub reference: PathBuf,
    /// Another MatNet-contract ONNX model to time beside the bundled one.
    #[arg(long)]
    pub extra_model: Option<PathBuf>,
    /// The photo to time on (default: pipelines/photos/room.png, 512²).
    #[arg(long, default_value = "pipelines/photos/room.png")]
    pub photo: PathBuf,
    /// Inference repetitions for the bundled model (medians reported).
    #[arg(long, default_value_t = 5)]
    pub runs: usize,
    /// Repetitions for the extra model.
    #[arg(long, default_value_t = 2)]
    pub extra_runs: usize,
    /// Run pipelines/photo.yaml on each reference bundle from the model's
    /// predictions (the bundled one or `--model`) and from the official
    /// ones, with this material_opt budget (seconds), and report re-render
    /// PSNR; 0 skips.
    #[arg(long, default_value_t = 0.0)]
    pub e2e_budget: f64,
    /// A parameter of pipelines/photo.yaml for both end-to-end runs
    /// (`STAGE.PARAM=VALUE`, as `matflow run --set`; repeatable), e.g.
    /// `mesh.normals=predicted`.
    #[arg(long = "e2e-set", value_name = "STAGE.PARAM=VALUE")]
    pub e2e_set: Vec<String>,
    /// Work folder for the end-to-end runs.
    #[arg(long, default_value = "target/bench-matnet")]
    pub work: PathBuf,
    #[arg(long, hide = true)]
    pub only_backend: Option<String>,
    #[arg(long, hide = true)]
    pub only_model: Option<PathBuf>,
}

/// The child: load once, predict `runs` times; one JSON line.
fn time_one(a: &BenchMatnetArgs, backend: Backend) -> Result<()> {
    let photo = read_matnet_photo(&a.photo).map_err(anyhow::Error::msg)?;
    let t0 = Instant::now();
    let m = load_matnet_model(a.only_model.as_deref(), backend).map_err(anyhow::Error::msg)?;
    let load = t0.elapsed().as_secs_f64();
    let mut whole = vec![];
    let mut net = vec![];
    for _ in 0..a.runs.max(1) {
        let t = Instant::now();
        matnet_predict(&photo, &m).map_err(anyhow::Error::msg)?;
        whole.push(t.elapsed().as_secs_f64());
        let n = m.contract.input;
        let x = network_input(&matnet_linear_square(&photo), n);
        let t = Instant::now();
        m.graph
            .run(&[1, 3, n, n], x.data)
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        net.push(t.elapsed().as_secs_f64());
    }
    println!(
        "{}",
        serde_json::json!({
            "load_s": load,
            "predict_s": median(whole),
            "network_s": median(net),
            "peak_mb": peak_rss_mib(),
            "input": m.contract.input,
            "mb": m.info.bytes as f64 / 1e6,
            "blake3": m.info.blake3,
        })
    );
    Ok(())
}

fn onnxruntime_installed() -> bool {
    std::env::var_os("ORT_DYLIB_PATH").is_some()
        || matflow_onnx::runtime::find_onnxruntime().is_ok()
}

fn timing_table(a: &BenchMatnetArgs) -> Result<()> {
    let mut models: Vec<(String, Option<PathBuf>, usize)> =
        vec![("bundled (matnet_rooms)".into(), None, a.runs)];
    if let Some(p) = &a.extra_model {
        models.push((p.display().to_string(), Some(p.clone()), a.extra_runs));
    }
    let mut backends = vec![Backend::Tract];
    if onnxruntime_installed() {
        backends.push(Backend::OnnxRuntime);
    } else {
        println!("(onnxruntime is not installed: tract only)");
    }
    println!(
        "\ninference per photo ({} → 512², one image at a time; medians)",
        a.photo.display()
    );
    println!(
        "| model | MB | input | backend | network | photo → maps | load | peak memory |\n|---|---|---|---|---|---|---|---|"
    );
    for (name, path, runs) in &models {
        for b in &backends {
            let mut c = Command::new(bench_exe()?);
            c.args(["matnet", "--only-backend", b.name()])
                .arg("--photo")
                .arg(&a.photo)
                .args(["--runs", &runs.to_string()]);
            if let Some(p) = path {
                c.arg("--only-model").arg(p);
            }
            let o = c.output()?;
            if !o.status.success() {
                println!(
                    "| {name} | | | {} | failed: {} | | | |",
                    b.name(),
                    String::from_utf8_lossy(&o.stderr).trim()
                );
                continue;
            }
            let v: serde_json::Value = serde_json::from_slice(&o.stdout)
                .with_context(|| String::from_utf8_lossy(&o.stdout).to_string())?;
            let f = |k: &str| v[k].as_f64().unwrap_or(f64::NAN);
            println!(
                "| {name} | {:.1} | {}² | {} | {:.3} s | {:.3} s | {:.2} s | {:.0} MB |",
                f("mb"),
                v["input"],
                b.name(),
                f("network_s"),
                f("predict_s"),
                f("load_s"),
                f("peak_mb")
            );
        }
    }
    Ok(())
}

/// Errors of predicted maps against reference maps over the pixels where
/// the reference depth is positive.
#[derive(Default, Clone, Copy)]
struct Errors {
    albedo: f64,
    roughness: f64,
    metallic: f64,
    normal_deg: f64,
    depth_absrel: f64,
    depth_aligned: f64,
}

impl Errors {
    fn row(&self, name: &str) -> String {
        format!(
            "| {name} | {:.3} | {:.3} | {:.3} | {:.1}° | {:.3} | {:.3} |",
            self.albedo,
            self.roughness,
            self.metallic,
            self.normal_deg,
            self.depth_absrel,
            self.depth_aligned
        )
    }
}

/// `pred` against `truth` (truth's size; the prediction is resized).
fn compare(pred: &MaterialMaps, z: &GrayImage, truth: &MaterialMaps, tz: &GrayImage) -> Errors {
    let (w, h) = (tz.width, tz.height);
    let valid: Vec<usize> = (0..w * h).filter(|&i| tz.data[i] > 0.0).collect();
    if valid.is_empty() {
        return Errors::default();
    }
    // Bilinear at pixel centres: the identity when the sizes agree.
    let resize = |img: &RgbImage| matflow_scene::io::resize_bilinear(img, w, h);
    let albedo = resize(&pred.albedo);
    let rough = resize(&pred.roughness.to_rgb());
    let metal = resize(&pred.metallic.to_rgb());
    let normal = resize(pred.normal.as_ref().expect("predictions carry normals"));
    let zp = resize(&z.to_rgb());
    let n = valid.len() as f64;
    let zt: Vec<f64> = valid.iter().map(|&i| tz.data[i] as f64).collect();
    let zq: Vec<f64> = valid.iter().map(|&i| zp.data[i].x as f64).collect();
    let scale = median(zt.clone()) / median(zq.clone()).max(1e-12);
    let mut e = Errors::default();
    let tn = truth.normal.as_ref();
    for (k, &i) in valid.iter().enumerate() {
        let ta = truth.albedo.data[i].clamp(Vec3::ZERO, Vec3::ONE);
        e.albedo += ((albedo.data[i] - ta).abs().element_sum() / 3.0) as f64;
        e.roughness += (rough.data[i].x - truth.roughness.data[i]).abs() as f64;
        e.metallic += (metal.data[i].x - truth.metallic.data[i]).abs() as f64;
        if let Some(tn) = tn {
            let a = normal.data[i].normalize_or_zero();
            let b = tn.data[i].normalize_or_zero();
            e.normal_deg += (a.dot(b).clamp(-1.0, 1.0) as f64).acos().to_degrees();
        }
        let (p, t) = (zq[k], zt[k]);
        e.depth_absrel += (p - t).abs() / t;
        e.depth_aligned += (p * scale - t).abs() / t;
    }
    e.albedo /= n;
    e.roughness /= n;
    e.metallic /= n;
    e.normal_deg /= n;
    e.depth_absrel /= n;
    e.depth_aligned /= n;
    e
}

/// What the accuracy tables and the end-to-end runs evaluate: `--model`,
/// or the bundled model.
fn model_name(a: &BenchMatnetArgs) -> String {
    match &a.model {
        Some(p) => p.display().to_string(),
        None => "the bundled model".to_string(),
    }
}

/// The accuracy tables ([`super::matnet_eval`]): the held-out `rooms`
/// scenes and the other renderer's scenes, each per scene and per kind.
fn kinds_tables(a: &BenchMatnetArgs) -> Result<()> {
    use super::matnet_eval::{bundle_scenes, dataset_scenes, print_tables, score};
    let m = load_matnet_model(a.model.as_deref(), Backend::Tract).map_err(anyhow::Error::msg)?;
    let what = model_name(a);
    let tmp = std::env::temp_dir().join(format!("matflow-bench-matnet-{}", std::process::id()));
    let sets = [
        (
            format!("held-out generated scenes ({})", a.heldout.display()),
            dataset_scenes(&a.heldout, &tmp)?,
            format!(
                "`matflow dataset train/matnet/kinds-heldout.yaml --out {}` makes them",
                a.heldout.display()
            ),
        ),
        (
            format!("scenes of another renderer ({})", a.scenes.display()),
            bundle_scenes(&a.scenes)?,
            format!(
                "`python3 crates/bench/scripts/relight_scenes.py --out {} --scenes 8 --kinds \
                 closed open stage outdoor --size 256 --spp 128` makes them (Mitsuba 3)",
                a.scenes.display()
            ),
        ),
    ];
    for (title, scenes, how) in sets {
        if scenes.is_empty() {
            println!(
                "
(no {title}: {how})"
            );
            continue;
        }
        let mut rows = vec![];
        for sc in scenes {
            let s = score(&sc.dir, &m).with_context(|| sc.dir.display().to_string())?;
            rows.push((sc, s));
        }
        print_tables(&format!("{what} on {title}"), &rows);
    }
    let _ = std::fs::remove_dir_all(&tmp);
    Ok(())
}

/// The official MatNet's stored predictions of a reference bundle, as
/// maps and z.
fn official(b: &Bundle) -> Result<(MaterialMaps, GrayImage)> {
    let mut m = b.load_materials(MaterialSource::Pred)?;
    m.albedo = m.albedo.map(|v| v.clamp(Vec3::ZERO, Vec3::ONE));
    Ok((m, b.load_depth()?))
}

fn reference_table(a: &BenchMatnetArgs) -> Result<()> {
    let names = ["indoor", "jinjya"];
    if !names.iter().all(|n| a.reference.join(n).is_dir()) {
        println!("\n(no reference bundles under {})", a.reference.display());
        return Ok(());
    }
    let m = load_matnet_model(a.model.as_deref(), Backend::Tract).map_err(anyhow::Error::msg)?;
    println!(
        "\n{} against the official MatNet's stored predictions (reference bundles; from gt_image.png)",
        model_name(a)
    );
    println!("| bundle | albedo MAE | roughness MAE | metallic MAE | normal angle | depth AbsRel | AbsRel, median-aligned |\n|---|---|---|---|---|---|---|");
    for n in names {
        let dir = a.reference.join(n);
        let b = Bundle::open(&dir)?;
        let (om, oz) = official(&b)?;
        let photo = read_matnet_photo(&dir.join("gt_image.png")).map_err(anyhow::Error::msg)?;
        let p = matnet_predict(&photo, &m).map_err(anyhow::Error::msg)?;
        println!("{}", compare(&p.materials(), &p.z, &om, &oz).row(n));
    }
    if a.e2e_budget > 0.0 {
        e2e(a, &names)?;
    }
    Ok(())
}

/// pipelines/photo.yaml's re-render from the model's predictions (the
/// bundled one or `--model`) and from the official ones (the `predict`
/// stage swapped for a `bundle` stage), each against the photo.
fn e2e(a: &BenchMatnetArgs, names: &[&str]) -> Result<()> {
    println!(
        "\nend to end: pipelines/photo.yaml (lighting {:.0} s, material_opt {:.0} s budgets{}), re-render PSNR against the photo (sRGB)",
        (a.e2e_budget / 3.0).max(1.0),
        a.e2e_budget,
        a.e2e_set.iter().map(|s| format!(", {s}")).collect::<String>()
    );
    println!(
        "| bundle | from {} | from the official MatNet predictions |\n|---|---|---|",
        model_name(a)
    );
    // The pipeline's paths are relative to its own folder.
    let model = match &a.model {
        Some(p) => {
            Some(std::fs::canonicalize(p).with_context(|| format!("--model {}", p.display()))?)
        }
        None => None,
    };
    let _ = std::fs::remove_dir_all(&a.work);
    std::fs::create_dir_all(&a.work)?;
    for n in names {
        let dir = a.reference.join(n);
        let truth = Bundle::open(&dir)?.load_gt_image()?;
        let mut row = vec![];
        for from in ["ours", "official"] {
            let out = a.work.join(format!("{n}-{from}.exr"));
            let mut c = Command::new(matflow_exe()?);
            c.args(["run", "pipelines/photo.yaml", "--quiet", "--cache"])
                .arg(a.work.join("cache"))
                .arg("--set")
                .arg(format!("rerender.output={}", out.display()))
                .arg("--set")
                .arg(format!("edited.output={}", a.work.join("e.exr").display()))
                .arg("--set")
                .arg(format!("relit.output={}", a.work.join("r.exr").display()))
                .arg("--set")
                .arg(format!(
                    "lighting.budget_seconds={}",
                    (a.e2e_budget / 3.0).max(1.0)
                ))
                .arg("--set")
                .arg(format!("recovered.budget_seconds={}", a.e2e_budget));
            for s in &a.e2e_set {
                c.args(["--set", s]);
            }
            if from == "ours" {
                c.arg("--set")
                    .arg(format!(
                        "predict.photo={}",
                        dir.join("gt_image.png").display()
                    ))
                    .arg("--set")
                    .arg(format!(
                        "predict.output={}",
                        a.work.join(format!("{n}-bundle")).display()
                    ));
                if let Some(m) = &model {
                    c.arg("--set").arg(format!("predict.model={}", m.display()));
                }
            } else {
                c.args(["--set", "predict.kind=bundle", "--set"])
                    .arg(format!("predict.path={}", dir.display()));
            }
            let o = c.output()?;
            if !o.status.success() {
                bail!(
                    "{n} from {from}: {}",
                    String::from_utf8_lossy(&o.stderr).trim()
                );
            }
            let img = matflow_scene::io::read_exr_rgb(&out)?;
            row.push(matflow_scene::metrics::psnr_gamma(&img, &truth));
        }
        println!("| {n} | {:.2} dB | {:.2} dB |", row[0], row[1]);
    }
    Ok(())
}

pub fn bench_matnet(a: BenchMatnetArgs) -> Result<()> {
    if let Some(b) = &a.only_backend {
        let backend = Backend::from_name(b).context("backend: tract or onnxruntime")?;
        return time_one(&a, backend);
    }
    println!(
        "machine: {} cores; release build",
        std::thread::available_parallelism()
            .map(|n| n.get())
            .unwrap_or(1)
    );
    if !a.accuracy_only {
        timing_table(&a)?;
    }
    kinds_tables(&a)?;
    if !a.accuracy_only {
        reference_table(&a)?;
    }
    Ok(())
}
