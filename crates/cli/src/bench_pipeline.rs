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
        format!("edited.spp={}", a.spp),
        format!("relit.spp={}", a.spp),
        format!(
            "shiny.mask_flood=[{}, {}]",
            (205.0 * scale).round(),
            (185.0 * scale).round()
        ),
        format!("edited.output={}", a.work.join("edited.exr").display()),
        format!("relit.output={}", a.work.join("relit.exr").display()),
    ];
    let run = |extra: &[String]| -> Result<(f64, String)> {
        let mut c = Command::new(&exe);
        c.arg("run")
            .arg(&a.pipeline)
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
    Ok(())
}
