//! `matflow dataset`: generate a dataset's shards (all of them, or one
//! process's share of a job split `--shards N --shard I`), and `matflow
//! dataset merge DIR`: check the shards against their manifests and index
//! them.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::{Args, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};
use matflow_dataset::{merge, Job};

use matflow_engine::spec;
use matflow_engine::{run_pipeline, Digest, Observer, StageReport, Status, Value};

#[derive(Args)]
#[command(args_conflicts_with_subcommands = true)]
pub struct DatasetArgs {
    #[command(subcommand)]
    pub cmd: Option<DatasetCmd>,
    #[command(flatten)]
    pub gen: GenerateArgs,
}

#[derive(Subcommand)]
pub enum DatasetCmd {
    /// Check every shard in DIR against its manifest (members, order,
    /// BLAKE3 digests, every sample once) and write manifest.jsonl and
    /// index.json; exits 1 listing what is wrong.
    Merge { dir: PathBuf },
    /// Write one sample's members from the dataset in DIR into a folder,
    /// checked against the manifest, laid out as the generator says (a
    /// `rooms` sample becomes a reference bundle `matflow render` reads).
    Unpack {
        dir: PathBuf,
        /// The sample's key (s00000012).
        key: String,
        #[arg(long)]
        to: PathBuf,
    },
}

#[derive(Args)]
pub struct GenerateArgs {
    /// The dataset spec: a YAML file with a `dataset:` section.
    pub spec: Option<PathBuf>,
    /// Output folder (default: the spec's `out`).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Split the job over this many processes (e.g. a job array's tasks):
    /// with --shard I, write tar shards I, I+N, I+2N, …
    #[arg(long, value_name = "N", requires = "shard")]
    pub shards: Option<u64>,
    /// Which process this is (0-based; with --shards).
    #[arg(long, value_name = "I", requires = "shards")]
    pub shard: Option<u64>,
    /// Cache folder (as for `run`).
    #[arg(long)]
    pub cache: Option<PathBuf>,
    /// Override: dataset.samples=N, dataset.params.size=64, or a stage
    /// parameter of the file's own stages (YAML syntax; repeatable).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub set: Vec<String>,
    /// Samples' stages run at once.
    #[arg(long, default_value_t = 2)]
    pub parallel: usize,
    /// No progress bar.
    #[arg(long)]
    pub quiet: bool,
    /// Write a JSON report (the run's stages and the shards) here.
    #[arg(long)]
    pub report: Option<PathBuf>,
    /// Run even when estimated at more than an hour with nothing cached.
    #[arg(long)]
    pub allow_expensive: bool,
    #[command(flatten)]
    pub remote: crate::cluster::RemoteArgs,
}

pub fn dataset(a: DatasetArgs) -> Result<()> {
    match a.cmd {
        Some(DatasetCmd::Merge { dir }) => merge_cmd(&dir),
        Some(DatasetCmd::Unpack { dir, key, to }) => {
            let files = matflow_dataset::unpack(&dir, &key, &to)?;
            outln!("{}: {} files of {key}", to.display(), files.len());
            Ok(())
        }
        None => {
            let Some(spec) = a.gen.spec.clone() else {
                bail!("give a dataset spec (matflow dataset SPEC.yaml --out DIR) or `merge DIR`");
            };
            generate(&spec, &a.gen)
        }
    }
}

fn merge_cmd(dir: &Path) -> Result<()> {
    let r = merge(dir)?;
    if !r.problems.is_empty() {
        for p in &r.problems {
            eprintln!("{p}");
        }
        bail!(
            "{}: {} problem{} in {} shard{}; nothing was written",
            dir.display(),
            r.problems.len(),
            if r.problems.len() == 1 { "" } else { "s" },
            r.shards,
            if r.shards == 1 { "" } else { "s" }
        );
    }
    outln!(
        "{}: {} samples in {} shards, {} bytes: manifest.jsonl and index.json written",
        dir.display(),
        r.samples,
        r.shards,
        r.bytes
    );
    Ok(())
}

/// Whether a YAML file has a `dataset:` section (what sends `matflow run`
/// here).
pub fn has_dataset_section(file: &Path) -> bool {
    let Ok(text) = std::fs::read_to_string(file) else {
        return false;
    };
    matches!(
        matflow_engine::value::parse_yaml(&text),
        Ok((Value::Map(m), _)) if m.iter().any(|e| e.0 == "dataset")
    )
}

/// Watches a dataset job's stages: a sample counts (on the progress bar)
/// when all its stages have finished, run or found cached, and a tar
/// shard is written as soon as all its samples have — so a long job's
/// shards appear as it goes, not at its end.
struct ShardWriter<'a> {
    job: &'a Job,
    out: &'a Path,
    fetch: &'a (dyn Fn(&str) -> std::result::Result<Vec<u8>, String> + Sync),
    bar: Option<ProgressBar>,
    roles: Vec<&'static str>,
    state: Mutex<WriterState>,
}

#[derive(Default)]
struct WriterState {
    /// Finished stages per unfinished sample.
    stages_done: BTreeMap<u64, usize>,
    /// Outputs of finished stages whose shard is not written yet.
    outputs: BTreeMap<String, BTreeMap<String, String>>,
    /// Samples left per shard of this process.
    left: BTreeMap<u64, u64>,
    bytes: u64,
    written: usize,
    errors: Vec<String>,
}

impl ShardWriter<'_> {
    /// The sample a stage belongs to (`ROLE-INDEX` of this dataset).
    fn sample_of(&self, stage: &str) -> Option<u64> {
        let (role, idx) = stage.rsplit_once('-')?;
        if !self.roles.contains(&role) {
            return None;
        }
        idx.parse().ok()
    }
}

impl Observer for ShardWriter<'_> {
    fn finished(&self, r: &StageReport) {
        if !matches!(r.status, Status::Executed | Status::Cached) {
            return;
        }
        let Some(i) = self.sample_of(&r.name) else {
            return;
        };
        let mut st = self.state.lock().unwrap();
        st.outputs.insert(r.name.clone(), r.outputs.clone());
        let n = st.stages_done.entry(i).or_insert(0);
        *n += 1;
        if *n < self.roles.len() {
            return;
        }
        st.stages_done.remove(&i);
        if let Some(b) = &self.bar {
            b.inc(1);
        }
        let k = i / self.job.spec.shard_size;
        let Some(left) = st.left.get_mut(&k) else {
            return;
        };
        *left -= 1;
        if *left > 0 {
            return;
        }
        st.left.remove(&k);
        match self.job.write_shard(k, &st.outputs, self.fetch, self.out) {
            Ok(b) => {
                st.bytes += b;
                st.written += 1;
            }
            Err(e) => st.errors.push(e.to_string()),
        }
        // What the shard needed is on disk now.
        for i in self.job.spec.shard_samples(k) {
            for role in &self.roles {
                st.outputs
                    .remove(&matflow_dataset::shards::stage_name(role, i));
            }
        }
    }
}

pub fn generate(file: &Path, a: &GenerateArgs) -> Result<()> {
    let t0 = Instant::now();
    let overrides = crate::run::parse_overrides(&a.set)?;
    let (ds_over, stage_over) = matflow_dataset::spec::split_overrides(&overrides);
    let (root, root_loc, spec) = read_spec(file, &ds_over)?;
    let out = match (&a.out, &spec.out) {
        (Some(o), _) => o.clone(),
        (None, Some(o)) => o.clone(),
        (None, None) => bail!(
            "{}: give --out DIR or `out:` in the dataset section",
            file.display()
        ),
    };
    check_out(&out, file, &spec.reads)?;
    let split = match (a.shards, a.shard) {
        (Some(0), _) => bail!("--shards 0: give at least 1"),
        (Some(n), Some(i)) if i >= n => bail!("--shard {i}: must be below --shards {n}"),
        (Some(n), Some(i)) => Some((n, i)),
        _ => None,
    };
    let job = Job::new(spec).map_err(anyhow::Error::msg)?;
    let shards = job.shards_of(split);
    let reg = matflow_nodes::registry();
    let doc = job.pipeline_root(Some(&root), &shards);
    let p =
        spec::parse_value(doc, root_loc, file, &reg, &stage_over).map_err(anyhow::Error::msg)?;
    if !a.allow_expensive {
        crate::run::refuse_if_expensive(file, &spec::estimate_seconds(&p, &reg))?;
    }
    job.claim(&out)?;
    let samples: u64 = shards
        .iter()
        .map(|&k| job.spec.shard_samples(k).count() as u64)
        .sum();
    if shards.is_empty() {
        outln!(
            "{}: this process has no shards (the dataset has {})",
            file.display(),
            job.spec.shard_count()
        );
        return Ok(());
    }
    let dir = crate::run::cache_dir(a.cache.as_deref());
    let reg = Arc::new(reg);
    let (store, exec) = crate::cluster::executor(
        &a.remote,
        p.remote_cache.as_deref(),
        &dir,
        reg.clone(),
        a.parallel,
    )?;
    let bar = (!a.quiet).then(|| progress(samples, &job.spec.name));
    let fetch = |hex: &str| -> std::result::Result<Vec<u8>, String> {
        let d = Digest::from_hex(hex).ok_or_else(|| format!("bad digest {hex}"))?;
        match store.get(&d) {
            Ok(Some(b)) => Ok(b.to_vec()),
            Ok(None) => Err(format!("blob {hex} is not in the store")),
            Err(e) => Err(e.to_string()),
        }
    };
    let obs = ShardWriter {
        job: &job,
        out: &out,
        fetch: &fetch,
        bar,
        roles: job.plan.sample(0).stages.iter().map(|s| s.role).collect(),
        state: Mutex::new(WriterState {
            left: shards
                .iter()
                .map(|&k| (k, job.spec.shard_samples(k).count() as u64))
                .collect(),
            ..Default::default()
        }),
    };
    let report = run_pipeline(&p, &reg, &store, exec.as_ref(), &obs);
    if let Some(b) = &obs.bar {
        b.finish_and_clear();
    }
    let st = obs.state.into_inner().unwrap();
    check_written(&st, &report, file, &out, shards.len())?;
    let bytes = st.bytes;
    let executed = report
        .stages
        .iter()
        .filter(|s| s.status == Status::Executed)
        .count();
    let cached = report
        .stages
        .iter()
        .filter(|s| s.status == Status::Cached)
        .count();
    let secs = t0.elapsed().as_secs_f64();
    outln!(
        "{}: {samples} samples in {} shard{} ({bytes} bytes) in {}: {executed} stages run, \
         {cached} cached; {:.2} samples/s",
        out.display(),
        shards.len(),
        if shards.len() == 1 { "" } else { "s" },
        crate::run::duration(secs),
        samples as f64 / secs.max(1e-9)
    );
    // One process wrote every shard: check and index them now.
    if split.is_none() {
        let r = merge(&out)?;
        if !r.problems.is_empty() {
            for p in &r.problems {
                eprintln!("{p}");
            }
            bail!(
                "{}: the shards just written do not check out",
                out.display()
            );
        }
    }
    if let Some(path) = &a.report {
        let json = serde_json::json!({
            "dataset": job.spec.name,
            "out": out.display().to_string(),
            "shards": shards,
            "samples": samples,
            "bytes": bytes,
            "seconds": secs,
            "stages_executed": executed,
            "stages_cached": cached,
            "run": report,
        });
        matflow_scene::io::write_atomic(path, &serde_json::to_vec_pretty(&json)?)
            .with_context(|| format!("writing the report {}", path.display()))?;
    }
    Ok(())
}

/// The spec file's YAML root (where it starts) and its `dataset:`
/// section read with the dataset's overrides.
fn read_spec(
    file: &Path,
    ds_over: &[spec::Override],
) -> Result<(Value, matflow_engine::Loc, matflow_dataset::DatasetSpec)> {
    let text = std::fs::read_to_string(file)
        .with_context(|| format!("{}: cannot read the dataset spec", file.display()))?;
    let (root, root_loc) = matflow_engine::value::parse_yaml(&text).map_err(|e| {
        anyhow::anyhow!(
            "{}:{}:{}: {}",
            file.display(),
            e.loc.line,
            e.loc.col,
            e.message
        )
    })?;
    let section = match &root {
        Value::Map(m) => m.iter().find(|e| e.0 == "dataset").cloned(),
        _ => None,
    };
    let Some((_, _, sv, sl)) = section else {
        bail!(
            "{}: no `dataset:` section (a dataset spec is a mapping with `dataset:`)",
            file.display()
        );
    };
    let spec =
        matflow_dataset::parse_section(&sv, sl, file, ds_over).map_err(anyhow::Error::msg)?;
    Ok((root, root_loc, spec))
}

/// The samples/s and ETA bar of a job of `samples` samples.
fn progress(samples: u64, name: &str) -> ProgressBar {
    let b = ProgressBar::new(samples);
    b.set_style(
        ProgressStyle::with_template(
            "{prefix} [{bar:30}] {pos}/{len} samples  {per_sec}  ETA {eta}",
        )
        .expect("a valid template")
        .progress_chars("=> "),
    );
    b.set_prefix(name.to_string());
    b
}

/// After the run: every shard this process owns was written, and no
/// stage failed; otherwise an error saying how far it got.
fn check_written(
    st: &WriterState,
    report: &matflow_engine::Report,
    file: &Path,
    out: &Path,
    shards: usize,
) -> Result<()> {
    if !st.errors.is_empty() {
        bail!(
            "{}: writing shards: {}",
            out.display(),
            st.errors.join("; ")
        );
    }
    if let Some(f) = report.failure() {
        bail!(
            "{}: {f} ({} of {} shards written; a re-run recomputes nothing finished)",
            file.display(),
            st.written,
            shards
        );
    }
    if st.written != shards {
        bail!(
            "{}: {} of {} shards written, yet every stage finished",
            out.display(),
            st.written,
            shards
        );
    }
    Ok(())
}

/// The output folder must not be, or hold, the spec or an input.
fn check_out(out: &Path, file: &Path, reads: &[(PathBuf, String)]) -> Result<()> {
    let real = |p: &Path| -> PathBuf {
        std::fs::canonicalize(p).unwrap_or_else(|_| {
            std::env::current_dir()
                .map(|c| c.join(p))
                .unwrap_or_else(|_| p.to_path_buf())
        })
    };
    let o = real(out);
    let mut inputs: Vec<(PathBuf, String)> = vec![(real(file), "the dataset spec".into())];
    inputs.extend(reads.iter().map(|(p, w)| (real(p), w.clone())));
    for (p, what) in inputs {
        if p.starts_with(&o) {
            bail!(
                "--out {}: holds {what} ({}); write the dataset elsewhere",
                out.display(),
                p.display()
            );
        }
    }
    Ok(())
}
