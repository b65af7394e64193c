//! One file per node kind.

pub mod bundle;
pub mod bundle_invert;
pub mod bundle_mesh;
pub mod bundle_render;
pub mod edit;
pub mod envmap_opt;
pub mod image;
pub mod insert;
pub mod material_opt;
pub mod matnet;
pub mod mesh;
pub mod refraction;
pub mod refraction_length;
pub mod relight;
pub mod render;
pub mod room;
pub mod synthetic_scene;
pub mod trace;
pub mod transparency;
