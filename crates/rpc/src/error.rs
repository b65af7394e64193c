//! What can go wrong reaching another machine, by kind: an address that is
//! not one, TLS files, a cache server that is missing or speaks otherwise,
//! a message that breaks the contract. Each names the endpoint or file.

use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum RpcError {
    /// Not `grpc://HOST:PORT`, `grpcs://HOST:PORT` or `HOST:PORT`.
    #[error("{endpoint}: {reason}")]
    Endpoint { endpoint: String, reason: String },
    /// A certificate, key or CA file that cannot be read.
    #[error("{what} {}: {source}", path.display())]
    TlsFile {
        what: &'static str,
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// TLS asked for but not set up completely.
    #[error("{0}")]
    TlsSetup(String),
    /// buildbox-casd, the cache server the launchers and tests start, is
    /// not installed (the message says what to install).
    #[error("{0}")]
    CasdMissing(String),
    /// The server answered with an error, or not at all.
    #[error("{endpoint}: {message}")]
    Server { endpoint: String, message: String },
    /// The server does not offer what matflow needs (a digest function,
    /// writes to the action cache).
    #[error("{endpoint}: {message}")]
    Unsupported { endpoint: String, message: String },
    /// A message that breaks the wire contract (an unbounded value, a
    /// non-finite number, a nested list).
    #[error("{0}")]
    Contract(String),
}
