//! New lighting: an HDR environment map from a file or an upstream stage,
//! rotated about the vertical axis and scaled in exposure.

use std::collections::BTreeMap;

use matflow_engine::node::Params;
use matflow_engine::{Node, NodeError, NodeInfo, OutputSpec, ParamSpec, ParamType, RunContext};
use matflow_scene::{Image, RgbImage};

use crate::artifact::Artifact;
use crate::err;
use crate::inputs::{encode_image, read_image};

/// Rotates a lat-long map by `deg` about the vertical axis (a horizontal
/// shift that wraps, linear between columns) and scales it by 2^ev.
pub fn rotate_and_expose(env: &RgbImage, deg: f64, ev: f64) -> RgbImage {
    let w = env.width;
    let shift = (deg / 360.0).rem_euclid(1.0) * w as f64;
    let k = 2f64.powf(ev) as f32;
    Image::from_fn(w, env.height, |x, y| {
        let src = (x as f64 - shift).rem_euclid(w as f64);
        let x0 = src.floor() as usize % w;
        let x1 = (x0 + 1) % w;
        let t = (src - src.floor()) as f32;
        (env.get(x0, y) * (1.0 - t) + env.get(x1, y) * t) * k
    })
}

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
            Some(path) => read_image(&path, 0).map(|_| ()).map_err(|e| e.0),
            None => Ok(()),
        }
    }
    fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
        let p = ctx.params;
        let env = match p.path("path") {
            Some(path) => read_image(&path, 0)?,
            None => {
                let b = ctx.input("source")?;
                match Artifact::decode(b, "envmap") {
                    Ok(a) => a.rgb("envmap")?,
                    Err(_) => Artifact::decode(b, "image")?.rgb("image")?,
                }
            }
        };
        if env.width < 2 || env.height < 2 || env.width > 16384 || env.height > 8192 {
            return Err(err(format!(
                "an envmap of {}x{} is out of range (2x2 to 16384x8192)",
                env.width, env.height
            )));
        }
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

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    #[test]
    fn rotation_shifts_columns_and_exposure_scales() {
        let env = Image::from_fn(8, 2, |x, _| Vec3::splat(x as f32));
        let r = rotate_and_expose(&env, 90.0, 1.0);
        // 90° = 2 columns: output column 2 reads input column 0.
        assert_eq!(r.get(2, 0), Vec3::splat(0.0));
        assert_eq!(r.get(3, 1), Vec3::splat(2.0));
        let full = rotate_and_expose(&env, 360.0, 0.0);
        assert_eq!(full.data, env.data);
    }
}
