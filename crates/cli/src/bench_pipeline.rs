//! `matflow bench pipeline`: the engine's incremental re-edit, timed over
//! the binary as a user runs it (each run a child `matflow run`).

use std::path::PathBuf;
use std::process::Command;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::Args;

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
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

pub fn bench_pipeline(a: BenchPipelineArgs) -> Result<()> {
    let exe = std::env::current_exe()?;
    if a.work.exists() {
        std::fs::remove_dir_all(&a.work)
            .with_context(|| format!("emptying {}", a.work.display()))?;
    }
    std::fs::create_dir_all(&a.work)?;
    let cache = a.work.join("cache");
    let scale = a.size as f64 / 256.0;
    let base: Vec<String> = vec![
        format!("scene.size={}", a.size),
        format!("base.spp={}", a.spp),
        format!("relit.spp={}", a.spp),
        format!(
            "shiny.mask_flood=[{}, {}]",
            (205.0 * scale).round(),
            (185.0 * scale).round()
        ),
        format!("edited.output={}", a.work.join("edited.exr").display()),
        format!("relit.output={}", a.work.join("relit.exr").display()),
    ];
    let run_file = |file: &std::path::Path, extra: &[String]| -> Result<(f64, String)> {
        let mut c = Command::new(&exe);
        c.arg("run")
            .arg(file)
            .arg("--quiet")
            .arg("--cache")
            .arg(&cache);
        for s in base.iter().chain(extra) {
            c.arg("--set").arg(s);
        }
        let t = Instant::now();
        let out = c.output()?;
        let secs = t.elapsed().as_secs_f64();
        if !out.status.success() {
            bail!(
                "matflow run failed:\n{}",
                String::from_utf8_lossy(&out.stderr)
            );
        }
        let text = String::from_utf8_lossy(&out.stdout).into_owned();
        let summary = text.lines().last().unwrap_or("").to_string();
        Ok((secs, summary))
    };
    let run = |extra: &[String]| run_file(&a.pipeline, extra);
    println!(
        "bench pipeline: {} at {}², {} spp, {} thread(s); each run is a child `matflow run`",
        a.pipeline.display(),
        a.size,
        a.spp,
        rayon::current_num_threads()
    );
    let (first, s) = run(&[])?;
    println!("first run (empty cache): {first:.2} s   [{s}]");
    let mut edits = Vec::new();
    let mut same = Vec::new();
    for k in 0..a.runs.max(1) {
        let r = format!("shiny.roughness={}", 0.3 + 0.1 * k as f64);
        let (t, s) = run(std::slice::from_ref(&r))?;
        println!("re-edit {}: {t:.2} s   [{s}]", k + 1);
        edits.push(t);
        let (t, s) = run(std::slice::from_ref(&r))?;
        println!("no change {}: {t:.2} s   [{s}]", k + 1);
        same.push(t);
    }
    println!(
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
        let text = std::fs::read_to_string(&a.pipeline)?;
        let Some(i) = text.find("\noutputs:") else {
            bail!("{}: no `outputs:` line", a.pipeline.display());
        };
        let end = text[i + 1..]
            .find('\n')
            .map(|j| i + 1 + j)
            .unwrap_or(text.len());
        let mut t = format!(
            "{}\noutputs: [edited, full, reference]{}",
            &text[..i],
            &text[end..]
        );
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
        let file = a
            .pipeline
            .parent()
            .unwrap_or(std::path::Path::new("."))
            .join(".bench-pipeline-check.yaml");
        std::fs::write(&file, t)?;
        let r = run_file(&file, &[]);
        let _ = std::fs::remove_file(&file);
        r?;
        let load = |n: &str| matflow_scene::io::read_exr_rgb(&a.work.join(format!("{n}.exr")));
        let (e, f, r) = (load("edited")?, load("full")?, load("reference")?);
        use matflow_scene::metrics::psnr_gamma;
        println!(
            "edit render against a {} spp reference (sRGB PSNR): from kept paths {:.2} dB, \
             full path trace at {} spp {:.2} dB",
            a.reference_spp,
            psnr_gamma(&e, &r),
            a.spp,
            psnr_gamma(&f, &r)
        );
    }
    Ok(())
}
