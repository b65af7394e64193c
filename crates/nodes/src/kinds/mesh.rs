//! `mesh`: the triangle mesh of a scene's depth map.

use std::collections::BTreeMap;

use matflow_engine::{Node, NodeError, NodeInfo, OutputSpec, ParamSpec, ParamType, RunContext};

use crate::data::{encode_mesh, mesh_of, SceneData};

pub struct MeshNode;

const MESH_INFO: NodeInfo = NodeInfo {
    kind: "mesh",
    version: 1,
    doc: "The triangle mesh of a scene's depth map (one vertex per pixel, cut at depth \
         discontinuities found by the reference's angle test).",
    params: &[
        ParamSpec {
            name: "scene",
            ty: ParamType::Ref(&["scene"]),
            default: None,
            unit: "",
            doc: "the scene whose depth is meshed",
        },
        ParamSpec {
            name: "angle",
            ty: ParamType::Float {
                min: 0.0,
                max: 90.0,
            },
            default: Some("6"),
            unit: "degrees",
            doc: "boundary threshold: triangles seen more obliquely than this are cut",
        },
    ],
    outputs: &[OutputSpec {
        name: "mesh",
        ty: "mesh",
        doc: "vertices, triangles, film positions",
    }],
};

impl Node for MeshNode {
    fn info(&self) -> &'static NodeInfo {
        &MESH_INFO
    }
    fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
        let s = SceneData::decode(ctx.input("scene")?)?;
        let tri = mesh_of(&s.depth, ctx.params.f64("angle"))?;
        Ok([(
            "mesh".to_string(),
            encode_mesh(s.depth.width, s.depth.height, &tri),
        )]
        .into())
    }
}
