//! Inverse rendering with fixed geometry (paper §3.2): recover the
//! environment map and refined albedo/roughness/metallic maps so that a
//! physically based render matches the photograph.
//!
//! Where the speed comes from: geometry never changes, so the path
//! tracer's rays are traced once ([`paths`], frozen light paths) and the estimator is
//! re-evaluated for new parameters without tracing ([`transport`]). With
//! materials fixed the image is linear in the envmap ([`envfit`]); with the
//! envmap and the deeper bounces' light fixed, each pixel depends only on
//! its own material through a few tabulated sums ([`tables`]).

// `!(x > 0.0)` is deliberate throughout: it is also true for NaN.
#![allow(
    clippy::neg_cmp_op_on_partial_ord,
    clippy::needless_range_loop,
    clippy::too_many_arguments
)]

pub mod brdf;
pub mod denoise;
pub mod envfit;
pub mod invert;
pub mod loss;
pub mod matfit;
pub mod mlp;
pub mod optim;
pub mod paths;
pub mod plan;
pub mod routes;
pub mod segments;
pub mod solve;
pub mod structure;
pub mod sun;
pub mod tables;
pub mod transport;

#[cfg(test)]
pub(crate) mod testutil;

#[cfg(test)]
mod stress;
