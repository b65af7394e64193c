//! Pipeline files: parsing and validation.
//!
//! ```yaml
//! pipeline: demo                 # a name (default: the file's stem)
//! outputs: [edited]              # the stages whose results are wanted
//! remote_cache: grpc://cache:9092 # optional: a shared REAPI cache
//! stages:
//!   scene: {kind: synthetic_scene, seed: 1}
//!   edited:
//!     kind: render
//!     scene: scene               # a reference: the stage `scene`
//!     spp: 64
//! ```
//!
//! Everything is checked before any work starts: unknown keys, wrong
//! types, out-of-range values, missing or dangling references, references
//! to a stage of the wrong type, cycles, missing input files. Each error
//! names the file, the line and the column.

use std::collections::{BTreeMap, BTreeSet};
use std::fmt;
use std::path::{Path, PathBuf};

use crate::node::{resolve_path, ParamType, Params, Registry};
use crate::value::{clip, parse_override, parse_yaml, Loc, Value};

/// A problem in a pipeline, found before any work starts.
#[derive(Debug, Clone)]
pub struct SpecError {
    pub file: PathBuf,
    /// Where in the file; `None` for problems that are not in the file
    /// (a `--set` override, an unreadable file).
    pub loc: Option<Loc>,
    pub message: String,
}

impl fmt::Display for SpecError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.loc {
            Some(l) if l.line > 0 => write!(
                f,
                "{}:{}:{}: {}",
                self.file.display(),
                l.line,
                l.col,
                self.message
            ),
            _ => write!(f, "{}: {}", self.file.display(), self.message),
        }
    }
}

impl std::error::Error for SpecError {}

/// One validated stage.
#[derive(Clone, Debug)]
pub struct Stage {
    pub name: String,
    pub kind: String,
    pub loc: Loc,
    /// Every declared parameter, defaults filled, numbers normalised,
    /// input paths absolute.
    pub params: Params,
    /// Reference parameters resolved to (stage, output).
    pub refs: BTreeMap<String, (String, String)>,
}

/// A validated pipeline.
#[derive(Clone, Debug)]
pub struct Pipeline {
    pub name: String,
    pub file: PathBuf,
    pub stages: Vec<Stage>,
    pub outputs: Vec<String>,
    /// The remote store tier named in the file (`remote_cache:`), if any.
    pub remote_cache: Option<String>,
    /// The file's `dataset:` section as written (the dataset crate reads
    /// it: the engine only carries it).
    pub dataset: Option<(Value, Loc)>,
}

impl Pipeline {
    pub fn stage(&self, name: &str) -> Option<&Stage> {
        self.stages.iter().find(|s| s.name == name)
    }
    /// Each stage's position in `stages`, by name.
    pub fn positions(&self) -> std::collections::HashMap<&str, usize> {
        self.stages
            .iter()
            .enumerate()
            .map(|(i, s)| (s.name.as_str(), i))
            .collect()
    }
}

/// A `--set stage.param=value` override.
#[derive(Clone, Debug)]
pub struct Override {
    pub stage: String,
    pub param: String,
    pub value: Value,
    pub text: String,
}

impl Override {
    pub fn parse(text: &str) -> Result<Override, String> {
        let (lhs, rhs) = text
            .split_once('=')
            .ok_or_else(|| format!("--set {}: expected stage.param=value", clip(text)))?;
        let (stage, param) = lhs
            .split_once('.')
            .ok_or_else(|| format!("--set {}: expected stage.param=value", clip(text)))?;
        if stage.is_empty() || param.is_empty() {
            return Err(format!("--set {}: expected stage.param=value", clip(text)));
        }
        let value = parse_override(rhs).map_err(|e| format!("--set {}: {e}", clip(text)))?;
        Ok(Override {
            stage: stage.to_string(),
            param: param.to_string(),
            value,
            text: text.to_string(),
        })
    }
}

/// Reads, parses and validates a pipeline file.
pub fn load(path: &Path, reg: &Registry, overrides: &[Override]) -> Result<Pipeline, SpecError> {
    let text = std::fs::read_to_string(path).map_err(|e| SpecError {
        file: path.to_path_buf(),
        loc: None,
        message: format!("cannot read the pipeline: {e}"),
    })?;
    parse(&text, path, reg, overrides)
}

/// Parses and validates pipeline text; `path` names it in errors and
/// relative paths inside it are resolved against its folder.
pub fn parse(
    text: &str,
    path: &Path,
    reg: &Registry,
    overrides: &[Override],
) -> Result<Pipeline, SpecError> {
    let (root, root_loc) = parse_yaml(text).map_err(|e| SpecError {
        file: path.to_path_buf(),
        loc: Some(e.loc),
        message: e.message,
    })?;
    parse_value(root, root_loc, path, reg, overrides)
}

/// Validates a pipeline already parsed from YAML (`root`, at `root_loc`
/// of `path`); what [`parse`] does after parsing, and how a dataset's
/// generated stages join a file's own. In steps: the top-level keys, the
/// stages as written, the `--set` overrides, each stage against its kind,
/// the files read and written, the outputs, cycles and film sizes.
pub fn parse_value(
    root: Value,
    root_loc: Loc,
    path: &Path,
    reg: &Registry,
    overrides: &[Override],
) -> Result<Pipeline, SpecError> {
    let mut cx = Checker {
        path,
        base: folder_of(path),
        reg,
        reads: vec![(real_path(path), "the pipeline file".into())],
        writes: Vec::new(),
    };
    let top = cx.top_level(root, root_loc)?;
    let empty = Value::Map(Vec::new());
    let (stages_v, stages_loc) = match &top.stages {
        Some((v, l)) => (v, *l),
        // A dataset spec alone: its stages are generated.
        None if top.dataset.is_some() && top.outputs.is_none() => (&empty, root_loc),
        None => return Err(cx.err(Some(root_loc), "missing `stages:`".into())),
    };
    let mut raws = cx.raw_stages(stages_v, stages_loc)?;
    cx.apply_overrides(&mut raws, overrides)?;
    let stage_names: BTreeSet<String> = raws.iter().map(|r| r.name.clone()).collect();
    let kind_of: std::collections::HashMap<&str, &str> = raws
        .iter()
        .map(|r| (r.name.as_str(), r.kind.as_str()))
        .collect();
    let stages = raws
        .iter()
        .map(|r| cx.stage(r, &stage_names, &kind_of))
        .collect::<Result<Vec<_>, _>>()?;
    check_writes(&cx.reads, &cx.writes).map_err(|(w, msg)| {
        if w.loc.is_none() {
            cx.err(None, format!("--set {}.{}: {msg}", w.stage, w.param))
        } else {
            cx.err(w.loc, format!("stage `{}`, `{}`: {msg}", w.stage, w.param))
        }
    })?;
    let no_outputs = Value::List(Vec::new());
    let (outputs_v, outputs_loc) = match &top.outputs {
        Some((v, l)) => (v, *l),
        None if top.dataset.is_some() && stages.is_empty() => (&no_outputs, root_loc),
        None => {
            return Err(cx.err(
                Some(root_loc),
                "missing `outputs:` (the stages whose results are wanted)".into(),
            ))
        }
    };
    let outputs = cx.outputs(outputs_v, outputs_loc, &stage_names, stages.is_empty())?;
    let p = Pipeline {
        name: top.name,
        file: path.to_path_buf(),
        stages,
        outputs,
        remote_cache: top.remote_cache,
        dataset: top.dataset,
    };
    if let Some(cycle) = crate::plan::find_cycle(&p) {
        let first = p.stage(&cycle[0]).map(|s| s.loc);
        return Err(cx.err(first, format!("cycle: {}", cycle.join(" -> "))));
    }
    check_film_sizes(&p, reg)
        .map_err(|(s, m)| cx.err(Some(s.loc), format!("stage `{}`: {m}", s.name)))?;
    Ok(p)
}

/// The folder a pipeline file's relative paths are relative to.
fn folder_of(path: &Path) -> PathBuf {
    path.parent()
        .map(|p| {
            if p.as_os_str().is_empty() {
                PathBuf::from(".")
            } else {
                p.to_path_buf()
            }
        })
        .unwrap_or_else(|| PathBuf::from("."))
}

/// The top-level keys of a pipeline, each where it was written.
struct TopLevel {
    name: String,
    stages: Option<(Value, Loc)>,
    outputs: Option<(Value, Loc)>,
    remote_cache: Option<String>,
    dataset: Option<(Value, Loc)>,
}

/// A stage as written: its kind and its parameters with where each key and
/// value stand (none for an override).
struct Raw {
    name: String,
    kind: String,
    loc: Loc,
    params: BTreeMap<String, (Value, Option<Loc>, Option<Loc>)>,
}

/// What checking one pipeline accumulates: the files it reads and writes
/// (checked against each other before anything runs).
struct Checker<'a> {
    path: &'a Path,
    /// The pipeline file's folder: relative paths in the file start there.
    base: PathBuf,
    reg: &'a Registry,
    reads: Vec<(PathBuf, String)>,
    writes: Vec<Written>,
}

impl Checker<'_> {
    fn err(&self, loc: Option<Loc>, message: String) -> SpecError {
        SpecError {
            file: self.path.to_path_buf(),
            loc,
            message,
        }
    }

    fn top_level(&self, root: Value, root_loc: Loc) -> Result<TopLevel, SpecError> {
        let Value::Map(top) = root else {
            return Err(self.err(
                Some(root_loc),
                "a pipeline is a mapping with `stages:` and `outputs:`".into(),
            ));
        };
        let mut t = TopLevel {
            name: self
                .path
                .file_stem()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_else(|| "pipeline".into()),
            stages: None,
            outputs: None,
            remote_cache: None,
            dataset: None,
        };
        for (k, kl, v, vl) in top {
            match k.as_str() {
                "pipeline" => match v {
                    Value::Str(s) => t.name = s,
                    _ => return Err(self.err(Some(vl), "`pipeline` must be a name".into())),
                },
                "description" => {}
                "remote_cache" => {
                    match v {
                        Value::Str(s) if s.starts_with("grpc://") || s.starts_with("grpcs://") => {
                            t.remote_cache = Some(s)
                        }
                        Value::Null => {}
                        _ => return Err(self.err(
                            Some(vl),
                            "`remote_cache` is an endpoint: grpc://HOST:PORT or grpcs://HOST:PORT"
                                .into(),
                        )),
                    }
                }
                "stages" => t.stages = Some((v, vl)),
                "outputs" => t.outputs = Some((v, vl)),
                "dataset" => t.dataset = Some((v, vl)),
                _ => {
                    return Err(self.err(
                        Some(kl),
                        format!(
                            "unknown key `{}` (a pipeline has pipeline, description, \
                             remote_cache, stages, outputs, dataset)",
                            clip(&k)
                        ),
                    ))
                }
            }
        }
        Ok(t)
    }

    /// The stages as written: names valid and unique, each a mapping with
    /// a known `kind`.
    fn raw_stages(&self, stages_v: &Value, stages_loc: Loc) -> Result<Vec<Raw>, SpecError> {
        let Value::Map(stage_entries) = stages_v else {
            return Err(self.err(
                Some(stages_loc),
                "`stages` must map stage names to stages".into(),
            ));
        };
        let mut raws: Vec<Raw> = Vec::new();
        let mut seen = BTreeSet::new();
        for (sname, sl, sv, svl) in stage_entries {
            if !valid_name(sname) {
                return Err(self.err(
                    Some(*sl),
                    format!(
                        "stage name `{}`: use letters, digits, `_` and `-`",
                        clip(sname)
                    ),
                ));
            }
            if !seen.insert(sname.clone()) {
                return Err(self.err(
                    Some(*sl),
                    format!("stage `{}` is defined twice", clip(sname)),
                ));
            }
            let Value::Map(fields) = sv else {
                return Err(self.err(
                    Some(*svl),
                    format!("stage `{}` must be a mapping with a `kind`", clip(sname)),
                ));
            };
            let mut kind = None;
            let mut params = BTreeMap::new();
            for (k, kl, v, vl) in fields {
                if k == "kind" {
                    match v {
                        Value::Str(s) => kind = Some((s.clone(), *vl)),
                        _ => {
                            return Err(
                                self.err(Some(*vl), "`kind` must be a node kind name".into())
                            )
                        }
                    }
                } else {
                    if params.contains_key(k) {
                        return Err(self.err(Some(*kl), format!("`{}` is given twice", clip(k))));
                    }
                    params.insert(k.clone(), (v.clone(), Some(*kl), Some(*vl)));
                }
            }
            let Some((kind, kind_loc)) = kind else {
                return Err(self.err(
                    Some(*sl),
                    format!(
                        "stage `{sname}` has no `kind` (one of: {})",
                        self.reg.kinds().join(", ")
                    ),
                ));
            };
            if self.reg.get(&kind).is_none() {
                return Err(self.err(
                    Some(kind_loc),
                    format!(
                        "stage `{sname}`: unknown kind `{}` (one of: {})",
                        clip(&kind),
                        self.reg.kinds().join(", ")
                    ),
                ));
            }
            raws.push(Raw {
                name: sname.clone(),
                kind,
                loc: *sl,
                params,
            });
        }
        Ok(raws)
    }

    /// `--set STAGE.kind=KIND` replaces the stage: the file's parameters
    /// for it are dropped, its other overrides and the kind's defaults
    /// make the new stage (how one pipeline runs on a generated scene or
    /// on a photo's bundle). Other overrides replace or add parameters;
    /// they carry no location.
    fn apply_overrides(&self, raws: &mut [Raw], overrides: &[Override]) -> Result<(), SpecError> {
        if let Some(o) = overrides
            .iter()
            .find(|o| !raws.iter().any(|r| r.name == o.stage))
        {
            return Err(self.err(
                None,
                format!(
                    "--set {}: there is no stage `{}`",
                    clip(&o.text),
                    clip(&o.stage)
                ),
            ));
        }
        for o in overrides.iter().filter(|o| o.param == "kind") {
            let r = raws
                .iter_mut()
                .find(|r| r.name == o.stage)
                .expect("stages checked");
            match &o.value {
                Value::Str(k) if self.reg.get(k).is_some() => {
                    r.kind = k.clone();
                    r.params.clear();
                }
                v => {
                    return Err(self.err(
                        None,
                        format!(
                            "--set {}: `{}` is not a node kind (one of: {})",
                            clip(&o.text),
                            clip(&v.to_string()),
                            self.reg.kinds().join(", ")
                        ),
                    ))
                }
            }
        }
        for o in overrides.iter().filter(|o| o.param != "kind") {
            let r = raws
                .iter_mut()
                .find(|r| r.name == o.stage)
                .expect("stages checked");
            let node = self.reg.get(&r.kind).expect("kind checked");
            if !node.params().iter().any(|p| p.name == o.param) {
                return Err(self.err(
                    None,
                    format!(
                        "--set {}: a {} stage has no parameter `{}` (it has: {})",
                        clip(&o.text),
                        r.kind,
                        clip(&o.param),
                        names(node.params().iter().map(|p| p.name))
                    ),
                ));
            }
            r.params
                .insert(o.param.clone(), (o.value.clone(), None, None));
        }
        Ok(())
    }

    /// One stage checked against its kind: every parameter given is
    /// declared, every declared one given or defaulted and of its type,
    /// references resolved to an upstream output; the kind's own checks;
    /// the files it writes noted.
    fn stage(
        &mut self,
        r: &Raw,
        stage_names: &BTreeSet<String>,
        kind_of: &std::collections::HashMap<&str, &str>,
    ) -> Result<Stage, SpecError> {
        let node = self.reg.get(&r.kind).expect("kind checked");
        let specs = node.params();
        for (k, (_, kl, _)) in &r.params {
            if !specs.iter().any(|p| p.name == k) {
                return Err(self.err(
                    *kl,
                    format!(
                        "stage `{}`: unknown parameter `{}` for kind {} (it has: {})",
                        r.name,
                        clip(k),
                        r.kind,
                        names(specs.iter().map(|p| p.name))
                    ),
                ));
            }
        }
        let mut st = StageParams {
            params: Params::default(),
            refs: BTreeMap::new(),
            out_at: None,
        };
        for p in specs {
            self.param(r, p, &mut st, stage_names, kind_of)?;
        }
        let StageParams {
            params,
            refs,
            out_at,
        } = st;
        node.check(&params)
            .map_err(|m| self.err(Some(r.loc), format!("stage `{}`: {m}", r.name)))?;
        node.preflight(&params)
            .map_err(|m| self.err(Some(r.loc), format!("stage `{}`: {m}", r.name)))?;
        for f in node.output_files(&params) {
            let (param, loc) = out_at.unwrap_or(("output", Some(r.loc)));
            self.writes.push(Written {
                real: real_path(&f),
                file: f,
                stage: r.name.clone(),
                param,
                loc,
            });
        }
        Ok(Stage {
            name: r.name.clone(),
            kind: r.kind.clone(),
            loc: r.loc,
            params,
            refs,
        })
    }

    /// One declared parameter of stage `r`: its value as given (or its
    /// default), checked and normalised into `st`.
    fn param(
        &mut self,
        r: &Raw,
        p: &crate::node::ParamSpec,
        st: &mut StageParams,
        stage_names: &BTreeSet<String>,
        kind_of: &std::collections::HashMap<&str, &str>,
    ) -> Result<(), SpecError> {
        let (v, loc) = match r.params.get(p.name) {
            Some((v, _, l)) => (v.clone(), *l),
            None => match p.default {
                None => {
                    return Err(self.err(
                        Some(r.loc),
                        format!(
                            "stage `{}`: missing parameter `{}` ({})",
                            r.name,
                            p.name,
                            p.ty.describe()
                        ),
                    ))
                }
                Some(d) => (
                    parse_override(d).expect("defaults are valid YAML"),
                    Some(Loc::default()),
                ),
            },
        };
        // Paths in the file (and defaults) are relative to its folder;
        // paths given with `--set`, to the current one.
        let from_file = matches!(loc, Some(l) if l.line > 0) || loc == Some(Loc::default());
        let dir = if from_file {
            self.base.clone()
        } else {
            PathBuf::from(".")
        };
        let where_ = |msg: String| {
            if loc.is_none() {
                self.err(None, format!("--set {}.{}: {msg}", r.name, p.name))
            } else {
                self.err(loc, format!("stage `{}`, `{}`: {msg}", r.name, p.name))
            }
        };
        if matches!(v, Value::Null) {
            if p.default.is_none() {
                return Err(where_(format!(
                    "is required ({}), got nothing",
                    p.ty.describe()
                )));
            }
            st.params.0.insert(p.name.to_string(), Value::Null);
            return Ok(());
        }
        let bad = |v: &Value| {
            where_(format!(
                "expected {}, got {}",
                p.ty.describe(),
                clip(&v.to_string())
            ))
        };
        let norm = match p.ty {
            ParamType::Bool
            | ParamType::Int { .. }
            | ParamType::Float { .. }
            | ParamType::Choice(_)
            | ParamType::Floats { .. }
            | ParamType::FloatOrFloats { .. } => match p.ty.normalize(&v) {
                Some(n) => n,
                None => return Err(bad(&v)),
            },
            ParamType::Records { .. } | ParamType::Record(_) => {
                let what = format!("stage `{}`'s `{}`", r.name, p.name);
                match normalize_fields(&p.ty, &v, loc, &dir, &what, &mut self.reads) {
                    Ok(n) => n,
                    Err((at, msg)) => {
                        return Err(if loc.is_none() {
                            self.err(None, format!("--set {}.{}{msg}", r.name, p.name))
                        } else {
                            self.err(at.or(loc), format!("stage `{}`, `{}`{msg}", r.name, p.name))
                        })
                    }
                }
            }
            ParamType::InPath | ParamType::OutPath => match &v {
                Value::Str(s) => {
                    let full = resolve_path(&dir, s);
                    if matches!(p.ty, ParamType::InPath) {
                        if let Err(e) = std::fs::metadata(&full) {
                            return Err(where_(format!("{}: {e}", full.display())));
                        }
                        self.reads.push((
                            real_path(&full),
                            format!("stage `{}`'s `{}`", r.name, p.name),
                        ));
                    } else if st.out_at.is_none() {
                        st.out_at = Some((p.name, loc));
                    }
                    Value::Str(full.to_string_lossy().into_owned())
                }
                _ => return Err(bad(&v)),
            },
            ParamType::Ref(accepts) => {
                let Value::Str(s) = &v else {
                    return Err(bad(&v));
                };
                let (up, out) = self
                    .resolve_ref(r, s, accepts, stage_names, kind_of)
                    .map_err(&where_)?;
                st.refs.insert(p.name.to_string(), (up, out));
                v
            }
        };
        st.params.0.insert(p.name.to_string(), norm);
        Ok(())
    }

    /// A reference `s` (`stage` or `stage.output`) from stage `r` to an
    /// upstream output of one of the `accepts` types: (stage, output), or
    /// what is wrong with it.
    fn resolve_ref(
        &self,
        r: &Raw,
        s: &str,
        accepts: &[&str],
        stage_names: &BTreeSet<String>,
        kind_of: &std::collections::HashMap<&str, &str>,
    ) -> Result<(String, String), String> {
        let (up, out) = match s.split_once('.') {
            Some((a, b)) => (a.to_string(), Some(b.to_string())),
            None => (s.to_string(), None),
        };
        if !stage_names.contains(&up) {
            return Err(format!("there is no stage `{}`", clip(&up)));
        }
        if up == r.name {
            return Err(format!(
                "stage `{up}` refers to itself (cycle: {up} -> {up})"
            ));
        }
        let up_kind = kind_of[up.as_str()];
        let up_node = self.reg.get(up_kind).expect("kind checked");
        let chosen = match &out {
            Some(o) => up_node.outputs().iter().find(|x| x.name == o),
            None => up_node.outputs().iter().find(|x| accepts.contains(&x.ty)),
        };
        match chosen {
            Some(o) if accepts.contains(&o.ty) => Ok((up, o.name.to_string())),
            _ => Err(format!(
                "stage `{up}` ({up_kind}) has no output of type {} (its outputs: {})",
                accepts.join(" or "),
                names(
                    up_node
                        .outputs()
                        .iter()
                        .map(|o| format!("{} ({})", o.name, o.ty))
                )
            )),
        }
    }

    /// `outputs:`: a stage name or a list of them, not empty when there
    /// are stages.
    fn outputs(
        &self,
        outputs_v: &Value,
        outputs_loc: Loc,
        stage_names: &BTreeSet<String>,
        no_stages: bool,
    ) -> Result<Vec<String>, SpecError> {
        let not_names = || self.err(Some(outputs_loc), "`outputs` must list stage names".into());
        let outputs: Vec<String> = match outputs_v {
            Value::List(xs) => xs
                .iter()
                .map(|x| match x {
                    Value::Str(s) => Ok(s.clone()),
                    _ => Err(not_names()),
                })
                .collect::<Result<_, _>>()?,
            Value::Str(s) => vec![s.clone()],
            _ => return Err(not_names()),
        };
        if outputs.is_empty() && !no_stages {
            return Err(self.err(Some(outputs_loc), "`outputs` is empty".into()));
        }
        for o in &outputs {
            if !stage_names.contains(o) {
                return Err(self.err(
                    Some(outputs_loc),
                    format!("`outputs` names `{}`, which is not a stage", clip(o)),
                ));
            }
        }
        Ok(outputs)
    }
}

/// What checking a stage's parameters builds up: the values, the
/// references to upstream outputs, and where its output path was given
/// (for messages about the files it writes).
struct StageParams {
    params: Params,
    refs: BTreeMap<String, (String, String)>,
    out_at: Option<(&'static str, Option<Loc>)>,
}

/// A file a stage writes: its path as given and as resolved, and where
/// that was said.
struct Written {
    real: PathBuf,
    file: PathBuf,
    stage: String,
    param: &'static str,
    loc: Option<Loc>,
}

/// `p` with symbolic links and `..` resolved as far as it exists (the
/// rest appended), so two spellings of one file compare equal.
/// A `Records` or `Record` value checked against its fields: each field's
/// type, no unknown fields, required fields present, defaults filled in
/// (absent optional fields are null), mappings in the fields' order; input
/// paths resolved against `base` and listed in `reads` (as read by
/// `what`). Errors carry the location of the offending field (or the
/// value's own) and a message that continues the parameter's name
/// ("[1].material: field `ior`: expected …").
pub fn normalize_fields(
    ty: &ParamType,
    v: &Value,
    loc: Option<Loc>,
    base: &Path,
    what: &str,
    reads: &mut Vec<(PathBuf, String)>,
) -> Result<Value, (Option<Loc>, String)> {
    let got = |v: &Value| clip(&v.to_string());
    match ty {
        ParamType::Records { fields, max } => {
            let Value::List(items) = v else {
                return Err((loc, format!(": expected {}, got {}", ty.describe(), got(v))));
            };
            if items.len() > *max {
                return Err((
                    loc,
                    format!(": {} entries, at most {max} are allowed", items.len()),
                ));
            }
            let mut out = Vec::with_capacity(items.len());
            for (i, item) in items.iter().enumerate() {
                // List items carry no location; a mapping's first key does.
                let at = match item {
                    Value::Map(m) if !m.is_empty() => Some(m[0].1),
                    _ => loc,
                };
                let n = normalize_fields(&ParamType::Record(fields), item, at, base, what, reads)
                    .map_err(|(l, m)| (l, format!("[{i}]{m}")))?;
                out.push(n);
            }
            Ok(Value::List(out))
        }
        ParamType::Record(fields) => {
            let Value::Map(entries) = v else {
                return Err((loc, format!(": expected {}, got {}", ty.describe(), got(v))));
            };
            for (k, kl, _, _) in entries {
                if !fields.iter().any(|f| f.name == k) {
                    return Err((
                        Some(*kl).filter(|l| l.line > 0).or(loc),
                        format!(
                            ": unknown field `{}` (the fields are: {})",
                            clip(k),
                            names(fields.iter().map(|f| f.name))
                        ),
                    ));
                }
            }
            let mut out = Vec::with_capacity(fields.len());
            for f in *fields {
                let found = entries.iter().find(|(k, ..)| k == f.name);
                let (fv, kl, vl) = match found {
                    Some((_, kl, fv, vl)) => (fv.clone(), *kl, *vl),
                    None => match f.default {
                        None => {
                            return Err((
                                loc,
                                format!(": missing field `{}` ({})", f.name, f.ty.describe()),
                            ))
                        }
                        Some(d) => (
                            parse_override(d).expect("defaults are valid YAML"),
                            Loc::default(),
                            Loc::default(),
                        ),
                    },
                };
                let at = Some(vl).filter(|l| l.line > 0).or(loc);
                let bad = |fv: &Value| {
                    (
                        at,
                        format!(
                            ": field `{}`: expected {}, got {}",
                            f.name,
                            f.ty.describe(),
                            got(fv)
                        ),
                    )
                };
                let n = if matches!(fv, Value::Null) {
                    if f.default.is_none() {
                        return Err(bad(&fv));
                    }
                    Value::Null
                } else {
                    match f.ty {
                        ParamType::InPath => {
                            let Value::Str(s) = &fv else {
                                return Err(bad(&fv));
                            };
                            let full = resolve_path(base, s);
                            if let Err(e) = std::fs::metadata(&full) {
                                return Err((
                                    at,
                                    format!(": field `{}`: {}: {e}", f.name, full.display()),
                                ));
                            }
                            reads.push((real_path(&full), format!("{what} (`{}`)", f.name)));
                            Value::Str(full.to_string_lossy().into_owned())
                        }
                        ParamType::Records { .. } | ParamType::Record(_) => {
                            normalize_fields(&f.ty, &fv, at, base, what, reads)
                                .map_err(|(l, m)| (l, format!(".{}{m}", f.name)))?
                        }
                        ParamType::OutPath | ParamType::Ref(_) => {
                            return Err((
                                at,
                                format!(": field `{}` cannot be given inside a list", f.name),
                            ))
                        }
                        _ => match f.ty.normalize(&fv) {
                            Some(n) => n,
                            None => return Err(bad(&fv)),
                        },
                    }
                };
                out.push((f.name.to_string(), kl, n, vl));
            }
            Ok(Value::Map(out))
        }
        _ => Err((loc, ": not a record type".into())),
    }
}

fn real_path(p: &Path) -> PathBuf {
    let abs = if p.is_absolute() {
        p.to_path_buf()
    } else {
        std::env::current_dir()
            .unwrap_or_else(|_| PathBuf::from("/"))
            .join(p)
    };
    let abs = resolve_path(Path::new("/"), &abs.to_string_lossy());
    let mut head = abs.as_path();
    let mut tail = Vec::new();
    loop {
        if let Ok(c) = std::fs::canonicalize(head) {
            let mut out = c;
            for t in tail.iter().rev() {
                out.push(t);
            }
            return out;
        }
        match (head.parent(), head.file_name()) {
            (Some(parent), Some(name)) => {
                tail.push(name.to_os_string());
                head = parent;
            }
            _ => return abs,
        }
    }
}

/// No stage may write a file the pipeline reads (or into a folder it
/// reads), and no two stages, or two outputs of one, may write one file:
/// the survivor of such a race would be arbitrary and an input could be
/// destroyed. Returns the offending write and why.
fn check_writes<'w>(
    reads: &[(PathBuf, String)],
    writes: &'w [Written],
) -> Result<(), (&'w Written, String)> {
    let read: std::collections::HashMap<&Path, &str> = reads
        .iter()
        .map(|(p, who)| (p.as_path(), who.as_str()))
        .collect();
    let mut written: std::collections::HashMap<&Path, &Written> = Default::default();
    for w in writes {
        for dir in w.real.ancestors() {
            let Some(who) = read.get(dir) else {
                continue;
            };
            let msg = if dir == w.real {
                format!("would overwrite {who}")
            } else if dir.is_dir() {
                format!("is inside {who}, a folder the pipeline reads")
            } else {
                continue;
            };
            return Err((
                w,
                format!(
                    "{} {msg} ({}); write somewhere else",
                    w.file.display(),
                    dir.display()
                ),
            ));
        }
        if w.real.is_dir() {
            return Err((w, format!("{} is a folder", w.file.display())));
        }
        if let Some(o) = written.insert(&w.real, w) {
            return Err((
                w,
                format!(
                    "{} is also written by stage `{}` (`{}`); each file may have one writer",
                    w.file.display(),
                    o.stage,
                    o.param
                ),
            ));
        }
    }
    Ok(())
}

/// Artifact types that have the film's size (an envmap or an image
/// stage's file need not).
const FILM_TYPES: [&str; 5] = ["scene", "materials", "mesh", "paths", "mask"];

/// The image size each stage works at, worked out before anything runs:
/// from the stages that state it ([`crate::Node::film_size`]), passed
/// along references to film-sized artifacts in dependency order. `None`
/// where nothing upstream states it. Indexed like `p.stages`.
pub fn film_sizes(p: &Pipeline, reg: &Registry) -> Vec<Option<(usize, usize)>> {
    let idx = p.positions();
    // Film-sized references: stage i reads stage j's film-sized output.
    let mut film_ups: Vec<Vec<usize>> = vec![Vec::new(); p.stages.len()];
    let mut downs: Vec<Vec<usize>> = vec![Vec::new(); p.stages.len()];
    let mut pending = vec![0usize; p.stages.len()];
    for (i, s) in p.stages.iter().enumerate() {
        for (up, out) in s.refs.values() {
            let Some(&j) = idx.get(up.as_str()) else {
                continue;
            };
            downs[j].push(i);
            pending[i] += 1;
            let ty = reg
                .get(&p.stages[j].kind)
                .and_then(|n| n.outputs().iter().find(|o| o.name == out))
                .map(|o| o.ty);
            if ty.is_some_and(|t| FILM_TYPES.contains(&t)) {
                film_ups[i].push(j);
            }
        }
    }
    // Kahn's order: every stage after the stages it reads.
    let mut size: Vec<Option<(usize, usize)>> = vec![None; p.stages.len()];
    let mut ready: Vec<usize> = (0..p.stages.len()).filter(|&i| pending[i] == 0).collect();
    while let Some(i) = ready.pop() {
        let s = &p.stages[i];
        size[i] = reg
            .get(&s.kind)
            .and_then(|n| n.film_size(&s.params))
            .or_else(|| film_ups[i].iter().find_map(|&j| size[j]));
        for &d in &downs[i] {
            pending[d] -= 1;
            if pending[d] == 0 {
                ready.push(d);
            }
        }
    }
    size
}

/// Lets each stage check its parameters against its image size.
fn check_film_sizes<'p>(p: &'p Pipeline, reg: &Registry) -> Result<(), (&'p Stage, String)> {
    for (s, size) in p.stages.iter().zip(film_sizes(p, reg)) {
        if let (Some(node), Some(wh)) = (reg.get(&s.kind), size) {
            node.check_film(&s.params, wh).map_err(|m| (s, m))?;
        }
    }
    Ok(())
}

/// A run whose stages are estimated to take longer than this in all (on
/// the reference 2-core machine, by the cost model of
/// [`crate::Node::estimate_seconds`]) is refused unless the user says it
/// may be expensive (`matflow run --allow-expensive`).
pub const EXPENSIVE_SECONDS: f64 = 3600.0;

/// Estimated seconds of each stage the outputs need, in run order, if
/// none were cached.
pub fn estimate_seconds(p: &Pipeline, reg: &Registry) -> Vec<(String, f64)> {
    let sizes = film_sizes(p, reg);
    let idx = p.positions();
    crate::plan::order(p)
        .into_iter()
        .map(|name| {
            let i = idx[name.as_str()];
            let s = &p.stages[i];
            let secs = reg
                .get(&s.kind)
                .map_or(0.0, |n| n.estimate_seconds(&s.params, sizes[i]));
            (name, secs)
        })
        .collect()
}

fn valid_name(s: &str) -> bool {
    !s.is_empty()
        && s.chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
}

fn names<S: AsRef<str>>(it: impl Iterator<Item = S>) -> String {
    it.map(|s| s.as_ref().to_string())
        .collect::<Vec<_>>()
        .join(", ")
}

#[cfg(test)]
mod record_tests {
    use super::*;
    use crate::node::{Node, NodeError, NodeInfo, OutputSpec, ParamSpec, RunContext};

    const MATERIAL: &[ParamSpec] = &[
        ParamSpec {
            name: "type",
            ty: ParamType::Choice(&["diffuse", "glass"]),
            default: None,
            unit: "",
            doc: "",
        },
        ParamSpec {
            name: "ior",
            ty: ParamType::Float { min: 1.0, max: 4.0 },
            default: Some("1.5"),
            unit: "",
            doc: "",
        },
    ];
    const OBJECT: &[ParamSpec] = &[
        ParamSpec {
            name: "mesh",
            ty: ParamType::InPath,
            default: None,
            unit: "",
            doc: "",
        },
        ParamSpec {
            name: "scale",
            ty: ParamType::FloatOrFloats {
                len: 3,
                min: 1e-4,
                max: 1e4,
            },
            default: Some("1"),
            unit: "",
            doc: "",
        },
        ParamSpec {
            name: "material",
            ty: ParamType::Record(MATERIAL),
            default: Some("~"),
            unit: "",
            doc: "",
        },
    ];
    static PLACER: NodeInfo = NodeInfo {
        kind: "placer",
        version: 1,
        doc: "",
        params: &[
            ParamSpec {
                name: "objects",
                ty: ParamType::Records {
                    fields: OBJECT,
                    max: 3,
                },
                default: None,
                unit: "",
                doc: "",
            },
            ParamSpec {
                name: "output",
                ty: ParamType::OutPath,
                default: Some("~"),
                unit: "",
                doc: "",
            },
        ],
        outputs: &[OutputSpec {
            name: "out",
            ty: "thing",
            doc: "",
        }],
    };
    struct Placer;
    impl Node for Placer {
        fn info(&self) -> &'static NodeInfo {
            &PLACER
        }
        fn run(&self, _: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
            Ok(BTreeMap::new())
        }
        fn output_files(&self, p: &Params) -> Vec<PathBuf> {
            p.path("output").into_iter().collect()
        }
    }

    fn setup(name: &str) -> (PathBuf, Registry) {
        let dir =
            std::env::temp_dir().join(format!("matflow-records-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(dir.join("m")).unwrap();
        std::fs::write(dir.join("m/a.obj"), "v 0 0 0\n").unwrap();
        let mut reg = Registry::default();
        reg.add(Box::new(Placer));
        (dir, reg)
    }

    fn load_text(dir: &Path, reg: &Registry, body: &str) -> Result<Pipeline, SpecError> {
        let text = format!("pipeline: t\noutputs: [s]\nstages:\n  s:\n    kind: placer\n{body}");
        let file = dir.join("p.yaml");
        std::fs::write(&file, &text).unwrap();
        load(&file, reg, &[])
    }

    #[test]
    fn records_are_normalised_with_defaults_and_resolved_paths() {
        let (dir, reg) = setup("ok");
        let p = load_text(
            &dir,
            &reg,
            "    objects:\n      - mesh: m/a.obj\n        scale: 2\n      - {mesh: m/a.obj, scale: [1, 2, 3], material: {type: glass}}\n",
        )
        .unwrap();
        let Value::List(items) = p.stages[0].params.get("objects") else {
            panic!("not a list")
        };
        let Value::Map(first) = &items[0] else {
            panic!()
        };
        let names: Vec<&str> = first.iter().map(|(k, ..)| k.as_str()).collect();
        assert_eq!(names, ["mesh", "scale", "material"], "fields in spec order");
        assert_eq!(
            first[0].2,
            Value::Str(dir.join("m/a.obj").to_string_lossy().into_owned())
        );
        assert_eq!(
            first[1].2,
            Value::List(vec![Value::Float(2.0); 3]),
            "broadcast"
        );
        assert_eq!(first[2].2, Value::Null, "absent optional field");
        let Value::Map(second) = &items[1] else {
            panic!()
        };
        let Value::Map(mat) = &second[2].2 else {
            panic!("material not a mapping")
        };
        assert_eq!(mat[1].2, Value::Float(1.5), "nested default");
        // Records naming files run where the files are, and their content
        // is in the key.
        let node = reg.get("placer").unwrap();
        assert!(crate::exec::reads_local_files(node, &p.stages[0].params));
        let k1 = crate::key::node_key(node, &p.stages[0].params, &BTreeMap::new()).unwrap();
        std::fs::write(dir.join("m/a.obj"), "v 1 0 0\n").unwrap();
        let k2 = crate::key::node_key(node, &p.stages[0].params, &BTreeMap::new()).unwrap();
        assert_ne!(k1, k2, "a referenced file's content enters the key");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn bad_records_are_located_errors() {
        let (dir, reg) = setup("bad");
        let cases = [
            (
                "    objects:\n      - mesh: m/a.obj\n        colour: red\n",
                "p.yaml:8:9:",
                "[0]: unknown field `colour`",
            ),
            ("    objects:\n      - scale: 2\n", "", "[0]: missing field `mesh`"),
            (
                "    objects:\n      - mesh: m/a.obj\n        scale: [1, 2]\n",
                "p.yaml:8:16:",
                "field `scale`: expected a number or a list of 3 numbers",
            ),
            (
                "    objects:\n      - mesh: m/a.obj\n      - mesh: m/a.obj\n        material: {type: glass, ior: 9}\n",
                "",
                "[1].material: field `ior`: expected a number in [1, 4], got 9",
            ),
            (
                "    objects:\n      - mesh: m/missing.obj\n",
                "p.yaml:7:15:",
                "field `mesh`: ",
            ),
            ("    objects: {mesh: m/a.obj}\n", "", "expected a list of at most 3 mappings"),
            (
                "    objects: [{mesh: m/a.obj}, {mesh: m/a.obj}, {mesh: m/a.obj}, {mesh: m/a.obj}]\n",
                "",
                "4 entries, at most 3",
            ),
            (
                "    objects:\n      - mesh: m/a.obj\n    output: m/a.obj\n",
                "",
                "s",
            ),
        ];
        for (body, at, want) in cases {
            let e = match load_text(&dir, &reg, body) {
                Ok(_) => panic!("accepted: {body}"),
                Err(e) => e.to_string(),
            };
            assert!(e.contains(want), "{body}: {e}");
            assert!(e.contains(at), "{body}: {e} (want {at})");
            assert!(e.contains("stage `s`"), "{e}");
        }
        // The output may not overwrite a file a record reads.
        let e = load_text(
            &dir,
            &reg,
            "    objects:\n      - mesh: m/a.obj\n    output: m/a.obj\n",
        )
        .err()
        .unwrap()
        .to_string();
        assert!(e.contains("`objects`") && e.contains("mesh"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// Two spellings of one file are one action: the same key (contents)
    /// and the same seed (the file only as given), so they compute the
    /// same bytes, whichever is served from the cache to the other.
    #[cfg(unix)]
    #[test]
    fn an_input_file_keys_and_seeds_by_contents_not_spelling() {
        use crate::key::{node_key, node_seed};
        let (dir, reg) = setup("spelling");
        std::fs::write(dir.join("m/b.obj"), "v 1 1 1\n").unwrap();
        let stage = |mesh: &str| {
            let p =
                load_text(&dir, &reg, &format!("    objects:\n      - mesh: {mesh}\n")).unwrap();
            p.stages[0].params.clone()
        };
        let node = reg.get("placer").unwrap();
        let none = BTreeMap::new();
        let key = |p: &Params| node_key(node, p, &none).unwrap();
        // The same file through a link (as a pipeline named by a relative
        // and by an absolute path resolves its files).
        std::os::unix::fs::symlink(dir.join("m"), dir.join("link")).unwrap();
        let (a, also_a) = (stage("m/a.obj"), stage("link/a.obj"));
        assert_ne!(a, also_a, "the paths are spelled differently");
        assert_eq!(key(&a), key(&also_a));
        assert_eq!(node_seed(node, &a), node_seed(node, &also_a));
        // Another file: another key, the same noise.
        let b = stage(&dir.join("m/b.obj").display().to_string());
        assert_ne!(key(&a), key(&b));
        assert_eq!(node_seed(node, &a), node_seed(node, &b));
        // What is not a file still seeds.
        let scaled = load_text(
            &dir,
            &reg,
            "    objects:\n      - {mesh: m/a.obj, scale: 2}\n",
        )
        .unwrap();
        assert_ne!(
            node_seed(node, &a),
            node_seed(node, &scaled.stages[0].params)
        );
        let _ = std::fs::remove_dir_all(&dir);
    }
}
