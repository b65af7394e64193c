//! The node kinds of matflow pipelines, one per file in `kinds/`. Each
//! adapts a numerical crate (scene, geom, render, inverse) to the engine's
//! [`Node`] trait: parameters and bytes in, bytes out; the domain logic
//! lives in those crates. `data` holds the artifact codecs the kinds
//! share, `recovery` what the two recovery kinds share.
//!
//! Artifact types flowing between stages: `image` (linear RGB), `scene`
//! (camera-space depth, the input image when there is one, predicted
//! materials), `mesh`, `materials`, `envmap` (lat-long linear RGB), `mask`,
//! `report` (JSON), `file` (a file's bytes) and `note` (a line for the
//! run report).

pub mod artifact;
mod data;
pub use data::{render_seconds, SceneData};
pub use kinds::insert::composite_differential;
pub use kinds::matnet::MIN_PHOTO_SIDE;
pub use kinds::matnet::{
    linear_square as matnet_linear_square, load_model as load_matnet_model,
    predict as matnet_predict, read_photo as read_matnet_photo, Loaded as MatnetModel,
    Prediction as MatnetPrediction, BUNDLED_MODEL as BUNDLED_MATNET_MODEL,
    BUNDLED_MODEL_BLAKE3 as BUNDLED_MATNET_MODEL_BLAKE3,
};
pub use kinds::refraction::OBJECT_NAMES as REFRACTION_OBJECTS;
pub use kinds::refraction_length::{
    BUNDLED_MODEL as BUNDLED_REFRACTION_MODEL,
    BUNDLED_MODEL_BLAKE3 as BUNDLED_REFRACTION_MODEL_BLAKE3,
};
pub mod bundle_scene;
pub mod completion;
mod files;
mod kinds;
pub mod memo;
pub mod objects;
pub mod recovery;
#[cfg(test)]
mod testutil;

use matflow_engine::{Node, NodeError, Registry};

/// Every node kind.
pub fn registry() -> Registry {
    let mut r = Registry::new();
    let nodes: Vec<Box<dyn Node>> = vec![
        Box::new(kinds::image::ImageNode),
        Box::new(kinds::bundle::BundleNode),
        Box::new(kinds::bundle_invert::BundleInvertNode),
        Box::new(kinds::bundle_mesh::BundleMeshNode),
        Box::new(kinds::bundle_render::BundleRenderNode),
        Box::new(kinds::synthetic_scene::SyntheticSceneNode),
        Box::new(kinds::mesh::MeshNode),
        Box::new(kinds::envmap_opt::EnvmapOptNode),
        Box::new(kinds::material_opt::MaterialOptNode),
        Box::new(kinds::edit::EditNode),
        Box::new(kinds::transparency::TransparencyNode),
        Box::new(kinds::relight::RelightNode),
        Box::new(kinds::render::RenderNode),
        Box::new(kinds::trace::TraceNode),
        Box::new(kinds::insert::InsertNode),
        Box::new(kinds::refraction::RefractionLabelsNode),
        Box::new(kinds::refraction::RefractionRenderNode),
        Box::new(kinds::room::RoomSampleNode),
        Box::new(kinds::refraction_length::RefractionLengthNode),
        Box::new(kinds::matnet::MatnetNode),
    ];
    for n in nodes {
        r.add(n);
    }
    r.set_artifact_type(artifact::Artifact::type_of);
    r
}

/// A node error from a message.
pub(crate) fn err(e: impl std::fmt::Display) -> NodeError {
    NodeError::new(e.to_string())
}

/// A node error from a typed error, its causes joined ("building the
/// scene: meshing the depth map: depth has 3 NaN values"), of the
/// machine's kind when an I/O error among them is the machine's (a full
/// disk: another attempt may succeed; [`NodeError::kind_of`]).
pub(crate) fn failed(e: impl std::error::Error + 'static) -> NodeError {
    let mut msg = e.to_string();
    let mut src = e.source();
    while let Some(s) = src {
        msg.push_str(": ");
        msg.push_str(&s.to_string());
        src = s.source();
    }
    NodeError(msg, NodeError::kind_of(&e))
}

/// `?` on a typed error inside a node: the error, its causes joined
/// ([`failed`]), after what was being done.
pub(crate) trait Context<T> {
    /// The error after `what` ("reading x.json: not found").
    fn context(self, what: impl FnOnce() -> String) -> Result<T, NodeError>;
    /// The error as it is.
    fn node_err(self) -> Result<T, NodeError>;
}

impl<T, E: std::error::Error + 'static> Context<T> for Result<T, E> {
    fn context(self, what: impl FnOnce() -> String) -> Result<T, NodeError> {
        self.map_err(|e| {
            let f = failed(e);
            NodeError(format!("{}: {}", what(), f.0), f.1)
        })
    }
    fn node_err(self) -> Result<T, NodeError> {
        self.map_err(failed)
    }
}

impl<T> Context<T> for Option<T> {
    fn context(self, what: impl FnOnce() -> String) -> Result<T, NodeError> {
        self.ok_or_else(|| NodeError::new(what()))
    }
    fn node_err(self) -> Result<T, NodeError> {
        self.ok_or_else(|| NodeError::new("missing"))
    }
}

/// Markdown reference of every node kind: parameters with type, default,
/// unit and meaning, and outputs (docs/pipelines.md's node reference is this).
pub fn reference_markdown() -> String {
    let mut s = String::new();
    for n in registry().iter() {
        s.push_str(&format!("#### `{}`\n\n{}\n\n", n.kind(), n.doc()));
        s.push_str("| parameter | accepts | default | unit | meaning |\n|---|---|---|---|---|\n");
        for p in n.params() {
            s.push_str(&format!(
                "| `{}` | {} | {} | {} | {} |\n",
                p.name,
                p.ty.describe(),
                match p.default {
                    None => "required".to_string(),
                    Some("~") => "—".to_string(),
                    Some(d) => format!("`{d}`"),
                },
                p.unit,
                p.doc
            ));
        }
        s.push_str("\nOutputs: ");
        s.push_str(
            &n.outputs()
                .iter()
                .map(|o| format!("`{}` ({}: {})", o.name, o.ty, o.doc))
                .collect::<Vec<_>>()
                .join("; "),
        );
        s.push_str("\n\n");
    }
    s
}
