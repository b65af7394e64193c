//! One module per suite; each prints its table and the command behind it.

pub mod compare;
pub mod dataset;
pub mod distributed;
pub mod export_rooms;
pub mod glass;
pub mod insert;
pub mod invert;
pub mod lanes;
pub mod matnet;
pub mod matnet_eval;
pub mod pipeline;
pub mod ply;
pub mod relight;
pub mod render;
pub mod select;
pub mod studio;
pub mod synthetic;
