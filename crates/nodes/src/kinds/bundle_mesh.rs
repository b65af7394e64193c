//! `bundle_mesh`: `matflow mesh` as a stage: a bundle folder's depth map
//! meshed, completed past the frame as the bundle says (or as its photo
//! supports under the bundle's own light), written as a PLY.

use std::collections::BTreeMap;
use std::path::PathBuf;

use matflow_engine::node::{Bytes, Params};
use matflow_engine::{Node, NodeError, NodeInfo, OutputSpec, ParamSpec, ParamType, RunContext};
use matflow_geom::{mesh_for_view, MeshParams, Silhouettes};
use matflow_render::PixelFilter;
use matflow_scene::Bundle;

use crate::completion::{completion_or_default, CompleteArg, EvidenceRender};
use crate::data::encode_mesh;
use crate::{err, Context};

pub struct BundleMeshNode;

/// The bundle folder a command reads, as `bundle_mesh` and
/// `bundle_render` take it.
pub(crate) const BUNDLE: ParamSpec = ParamSpec {
    name: "bundle",
    ty: ParamType::InPath,
    default: None,
    unit: "",
    doc: "the bundle folder (reference layout: depth, gt_image, predictions and/or results)",
};

/// The random seed of the commands' renders, as given (`--seed`).
pub(crate) const SEED: ParamSpec = ParamSpec {
    name: "seed",
    ty: ParamType::Int {
        min: 0,
        max: i64::MAX,
    },
    default: Some("0"),
    unit: "",
    doc: "random seed",
};

const COMPLETE: ParamSpec = ParamSpec {
    name: "complete",
    ty: ParamType::Choice(&CompleteArg::NAMES),
    default: Some("~"),
    unit: "",
    doc: "geometry past the frame (see `bundle_render`'s): auto, room, closed, planes, or \
          none (the depth mesh alone). Default: the completion the bundle declares for its \
          own geometry (geometry.json, which `matflow synth` and `matflow invert` write), \
          otherwise auto: the photo tests each under the bundle's own light and materials \
          (best_results, else ground_truth); room without them (as `invert`)",
};

const INFO: NodeInfo = NodeInfo {
    kind: "bundle_mesh",
    version: 2,
    doc: "`matflow mesh` as a stage: the triangle mesh of a bundle folder's depth map (one \
          vertex per pixel, cut at depth discontinuities), completed past the frame as the \
          bundle declares or as its photo supports, written as a binary PLY.",
    params: &[
        BUNDLE,
        crate::kinds::mesh::ANGLE,
        crate::kinds::mesh::SILHOUETTES,
        COMPLETE,
        ParamSpec {
            name: "output",
            ty: ParamType::OutPath,
            default: Some("~"),
            unit: "",
            doc: "the PLY file to write",
        },
    ],
    outputs: &[
        OutputSpec {
            name: "mesh",
            ty: "mesh",
            doc: "vertices, triangles, film positions (for stages downstream)",
        },
        OutputSpec {
            name: "mesh.ply",
            ty: "file",
            doc: "the mesh as a binary PLY",
        },
        OutputSpec {
            name: "note",
            ty: "note",
            doc: "the completion taken and why, the photo's scores, the mesh's counts",
        },
    ],
};

impl Node for BundleMeshNode {
    fn info(&self) -> &'static NodeInfo {
        &INFO
    }

    fn preflight(&self, p: &Params) -> Result<(), String> {
        bundle_preflight(p)
    }

    fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
        let p = ctx.params;
        let dir = p.path("bundle").unwrap_or_default();
        let silhouettes = silhouettes(p)?;
        let params = MeshParams {
            min_angle_deg: p.f64("angle"),
            silhouettes,
        };
        let asked = complete_arg(p)?;
        let bundle = Bundle::open(&dir).node_err()?;
        let depth = bundle.load_depth().node_err()?;
        let (cam, mut m) = mesh_for_view(&depth, &params).node_err()?;
        let decision = completion_or_default(
            &dir,
            asked,
            EvidenceRender {
                mesh: params,
                filter: PixelFilter::default(),
                max_depth: 4,
            },
        )?;
        let mut lines = decision.lines();
        if let Some(params) = decision.params() {
            let c = matflow_geom::complete_beyond_frame(&mut m.mesh, &depth, &cam, &params);
            for f in &c.extended {
                lines.push(format!(
                    "extended {:?} n=({:.3}, {:.3}, {:.3}) d={:.3}: {:.1} % of the view, reaches {:?} (left, right, top, bottom)",
                    f.kind,
                    f.plane.n.x,
                    f.plane.n.y,
                    f.plane.n.z,
                    f.plane.d,
                    100.0 * f.fraction,
                    f.reaches
                ));
            }
            lines.push(format!(
                "completion: {} plane(s) extended ({} triangles), {} found but not extended; \
                 {} triangles continue objects cut by the border",
                c.extended.len(),
                c.triangles - c.border_triangles,
                c.kept_in,
                c.border_triangles
            ));
        }
        let mut ply = Vec::new();
        m.mesh
            .write_ply(&mut ply, cam.width, cam.height)
            .context(|| "writing the PLY".to_string())?;
        lines.push(format!(
            "mesh: {} vertices, {} triangles ({} silhouettes: {} boundary pixels moved, {} kept as edges; {} copies, {} direct, {} after 1 copy, {} after 2, {} dropped; backs: {} vertices, {} triangles)",
            m.mesh.vertex_count(),
            m.mesh.triangle_count(),
            silhouettes,
            m.stats.boundary_pixels - m.stats.kept_edges,
            m.stats.kept_edges,
            m.stats.copies,
            m.stats.emitted_direct,
            m.stats.emitted_one_copy,
            m.stats.emitted_two_copies,
            m.stats.dropped,
            m.stats.back_vertices,
            m.stats.back_triangles,
        ));
        Ok([
            (
                "mesh".to_string(),
                encode_mesh(cam.width, cam.height, &m.mesh),
            ),
            ("mesh.ply".to_string(), ply),
            ("note".to_string(), lines.join("\n").into_bytes()),
        ]
        .into())
    }

    fn materialize(
        &self,
        params: &Params,
        outputs: &BTreeMap<String, Bytes>,
    ) -> Result<Vec<PathBuf>, NodeError> {
        let Some(path) = params.path("output") else {
            return Ok(vec![]);
        };
        crate::files::write_file(&path, outputs.get("mesh.ply"))?;
        Ok(vec![path])
    }
}

/// The `bundle` folder opens (its depth is there): what the commands'
/// kinds check before anything runs.
pub(crate) fn bundle_preflight(p: &Params) -> Result<(), String> {
    let dir = p.path("bundle").unwrap_or_default();
    Bundle::open(&dir).map(|_| ()).map_err(|e| e.to_string())
}

/// The `bundle` folder's image size, from its depth map's header.
pub(crate) fn bundle_film_size(p: &Params) -> Option<(usize, usize)> {
    Bundle::open(p.path("bundle")?).ok()?.depth_size().ok()
}

/// `silhouettes` as the mesher takes it.
pub(crate) fn silhouettes(p: &Params) -> Result<Silhouettes, NodeError> {
    Silhouettes::parse(p.str("silhouettes"))
        .ok_or_else(|| err("silhouettes: not kept or reference"))
}

/// `complete` as asked (`None`: not given, the bundle decides).
pub(crate) fn complete_arg(p: &Params) -> Result<Option<CompleteArg>, NodeError> {
    match p.get("complete") {
        matflow_engine::Value::Str(s) => s.parse().map(Some).map_err(err),
        _ => Ok(None),
    }
}

/// A switch given as `on` or `off` (as the commands take them).
pub(crate) const fn on_off(
    name: &'static str,
    default: &'static str,
    doc: &'static str,
) -> ParamSpec {
    ParamSpec {
        name,
        ty: ParamType::Choice(&["on", "off"]),
        default: Some(default),
        unit: "",
        doc,
    }
}
