use std::path::PathBuf;

/// Errors raised while reading or writing scene data. Every variant names the
/// file it is about, so a user can tell which input is at fault.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: cannot decode: {message}")]
    Decode { path: PathBuf, message: String },
    #[error("{path}: cannot encode: {message}")]
    Encode { path: PathBuf, message: String },
    #[error("{path}: {message}")]
    Invalid { path: PathBuf, message: String },
    #[error("{path}: {count} pixel(s) hold NaN or Inf values (first at x={x}, y={y}); fix or regenerate this file")]
    NonFinite {
        path: PathBuf,
        count: usize,
        x: usize,
        y: usize,
    },
    #[error("{path}: size {got_w}x{got_h} does not match the scene's {want_w}x{want_h}")]
    SizeMismatch {
        path: PathBuf,
        got_w: usize,
        got_h: usize,
        want_w: usize,
        want_h: usize,
    },
    #[error("{dir}: bundle has no {what} (looked for {looked_for})")]
    Missing {
        dir: PathBuf,
        what: String,
        looked_for: String,
    },
}

impl SceneError {
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        SceneError::Io {
            path: path.into(),
            source,
        }
    }
    pub fn invalid(path: impl Into<PathBuf>, message: impl Into<String>) -> Self {
        SceneError::Invalid {
            path: path.into(),
            message: message.into(),
        }
    }
}

pub type Result<T> = std::result::Result<T, SceneError>;
