//! What makes a dataset's samples. A generator declares its parameters
//! (checked like a node's) and turns sample i into pipeline stages: each
//! stage a node kind with explicit parameters (the object, the viewpoint,
//! the envmap chosen for that sample), so the engine caches every sample's
//! pieces by content and a changed parameter re-runs only the stages whose
//! parameters it changes. Each stage's outputs become the sample's members
//! (`{key}.{output}` in the shards).

use matflow_engine::spec::SpecError;
use matflow_engine::{ParamSpec, Value};

use crate::spec::DatasetSpec;

/// One stage of a sample.
#[derive(Clone, Debug, PartialEq)]
pub struct SampleStage {
    /// Names the stage (`{role}-{index}`).
    pub role: &'static str,
    pub kind: &'static str,
    pub params: Vec<(String, Value)>,
}

/// What sample i is made of, and what the manifest says about it.
#[derive(Clone, Debug, PartialEq)]
pub struct Sample {
    pub stages: Vec<SampleStage>,
    /// The choices that made it (object, viewpoint, envmap, materials).
    pub meta: serde_json::Map<String, serde_json::Value>,
}

/// A generator prepared for one spec (folders listed, files checked).
pub trait Plan: Send + Sync {
    /// Sample `i`: a pure function of the spec, its seed and `i`.
    fn sample(&self, i: u64) -> Sample;
    /// Facts about the whole dataset for its header (the normaliser, the
    /// objects and envmaps drawn from).
    fn header(&self) -> serde_json::Value;
    /// The member names every sample has, in order.
    fn members(&self) -> Vec<String>;
    /// Where `matflow dataset unpack` puts each member in a sample's
    /// folder (a path relative to it); members not listed keep their name.
    fn layout(&self) -> Vec<(&'static str, &'static str)> {
        Vec::new()
    }
}

pub trait Generator: Sync {
    fn name(&self) -> &'static str;
    fn doc(&self) -> &'static str;
    fn params(&self) -> &'static [ParamSpec];
    /// Checks across parameters; the message names them.
    fn check(&self, _spec: &DatasetSpec) -> Result<(), String> {
        Ok(())
    }
    /// Prepares sampling: lists object folders, reads and checks the
    /// envmap files once (errors name the file).
    fn plan(&self, spec: &DatasetSpec) -> Result<Box<dyn Plan>, SpecError>;
}

/// The generators' names.
pub const GENERATORS: &[&str] = &["refraction", "rooms"];

/// The generator called `name`.
pub fn generator(name: &str) -> Option<&'static dyn Generator> {
    match name {
        "refraction" => Some(&crate::refraction::RefractionGenerator),
        "rooms" => Some(&crate::rooms::RoomsGenerator),
        _ => None,
    }
}

/// Sample i's random stream for one purpose (`salt`): SplitMix64 seeded
/// from (seed, i, salt) alone.
pub struct Rng(matflow_scene::rng::Rng);

impl Rng {
    pub fn for_sample(seed: u64, i: u64, salt: u64) -> Rng {
        use matflow_scene::rng::Rng as SplitMix;
        let a = SplitMix(seed ^ salt.wrapping_mul(0xd1b5_4a32_d192_ed03)).next_u64();
        Rng(SplitMix(a ^ i.wrapping_mul(0x9e37_79b9_7f4a_7c15)))
    }
    pub fn next_u64(&mut self) -> u64 {
        self.0.next_u64()
    }
    /// Uniform in [0, 1), with 53 bits.
    pub fn f64(&mut self) -> f64 {
        (self.0.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }
    pub fn range(&mut self, a: f64, b: f64) -> f64 {
        a + (b - a) * self.f64()
    }
    /// Uniform in 0..n (n > 0).
    pub fn below(&mut self, n: u64) -> u64 {
        self.0.below(n)
    }
}

/// A value as JSON (for the manifest).
pub fn json_of(v: &Value) -> serde_json::Value {
    use serde_json::Value as J;
    match v {
        Value::Null => J::Null,
        Value::Bool(b) => J::Bool(*b),
        Value::Int(i) => J::from(*i),
        Value::Float(f) => serde_json::Number::from_f64(*f).map_or(J::Null, J::Number),
        Value::Str(s) => J::String(s.clone()),
        Value::List(xs) => J::Array(xs.iter().map(json_of).collect()),
        Value::Map(m) => J::Object(
            m.iter()
                .map(|(k, _, v, _)| (k.clone(), json_of(v)))
                .collect(),
        ),
    }
}
