//! Scene data for matflow: images, colour transfer functions, the camera
//! conventions of the reference implementation, EXR/PNG/HDR input and output,
//! image metrics and the Materialist scene bundle (its folder layout).
//!
//! Everything here is plain data and file formats; no rendering.

// `!(x > 0.0)` is deliberate throughout: it is also true for NaN.
#![allow(clippy::neg_cmp_op_on_partial_ord, clippy::needless_range_loop)]

pub mod bundle;
pub mod camera;
pub mod color;
pub mod edit;
pub mod error;
pub mod image;
pub mod io;
pub mod lamps;
pub mod meshfile;
pub mod metrics;
pub mod npy;
pub mod rng;
pub mod select;
pub mod transparency;

pub use bundle::{BestResults, Bundle, MaterialMaps, MaterialSource};
pub use camera::Camera;
pub use error::SceneError;
pub use image::{GrayImage, Image, RgbImage};
