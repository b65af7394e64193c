//! A dataset job's stages, its tar shards and manifests, and their merge.
//!
//! Samples are grouped into tar shards of `shard_size` by index (shard k
//! holds samples k·S … k·S + S − 1), whatever the number of processes: a
//! process given `--shards N --shard I` writes tar shards I, I + N, … So
//! every shard — and every sample's bytes — is the same however the job
//! is split, and a shard is a unit a cluster task finishes or redoes.
//!
//! In the output folder:
//! - `{name}-{k:06}.tar`: WebDataset shards; sample i's members are
//!   `s{i:08}.{member}` (the generator's members and `meta.json`, the
//!   choices that made it), consecutive, in a fixed order;
//! - `{name}-{k:06}.jsonl`: one line per sample: key, index, shard, each
//!   member's BLAKE3 and size, and the choices that made it;
//! - `dataset.json`: the spec (generator, seed, samples, shard size,
//!   parameters), the generator's header (normaliser, objects, envmaps)
//!   and the shard pattern;
//! - after `merge`: `manifest.jsonl` (every sample in order) and
//!   `index.json` (per shard: samples, bytes, BLAKE3 of the file).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use matflow_engine::{Loc, Value};
use serde_json::json;

use crate::generator::{json_of, Plan};
use crate::spec::DatasetSpec;
use crate::tar;

/// A dataset job: the spec and its prepared generator.
pub struct Job {
    pub spec: DatasetSpec,
    pub plan: Box<dyn Plan>,
}

#[derive(Debug, thiserror::Error)]
pub enum ShardError {
    #[error("{path}: {message}")]
    Io { path: PathBuf, message: String },
    #[error("{0}")]
    Invalid(String),
}

fn io_err(path: &Path, e: impl std::fmt::Display) -> ShardError {
    ShardError::Io {
        path: path.to_path_buf(),
        message: e.to_string(),
    }
}

/// The WebDataset key of sample `i`.
pub fn key(i: u64) -> String {
    format!("s{i:08}")
}

/// The stage of sample `i` with role `role`.
pub fn stage_name(role: &str, i: u64) -> String {
    format!("{role}-{i:08}")
}

impl Job {
    pub fn new(spec: DatasetSpec) -> Result<Job, matflow_engine::SpecError> {
        let plan = spec.generator.plan(&spec)?;
        Ok(Job { spec, plan })
    }

    /// The tar shards process `shard` of `shards` writes (all of them
    /// for `None`).
    pub fn shards_of(&self, split: Option<(u64, u64)>) -> Vec<u64> {
        let n = self.spec.shard_count();
        match split {
            None => (0..n).collect(),
            Some((count, me)) => (0..n).filter(|k| k % count.max(1) == me).collect(),
        }
    }

    /// The file name of tar shard `k` (`ext`: tar or jsonl).
    pub fn shard_file(&self, k: u64, ext: &str) -> String {
        format!("{}-{k:06}.{ext}", self.spec.name)
    }

    /// The pipeline stages of `shards`' samples, as a `stages:` mapping
    /// for the pipeline loader, and their names (the outputs wanted).
    pub fn stages(&self, shards: &[u64]) -> (Value, Vec<String>) {
        let at = self.spec.loc;
        let mut stages = Vec::new();
        let mut names = Vec::new();
        for &k in shards {
            for i in self.spec.shard_samples(k) {
                for st in self.plan.sample(i).stages {
                    let name = stage_name(st.role, i);
                    let mut fields =
                        vec![("kind".to_string(), at, Value::Str(st.kind.to_string()), at)];
                    fields.extend(st.params.into_iter().map(|(k, v)| (k, at, v, at)));
                    stages.push((name.clone(), at, Value::Map(fields), at));
                    names.push(name);
                }
            }
        }
        (Value::Map(stages), names)
    }

    /// A pipeline document (as the loader reads one) running `shards`:
    /// `root`'s own stages and outputs (a pipeline with a `dataset:`
    /// section), or none, plus the samples'.
    pub fn pipeline_root(&self, root: Option<&Value>, shards: &[u64]) -> Value {
        let (Value::Map(gen), names) = self.stages(shards) else {
            unreachable!("stages() returns a mapping")
        };
        let at = self.spec.loc;
        let mut top: Vec<(String, Loc, Value, Loc)> = match root {
            Some(Value::Map(m)) => m.iter().filter(|e| e.0 != "dataset").cloned().collect(),
            _ => vec![(
                "pipeline".into(),
                at,
                Value::Str(self.spec.name.clone()),
                at,
            )],
        };
        let mut put =
            |key: &str, add: Vec<(String, Loc, Value, Loc)>, list: Option<Vec<Value>>| match top
                .iter_mut()
                .find(|e| e.0 == key)
            {
                Some(e) => match (&mut e.2, list) {
                    (Value::Map(m), None) => m.extend(add),
                    (Value::List(l), Some(xs)) => l.extend(xs),
                    (v @ Value::Str(_), Some(mut xs)) => {
                        xs.insert(0, v.clone());
                        *v = Value::List(xs);
                    }
                    _ => {}
                },
                None => top.push((
                    key.into(),
                    at,
                    match list {
                        Some(xs) => Value::List(xs),
                        None => Value::Map(add),
                    },
                    at,
                )),
            };
        put("stages", gen, None);
        put(
            "outputs",
            Vec::new(),
            Some(names.into_iter().map(Value::Str).collect()),
        );
        Value::Map(top)
    }

    /// What `dataset.json` holds.
    pub fn description(&self) -> serde_json::Value {
        let s = &self.spec;
        let mut members = self.plan.members();
        members.push("meta.json".into());
        json!({
            "format": "webdataset",
            "name": s.name,
            "generator": s.generator.name(),
            "seed": s.seed,
            "samples": s.samples,
            "shard_size": s.shard_size,
            "shards": s.shard_count(),
            "shard_pattern": format!(
                "{}-{{{:06}..{:06}}}.tar",
                s.name,
                0,
                s.shard_count().saturating_sub(1)
            ),
            "key_pattern": "s{index:08}",
            "members": members,
            "layout": self.plan.layout().into_iter().collect::<BTreeMap<_, _>>(),
            "params": json_of(&s.params),
            "header": self.plan.header(),
        })
    }

    /// Writes `dataset.json` into `out`, or checks that the one there
    /// describes this dataset (another spec's shards must not mix in).
    pub fn claim(&self, out: &Path) -> Result<(), ShardError> {
        std::fs::create_dir_all(out).map_err(|e| io_err(out, e))?;
        let path = out.join("dataset.json");
        let want = self.description();
        if let Ok(text) = std::fs::read_to_string(&path) {
            let have: serde_json::Value =
                serde_json::from_str(&text).map_err(|e| io_err(&path, e))?;
            if have != want {
                return Err(ShardError::Invalid(format!(
                    "{} describes another dataset (generator, seed, samples, shard size or \
                     parameters differ): write this one elsewhere, or remove that folder",
                    path.display()
                )));
            }
            return Ok(());
        }
        let bytes = serde_json::to_vec_pretty(&want).expect("JSON values serialise");
        matflow_scene::io::write_atomic(&path, &bytes).map_err(|e| io_err(&path, e))
    }

    /// Writes tar shard `k` and its manifest from the stages' outputs
    /// (`outputs`: stage → output → BLAKE3 hex, as a run reports them;
    /// `fetch`: a blob's bytes by its hex digest). Returns the tar's size.
    pub fn write_shard(
        &self,
        k: u64,
        outputs: &BTreeMap<String, BTreeMap<String, String>>,
        fetch: &dyn Fn(&str) -> Result<Vec<u8>, String>,
        out: &Path,
    ) -> Result<u64, ShardError> {
        let mut w = tar::Writer::new();
        let mut lines = String::new();
        let tar_name = self.shard_file(k, "tar");
        for i in self.spec.shard_samples(k) {
            let sample = self.plan.sample(i);
            let key = key(i);
            let mut members: Vec<(String, Vec<u8>)> = Vec::new();
            for st in &sample.stages {
                let name = stage_name(st.role, i);
                let outs = outputs.get(&name).ok_or_else(|| {
                    ShardError::Invalid(format!("sample {key}: stage `{name}` has no results"))
                })?;
                for (member, digest) in outs {
                    let bytes = fetch(digest).map_err(|e| {
                        ShardError::Invalid(format!("sample {key}, `{member}`: {e}"))
                    })?;
                    members.push((member.clone(), bytes));
                }
            }
            let meta = serde_json::to_vec(&sample.meta).expect("JSON values serialise");
            members.push(("meta.json".into(), meta));
            // The generator's order, then meta.json.
            let order = self.plan.members();
            let rank = |m: &str| order.iter().position(|o| o == m).unwrap_or(order.len());
            members.sort_by_key(|(m, _)| rank(m));
            let mut listed = serde_json::Map::new();
            for (m, bytes) in &members {
                w.add(&format!("{key}.{m}"), bytes)
                    .map_err(|e| ShardError::Invalid(e.to_string()))?;
                listed.insert(
                    m.clone(),
                    json!({"blake3": blake3::hash(bytes).to_hex().to_string(), "bytes": bytes.len()}),
                );
            }
            let line = json!({
                "key": key,
                "index": i,
                "shard": tar_name,
                "members": listed,
                "params": sample.meta,
            });
            lines.push_str(&line.to_string());
            lines.push('\n');
        }
        let bytes = w.finish();
        let tar_path = out.join(&tar_name);
        matflow_scene::io::write_if_changed(&tar_path, &bytes).map_err(|e| io_err(&tar_path, e))?;
        let jl = out.join(self.shard_file(k, "jsonl"));
        matflow_scene::io::write_if_changed(&jl, lines.as_bytes()).map_err(|e| io_err(&jl, e))?;
        Ok(bytes.len() as u64)
    }
}

/// What `merge` found.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct MergeReport {
    pub shards: u64,
    pub samples: u64,
    pub bytes: u64,
    /// Problems, one per line; the merge writes nothing when there are any.
    pub problems: Vec<String>,
}

/// Checks every shard of the dataset in `dir` against its manifest
/// (members present, in order, with their BLAKE3 digests; every sample of
/// the spec present once) and, when all is well, writes `manifest.jsonl`
/// and `index.json`.
pub fn merge(dir: &Path) -> Result<MergeReport, ShardError> {
    let d = description(dir)?;
    let mut report = MergeReport {
        shards: d.shards,
        ..Default::default()
    };
    let mut manifest = String::new();
    let mut index = Vec::new();
    for k in 0..d.shards {
        match check_shard(dir, &d, k) {
            Ok(shard) => {
                report.samples += shard.count;
                report.bytes += shard.bytes;
                manifest.push_str(&shard.manifest);
                index.push(shard.entry);
            }
            Err(problems) => report.problems.extend(problems),
        }
    }
    if report.problems.is_empty() {
        let idx = json!({
            "name": d.name,
            "samples": report.samples,
            "bytes": report.bytes,
            "shards": index,
        });
        let p = dir.join("manifest.jsonl");
        matflow_scene::io::write_if_changed(&p, manifest.as_bytes()).map_err(|e| io_err(&p, e))?;
        let p = dir.join("index.json");
        let b = serde_json::to_vec_pretty(&idx).expect("JSON values serialise");
        matflow_scene::io::write_if_changed(&p, &b).map_err(|e| io_err(&p, e))?;
    }
    Ok(report)
}

/// What `dataset.json` says of a dataset's shards.
struct Description {
    name: String,
    samples: u64,
    shard_size: u64,
    shards: u64,
    /// Each sample's members, in order.
    members: Vec<String>,
}

fn description(dir: &Path) -> Result<Description, ShardError> {
    let desc_path = dir.join("dataset.json");
    let text = std::fs::read_to_string(&desc_path).map_err(|e| io_err(&desc_path, e))?;
    let desc: serde_json::Value = serde_json::from_str(&text).map_err(|e| io_err(&desc_path, e))?;
    let num = |k: &str| desc.get(k).and_then(|v| v.as_u64());
    let (Some(samples), Some(shard_size), Some(shards), Some(name)) = (
        num("samples"),
        num("shard_size"),
        num("shards"),
        desc.get("name").and_then(|v| v.as_str()),
    ) else {
        return Err(io_err(
            &desc_path,
            "not a dataset description (needs name, samples, shard_size, shards)",
        ));
    };
    let members: Vec<String> = desc
        .get("members")
        .and_then(|m| m.as_array())
        .map(|a| {
            a.iter()
                .filter_map(|v| v.as_str().map(String::from))
                .collect()
        })
        .unwrap_or_default();
    Ok(Description {
        name: name.to_string(),
        samples,
        shard_size,
        shards,
        members,
    })
}

/// A shard that checks out: its manifest lines, samples, size and index
/// entry.
struct CheckedShard {
    manifest: String,
    count: u64,
    bytes: u64,
    entry: serde_json::Value,
}

/// Shard `k` against its manifest: every sample in order, every member in
/// place with the BLAKE3 the manifest claims, nothing more; or what is
/// wrong with it.
fn check_shard(dir: &Path, d: &Description, k: u64) -> Result<CheckedShard, Vec<String>> {
    let mut manifest = String::new();
    let tar_name = format!("{}-{k:06}.tar", d.name);
    let tar_path = dir.join(&tar_name);
    let jl_path = dir.join(format!("{}-{k:06}.jsonl", d.name));
    let (bytes, lines) = match (std::fs::read(&tar_path), std::fs::read_to_string(&jl_path)) {
        (Ok(b), Ok(l)) => (b, l),
        (Err(e), _) => return Err(vec![format!("{}: {e}", tar_path.display())]),
        (_, Err(e)) => return Err(vec![format!("{}: {e}", jl_path.display())]),
    };
    let entries = match tar::read(&bytes) {
        Ok(e) => e,
        Err(e) => return Err(vec![format!("{}: {e}", tar_path.display())]),
    };
    let expect: Vec<u64> = (k * d.shard_size..((k + 1) * d.shard_size).min(d.samples)).collect();
    let mut at = 0usize;
    let mut problems = Vec::new();
    let mut count = 0u64;
    for (n, line) in lines.lines().enumerate() {
        let v: serde_json::Value = match serde_json::from_str(line) {
            Ok(v) => v,
            Err(e) => {
                problems.push(format!("{}:{}: {e}", jl_path.display(), n + 1));
                break;
            }
        };
        let index = v.get("index").and_then(|x| x.as_u64());
        if index != expect.get(n).copied() {
            problems.push(format!(
                "{}:{}: sample {:?}, expected {:?}",
                jl_path.display(),
                n + 1,
                index,
                expect.get(n)
            ));
            break;
        }
        let key = key(index.unwrap_or(0));
        let listed = v.get("members").and_then(|m| m.as_object());
        for m in &d.members {
            let want = format!("{key}.{m}");
            let Some(e) = entries.get(at).filter(|e| e.name == want) else {
                problems.push(format!(
                    "{tar_name}: expected member {want} at position {at}, found {}",
                    entries.get(at).map_or("the end".into(), |e| e.name.clone())
                ));
                break;
            };
            let digest = blake3::hash(&bytes[e.offset..e.offset + e.size])
                .to_hex()
                .to_string();
            let claimed = listed
                .and_then(|l| l.get(m))
                .and_then(|x| x.get("blake3"))
                .and_then(|x| x.as_str());
            if claimed != Some(digest.as_str()) {
                problems.push(format!(
                    "{tar_name}: {want} has BLAKE3 {digest}, the manifest says {}",
                    claimed.unwrap_or("nothing")
                ));
            }
            at += 1;
        }
        if !problems.is_empty() {
            break;
        }
        manifest.push_str(line);
        manifest.push('\n');
        count += 1;
    }
    if problems.is_empty() && count != expect.len() as u64 {
        problems.push(format!(
            "{}: {count} samples, the spec puts {} in this shard",
            jl_path.display(),
            expect.len()
        ));
    }
    if problems.is_empty() && at != entries.len() {
        problems.push(format!(
            "{tar_name}: {} members beyond the manifest's",
            entries.len() - at
        ));
    }
    if !problems.is_empty() {
        return Err(problems);
    }
    Ok(CheckedShard {
        manifest,
        count,
        bytes: bytes.len() as u64,
        entry: json!({
            "file": tar_name,
            "samples": count,
            "first": expect.first(),
            "bytes": bytes.len(),
            "blake3": blake3::hash(&bytes).to_hex().to_string(),
        }),
    })
}

/// Writes sample `key`'s members from the dataset in `dir` into the folder
/// `to`, each checked against its manifest digest and placed where the
/// dataset's `layout` says (e.g. a rooms sample as a reference bundle).
/// Returns the files written.
pub fn unpack(dir: &Path, key: &str, to: &Path) -> Result<Vec<PathBuf>, ShardError> {
    let desc_path = dir.join("dataset.json");
    let text = std::fs::read_to_string(&desc_path).map_err(|e| io_err(&desc_path, e))?;
    let desc: serde_json::Value = serde_json::from_str(&text).map_err(|e| io_err(&desc_path, e))?;
    let (Some(name), Some(shard_size), Some(samples)) = (
        desc.get("name").and_then(|v| v.as_str()),
        desc.get("shard_size").and_then(|v| v.as_u64()),
        desc.get("samples").and_then(|v| v.as_u64()),
    ) else {
        return Err(io_err(&desc_path, "not a dataset description"));
    };
    let index = key
        .strip_prefix('s')
        .and_then(|d| d.parse::<u64>().ok())
        .filter(|&i| i < samples && self::key(i) == key)
        .ok_or_else(|| {
            ShardError::Invalid(format!(
                "no sample `{key}` (keys are s00000000 to {})",
                self::key(samples.saturating_sub(1))
            ))
        })?;
    let k = index / shard_size;
    let tar_path = dir.join(format!("{name}-{k:06}.tar"));
    let jl_path = dir.join(format!("{name}-{k:06}.jsonl"));
    let bytes = std::fs::read(&tar_path).map_err(|e| io_err(&tar_path, e))?;
    let lines = std::fs::read_to_string(&jl_path).map_err(|e| io_err(&jl_path, e))?;
    let line: serde_json::Value = lines
        .lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .find(|v| v.get("key").and_then(|k| k.as_str()) == Some(key))
        .ok_or_else(|| io_err(&jl_path, format!("no line for sample {key}")))?;
    let entries = tar::read(&bytes).map_err(|e| io_err(&tar_path, e))?;
    let layout = desc.get("layout").and_then(|l| l.as_object());
    let prefix = format!("{key}.");
    let mut written = Vec::new();
    for e in entries.iter().filter(|e| e.name.starts_with(&prefix)) {
        let member = &e.name[prefix.len()..];
        let data = &bytes[e.offset..e.offset + e.size];
        let want = line
            .get("members")
            .and_then(|m| m.get(member))
            .and_then(|m| m.get("blake3"))
            .and_then(|d| d.as_str());
        let got = blake3::hash(data).to_hex().to_string();
        if want != Some(got.as_str()) {
            return Err(io_err(
                &tar_path,
                format!(
                    "{}: BLAKE3 {got}, the manifest says {}",
                    e.name,
                    want.unwrap_or("nothing")
                ),
            ));
        }
        let rel = layout
            .and_then(|l| l.get(member))
            .and_then(|v| v.as_str())
            .unwrap_or(member);
        let path = to.join(rel);
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent).map_err(|e| io_err(parent, e))?;
        }
        matflow_scene::io::write_atomic(&path, data).map_err(|e| io_err(&path, e))?;
        written.push(path);
    }
    if written.is_empty() {
        return Err(io_err(&tar_path, format!("no members for sample {key}")));
    }
    Ok(written)
}
