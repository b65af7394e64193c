//! `matflow run` and `matflow cache`: the pipeline engine's front end.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use anyhow::{bail, Context, Result};
use clap::{Args, Subcommand};
use indicatif::{MultiProgress, ProgressBar, ProgressStyle};
use matflow_engine::exec::cached_keys;
use matflow_engine::spec::{self, Override};
use matflow_engine::store::GcPolicy;
use matflow_engine::{run_pipeline, Observer, Report, StageReport, Status, Store};

#[derive(Args)]
pub struct RunArgs {
    /// The pipeline file (YAML).
    pub pipeline: PathBuf,
    /// Cache folder (default: $MATFLOW_CACHE, else $XDG_CACHE_HOME/matflow,
    /// else ~/.cache/matflow).
    #[arg(long)]
    pub cache: Option<PathBuf>,
    /// Override a parameter: stage.param=value (YAML syntax; repeatable).
    #[arg(long = "set", value_name = "STAGE.PARAM=VALUE")]
    pub set: Vec<String>,
    /// Write the run's JSON report here.
    #[arg(long)]
    pub report: Option<PathBuf>,
    /// Stages run at once when independent.
    #[arg(long, default_value_t = 2)]
    pub parallel: usize,
    /// No progress bars.
    #[arg(long)]
    pub quiet: bool,
    /// Run even when the stages are estimated to take more than an hour
    /// in all (on the reference 2-core machine; without this flag such a
    /// run is refused before it starts, with the estimate).
    #[arg(long)]
    pub allow_expensive: bool,
    /// Split the pipeline's outputs into this many shards (one per job-array
    /// task): with --shard I, run only outputs I, I+N, I+2N, … (in the
    /// order `outputs:` lists them) and what they need. Shards sharing a
    /// store share their common stages' results; a run without --shard then
    /// finds every stage cached.
    #[arg(long, value_name = "N", requires = "shard")]
    pub shards: Option<usize>,
    /// Which shard this run is (0-based; with --shards).
    #[arg(long, value_name = "I", requires = "shards")]
    pub shard: Option<usize>,
    #[command(flatten)]
    pub remote: crate::cluster::RemoteArgs,
}

/// Keeps outputs `shard`, `shard + shards`, … of the pipeline.
pub fn select_shard(p: &mut spec::Pipeline, shards: usize, shard: usize) -> Result<()> {
    if shards == 0 {
        bail!("--shards 0: give at least 1");
    }
    if shard >= shards {
        bail!("--shard {shard}: shards are numbered 0 to {}", shards - 1);
    }
    p.outputs = p
        .outputs
        .iter()
        .enumerate()
        .filter(|(i, _)| i % shards == shard)
        .map(|(_, o)| o.clone())
        .collect();
    Ok(())
}

#[derive(Subcommand)]
pub enum CacheCmd {
    /// List the action cache: node key, kind, stage, outputs, last use.
    Ls(CacheDir),
    /// Totals: blobs, bytes, actions.
    Stats(CacheDir),
    /// Re-hash every blob and check every action; remove what is corrupt.
    Verify(CacheDir),
    /// Remove entries: keep what the given pipelines reference, and/or
    /// drop entries unused for a while, and/or shrink to a size.
    Gc(GcArgs),
}

#[derive(Args)]
pub struct CacheDir {
    #[arg(long)]
    pub cache: Option<PathBuf>,
}

#[derive(Args)]
pub struct GcArgs {
    #[arg(long)]
    pub cache: Option<PathBuf>,
    /// Keep only entries these pipelines (as they are now, with their
    /// defaults) reference.
    #[arg(long, value_name = "PIPELINE.yaml")]
    pub keep: Vec<PathBuf>,
    /// Remove entries not used for this many days.
    #[arg(long, value_name = "DAYS")]
    pub older_than: Option<f64>,
    /// Remove least recently used entries until the blobs fit (bytes, or
    /// with a K, M or G suffix).
    #[arg(long, value_name = "SIZE")]
    pub max_size: Option<String>,
}

/// The cache folder: flag, then $MATFLOW_CACHE, then the per-user cache.
pub fn cache_dir(flag: Option<&Path>) -> PathBuf {
    if let Some(p) = flag {
        return p.to_path_buf();
    }
    if let Some(p) = std::env::var_os("MATFLOW_CACHE").filter(|v| !v.is_empty()) {
        return PathBuf::from(p);
    }
    if let Some(p) = std::env::var_os("XDG_CACHE_HOME").filter(|v| !v.is_empty()) {
        return PathBuf::from(p).join("matflow");
    }
    if let Some(h) = std::env::var_os("HOME").filter(|v| !v.is_empty()) {
        return PathBuf::from(h).join(".cache").join("matflow");
    }
    PathBuf::from(".matflow-cache")
}

struct Bars {
    multi: MultiProgress,
    bars: Mutex<BTreeMap<String, ProgressBar>>,
    quiet: bool,
}

impl Observer for Bars {
    fn started(&self, stage: &str, kind: &str, worker: &str) {
        if self.quiet {
            return;
        }
        let pb = self.multi.add(ProgressBar::new(0));
        pb.set_style(
            ProgressStyle::with_template("{prefix:>18} {spinner} {msg} {elapsed}").unwrap(),
        );
        pb.set_prefix(stage.to_string());
        pb.set_message(if worker == "local" {
            kind.to_string()
        } else {
            format!("{kind} on {worker}")
        });
        pb.enable_steady_tick(Duration::from_millis(200));
        self.bars.lock().unwrap().insert(stage.to_string(), pb);
    }
    fn progress(&self, stage: &str, done: u64, total: u64) {
        if let Some(pb) = self.bars.lock().unwrap().get(stage) {
            if total > 0 {
                if pb.length() != Some(total) {
                    pb.set_style(
                        ProgressStyle::with_template(
                            "{prefix:>18} [{bar:30}] {pos}/{len} {msg} {elapsed}",
                        )
                        .unwrap()
                        .progress_chars("=> "),
                    );
                    pb.set_length(total);
                }
                pb.set_position(done);
            } else {
                pb.set_message(format!("step {done}"));
            }
        }
    }
    fn retried(&self, stage: &str, reason: &str) {
        if let Some(pb) = self.bars.lock().unwrap().get(stage) {
            pb.set_message(format!("retrying: {reason}"));
        }
    }
    fn finished(&self, r: &StageReport) {
        if let Some(pb) = self.bars.lock().unwrap().remove(&r.name) {
            pb.finish_and_clear();
            self.multi.remove(&pb);
        }
    }
}

/// The files a stage wrote, in words: each, or past six (a bundle
/// folder's), their count and the folder they share.
fn written_lines(files: &[String]) -> Vec<String> {
    if files.len() <= 6 {
        return files.iter().map(|f| format!("wrote {f}")).collect();
    }
    let parents: Vec<&std::path::Path> = files
        .iter()
        .filter_map(|f| std::path::Path::new(f).parent())
        .collect();
    let mut common = parents.first().copied().unwrap_or(std::path::Path::new(""));
    while !parents.iter().all(|p| p.starts_with(common)) {
        common = common.parent().unwrap_or(std::path::Path::new(""));
    }
    vec![format!(
        "wrote {} files under {} ({}, …)",
        files.len(),
        if common.as_os_str().is_empty() {
            ".".to_string()
        } else {
            common.display().to_string()
        },
        files[0]
    )]
}

fn print_table(r: &Report) {
    outln!(
        "{:<18} {:<16} {:<9} {:>8}  outputs",
        "stage",
        "kind",
        "status",
        "seconds"
    );
    for s in &r.stages {
        let outs = s
            .outputs
            .iter()
            .map(|(k, d)| format!("{k}={}", &d[..12]))
            .collect::<Vec<_>>()
            .join(" ");
        outln!(
            "{:<18} {:<16} {:<9} {:>8.2}  {}",
            s.name,
            s.kind,
            s.status.as_str(),
            s.seconds,
            outs
        );
        if let Some(w) = s.worker.as_deref().filter(|w| *w != "local") {
            outln!(
                "{:<18} on {w}: {} attempt{}, {} B in, {} B out",
                "",
                s.attempts,
                if s.attempts == 1 { "" } else { "s" },
                s.bytes_in,
                s.bytes_out
            );
        }
        for r in &s.retries {
            outln!("{:<18} retried: {r}", "");
        }
        for line in s.notes.iter().flat_map(|n| n.lines()) {
            outln!("{:<18} {line}", "");
        }
        for line in written_lines(&s.files) {
            outln!("{:<18} {line}", "");
        }
    }
    let n = |st: Status| r.stages.iter().filter(|s| s.status == st).count();
    outln!(
        "{}: {} executed, {} cached, {} skipped in {:.2} s (cache {}; {})",
        r.pipeline,
        n(Status::Executed),
        n(Status::Cached),
        n(Status::Skipped),
        r.seconds,
        r.cache,
        r.executor
    );
    if r.bytes_uploaded + r.bytes_downloaded > 0 {
        outln!(
            "remote store: {} B uploaded, {} B downloaded",
            r.bytes_uploaded,
            r.bytes_downloaded
        );
    }
}

/// Refuses a run estimated above [`spec::EXPENSIVE_SECONDS`], naming the
/// estimate and the stages that make it up.
pub fn refuse_if_expensive(pipeline: &std::path::Path, est: &[(String, f64)]) -> Result<()> {
    let total: f64 = est.iter().map(|(_, s)| s).sum();
    if total <= spec::EXPENSIVE_SECONDS {
        return Ok(());
    }
    let mut top: Vec<&(String, f64)> = est.iter().filter(|(_, s)| *s > 0.0).collect();
    top.sort_by(|a, b| b.1.total_cmp(&a.1));
    let parts: Vec<String> = top
        .iter()
        .take(3)
        .map(|(n, s)| format!("`{n}` {}", duration(*s)))
        .collect();
    bail!(
        "{}: this run is estimated at {} on the reference 2-core machine if nothing is cached \
         (most: {}); the limit without --allow-expensive is {}. Lower spp or size, or pass \
         --allow-expensive",
        pipeline.display(),
        duration(total),
        parts.join(", "),
        duration(spec::EXPENSIVE_SECONDS)
    )
}

/// Seconds as a short human duration.
pub fn duration(s: f64) -> String {
    if s < 120.0 {
        format!("{s:.0} s")
    } else if s < 7200.0 {
        format!("{:.0} min", s / 60.0)
    } else if s < 172_800.0 {
        format!("{:.1} h", s / 3600.0)
    } else {
        format!("{:.0} days", s / 86400.0)
    }
}

/// The `--set` arguments, parsed.
pub fn parse_overrides(set: &[String]) -> Result<Vec<Override>> {
    set.iter()
        .map(|s| Override::parse(s))
        .collect::<std::result::Result<Vec<_>, String>>()
        .map_err(anyhow::Error::msg)
}

pub fn run(a: RunArgs) -> Result<()> {
    // A file with a `dataset:` section is a dataset job (with its own
    // stages, if any).
    if crate::dataset::has_dataset_section(&a.pipeline) {
        return crate::dataset::generate(
            &a.pipeline,
            &crate::dataset::GenerateArgs {
                spec: Some(a.pipeline.clone()),
                out: None,
                shards: a.shards.map(|n| n as u64),
                shard: a.shard.map(|i| i as u64),
                cache: a.cache.clone(),
                set: a.set.clone(),
                parallel: a.parallel,
                quiet: a.quiet,
                report: a.report.clone(),
                allow_expensive: a.allow_expensive,
                remote: a.remote.clone(),
            },
        );
    }
    let reg = matflow_nodes::registry();
    let overrides = parse_overrides(&a.set)?;
    // Everything is validated before the cache is even opened.
    let mut p = spec::load(&a.pipeline, &reg, &overrides).map_err(anyhow::Error::msg)?;
    if let (Some(n), Some(i)) = (a.shards, a.shard) {
        select_shard(&mut p, n, i)?;
        if p.outputs.is_empty() {
            outln!(
                "{}: shard {i} of {n} has no outputs (the pipeline lists fewer than {n})",
                a.pipeline.display()
            );
        }
    }
    if !a.allow_expensive {
        refuse_if_expensive(&a.pipeline, &spec::estimate_seconds(&p, &reg))?;
    }
    execute(
        &p,
        reg,
        &Execution {
            cache: a.cache.as_deref(),
            remote: &a.remote,
            parallel: a.parallel,
            quiet: a.quiet,
            report: a.report.as_deref(),
            label: &a.pipeline.display().to_string(),
        },
    )
    .map(|_| ())
}

/// How [`execute`] runs a pipeline.
pub struct Execution<'a> {
    pub cache: Option<&'a Path>,
    pub remote: &'a crate::cluster::RemoteArgs,
    pub parallel: usize,
    pub quiet: bool,
    pub report: Option<&'a Path>,
    /// Names the pipeline in a failure.
    pub label: &'a str,
}

/// Runs a loaded pipeline: the store and executor, progress bars, the
/// report (printed, and written when asked), an error when a stage failed.
pub fn execute(p: &spec::Pipeline, reg: matflow_engine::Registry, e: &Execution) -> Result<Report> {
    let dir = cache_dir(e.cache);
    let reg = Arc::new(reg);
    let (store, exec) = crate::cluster::executor(
        e.remote,
        p.remote_cache.as_deref(),
        &dir,
        reg.clone(),
        e.parallel,
    )?;
    let bars = Bars {
        multi: MultiProgress::new(),
        bars: Mutex::new(BTreeMap::new()),
        quiet: e.quiet,
    };
    let report = run_pipeline(p, &reg, &store, exec.as_ref(), &bars);
    if let Some(path) = e.report {
        let json = serde_json::to_vec_pretty(&report)?;
        matflow_scene::io::write_atomic(path, &json)
            .with_context(|| format!("writing the report {}", path.display()))?;
    }
    print_table(&report);
    if let Some(f) = report.failure() {
        bail!("{}: {f}", e.label);
    }
    Ok(report)
}

fn parse_size(s: &str) -> Result<u64> {
    let s = s.trim();
    let (num, mult) = match s.chars().last() {
        Some('K' | 'k') => (&s[..s.len() - 1], 1u64 << 10),
        Some('M' | 'm') => (&s[..s.len() - 1], 1 << 20),
        Some('G' | 'g') => (&s[..s.len() - 1], 1 << 30),
        _ => (s, 1),
    };
    let x: f64 = num
        .parse()
        .with_context(|| format!("--max-size {s}: not a size"))?;
    if x.is_nan() || x < 0.0 {
        bail!("--max-size {s}: not a size");
    }
    Ok((x * mult as f64) as u64)
}

/// Lists on stderr what a cache tool could not do, and fails with
/// `summary` when there is anything.
fn fail_on(errors: &[String], what: &str, summary: String) -> Result<()> {
    if errors.is_empty() {
        return Ok(());
    }
    for e in errors {
        eprintln!("{what}: {e}");
    }
    bail!(summary)
}

pub fn cache(c: CacheCmd) -> Result<()> {
    match c {
        CacheCmd::Ls(d) => cache_ls(&d),
        CacheCmd::Stats(d) => cache_stats(&d),
        CacheCmd::Verify(d) => cache_verify(&d),
        CacheCmd::Gc(g) => cache_gc(&g),
    }
}

/// `cache ls`: one line per action (key, kind, stage, pipeline, the bytes
/// of its outputs, when last used).
fn cache_ls(d: &CacheDir) -> Result<()> {
    let store = Store::open(cache_dir(d.cache.as_deref()))?;
    let sizes: BTreeMap<_, _> = store.blobs().into_iter().collect();
    outln!(
        "{:<14} {:<16} {:<18} {:<12} {:>10}  last used",
        "key",
        "kind",
        "stage",
        "pipeline",
        "bytes"
    );
    for (k, a, t) in store.actions() {
        let age = t.elapsed().map(|d| d.as_secs()).unwrap_or(0);
        match a {
            Some(a) => {
                let bytes: u64 = a
                    .digests()
                    .unwrap_or_default()
                    .values()
                    .map(|d| sizes.get(d).copied().unwrap_or(0))
                    .sum();
                outln!(
                    "{:<14} {:<16} {:<18} {:<12} {:>10}  {} s ago",
                    &k.hex()[..12],
                    a.kind,
                    a.stage,
                    a.pipeline,
                    bytes,
                    age
                );
            }
            None => outln!("{:<14} (unreadable entry)", &k.hex()[..12]),
        }
    }
    Ok(())
}

/// `cache stats`: counts and sizes.
fn cache_stats(d: &CacheDir) -> Result<()> {
    let store = Store::open(cache_dir(d.cache.as_deref()))?;
    let s = store.stats();
    outln!(
        "{}: {} blobs, {} bytes ({:.1} MB), {} actions, {} temporary files",
        store.root().display(),
        s.blobs,
        s.blob_bytes,
        s.blob_bytes as f64 / 1e6,
        s.actions,
        s.temp_files
    );
    Ok(())
}

/// `cache verify`: every blob against its digest, every action's outputs
/// against the types their nodes declare; damage is removed and counted.
fn cache_verify(d: &CacheDir) -> Result<()> {
    let store = Store::open(cache_dir(d.cache.as_deref()))?;
    let reg = matflow_nodes::registry();
    // Each output must decode as the type its node declares.
    let r = store.verify_with(|a, name, bytes| {
        let node = reg
            .get(&a.kind)
            .ok_or_else(|| format!("unknown node kind `{}`", a.kind))?;
        let spec = node
            .outputs()
            .iter()
            .find(|o| o.name == name)
            .ok_or_else(|| format!("a {} stage has no output `{name}`", a.kind))?;
        // A note is text and a file any bytes (what a stage writes out
        // as it is); every other output is an artifact of its type.
        let ok = match spec.ty {
            "file" => true,
            "note" => std::str::from_utf8(bytes).is_ok(),
            ty => reg.artifact_is(bytes, &[ty]),
        };
        if ok {
            Ok(())
        } else if spec.ty == "note" {
            Err("not text (a note)".into())
        } else {
            Err(format!("not a {} artifact", spec.ty))
        }
    });
    let bad = r.blobs_corrupt.len()
        + r.actions_unreadable.len()
        + r.actions_incomplete.len()
        + r.actions_wrong_type.len();
    outln!(
            "{} blobs intact, {} corrupt; {} actions complete, {} unreadable, {} incomplete, {} of the wrong type; removed {} blobs and {} actions",
            r.blobs_ok,
            r.blobs_corrupt.len(),
            r.actions_ok,
            r.actions_unreadable.len(),
            r.actions_incomplete.len(),
            r.actions_wrong_type.len(),
            r.blobs_removed,
            r.actions_removed
        );
    for b in &r.blobs_corrupt {
        outln!("corrupt blob {b}");
    }
    for w in &r.actions_wrong_type {
        outln!("wrong type {w}");
    }
    fail_on(
        &r.errors,
        "could not read or remove",
        format!(
            "verify: {} files could not be read or removed ({bad} damaged entries found)",
            r.errors.len()
        ),
    )?;
    Ok(())
}

/// `cache gc`: removes what the policy does not keep.
fn cache_gc(g: &GcArgs) -> Result<()> {
    if g.keep.is_empty() && g.older_than.is_none() && g.max_size.is_none() {
        bail!(
            "gc: say what to keep: --keep PIPELINE.yaml, --older-than DAYS and/or --max-size SIZE"
        );
    }
    let store = Store::open(cache_dir(g.cache.as_deref()))?;
    let mut keep_stages = std::collections::BTreeSet::new();
    let keep = if g.keep.is_empty() {
        None
    } else {
        let reg = matflow_nodes::registry();
        let mut keys = std::collections::BTreeSet::new();
        for f in &g.keep {
            let p = spec::load(f, &reg, &[]).map_err(anyhow::Error::msg)?;
            let c = cached_keys(&p, &reg, &store);
            keys.extend(c.keys);
            keep_stages.extend(c.unresolved);
        }
        Some(keys)
    };
    let older_than = match g.older_than {
        Some(d) if d >= 0.0 && d.is_finite() => Some(Duration::from_secs_f64(d * 86400.0)),
        Some(d) => bail!("--older-than {d}: give a number of days ≥ 0"),
        None => None,
    };
    let max_bytes = g.max_size.as_deref().map(parse_size).transpose()?;
    let r = store.gc(&GcPolicy {
        keep,
        older_than,
        max_bytes,
        keep_stages,
    });
    outln!(
        "removed {} actions, {} blobs ({} bytes), {} stale temporary files",
        r.actions_removed,
        r.blobs_removed,
        r.bytes_freed,
        r.temp_removed
    );
    if r.actions_kept_unresolved > 0 {
        outln!(
                "kept {} entries of stages whose keys could not be worked out (an entry above them is missing or damaged; run the pipeline to repair it)",
                r.actions_kept_unresolved
            );
    }
    fail_on(
        &r.errors,
        "could not remove",
        format!(
            "gc: {} removals failed (nothing counted above was left behind)",
            r.errors.len()
        ),
    )?;
    Ok(())
}
