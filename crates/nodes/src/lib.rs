//! The node kinds of matflow pipelines. Each wraps a numerical crate
//! (scene, geom, render, inverse) behind the engine's [`Node`] trait; the
//! engine sees only parameters and bytes.
//!
//! Artifact types flowing between stages: `image` (linear RGB), `scene`
//! (camera-space depth, the input image when there is one, predicted
//! materials), `mesh`, `materials`, `envmap` (lat-long linear RGB), `mask`
//! and `report` (JSON).

pub mod artifact;
mod edit;
mod inputs;
mod optimise;
mod relight;
mod render;
mod trace;

use matflow_engine::{Node, NodeError, Registry};

pub use edit::{apply_ops, flood_mask, hsv_shift, EditOps};

/// Every node kind.
pub fn registry() -> Registry {
    let mut r = Registry::new();
    let nodes: Vec<Box<dyn Node>> = vec![
        Box::new(inputs::ImageNode),
        Box::new(inputs::BundleNode),
        Box::new(inputs::SyntheticSceneNode),
        Box::new(inputs::MeshNode),
        Box::new(optimise::EnvmapOptNode),
        Box::new(optimise::MaterialOptNode),
        Box::new(edit::EditNode),
        Box::new(relight::RelightNode),
        Box::new(render::RenderNode),
        Box::new(trace::TraceNode),
    ];
    for n in nodes {
        r.add(n);
    }
    r
}

pub(crate) fn err(e: impl std::fmt::Display) -> NodeError {
    NodeError::new(e.to_string())
}

/// Markdown reference of every node kind: parameters with type, default,
/// unit and meaning, and outputs (the README's pipeline section is this).
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
