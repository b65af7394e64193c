//! `mesh`: the triangle mesh of a scene's depth map.

use std::collections::BTreeMap;

use matflow_engine::{Node, NodeError, NodeInfo, OutputSpec, ParamSpec, ParamType, RunContext};

use matflow_geom::{complete_beyond_frame, CompleteParams, MeshParams, Silhouettes};
use matflow_render::evidence::{choose_under_seen_sky, completion_hypotheses, EvidenceOptions};
use matflow_scene::Camera;

use crate::data::{encode_mesh, mesh_of, SceneData};

pub struct MeshNode;

/// `complete`'s values: auto, then matflow_geom's modes.
const COMPLETE_CHOICES: [&str; 5] = ["auto", "none", "planes", "room", "closed"];

/// The mode `auto` takes for the scene `s`: the photo's choice under the
/// sky it shows, else room (no photo, or no open sky to weigh the light
/// by: a sky seen only through windows comes with light it does not show,
/// and so does a view that needs far more light than its sky gives).
fn auto_mode(s: &SceneData, mesh: MeshParams) -> Result<&'static str, NodeError> {
    let Some(photo) = &s.target else {
        return Ok("room");
    };
    let hyps = completion_hypotheses();
    let opts = EvidenceOptions {
        filter: matflow_render::PixelFilter::Box,
        ..Default::default()
    };
    let tested = choose_under_seen_sky(&s.depth, &s.pred, mesh, photo, &hyps, &opts)
        .map_err(|e| crate::err(format!("testing the geometry past the frame: {e}")))?;
    Ok(match tested {
        Some((c, _)) => matflow_geom::COMPLETE_MODES[c.chosen],
        None => "room",
    })
}

/// Shading normals for the first `seen` vertices of `tri` (the depth
/// mesh's, before any completion): the normal map's at each vertex's film
/// position (the pixel it was made from), unit length; a vertex with no
/// film position, or a map value that is not a direction, gets a zero
/// vector, which the renderer reads as "the mesh's own".
fn predicted_normals(
    tri: &matflow_geom::TriMesh,
    seen: usize,
    map: &matflow_scene::RgbImage,
) -> Vec<glam::Vec3> {
    let (w, h) = (map.width, map.height);
    (0..seen.min(tri.positions.len()))
        .map(|i| {
            let Some(f) = tri.film.get(i) else {
                return glam::Vec3::ZERO;
            };
            if !(f.x.is_finite() && f.y.is_finite()) {
                return glam::Vec3::ZERO;
            }
            let x = (f.x.max(0.0) as usize).min(w.saturating_sub(1));
            let y = (f.y.max(0.0) as usize).min(h.saturating_sub(1));
            let n = map.get(x, y);
            if n.is_finite() && n.length() > 0.5 {
                n.normalize()
            } else {
                glam::Vec3::ZERO
            }
        })
        .collect()
}

/// The boundary angle, as `mesh` and the commands on a bundle take it.
pub(crate) const ANGLE: ParamSpec = ParamSpec {
    name: "angle",
    ty: ParamType::Float {
        min: 0.0,
        max: 90.0,
    },
    default: Some("6"),
    unit: "degrees",
    doc: "boundary threshold: triangles seen more obliquely than this are cut",
};

/// The silhouettes' side, as `mesh` and the commands on a bundle take it.
pub(crate) const SILHOUETTES: ParamSpec = ParamSpec {
    name: "silhouettes",
    ty: ParamType::Choice(&Silhouettes::NAMES),
    default: Some("kept"),
    unit: "",
    doc: "the near side of a depth discontinuity: kept (an object's edge keeps its depth \
          and reaches the pixel border; only pixels between two depths move back; a solid's \
          unseen back is its front mirrored about its silhouettes) or \
          reference (every boundary pixel takes the background's depth, as the reference \
          implementation: objects lose a pixel and a half)",
};

const MESH_INFO: NodeInfo = NodeInfo {
    kind: "mesh",
    version: 12,
    doc: "The triangle mesh of a scene's depth map (one vertex per pixel, cut at depth \
         discontinuities found by the reference's angle test), optionally completed past the \
         frame.",
    params: &[
        ParamSpec {
            name: "scene",
            ty: ParamType::Ref(&["scene"]),
            default: None,
            unit: "",
            doc: "the scene whose depth is meshed",
        },
        ANGLE,
        SILHOUETTES,
        ParamSpec {
            name: "complete",
            ty: ParamType::Choice(&COMPLETE_CHOICES),
            default: Some("auto"),
            unit: "",
            doc: "geometry past the frame: none (the depth mesh alone); planes (the floor, walls and ceiling seen, \
                  extended and filled behind what hides them, and objects cut by the border \
                  continued); room (also a room the view shows closed, each assumed wall with a \
                  typical window); closed (assumed walls without windows); auto (the least \
                  assuming the photo supports, each tested with the predicted maps under the sky \
                  the photo shows, as `invert`; room where it shows no open sky (none, or only \
                  through openings: under a lintel, or framed by one wall), or where the least \
                  assuming needs ten times the light of the sky it shows)",
        },
        ParamSpec {
            name: "normals",
            ty: ParamType::Choice(&["mesh", "predicted"]),
            default: Some("mesh"),
            unit: "",
            doc: "shading normals of the depth mesh: the triangles' own, averaged (mesh, as the \
                  reference's default use_mesh_normal), or the scene's predicted normal map \
                  (predicted: a depth map with waves the photo does not show shades them as \
                  waves, and the recovered albedo takes them up as swirls; a predicted normal \
                  map is usually smoother). Where a predicted normal faces away from the \
                  triangles', the mesh's is kept",
        },
    ],
    outputs: &[
        OutputSpec {
            name: "mesh",
            ty: "mesh",
            doc: "vertices, triangles, film positions",
        },
        OutputSpec {
            name: "note",
            ty: "note",
            doc: "the geometry taken past the frame (and whether `auto` chose it)",
        },
    ],
};

impl Node for MeshNode {
    fn info(&self) -> &'static NodeInfo {
        &MESH_INFO
    }
    fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
        let s = SceneData::decode(ctx.input("scene")?)?;
        let mesh = MeshParams {
            min_angle_deg: ctx.params.f64("angle"),
            silhouettes: Silhouettes::parse(ctx.params.str("silhouettes"))
                .ok_or_else(|| crate::err("silhouettes: not kept or reference"))?,
        };
        let mut tri = mesh_of(&s.depth, &mesh)?;
        let asked = ctx.params.str("complete");
        let mode = match asked {
            "auto" => auto_mode(&s, mesh)?,
            m => m,
        };
        let note = if asked == "auto" {
            format!("past the frame: {mode} (chosen by auto)")
        } else {
            format!("past the frame: {mode}")
        };
        let seen = tri.vertex_count();
        if let Some(p) = CompleteParams::for_mode(mode) {
            let cam = Camera::new(s.depth.width, s.depth.height);
            complete_beyond_frame(&mut tri, &s.depth, &cam, &p);
        }
        if ctx.params.str("normals") == "predicted" {
            let n = s.pred.normal.as_ref().ok_or_else(|| {
                crate::err("normals: predicted, but the scene has no predicted normal map")
            })?;
            tri.normals = predicted_normals(&tri, seen, n);
        }
        Ok([
            (
                "mesh".to_string(),
                encode_mesh(s.depth.width, s.depth.height, &tri),
            ),
            ("note".to_string(), note.into_bytes()),
        ]
        .into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data::decode_mesh;
    use crate::testutil::params_of;
    use matflow_engine::Value;
    use matflow_geom::TriMesh;

    /// The stage's mesh of synthetic scene 3 with `complete` set, or left
    /// at its default.
    fn mesh_with_param(complete: Option<&str>) -> TriMesh {
        mesh_of_scene(complete, false)
    }

    /// The stage's mesh of synthetic scene 3, with its photo (rendered on
    /// the depth mesh alone, under its own sky) when `photo`.
    fn mesh_of_scene(complete: Option<&str>, photo: bool) -> TriMesh {
        let s = matflow_procgen::synthetic::generate(3, 48, 48);
        let target = photo.then(|| {
            let env = matflow_render::EnvMap::new(&s.envmap).unwrap();
            let (scene, _, _) = matflow_render::scene_from_depth(
                &s.depth,
                &s.maps,
                env,
                matflow_geom::MeshParams::default(),
                None,
            )
            .unwrap();
            let o = matflow_render::RenderOptions {
                spp: 32,
                ..Default::default()
            };
            matflow_render::render(&scene, &o, &|_, _| {}).image
        });
        let scene = SceneData {
            depth: s.depth,
            target,
            pred: s.maps,
        }
        .encode();
        let given: Vec<(&str, Value)> = complete
            .map(|c| ("complete", Value::Str(c.into())))
            .into_iter()
            .collect();
        let p = params_of(&MESH_INFO, &given);
        let inputs = [("scene".to_string(), std::sync::Arc::new(scene))].into();
        let out = crate::testutil::run_node(&MeshNode, &p, inputs, 1).unwrap();
        let (cam, tri) = decode_mesh(&out["mesh"]).unwrap();
        assert_eq!((cam.width, cam.height), (48, 48));
        tri
    }

    fn mesh_with(complete: &str) -> TriMesh {
        mesh_with_param(Some(complete))
    }

    #[test]
    fn the_mesh_stage_completes_the_room_past_the_frame() {
        let plain = mesh_with("none");
        assert!(plain.material_pixel.is_empty());
        let s = matflow_procgen::synthetic::generate(3, 48, 48);
        assert_eq!(plain, mesh_of(&s.depth, &MeshParams::default()).unwrap());
        for mode in ["planes", "room"] {
            let done = mesh_with(mode);
            // The view's own mesh first, then what continues it, each
            // added triangle naming a pixel of the view for its material.
            assert!(done.indices.len() > plain.indices.len(), "{mode}");
            assert_eq!(done.indices[..plain.indices.len()], plain.indices[..]);
            assert_eq!(done.material_pixel.len(), done.indices.len());
            assert!(done.material_pixel[plain.indices.len()..]
                .iter()
                .all(|&p| (p as usize) < 48 * 48));
            assert!(done.positions.iter().all(|p| p.is_finite()));
        }
        // Only a closed room has windows, which the mesh carries as
        // portals for renderers to aim at.
        assert!(mesh_with("planes").portals.is_empty());
        let room = mesh_with("room");
        assert!(!room.portals.is_empty());
        assert!(room.portals.iter().all(|p| p.is_valid()));
        // The same depth completes the same way every time.
        assert_eq!(room, mesh_with("room"));
    }

    #[test]
    fn auto_takes_the_completion_the_photo_supports() {
        // Scene 3 shows its sky; its photo was rendered on the depth mesh
        // alone, which the photo supports and which assumes least.
        let s = matflow_procgen::synthetic::generate(3, 48, 48);
        assert!(s.depth.data.iter().filter(|&&z| z <= 0.0).count() > 48 * 48 / 50);
        assert_eq!(mesh_of_scene(Some("auto"), true), mesh_with("none"));
        // Auto is what a stage that says nothing gets.
        assert_eq!(mesh_of_scene(None, true), mesh_with("none"));
        // Without a photo there is nothing to test: room.
        assert_eq!(mesh_of_scene(Some("auto"), false), mesh_with("room"));
        assert_eq!(mesh_of_scene(None, false), mesh_with("room"));
    }
}
