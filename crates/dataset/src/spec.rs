//! The `dataset:` section of a YAML file — a dataset spec on its own, or
//! beside a pipeline's stages — read with the pipeline loader (line and
//! column on every error, paths resolved against the file's folder):
//!
//! ```yaml
//! dataset:
//!   name: refraction          # shard and manifest names (default: the file's)
//!   generator: refraction     # what makes each sample
//!   samples: 10000
//!   seed: 1                   # sample i is a function of (spec, seed, i)
//!   shard_size: 64            # samples per tar shard
//!   out: ../data/refraction   # default output folder (`--out` overrides)
//!   params: { size: 128 }     # the generator's parameters
//! ```

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use matflow_engine::node::resolve_path;
use matflow_engine::spec::{normalize_fields, Override, SpecError};
use matflow_engine::value::clip;
use matflow_engine::{Loc, ParamType, Value};

use crate::generator::{generator, Generator, GENERATORS};

/// Most samples a dataset may have.
pub const MAX_SAMPLES: i64 = 100_000_000;
/// Default samples per tar shard.
pub const DEFAULT_SHARD_SIZE: i64 = 64;

/// A validated dataset spec.
#[derive(Clone)]
pub struct DatasetSpec {
    pub file: PathBuf,
    /// Where the section starts.
    pub loc: Loc,
    pub name: String,
    pub generator: &'static dyn Generator,
    pub samples: u64,
    pub seed: u64,
    pub shard_size: u64,
    pub out: Option<PathBuf>,
    /// The generator's parameters: every field, defaults filled, paths
    /// absolute, in the generator's order.
    pub params: Value,
    /// The input files the parameters name (for the output checks).
    pub reads: Vec<(PathBuf, String)>,
}

impl std::fmt::Debug for DatasetSpec {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DatasetSpec")
            .field("name", &self.name)
            .field("generator", &self.generator.name())
            .field("samples", &self.samples)
            .field("seed", &self.seed)
            .field("shard_size", &self.shard_size)
            .finish()
    }
}

impl DatasetSpec {
    /// Tar shards in all.
    pub fn shard_count(&self) -> u64 {
        self.samples.div_ceil(self.shard_size)
    }
    /// The samples of tar shard `k`.
    pub fn shard_samples(&self, k: u64) -> std::ops::Range<u64> {
        let a = k * self.shard_size;
        a..((k + 1) * self.shard_size).min(self.samples)
    }
    /// A generator parameter (normalised).
    pub fn param(&self, name: &str) -> &Value {
        match &self.params {
            Value::Map(m) => m
                .iter()
                .find(|(k, ..)| k == name)
                .map_or(&Value::Null, |e| &e.2),
            _ => &Value::Null,
        }
    }
}

/// `--set dataset.KEY=VALUE` overrides (`KEY`: samples, seed, shard_size,
/// out, name, generator, or `params.NAME`), split from a pipeline's own.
pub fn split_overrides(all: &[Override]) -> (Vec<Override>, Vec<Override>) {
    all.iter().cloned().partition(|o| o.stage == "dataset")
}

/// The keys a `dataset:` section may have.
const KEYS: &[&str] = &[
    "name",
    "description",
    "generator",
    "samples",
    "seed",
    "shard_size",
    "out",
    "params",
];

/// Reads the `dataset:` section (`v` at `loc`) of `file`, with overrides:
/// its fields as written and overridden, then the generator, the counts,
/// the name, the output folder and the generator's parameters.
pub fn parse_section(
    v: &Value,
    loc: Loc,
    file: &Path,
    overrides: &[Override],
) -> Result<DatasetSpec, SpecError> {
    let base = match file.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let mut s = Section {
        file,
        loc,
        fields: BTreeMap::new(),
    };
    let Value::Map(entries) = v else {
        return Err(s.err(
            Some(loc),
            "`dataset` must be a mapping with `generator`, `samples`, …".into(),
        ));
    };
    let param_overrides = s.collect_fields(entries, overrides)?;
    let gen = s.generator()?;
    let samples = s.int("samples", 1, MAX_SAMPLES, None)? as u64;
    let seed = s.int("seed", 0, i64::MAX, Some(0))? as u64;
    let shard_size = s.int("shard_size", 1, 1 << 20, Some(DEFAULT_SHARD_SIZE))? as u64;
    let name = s.name()?;
    let out = s.out(&base)?;
    let params_loc = s.at("params");
    let mut reads = Vec::new();
    let params = s.generator_params(gen, param_overrides, &base, &mut reads)?;
    let spec = DatasetSpec {
        file: file.to_path_buf(),
        loc,
        name,
        generator: gen,
        samples,
        seed,
        shard_size,
        out,
        params,
        reads,
    };
    gen.check(&spec)
        .map_err(|m| s.err(params_loc, format!("dataset `params`: {m}")))?;
    Ok(spec)
}

/// A `dataset:` section being read: field → (value, key location, value
/// location); overrides carry no locations.
struct Section<'a> {
    file: &'a Path,
    loc: Loc,
    fields: BTreeMap<String, (Value, Option<Loc>, Option<Loc>)>,
}

impl Section<'_> {
    fn err(&self, loc: Option<Loc>, message: String) -> SpecError {
        SpecError {
            file: self.file.to_path_buf(),
            loc,
            message,
        }
    }

    /// Where field `name`'s value stands (the section's place if absent
    /// or overridden).
    fn at(&self, name: &str) -> Option<Loc> {
        self.fields.get(name).and_then(|f| f.2).or(Some(self.loc))
    }

    fn get(&self, name: &str) -> Option<&Value> {
        self.fields.get(name).map(|f| &f.0)
    }

    /// The section's fields with the overrides applied; returns the
    /// overrides of the generator's parameters (`params.NAME`). Unknown
    /// keys, written or overridden, are errors.
    fn collect_fields<'o>(
        &mut self,
        entries: &[(String, Loc, Value, Loc)],
        overrides: &'o [Override],
    ) -> Result<Vec<(String, &'o Override)>, SpecError> {
        for (k, kl, fv, vl) in entries {
            self.fields
                .insert(k.clone(), (fv.clone(), Some(*kl), Some(*vl)));
        }
        let mut param_overrides = Vec::new();
        for o in overrides {
            if let Some(p) = o.param.strip_prefix("params.") {
                param_overrides.push((p.to_string(), o));
            } else if KEYS.contains(&o.param.as_str()) {
                self.fields
                    .insert(o.param.clone(), (o.value.clone(), None, None));
            } else {
                return Err(self.err(
                    None,
                    format!(
                        "--set {}: a dataset has no `{}` (it has: {}, params.NAME)",
                        clip(&o.text),
                        clip(&o.param),
                        KEYS.join(", ")
                    ),
                ));
            }
        }
        for (k, (_, kl, _)) in &self.fields {
            if !KEYS.contains(&k.as_str()) {
                return Err(self.err(
                    *kl,
                    format!(
                        "dataset: unknown key `{}` (a dataset has {})",
                        clip(k),
                        KEYS.join(", ")
                    ),
                ));
            }
        }
        Ok(param_overrides)
    }

    /// Integer field `name` in [min, max], or its default.
    fn int(&self, name: &str, min: i64, max: i64, default: Option<i64>) -> Result<i64, SpecError> {
        match self.get(name) {
            Some(Value::Int(i)) if (min..=max).contains(i) => Ok(*i),
            Some(v) => Err(self.err(
                self.at(name),
                format!(
                    "dataset `{name}`: expected an integer in [{min}, {max}], got {}",
                    clip(&v.to_string())
                ),
            )),
            None => default.ok_or_else(|| {
                self.err(
                    Some(self.loc),
                    format!("dataset: missing `{name}` (an integer in [{min}, {max}])"),
                )
            }),
        }
    }

    fn generator(&self) -> Result<&'static dyn Generator, SpecError> {
        let generator_name = match self.get("generator") {
            Some(Value::Str(s)) => s.clone(),
            Some(v) => {
                return Err(self.err(
                    self.at("generator"),
                    format!(
                        "dataset `generator`: expected a generator name, got {}",
                        clip(&v.to_string())
                    ),
                ))
            }
            None => {
                return Err(self.err(
                    Some(self.loc),
                    format!(
                        "dataset: missing `generator` (one of: {})",
                        GENERATORS.join(", ")
                    ),
                ))
            }
        };
        generator(&generator_name).ok_or_else(|| {
            self.err(
                self.at("generator"),
                format!(
                    "dataset: unknown generator `{}` (one of: {})",
                    clip(&generator_name),
                    GENERATORS.join(", ")
                ),
            )
        })
    }

    /// `name`: 1 to 64 letters, digits, `_` and `-`; the file's stem by
    /// default.
    fn name(&self) -> Result<String, SpecError> {
        match self.get("name") {
            None => Ok(self
                .file
                .file_stem()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_else(|| "dataset".into())),
            Some(Value::Str(s))
                if !s.is_empty()
                    && s.len() <= 64
                    && s.chars()
                        .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-') =>
            {
                Ok(s.clone())
            }
            Some(v) => Err(self.err(
                self.at("name"),
                format!(
                    "dataset `name`: use 1 to 64 letters, digits, `_` and `-`, got {}",
                    clip(&v.to_string())
                ),
            )),
        }
    }

    /// `out`: a folder relative to the file's (to the current one when
    /// overridden); none by default.
    fn out(&self, base: &Path) -> Result<Option<PathBuf>, SpecError> {
        match self.get("out") {
            None | Some(Value::Null) => Ok(None),
            Some(Value::Str(s)) => Ok(Some(match self.fields["out"].2 {
                Some(_) => resolve_path(base, s),
                None => resolve_path(Path::new("."), s),
            })),
            Some(v) => Err(self.err(
                self.at("out"),
                format!(
                    "dataset `out`: expected a folder, got {}",
                    clip(&v.to_string())
                ),
            )),
        }
    }

    /// The generator's parameters (`params`, then its overrides), checked
    /// like a record parameter; the files they read go to `reads`.
    fn generator_params(
        &self,
        gen: &'static dyn Generator,
        param_overrides: Vec<(String, &Override)>,
        base: &Path,
        reads: &mut Vec<(PathBuf, String)>,
    ) -> Result<Value, SpecError> {
        let mut given = match self.get("params") {
            None | Some(Value::Null) => Vec::new(),
            Some(Value::Map(m)) => m.clone(),
            Some(v) => {
                return Err(self.err(
                    self.at("params"),
                    format!(
                        "dataset `params`: expected a mapping, got {}",
                        clip(&v.to_string())
                    ),
                ))
            }
        };
        for (name, o) in param_overrides {
            given.retain(|e| e.0 != name);
            given.push((name, Loc::default(), o.value.clone(), Loc::default()));
        }
        let params_loc = self.at("params");
        let ty = ParamType::Record(gen.params());
        normalize_fields(
            &ty,
            &Value::Map(given),
            params_loc,
            base,
            "the dataset's `params`",
            reads,
        )
        .map_err(|(l, m)| self.err(l.or(params_loc), format!("dataset `params`{m}")))
    }
}

/// Reads a dataset spec file: a YAML file with a `dataset:` section.
pub fn load(file: &Path, overrides: &[Override]) -> Result<DatasetSpec, SpecError> {
    let text = std::fs::read_to_string(file).map_err(|e| SpecError {
        file: file.to_path_buf(),
        loc: None,
        message: format!("cannot read the dataset spec: {e}"),
    })?;
    let (root, root_loc) = matflow_engine::value::parse_yaml(&text).map_err(|e| SpecError {
        file: file.to_path_buf(),
        loc: Some(e.loc),
        message: e.message,
    })?;
    let section = match &root {
        Value::Map(m) => m.iter().find(|e| e.0 == "dataset"),
        _ => None,
    };
    let Some((_, _, v, vl)) = section else {
        return Err(SpecError {
            file: file.to_path_buf(),
            loc: Some(root_loc),
            message: "no `dataset:` section (a dataset spec is a mapping with `dataset:`)".into(),
        });
    };
    parse_section(v, *vl, file, overrides)
}
