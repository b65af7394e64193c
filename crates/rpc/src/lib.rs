//! matflow over gRPC.
//!
//! - [`pb`]: the node service (`proto/matflow/v1/node.proto`), compiled
//!   at build time with protox and tonic-prost-build.
//! - [`reapi`]: a store tier that speaks the Remote Execution API's
//!   Capabilities, ContentAddressableStorage, ByteStream and ActionCache
//!   to any compliant cache server (bazel-remote, Buildbarn, NativeLink,
//!   buildbox-casd).
//! - [`worker`]: the node service over the engine's registry.
//! - [`remote`]: the executor that places stages on workers by free
//!   slots, with deadlines, heartbeats and bounded re-dispatch.
//! - [`auth`] and [`net`]: bearer tokens compared in constant time,
//!   endpoints, TLS through rustls.

pub mod pb {
    #![allow(clippy::all)]
    tonic::include_proto!("matflow.v1");
}

pub mod auth;
pub mod convert;
pub mod error;
pub mod net;
pub mod reapi;
pub mod remote;
pub mod worker;

pub use error::RpcError;

/// The largest request a worker accepts, and the
/// largest blob sent in one batch message.
pub const MAX_MESSAGE_BYTES: usize = 4 << 20;
