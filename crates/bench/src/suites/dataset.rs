//! `matflow-bench dataset`: samples per second of each generator at its
//! default resolution, and how a job scales from one shard process to two
//! (each process one thread, as job-array tasks on one core each), over
//! the binary. `matflow-bench refraction`: the refraction-length
//! network's inference time per 512² image on each backend, and its
//! held-out error next to the constant and thickness-rule baselines.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::Args;
use glam::Vec3;
use matflow_onnx::refraction::{expand, prepare, CROP, IN_CH, OUT_CH};
use matflow_onnx::{Backend, Model};
use matflow_scene::{Camera, GrayImage, Image};

use crate::harness::{bench_exe, matflow_exe, median};

#[derive(Args)]
pub struct BenchDatasetArgs {
    /// Samples of each generator's run.
    #[arg(long, default_value_t = 32)]
    pub samples: u64,
    /// Samples of the `rooms` run (its default 256² at 64 spp is slower).
    #[arg(long, default_value_t = 8)]
    pub room_samples: u64,
    /// Repetitions (medians are reported).
    #[arg(long, default_value_t = 3)]
    pub runs: usize,
    /// Work folder (specs, caches, shards); emptied first.
    #[arg(long, default_value = "target/bench-dataset")]
    pub work: PathBuf,
}

/// One `matflow dataset` job split over `procs` processes of `threads`
/// rayon threads each, all at once, on a fresh cache: its wall time.
fn job(spec: &Path, work: &Path, procs: u64, threads: usize, parallel: usize) -> Result<f64> {
    let cache = work.join("cache");
    let out = work.join("out");
    let _ = std::fs::remove_dir_all(&cache);
    let _ = std::fs::remove_dir_all(&out);
    let t0 = Instant::now();
    let kids: Vec<_> = (0..procs)
        .map(|i| {
            let mut c = Command::new(matflow_exe()?);
            c.args(["dataset"])
                .arg(spec)
                .arg("--out")
                .arg(&out)
                .arg("--cache")
                .arg(&cache)
                .args(["--quiet", "--parallel", &parallel.to_string()])
                .env("RAYON_NUM_THREADS", threads.to_string())
                .stdout(Stdio::null())
                .stderr(Stdio::piped());
            if procs > 1 {
                c.args(["--shards", &procs.to_string(), "--shard", &i.to_string()]);
            }
            c.spawn().context("starting matflow dataset")
        })
        .collect::<Result<_>>()?;
    for k in kids {
        let o = k.wait_with_output()?;
        if !o.status.success() {
            bail!(
                "matflow dataset failed: {}",
                String::from_utf8_lossy(&o.stderr)
            );
        }
    }
    Ok(t0.elapsed().as_secs_f64())
}

pub fn bench_dataset(a: BenchDatasetArgs) -> Result<()> {
    let _ = std::fs::remove_dir_all(&a.work);
    std::fs::create_dir_all(&a.work)?;
    let runs = a.runs.max(1);
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    outln!("bench dataset: {cores} cores, {runs} run(s) each, medians; every run on a fresh cache");
    let spec = |name: &str, generator: &str, samples: u64, shard: u64| -> Result<PathBuf> {
        let f = a.work.join(format!("{name}.yaml"));
        std::fs::write(
            &f,
            format!(
                "dataset:\n  name: {name}\n  generator: {generator}\n  samples: {samples}\n  \
                 seed: 1\n  shard_size: {shard}\n"
            ),
        )?;
        Ok(f)
    };
    outln!(
        "{:<12} {:>8} {:>14} {:>10} {:>12}",
        "generator",
        "samples",
        "resolution",
        "seconds",
        "samples/s"
    );
    let gens = [
        ("refraction", a.samples, "128² 32 spp"),
        ("rooms", a.room_samples, "256² 64 spp"),
    ];
    for (g, n, res) in gens {
        let f = spec(g, g, n, n.div_ceil(4).max(1))?;
        let t = median(
            (0..runs)
                .map(|_| job(&f, &a.work, 1, cores, 2))
                .collect::<Result<Vec<_>>>()?,
        );
        outln!(
            "{:<12} {:>8} {:>14} {:>10.2} {:>12.2}",
            g,
            n,
            res,
            t,
            n as f64 / t
        );
    }
    // Scaling: the refraction job as 1 and as 2 shard processes of one
    // thread each (and one process on every core, for reference).
    let f = spec("scaling", "refraction", a.samples, 4)?;
    let one = median(
        (0..runs)
            .map(|_| job(&f, &a.work, 1, 1, 1))
            .collect::<Result<Vec<_>>>()?,
    );
    let two = median(
        (0..runs)
            .map(|_| job(&f, &a.work, 2, 1, 1))
            .collect::<Result<Vec<_>>>()?,
    );
    let all = median(
        (0..runs)
            .map(|_| job(&f, &a.work, 1, cores, 2))
            .collect::<Result<Vec<_>>>()?,
    );
    outln!(
        "shard scaling (refraction, {} samples in shards of 4):",
        a.samples
    );
    outln!(
        "  1 process x 1 thread   {:>8.2} s  {:>6.2} samples/s",
        one,
        a.samples as f64 / one
    );
    outln!(
        "  2 processes x 1 thread {:>8.2} s  {:>6.2} samples/s  speed-up {:.2}x",
        two,
        a.samples as f64 / two,
        one / two
    );
    outln!(
        "  1 process x {cores} threads  {:>8.2} s  {:>6.2} samples/s  speed-up {:.2}x",
        all,
        a.samples as f64 / all,
        one / all
    );
    Ok(())
}

#[derive(Args)]
pub struct BenchRefractionArgs {
    /// Held-out dataset (a `refraction` dataset's folder) for the error
    /// table; skipped when absent.
    #[arg(long, default_value = "out/refraction/heldout")]
    pub heldout: PathBuf,
    /// The model (default: the bundled one).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Inference repetitions (medians are reported).
    #[arg(long, default_value_t = 10)]
    pub runs: usize,
    /// Time this backend only, in this process (what the benchmark runs
    /// itself with, once per backend: a process has one).
    #[arg(long, hide = true)]
    pub only_backend: Option<String>,
}

fn model_bytes(a: &BenchRefractionArgs) -> Result<(Vec<u8>, String)> {
    Ok(match &a.model {
        Some(p) => (
            std::fs::read(p).with_context(|| format!("reading {}", p.display()))?,
            p.display().to_string(),
        ),
        None => (
            matflow_nodes::BUNDLED_REFRACTION_MODEL.to_vec(),
            "the bundled model".into(),
        ),
    })
}

/// A 512² photograph of a ball filling a third of it, with its depth and
/// normals: the inference benchmark's input.
fn ball_photo(n: usize) -> (Image<Vec3>, Image<bool>, GrayImage, Image<Vec3>) {
    let cam = Camera::new(n, n);
    let (c, r) = (Vec3::new(0.0, 0.0, -3.0), 0.6f32);
    let mut mask = Image::new(n, n, false);
    let mut depth = Image::new(n, n, 0.0f32);
    let mut normal = Image::new(n, n, Vec3::Z);
    let mut img = Image::new(n, n, Vec3::splat(0.3));
    for y in 0..n {
        for x in 0..n {
            let d = cam
                .film_to_dir(glam::Vec2::new(x as f32 + 0.5, y as f32 + 0.5))
                .normalize();
            let b = d.dot(c);
            let disc = b * b - (c.length_squared() - r * r);
            if disc > 0.0 {
                let t = b - disc.sqrt();
                let p = d * t;
                let nn = (p - c) / r;
                mask.set(x, y, true);
                depth.set(x, y, -p.z);
                normal.set(x, y, nn);
                img.set(x, y, Vec3::splat(0.2 + 0.6 * nn.z.max(0.0)));
            }
        }
    }
    (img, mask, depth, normal)
}

fn time_backend(a: &BenchRefractionArgs, backend: Backend) -> Result<(f64, f64, f64)> {
    let (bytes, what) = model_bytes(a)?;
    let t0 = Instant::now();
    let m = Model::load(
        &bytes,
        &what,
        backend,
        [IN_CH, CROP, CROP],
        [OUT_CH, CROP, CROP],
    )?;
    let load = t0.elapsed().as_secs_f64();
    let n = 512;
    let (img, mask, depth, normal) = ball_photo(n);
    let focal = Camera::new(n, n).focal();
    let mut net = Vec::new();
    let mut total = Vec::new();
    for _ in 0..a.runs.max(1) {
        let t0 = Instant::now();
        let p = prepare(&img, &mask, &depth, &normal, focal)?;
        let t1 = Instant::now();
        let out = m.run(1, p.input.clone())?;
        let t2 = Instant::now();
        let maps = expand(&out, &p, &mask);
        std::hint::black_box(&maps);
        net.push((t2 - t1).as_secs_f64());
        total.push(t0.elapsed().as_secs_f64());
    }
    Ok((load, median(net), median(total)))
}

pub fn bench_refraction(a: BenchRefractionArgs) -> Result<()> {
    if let Some(b) = &a.only_backend {
        let backend = Backend::from_name(b).context("--only-backend: tract or onnxruntime")?;
        let (load, net, total) = time_backend(&a, backend)?;
        outln!("{load} {net} {total}");
        return Ok(());
    }
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    outln!(
        "bench refraction: {cores} cores; inference per 512² image (a ball filling a third), \
         median of {} runs",
        a.runs
    );
    outln!(
        "{:<12} {:>10} {:>12} {:>14}",
        "backend",
        "load ms",
        "network ms",
        "crop+net+map ms"
    );
    for b in Backend::NAMES {
        let mut c = Command::new(bench_exe()?);
        c.args(["refraction", "--only-backend", b, "--runs"])
            .arg(a.runs.to_string());
        if let Some(m) = &a.model {
            c.arg("--model").arg(m);
        }
        let o = c.output()?;
        let text = String::from_utf8_lossy(&o.stdout);
        let v: Vec<f64> = text
            .split_whitespace()
            .filter_map(|t| t.parse().ok())
            .collect();
        if !o.status.success() || v.len() != 3 {
            outln!(
                "{:<12} unavailable: {}",
                b,
                String::from_utf8_lossy(&o.stderr).trim()
            );
            continue;
        }
        outln!(
            "{:<12} {:>10.1} {:>12.2} {:>14.2}",
            b,
            v[0] * 1e3,
            v[1] * 1e3,
            v[2] * 1e3
        );
    }
    if !a.heldout.join("dataset.json").is_file() {
        outln!(
            "(no held-out data in {}: matflow dataset train/refraction/heldout.yaml --out {})",
            a.heldout.display(),
            a.heldout.display()
        );
        return Ok(());
    }
    heldout_errors(&a)
}

/// Mean absolute errors over the held-out samples' object pixels, in
/// scene units (the objects are 1 across): the network, the constant
/// baseline (the training mean, times each object's extent s) and the
/// thickness rule (d1 = the round-object chord, d2 = d1, length = d1).
fn heldout_errors(a: &BenchRefractionArgs) -> Result<()> {
    let (bytes, what) = model_bytes(a)?;
    let m = Model::load(
        &bytes,
        &what,
        Backend::Tract,
        [IN_CH, CROP, CROP],
        [OUT_CH, CROP, CROP],
    )?;
    let card: serde_json::Value = serde_json::from_slice(&std::fs::read(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../models/refraction_length.train.json"),
    )?)?;
    let constant: Vec<f32> = ["length", "d1", "d2"]
        .iter()
        .map(|k| card["constant"][k].as_f64().unwrap_or(0.0) as f32)
        .collect();
    let desc: serde_json::Value =
        serde_json::from_slice(&std::fs::read(a.heldout.join("dataset.json"))?)?;
    let name = desc["name"].as_str().unwrap_or("");
    let norm = desc["header"]["normaliser"]["length.npy"]
        .as_f64()
        .unwrap_or(1.0) as f32;
    // [method][channel]: (sum of |error|, pixels).
    let mut sums = [[(0.0f64, 0usize); 3]; 3];
    let mut samples = 0;
    for k in 0..desc["shards"].as_u64().unwrap_or(0) {
        let bytes = std::fs::read(a.heldout.join(format!("{name}-{k:06}.tar")))?;
        let entries = matflow_dataset::tar::read(&bytes)?;
        let mut by_key: std::collections::BTreeMap<
            String,
            std::collections::BTreeMap<String, &[u8]>,
        > = Default::default();
        for e in &entries {
            if let Some((key, member)) = e.name.split_once('.') {
                by_key
                    .entry(key.to_string())
                    .or_default()
                    .insert(member.to_string(), &bytes[e.offset..e.offset + e.size]);
            }
        }
        for members in by_key.values() {
            let npy = |m: &str| matflow_scene::npy::decode(members[m]).map_err(anyhow::Error::msg);
            let mask_png = image::load_from_memory(members["mask.png"])?.to_luma8();
            let (w, h) = (mask_png.width() as usize, mask_png.height() as usize);
            let mask = Image::from_fn(w, h, |x, y| {
                mask_png.get_pixel(x as u32, y as u32).0[0] > 127
            });
            if !mask.data.iter().any(|&b| b) {
                continue;
            }
            let photo_png = image::load_from_memory(members["image.png"])?.to_rgb8();
            let photo = Image::from_fn(w, h, |x, y| {
                let p = photo_png.get_pixel(x as u32, y as u32).0;
                Vec3::from_array(p.map(|c| matflow_scene::color::srgb_to_linear(c as f32 / 255.0)))
            });
            let gray = |m: &str| -> Result<GrayImage> { Ok(Image::from_vec(w, h, npy(m)?.values)) };
            let depth = gray("depth.npy")?;
            let nv = npy("normal.npy")?.values;
            let normal = Image::from_fn(w, h, |x, y| {
                let i = 3 * (y * w + x);
                Vec3::new(nv[i], nv[i + 1], nv[i + 2])
            });
            let truth = [
                gray("length.npy")?.map(|v| v * norm),
                gray("d1.npy")?,
                gray("d2.npy")?,
            ];
            let focal = Camera::new(w, h).focal();
            let p = prepare(&photo, &mask, &depth, &normal, focal)?;
            let out = m.run(1, p.input.clone())?;
            let net = expand(&out, &p, &mask);
            let thick = matflow_scene::transparency::thickness_rule(&mask, &depth, focal, 1.0);
            for q in 0..w * h {
                if !mask.data[q] {
                    continue;
                }
                for ch in 0..3 {
                    let t = truth[ch].data[q];
                    // d2 counts where something lies behind the object.
                    if ch == 2 && t <= 0.0 {
                        continue;
                    }
                    let guesses = [net[ch].data[q], constant[ch] * p.scale, thick.data[q]];
                    for (mi, g) in guesses.iter().enumerate() {
                        sums[mi][ch].0 += (g - t).abs() as f64;
                        sums[mi][ch].1 += 1;
                    }
                }
            }
            samples += 1;
        }
    }
    outln!(
        "held-out error ({samples} samples of {}; mean |error| over object pixels, scene \
         units, objects 1 across):",
        a.heldout.display()
    );
    outln!("{:<16} {:>9} {:>9} {:>9}", "method", "length", "d1", "d2");
    for (mi, name) in ["network", "constant", "thickness rule"].iter().enumerate() {
        let v: Vec<f64> = sums[mi]
            .iter()
            .map(|(s, n)| s / (*n).max(1) as f64)
            .collect();
        outln!("{:<16} {:>9.4} {:>9.4} {:>9.4}", name, v[0], v[1], v[2]);
    }
    Ok(())
}
