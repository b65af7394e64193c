//! ONNX inference inside matflow ([`runtime`]: `ort` with the tract or
//! onnxruntime backend; [`model_file`]: a model's digest, metadata and
//! memory needs) and what the networks need around it: the
//! refraction-length network's crop ([`refraction`]) and MatNet's contract
//! ([`matnet`]).

pub mod matnet;
pub mod model_file;
pub mod refraction;
pub mod runtime;

pub use runtime::{Backend, Graph, Model, OnnxError, Output, Port, Source};
