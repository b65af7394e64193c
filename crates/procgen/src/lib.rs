//! Procedural content, one home for all of it: every generator is a pure
//! function of its seed, drawing from [`matflow_scene::rng::Rng`].
//!
//! - [`synthetic`]: a room seen as a depth map with known materials and a
//!   sky (`matflow synth`, the demo's scene, the inverse tests);
//! - [`envgen`]: procedural skies and rooms as environment maps;
//! - [`rooms`]: whole scenes with ground truth — open rooms there,
//!   closed rooms, stages and outdoor scenes in [`kinds`] (the `rooms`
//!   dataset, the prediction network's training data);
//! - [`framing`]: where the camera stands (as drawn, or near an object);
//! - [`shapes`]: meshes for insertion and for the refraction dataset (jug,
//!   torus, sphere, cup, …);
//! - [`refraction`]: the refraction dataset's labels of an object in view.

// `!(x > 0.0)` is how NaN is kept out: it reads as meant.
#![allow(clippy::neg_cmp_op_on_partial_ord, clippy::needless_range_loop)]

pub mod envgen;
pub mod framing;
pub mod kinds;
pub mod refraction;
pub mod rooms;
pub mod shapes;
pub mod synthetic;
