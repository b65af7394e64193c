//! `image`: a photo (PNG/JPEG, centre-cropped and linearised) or a linear
//! EXR / Radiance HDR file.

use std::collections::BTreeMap;

use matflow_engine::node::Params;
use matflow_engine::{Node, NodeError, NodeInfo, OutputSpec, ParamSpec, ParamType, RunContext};

use crate::data::{encode_image, read_image};

const IMAGE_OUT: &[OutputSpec] = &[OutputSpec {
    name: "image",
    ty: "image",
    doc: "linear RGB",
}];

pub struct ImageNode;

const IMAGE_INFO: NodeInfo = NodeInfo {
    kind: "image",
    version: 1,
    doc: "An image file: a photo (PNG/JPEG; centre-cropped to a square, resized, linearised \
         with power 2.2 as the reference does) or a linear EXR / Radiance HDR (as is).",
    params: &[
        ParamSpec {
            name: "path",
            ty: ParamType::InPath,
            default: None,
            unit: "",
            doc: "the file (relative to the pipeline file)",
        },
        ParamSpec {
            name: "size",
            ty: ParamType::Int { min: 0, max: 8192 },
            default: Some("512"),
            unit: "px",
            doc: "photos: side of the square they are resized to (0: the shorter side)",
        },
    ],
    outputs: IMAGE_OUT,
};

impl Node for ImageNode {
    fn info(&self) -> &'static NodeInfo {
        &IMAGE_INFO
    }
    fn preflight(&self, p: &Params) -> Result<(), String> {
        read_image(&p.path("path").unwrap_or_default(), p.i64("size") as usize)
            .map(|_| ())
            .map_err(|e| e.0)
    }
    fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
        let p = ctx.params;
        let img = read_image(&p.path("path").unwrap_or_default(), p.i64("size") as usize)?;
        Ok([("image".to_string(), encode_image("image", "image", &img))].into())
    }
}
