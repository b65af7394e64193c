//! Forward rendering for matflow: the simplified Disney BRDF, the
//! environment map with importance sampling, pixel filters and a path
//! tracer over a depth-derived mesh whose materials live in screen space.

// `!(x > 0.0)` is deliberate throughout: it is also true for NaN.
#![allow(clippy::neg_cmp_op_on_partial_ord, clippy::needless_range_loop)]

pub mod bsdf;
pub mod envmap;
pub mod filter;
pub mod integrator;
pub mod rng;
pub mod scene;
pub mod warp;

pub use bsdf::Material;
pub use envmap::EnvMap;
pub use filter::PixelFilter;
pub use integrator::{render, Crop, RenderOptions, RenderOutput, RenderStats};
pub use scene::RenderScene;

#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    #[error("{0}")]
    Invalid(String),
}
