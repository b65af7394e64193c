//! Forward rendering for matflow: the simplified Disney BRDF, the
//! environment map with importance sampling, pixel filters and a path
//! tracer over a depth-derived mesh whose materials live in screen space.

// `!(x > 0.0)` is deliberate throughout: it is also true for NaN.
#![allow(clippy::neg_cmp_op_on_partial_ord, clippy::needless_range_loop)]

pub mod bsdf;
pub mod denoise;
pub mod dielectric;
pub mod envmap;
pub mod evidence;
pub mod filter;
pub mod fmath;
pub mod guide;
pub mod integrator;
pub mod lanes;
pub mod portal;
pub mod rng;
pub mod scene;
pub mod warp;

pub use bsdf::Material;
pub use dielectric::Dielectric;
pub use envmap::EnvMap;
pub use filter::PixelFilter;
pub use integrator::{render, render_until, Crop, RenderOptions, RenderOutput, RenderStats};
pub use scene::{scene_from_depth, texture_at, Lamp, LampAt, RenderScene, SceneObject, Surface};

#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    #[error("material maps are {maps_width}x{maps_height} but the camera is {width}x{height}")]
    MaterialSize {
        maps_width: usize,
        maps_height: usize,
        width: usize,
        height: usize,
    },
    #[error("environment map must be at least 2x2, got {width}x{height}")]
    EnvmapTooSmall { width: usize, height: usize },
    #[error("environment map has {count} texel(s) with NaN or Inf")]
    EnvmapNotFinite { count: usize },
    #[error("meshing the depth map")]
    Mesh(#[from] matflow_geom::MeshError),
    #[error("lamp {index} has a non-finite position or a negative or non-finite intensity")]
    Lamp { index: usize },
    #[error("the mesh names a material pixel outside the {pixels} pixels of the image")]
    MaterialPixel { pixels: usize },
    #[error(
        "portal {index} is not a finite rectangle (two perpendicular edges of positive length)"
    )]
    Portal { index: usize },
    #[error("the mesh has {count} portals; at most {max} are sampled")]
    TooManyPortals { count: usize, max: usize },
}
