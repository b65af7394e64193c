//! Datasets as sharded engine jobs.
//!
//! A dataset spec (YAML, the `dataset:` section; [`spec`]) names a
//! generator ([`generator`]), its parameters, a sample count and a seed.
//! The job ([`shards::Job`]) turns each sample into pipeline stages with
//! explicit parameters, so the engine caches every sample by content and
//! runs them wherever it runs stages; the samples' outputs are then packed
//! into deterministic WebDataset tar shards ([`tar`]) with JSON-lines
//! manifests, which [`shards::merge`] checks and indexes.
//!
//! Generators: [`refraction`], the paper's refraction-length dataset;
//! [`rooms`], synthetic interiors with ground-truth materials.

pub mod generator;
pub mod refraction;
pub mod rooms;
pub mod shards;
pub mod spec;
pub mod tar;

pub use generator::{generator, Generator, Plan, Sample, SampleStage, GENERATORS};
pub use shards::{merge, unpack, Job, MergeReport, ShardError};
pub use spec::{load, parse_section, DatasetSpec};
