//! The one interface the engine knows nodes by.
//!
//! A node kind declares its parameters (type, default, unit, doc) and its
//! outputs (name and artifact type). The engine validates a stage against
//! that schema before anything runs, fills defaults, hashes the result into
//! the node key, and hands the node its parameters and its inputs' bytes.
//! A node returns bytes; where it runs is the executor's business.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use crate::value::Value;

/// What a parameter accepts.
#[derive(Clone, Copy, Debug)]
pub enum ParamType {
    Bool,
    Int {
        min: i64,
        max: i64,
    },
    Float {
        min: f64,
        max: f64,
    },
    /// One of the listed words.
    Choice(&'static [&'static str]),
    /// An existing file or folder, read by the node. Its *content* (not
    /// its name) enters the node key.
    InPath,
    /// A file the node's result is copied to after the run (not part of
    /// the key: where a result is written does not change it).
    OutPath,
    /// A list of `len` numbers, each in [min, max].
    Floats {
        len: usize,
        min: f64,
        max: f64,
    },
    /// A reference to an upstream stage (`name` or `name.output`) whose
    /// output has one of these artifact types.
    Ref(&'static [&'static str]),
    /// One number (for every component) or a list of `len` numbers, each
    /// in [min, max]; always held as the list.
    FloatOrFloats {
        len: usize,
        min: f64,
        max: f64,
    },
    /// A list of at most `max` mappings with these fields (nested types
    /// other than `Ref` and `OutPath`; input paths resolve like the
    /// stage's own and their contents enter the key).
    Records {
        fields: &'static [ParamSpec],
        max: usize,
    },
    /// One mapping with these fields.
    Record(&'static [ParamSpec]),
}

impl ParamType {
    /// The value in canonical form (floats as f64, integers in range), or
    /// `None` when it does not fit. Paths and references are checked by
    /// the pipeline loader (they need the file system and the other
    /// stages); here they only have to be strings.
    pub fn normalize(&self, v: &Value) -> Option<Value> {
        match (self, v) {
            (ParamType::Bool, Value::Bool(_)) => Some(v.clone()),
            (ParamType::Int { min, max }, Value::Int(i)) if i >= min && i <= max => Some(v.clone()),
            (ParamType::Float { min, max }, _) => match v.as_f64() {
                Some(x) if x >= *min && x <= *max => Some(Value::Float(x)),
                _ => None,
            },
            (ParamType::Choice(c), Value::Str(s)) if c.contains(&s.as_str()) => Some(v.clone()),
            (ParamType::Floats { len, min, max }, Value::List(xs)) if xs.len() == *len => xs
                .iter()
                .map(|x| match x.as_f64() {
                    Some(f) if f >= *min && f <= *max => Some(Value::Float(f)),
                    _ => None,
                })
                .collect::<Option<Vec<_>>>()
                .map(Value::List),
            (ParamType::FloatOrFloats { len, min, max }, _) => match v {
                Value::List(_) => ParamType::Floats {
                    len: *len,
                    min: *min,
                    max: *max,
                }
                .normalize(v),
                _ => match v.as_f64() {
                    Some(f) if f >= *min && f <= *max => {
                        Some(Value::List(vec![Value::Float(f); *len]))
                    }
                    _ => None,
                },
            },
            (ParamType::InPath | ParamType::OutPath | ParamType::Ref(_), Value::Str(_)) => {
                Some(v.clone())
            }
            _ => None,
        }
    }

    pub fn describe(&self) -> String {
        match self {
            ParamType::Bool => "true or false".into(),
            ParamType::Int { min, max } => format!("an integer in [{min}, {max}]"),
            ParamType::Float { min, max } => format!("a number in [{min}, {max}]"),
            ParamType::Choice(c) => format!("one of {}", c.join(", ")),
            ParamType::InPath => "an existing file or folder".into(),
            ParamType::OutPath => "an output file path".into(),
            ParamType::Floats { len, min, max } => {
                format!("a list of {len} numbers in [{min}, {max}]")
            }
            ParamType::Ref(t) => format!("the name of a stage producing {}", t.join(" or ")),
            ParamType::FloatOrFloats { len, min, max } => {
                format!("a number or a list of {len} numbers, in [{min}, {max}]")
            }
            ParamType::Records { fields, max } => format!(
                "a list of at most {max} mappings with fields {}",
                fields
                    .iter()
                    .map(|f| if f.default.is_none() {
                        format!("`{}` (required)", f.name)
                    } else {
                        format!("`{}`", f.name)
                    })
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
            ParamType::Record(fields) => format!(
                "a mapping with fields {}",
                fields
                    .iter()
                    .map(|f| format!("`{}`", f.name))
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
        }
    }

    /// Whether `v`, a normalised value of this type, names an input file
    /// (an `InPath`, here or in a record's fields).
    pub fn reads_files(&self, v: &Value) -> bool {
        match (self, v) {
            (_, Value::Null) => false,
            (ParamType::InPath, _) => true,
            (ParamType::Records { fields, .. }, Value::List(items)) => items
                .iter()
                .any(|i| ParamType::Record(fields).reads_files(i)),
            (ParamType::Record(fields), Value::Map(m)) => m
                .iter()
                .any(|(k, _, fv, _)| fields.iter().any(|f| f.name == k && f.ty.reads_files(fv))),
            _ => false,
        }
    }
}

/// One parameter of a node kind.
#[derive(Clone, Copy, Debug)]
pub struct ParamSpec {
    pub name: &'static str,
    pub ty: ParamType,
    /// The default as YAML text; `None`: required; `Some("~")`: optional,
    /// absent by default.
    pub default: Option<&'static str>,
    pub unit: &'static str,
    pub doc: &'static str,
}

/// One output of a node kind.
#[derive(Clone, Copy, Debug)]
pub struct OutputSpec {
    pub name: &'static str,
    /// Artifact type, matched against [`ParamType::Ref`].
    pub ty: &'static str,
    pub doc: &'static str,
}

/// A node failed. The message names what was wrong (a file, a pixel
/// count, a parameter); the kind says whether running it again could help.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct NodeError(pub String, pub NodeErrorKind);

/// Why a node failed, as far as running it again is concerned.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NodeErrorKind {
    /// The stage's inputs or parameters fail it (a file that does not
    /// decode, a mask outside the image, numerics that refuse): the same
    /// job fails again, anywhere. The run reports it.
    Stage,
    /// The machine failed it (its disk full, its memory, an interrupted
    /// write): another attempt may succeed, so a remote stage is retried
    /// on another worker as a lost one is.
    Machine,
    /// The run that asked for it no longer wants it (see
    /// [`RunContext::cancelled`]): nothing is stored, nothing failed.
    Cancelled,
}

impl NodeError {
    /// A failure of the stage itself ([`NodeErrorKind::Stage`]).
    pub fn new(msg: impl Into<String>) -> NodeError {
        NodeError(msg.into(), NodeErrorKind::Stage)
    }
    /// A failure of the machine ([`NodeErrorKind::Machine`]).
    pub fn machine(msg: impl Into<String>) -> NodeError {
        NodeError(msg.into(), NodeErrorKind::Machine)
    }
    /// The stage stopped because its run no longer wants it
    /// ([`NodeErrorKind::Cancelled`]).
    pub fn cancelled() -> NodeError {
        NodeError(
            "cancelled: a newer request superseded the run".into(),
            NodeErrorKind::Cancelled,
        )
    }
    pub fn kind(&self) -> NodeErrorKind {
        self.1
    }
    /// The kind of failure an I/O error of this kind is: the machine's
    /// where a resource ran out or the operation was cut short (a full
    /// disk or quota, memory, a write that wrote nothing, a timeout, an
    /// interruption); the stage's otherwise (a file not found, not
    /// permitted, not decodable fails again anywhere).
    pub fn io_kind(k: std::io::ErrorKind) -> NodeErrorKind {
        use std::io::ErrorKind as K;
        match k {
            K::StorageFull
            | K::QuotaExceeded
            | K::FileTooLarge
            | K::OutOfMemory
            | K::WriteZero
            | K::TimedOut
            | K::Interrupted
            | K::ResourceBusy => NodeErrorKind::Machine,
            _ => NodeErrorKind::Stage,
        }
    }
    /// The kind of failure `e` is: [`NodeErrorKind::Machine`] when an I/O
    /// error in its chain of causes is the machine's
    /// ([`NodeError::io_kind`]).
    pub fn kind_of(e: &(dyn std::error::Error + 'static)) -> NodeErrorKind {
        let mut cur = Some(e);
        while let Some(c) = cur {
            if let Some(io) = c.downcast_ref::<std::io::Error>() {
                if Self::io_kind(io.kind()) == NodeErrorKind::Machine {
                    return NodeErrorKind::Machine;
                }
            }
            if let Some(n) = c.downcast_ref::<NodeError>() {
                if n.kind() == NodeErrorKind::Machine {
                    return NodeErrorKind::Machine;
                }
            }
            cur = c.source();
        }
        NodeErrorKind::Stage
    }
}

/// Validated, default-filled parameters of one stage.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Params(pub BTreeMap<String, Value>);

impl Params {
    pub fn get(&self, name: &str) -> &Value {
        self.0.get(name).unwrap_or(&Value::Null)
    }
    pub fn is_set(&self, name: &str) -> bool {
        !matches!(self.get(name), Value::Null)
    }
    pub fn f64(&self, name: &str) -> f64 {
        self.get(name).as_f64().unwrap_or(0.0)
    }
    pub fn f32(&self, name: &str) -> f32 {
        self.f64(name) as f32
    }
    pub fn opt_f64(&self, name: &str) -> Option<f64> {
        self.get(name).as_f64()
    }
    pub fn i64(&self, name: &str) -> i64 {
        match self.get(name) {
            Value::Int(i) => *i,
            _ => 0,
        }
    }
    pub fn opt_i64(&self, name: &str) -> Option<i64> {
        match self.get(name) {
            Value::Int(i) => Some(*i),
            _ => None,
        }
    }
    pub fn bool(&self, name: &str) -> bool {
        matches!(self.get(name), Value::Bool(true))
    }
    pub fn str(&self, name: &str) -> &str {
        match self.get(name) {
            Value::Str(s) => s,
            _ => "",
        }
    }
    /// A choice parameter parsed into its type. The engine has already
    /// checked the word against the declared choices; a word the type does
    /// not know is an error naming the parameter, never a fallback.
    pub fn parse<T>(&self, name: &str) -> Result<T, NodeError>
    where
        T: std::str::FromStr,
        T::Err: std::fmt::Display,
    {
        self.str(name)
            .parse()
            .map_err(|e| NodeError::new(format!("parameter `{name}`: {e}")))
    }
    pub fn path(&self, name: &str) -> Option<PathBuf> {
        match self.get(name) {
            Value::Str(s) => Some(PathBuf::from(s)),
            _ => None,
        }
    }
    pub fn floats(&self, name: &str) -> Option<Vec<f64>> {
        match self.get(name) {
            Value::List(v) => v.iter().map(|x| x.as_f64()).collect(),
            _ => None,
        }
    }
}

/// A blob's bytes, shared (not copied) between the store's in-run memo,
/// the stages that read it and the files written from it.
pub type Bytes = Arc<Vec<u8>>;

/// What a node sees while it runs.
pub struct RunContext<'a> {
    pub stage: &'a str,
    pub params: &'a Params,
    /// Input bytes by reference parameter name (absent optional refs are
    /// missing).
    pub inputs: BTreeMap<String, Bytes>,
    /// A seed derived from the node kind and its parameters (not from its
    /// inputs, so an upstream edit keeps the noise pattern).
    pub seed: u64,
    pub progress: &'a (dyn Fn(u64, u64) + Sync),
    /// A named number as the stage goes (an optimiser's loss per step),
    /// for a front end to plot; nothing keeps it.
    pub metric: &'a (dyn Fn(&str, f64) + Sync),
    /// Whether the run still wants this stage. A long stage asks between
    /// pieces of its work (tiles, optimiser stages) and, when it is no
    /// longer wanted, returns [`NodeError::cancelled`]: a front end whose
    /// newer edit supersedes a render does not wait for it. Always false
    /// on workers and in plain runs.
    pub cancelled: &'a (dyn Fn() -> bool + Sync),
    /// Where the stage may show an intermediate image (`name`, width,
    /// height, linear RGB row by row), e.g. an optimiser's current
    /// re-render; `None` when nobody watches, so that the stage spends
    /// nothing making one. Nothing keeps it.
    pub image: Option<&'a LiveImage<'a>>,
}

/// See [`RunContext::image`].
pub type LiveImage<'a> = dyn Fn(&str, usize, usize, &[f32]) + Sync + 'a;

/// A [`RunContext::cancelled`] for runs nobody cancels.
pub fn never_cancelled() -> bool {
    false
}

impl RunContext<'_> {
    pub fn input(&self, name: &str) -> Result<&[u8], NodeError> {
        self.inputs.get(name).map(|v| v.as_slice()).ok_or_else(|| {
            NodeError::new(format!(
                "stage '{}': parameter '{name}' names no stage",
                self.stage
            ))
        })
    }
    pub fn opt_input(&self, name: &str) -> Option<&[u8]> {
        self.inputs.get(name).map(|v| v.as_slice())
    }
    /// `Err(`[`NodeError::cancelled`]`)` once the run no longer wants the
    /// stage.
    pub fn check_cancelled(&self) -> Result<(), NodeError> {
        if (self.cancelled)() {
            Err(NodeError::cancelled())
        } else {
            Ok(())
        }
    }
}

/// What a node kind is: its name, implementation version (part of the
/// key: bumped whenever its output for the same inputs changes), a
/// description, its parameters and its outputs.
#[derive(Debug)]
pub struct NodeInfo {
    pub kind: &'static str,
    pub version: u32,
    pub doc: &'static str,
    pub params: &'static [ParamSpec],
    pub outputs: &'static [OutputSpec],
}

/// A node kind: a pure function of its parameters and input bytes.
pub trait Node: Send + Sync {
    fn info(&self) -> &'static NodeInfo;
    fn kind(&self) -> &'static str {
        self.info().kind
    }
    fn version(&self) -> u32 {
        self.info().version
    }
    fn doc(&self) -> &'static str {
        self.info().doc
    }
    fn params(&self) -> &'static [ParamSpec] {
        self.info().params
    }
    fn outputs(&self) -> &'static [OutputSpec] {
        self.info().outputs
    }
    /// Checks across parameters (e.g. exactly one mask); the message
    /// names the parameters.
    fn check(&self, _params: &Params) -> Result<(), String> {
        Ok(())
    }
    /// Checks the node's input files before any work starts (a corrupt
    /// image, a bundle without depth); the message names the file.
    fn preflight(&self, _params: &Params) -> Result<(), String> {
        Ok(())
    }
    /// The size (width, height) of the images this stage makes when its
    /// parameters alone say it (a scene generator's `size`, a bundle's
    /// depth map); `None` for stages that take it from their inputs.
    fn film_size(&self, _params: &Params) -> Option<(usize, usize)> {
        None
    }
    /// Checks parameters against the image size the stage will work at
    /// (known before anything runs: see [`Node::film_size`]), e.g. that
    /// a pixel position lies inside the image.
    fn check_film(&self, _params: &Params, _size: (usize, usize)) -> Result<(), String> {
        Ok(())
    }
    /// Roughly how long the stage takes on the reference 2-core machine
    /// (seconds), from its parameters and image size, before anything
    /// runs; for refusing runs that would take hours by mistake. Zero for
    /// cheap stages.
    fn estimate_seconds(&self, _params: &Params, _film: Option<(usize, usize)>) -> f64 {
        0.0
    }
    /// Every file [`Node::materialize`] may write for these parameters,
    /// for the loader to check that no two stages write one file and no
    /// stage overwrites an input. By default the [`ParamType::OutPath`]
    /// parameters' paths.
    fn output_files(&self, params: &Params) -> Vec<PathBuf> {
        self.params()
            .iter()
            .filter(|p| matches!(p.ty, ParamType::OutPath))
            .filter_map(|p| params.path(p.name))
            .collect()
    }
    /// Computes the outputs (by output name). An output may be left out
    /// when the inputs do not have it (a bundle without results).
    fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError>;
    /// Writes results to the user's paths (parameters of type
    /// [`ParamType::OutPath`]); runs for cached stages too. Returns the
    /// files written.
    fn materialize(
        &self,
        _params: &Params,
        _outputs: &BTreeMap<String, Bytes>,
    ) -> Result<Vec<PathBuf>, NodeError> {
        Ok(Vec::new())
    }
}

/// Reads the artifact type declared by an output's bytes (`None`: not an
/// artifact).
pub type ArtifactType = fn(&[u8]) -> Option<String>;

/// The node kinds a pipeline may use.
#[derive(Default)]
pub struct Registry {
    nodes: BTreeMap<&'static str, Box<dyn Node>>,
    /// Reads the artifact type an output's bytes declare (`None`: not an
    /// artifact); set by the crate that defines the artifact format.
    artifact_type: Option<ArtifactType>,
}

impl Registry {
    /// Tells the registry how to read an artifact's type from its bytes,
    /// so cached outputs can be checked against the types nodes declare.
    pub fn set_artifact_type(&mut self, f: ArtifactType) {
        self.artifact_type = Some(f);
    }
    /// Whether `bytes` are an artifact of one of the types `accepts`
    /// (always, when no artifact format is known).
    pub fn artifact_is(&self, bytes: &[u8], accepts: &[&str]) -> bool {
        match self.artifact_type {
            None => true,
            Some(f) => f(bytes).is_some_and(|t| accepts.contains(&t.as_str())),
        }
    }
    pub fn new() -> Registry {
        Registry::default()
    }
    pub fn add(&mut self, n: Box<dyn Node>) {
        self.nodes.insert(n.kind(), n);
    }
    pub fn get(&self, kind: &str) -> Option<&dyn Node> {
        self.nodes.get(kind).map(|b| b.as_ref())
    }
    pub fn kinds(&self) -> Vec<&'static str> {
        self.nodes.keys().copied().collect()
    }
    pub fn iter(&self) -> impl Iterator<Item = &dyn Node> {
        self.nodes.values().map(|b| b.as_ref())
    }
}

/// Resolves a path written in a pipeline file against the file's folder,
/// folding `.` and `..` lexically (`pipelines/../out` → `out`).
pub fn resolve_path(base: &Path, p: &str) -> PathBuf {
    use std::path::Component;
    let pb = PathBuf::from(p);
    let joined = if pb.is_absolute() { pb } else { base.join(pb) };
    let mut out = PathBuf::new();
    for c in joined.components() {
        match c {
            Component::CurDir => {}
            Component::ParentDir => {
                let last = out.components().next_back();
                match last {
                    Some(Component::Normal(_)) => {
                        out.pop();
                    }
                    Some(Component::RootDir) | Some(Component::Prefix(_)) => {}
                    _ => out.push(".."),
                }
            }
            c => out.push(c),
        }
    }
    if out.as_os_str().is_empty() {
        out.push(".");
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paths_resolve_against_the_pipeline_folder() {
        let r = |b: &str, p: &str| resolve_path(Path::new(b), p);
        assert_eq!(r("pipelines", "../out/a.exr"), PathBuf::from("out/a.exr"));
        assert_eq!(r("pipelines", "/abs/x"), PathBuf::from("/abs/x"));
        assert_eq!(r(".", "../../shared/x"), PathBuf::from("../../shared/x"));
        assert_eq!(r("a/b", "./c/../d"), PathBuf::from("a/b/d"));
        assert_eq!(r("a", ".."), PathBuf::from("."));
    }
}
