//! `relight`: new lighting, an HDR environment map from a file or an upstream stage,
//! rotated about the vertical axis and scaled in exposure.

use std::collections::BTreeMap;

use matflow_engine::node::Params;
use matflow_engine::{Node, NodeError, NodeInfo, OutputSpec, ParamSpec, ParamType, RunContext};
use matflow_render::envmap::rotate_and_expose;

use crate::artifact::Artifact;
use crate::data::encode_image;
use crate::err;
use matflow_scene::io;

pub struct RelightNode;

const RELIGHT_INFO: NodeInfo = NodeInfo {
    kind: "relight",
    version: 1,
    doc: "New lighting for a render: an HDR environment map (lat-long, Mitsuba's orientation) \
         from a file or from an `image`/envmap stage, rotated and exposed. Exactly one of \
         path and source.",
    params: &[
        ParamSpec {
            name: "path",
            ty: ParamType::InPath,
            default: Some("~"),
            unit: "",
            doc: "a .hdr or .exr environment map",
        },
        ParamSpec {
            name: "source",
            ty: ParamType::Ref(&["envmap", "image"]),
            default: Some("~"),
            unit: "",
            doc: "a stage giving the map (e.g. envmap_opt, or image of an .hdr)",
        },
        ParamSpec {
            name: "rotation",
            ty: ParamType::Float {
                min: -360.0,
                max: 360.0,
            },
            default: Some("0"),
            unit: "degrees",
            doc: "turn the lighting about the vertical axis",
        },
        ParamSpec {
            name: "exposure",
            ty: ParamType::Float {
                min: -30.0,
                max: 30.0,
            },
            default: Some("0"),
            unit: "EV",
            doc: "scale the lighting by 2^exposure",
        },
    ],
    outputs: &[OutputSpec {
        name: "envmap",
        ty: "envmap",
        doc: "the new lighting",
    }],
};

impl Node for RelightNode {
    fn info(&self) -> &'static NodeInfo {
        &RELIGHT_INFO
    }
    fn check(&self, p: &Params) -> Result<(), String> {
        if p.is_set("path") == p.is_set("source") {
            return Err("give exactly one of path and source".into());
        }
        Ok(())
    }
    fn preflight(&self, p: &Params) -> Result<(), String> {
        match p.path("path") {
            Some(path) => io::read_envmap(&path)
                .map(|_| ())
                .map_err(|e| e.to_string()),
            None => Ok(()),
        }
    }
    fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
        let p = ctx.params;
        let env = match p.path("path") {
            Some(path) => io::read_envmap(&path).map_err(err)?,
            None => {
                let b = ctx.input("source")?;
                match Artifact::decode(b, "envmap") {
                    Ok(a) => a.rgb("envmap")?,
                    Err(_) => Artifact::decode(b, "image")?.rgb("image")?,
                }
            }
        };
        io::check_envmap(std::path::Path::new("the `source` stage's map"), &env).map_err(err)?;
        let out = rotate_and_expose(&env, p.f64("rotation"), p.f64("exposure"));
        if out
            .data
            .iter()
            .any(|v| !v.is_finite() || v.min_element() < 0.0)
        {
            return Err(err(
                "the envmap holds negative or non-finite values after exposure",
            ));
        }
        Ok([("envmap".to_string(), encode_image("envmap", "envmap", &out))].into())
    }
}
