//! ONNX inference inside matflow ([`runtime`]: `ort` with the tract or
//! onnxruntime backend) and what the refraction-length network needs
//! around it ([`refraction`]: the crop it sees and how its output maps
//! back to the image).

pub mod matnet;
pub mod refraction;
pub mod runtime;

pub use runtime::{Backend, Model, OnnxError};
