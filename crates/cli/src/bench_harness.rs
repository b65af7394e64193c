//! What every benchmark shares: the binary it re-runs as a child, the
//! `matflow run` of a pipeline as a timed child, medians, peak memory.
//! (Issue 48: the seed of the `matflow-bench` program's harness.)

use std::path::PathBuf;
use std::process::Command;
use std::time::Instant;

use anyhow::{bail, Context, Result};

/// The matflow binary running now: benchmarks run it again as children.
pub fn matflow_exe() -> Result<PathBuf> {
    std::env::current_exe().context("finding the matflow binary")
}

/// The median of `v` (the upper of the middle two for an even count);
/// NaN when empty.
pub fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

/// This process's peak resident memory in MiB (Linux), NaN elsewhere.
pub fn peak_rss_mib() -> f64 {
    crate::invert::peak_memory_bytes()
        .map(|b| b as f64 / (1024.0 * 1024.0))
        .unwrap_or(f64::NAN)
}

/// `matflow run FILE --quiet --cache CACHE --set S…` (the `sets`, then
/// `extra`) as a child process, as a user runs it: its wall time and the
/// summary line it ends with.
pub fn run_child(
    exe: &std::path::Path,
    file: &std::path::Path,
    cache: &std::path::Path,
    sets: &[String],
    extra: &[String],
) -> Result<(f64, String)> {
    let mut c = Command::new(exe);
    c.arg("run")
        .arg(file)
        .arg("--quiet")
        .arg("--cache")
        .arg(cache);
    for s in sets.iter().chain(extra) {
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
    Ok((secs, text.lines().last().unwrap_or("").to_string()))
}

/// The text of the pipeline `file` with its `outputs:` line replaced by
/// `outputs: OUTPUTS` (a benchmark appends its own check stages).
pub fn with_outputs(file: &std::path::Path, outputs: &str) -> Result<String> {
    let text = std::fs::read_to_string(file)?;
    let Some(i) = text.find("\noutputs:") else {
        bail!("{}: no `outputs:` line", file.display());
    };
    let end = text[i + 1..]
        .find('\n')
        .map(|j| i + 1 + j)
        .unwrap_or(text.len());
    Ok(format!(
        "{}\noutputs: {outputs}{}",
        &text[..i],
        &text[end..]
    ))
}
