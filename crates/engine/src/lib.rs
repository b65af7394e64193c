//! The dataflow engine: a pipeline is a YAML file of named stages; each
//! stage is a node (a pure function of its parameters and its inputs'
//! bytes), cached in a BLAKE3 content-addressed store and run by an
//! executor.
//!
//! - [`spec`]: YAML → [`spec::Pipeline`], with line and column on every
//!   error, validated against the node schemas before any work starts.
//! - [`node`]: the one trait the engine knows nodes by, and their
//!   parameter schemas.
//! - [`key`]: the canonical, length-prefixed encoding hashed into node keys.
//! - [`store`]: blobs by content hash and the action cache (node key →
//!   output digests); atomic writes, verified reads.
//! - [`plan`]: reference resolution, cycle detection, demand-driven stage
//!   selection.
//! - [`tier`]: the store as `Cas` + `ActionCache` tiers; a local disk
//!   tier in front of an optional remote one.
//! - [`exec`]: the scheduler, the executor interface and the in-process
//!   executor.

pub mod exec;
pub mod key;
pub mod node;
pub mod plan;
pub mod spec;
pub mod store;
pub mod tier;
pub mod value;

pub use exec::{
    execute_job, run_pipeline, Done, Event, Executor, Failure, Job, LocalExecutor, Observer,
    Report, Sink, StageReport, Status,
};
pub use node::{
    Node, NodeError, NodeErrorKind, NodeInfo, OutputSpec, ParamSpec, ParamType, Registry,
    RunContext,
};
pub use spec::{Pipeline, SpecError};
pub use store::{Digest, Store, StoreError};
pub use tier::{ActionCache, Cas, CasRef, StoreTier, Tiered};
pub use value::{Loc, Value};
