//! What every suite shares: the `matflow` binary it runs as a child (and
//! this program, for a suite that times one backend per process), the
//! `matflow run` of a pipeline as a timed child, medians, peak memory.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use anyhow::{bail, Context, Result};

/// The `matflow` binary the suites run as children: `$MATFLOW_BIN`, else
/// the one built beside this program (`cargo build --release` builds both
/// into `target/release/`).
pub fn matflow_exe() -> Result<PathBuf> {
    if let Some(p) = std::env::var_os("MATFLOW_BIN") {
        return Ok(PathBuf::from(p));
    }
    let me = bench_exe()?;
    let exe = me.with_file_name(format!("matflow{}", std::env::consts::EXE_SUFFIX));
    if !exe.is_file() {
        bail!(
            "no matflow binary beside {} (build it with `cargo build --release \
             -p matflow-cli`, or name one in $MATFLOW_BIN)",
            me.display()
        );
    }
    Ok(exe)
}

/// This program, for suites that time each backend in a process of its
/// own (`matflow-bench matnet --only-backend …`).
pub fn bench_exe() -> Result<PathBuf> {
    std::env::current_exe().context("finding the matflow-bench binary")
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
    matflow_engine::exec::peak_memory_bytes()
        .map(|b| b as f64 / (1024.0 * 1024.0))
        .unwrap_or(f64::NAN)
}

/// `matflow run FILE --quiet --cache CACHE --set S…` (the `sets`, then
/// `extra`) as a child process, as a user runs it: its wall time and the
/// summary line it ends with.
pub fn run_child(
    exe: &Path,
    file: &Path,
    cache: &Path,
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
    let (secs, text) = timed(c, &format!("matflow run {}", file.display()))?;
    Ok((secs, text.lines().last().unwrap_or("").to_string()))
}

/// Runs `c` as a timed child: its wall seconds and stdout, or an error
/// naming `what` with the child's stderr.
pub fn timed(mut c: Command, what: &str) -> Result<(f64, String)> {
    let t = Instant::now();
    let out = c.output().with_context(|| format!("starting {what}"))?;
    let secs = t.elapsed().as_secs_f64();
    if !out.status.success() {
        bail!("{what} failed:\n{}", String::from_utf8_lossy(&out.stderr));
    }
    Ok((secs, String::from_utf8_lossy(&out.stdout).into_owned()))
}

/// Runs the pipeline `text` as a file named `name` beside `original` (so
/// its relative paths resolve as the original's), through `run`; the
/// file is removed whatever the run's outcome.
pub fn run_beside<T>(
    original: &Path,
    name: &str,
    text: &str,
    run: impl FnOnce(&Path) -> Result<T>,
) -> Result<T> {
    let file = original.parent().unwrap_or(Path::new(".")).join(name);
    std::fs::write(&file, text).with_context(|| format!("writing {}", file.display()))?;
    let r = run(&file);
    let _ = std::fs::remove_file(&file);
    r
}

/// The text of the pipeline `file` with its `outputs:` line replaced by
/// `outputs: OUTPUTS` (a benchmark appends its own check stages).
pub fn with_outputs(file: &Path, outputs: &str) -> Result<String> {
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

/// Runs this binary as a child `matflow ARGS` (its stdout shown or
/// discarded); an error names the command and how it ended.
pub fn child(exe: &Path, args: &[impl AsRef<str>], show_stdout: bool) -> Result<()> {
    let args: Vec<&str> = args.iter().map(|a| a.as_ref()).collect();
    let mut cmd = std::process::Command::new(exe);
    cmd.args(&args);
    if !show_stdout {
        cmd.stdout(std::process::Stdio::null());
    }
    let status = cmd
        .status()
        .with_context(|| format!("running {}", exe.display()))?;
    if !status.success() {
        anyhow::bail!("`matflow {}` failed ({status})", args.join(" "));
    }
    Ok(())
}

/// What a stage command's child run measured, from its run report.
#[derive(Clone, Copy, Debug)]
pub struct StageTiming {
    /// The stage's seconds.
    pub seconds: f64,
    /// The child process's peak resident memory, in bytes (NaN where
    /// unknown).
    pub peak_bytes: f64,
}

/// Runs a stage command (`matflow invert`, `render`, `mesh`: a one-stage
/// pipeline) as a child that computes afresh, in an empty cache of its
/// own (removed after), so that a repeated benchmark never times a cache
/// hit; its stdout shown or discarded. Returns the stage's seconds and
/// the child's peak memory, from its run report.
pub fn stage_child(exe: &Path, args: &[impl AsRef<str>], show_stdout: bool) -> Result<StageTiming> {
    static RUNS: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    let n = RUNS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let dir = std::env::temp_dir().join(format!("matflow-bench-{}-{n}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let report = dir.join("report.json");
    let mut all: Vec<String> = args.iter().map(|a| a.as_ref().to_string()).collect();
    all.extend([
        "--cache".to_string(),
        path_arg(&dir.join("cache")),
        "--report".to_string(),
        path_arg(&report),
    ]);
    let ran = child(exe, &all, show_stdout).and_then(|_| {
        let text =
            std::fs::read(&report).with_context(|| format!("reading {}", report.display()))?;
        let r: serde_json::Value = serde_json::from_slice(&text)?;
        Ok(StageTiming {
            seconds: r["stages"][0]["seconds"].as_f64().unwrap_or(f64::NAN),
            peak_bytes: r["peak_memory_bytes"].as_f64().unwrap_or(f64::NAN),
        })
    });
    let _ = std::fs::remove_dir_all(&dir);
    ran
}

/// A path as a child's argument.
pub fn path_arg(p: &Path) -> String {
    p.display().to_string()
}

/// The machine, for a table's heading: CPU model and the threads this
/// process may use (Linux; "unknown CPU" elsewhere).
pub fn machine() -> String {
    let cpu = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split_once(':'))
                .map(|(_, v)| v.trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".into());
    let threads = std::thread::available_parallelism().map_or(0, |n| n.get());
    format!("{cpu}, {threads} threads")
}
