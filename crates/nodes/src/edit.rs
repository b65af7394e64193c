//! Material edits: a mask (a PNG, a rectangle, or a region grown from a
//! seed pixel over the albedo) and operations on the masked pixels.

use std::collections::{BTreeMap, VecDeque};

use glam::Vec3;
use matflow_engine::node::Params;
use matflow_engine::{Node, NodeError, NodeInfo, OutputSpec, ParamSpec, ParamType, RunContext};
use matflow_scene::color::{gamma_to_linear, linear_to_gamma};
use matflow_scene::{io, Image, MaterialMaps, RgbImage};

use crate::artifact::Artifact;
use crate::err;
use crate::inputs::{encode_materials, materials_from};

/// The operations of one edit. Colours and the HSV shift work on
/// γ-encoded albedo (power 1/2.2, the reference's display encoding), the
/// space a colour picker shows; results are stored linear.
#[derive(Clone, Debug, Default)]
pub struct EditOps {
    pub roughness: Option<f32>,
    pub roughness_scale: f32,
    pub metallic: Option<f32>,
    pub metallic_scale: f32,
    /// γ-encoded RGB in [0, 1].
    pub albedo: Option<Vec3>,
    pub hue_shift_deg: f32,
    pub saturation_scale: f32,
    pub value_scale: f32,
}

/// Shifts hue (degrees), scales saturation and value of a γ-encoded colour.
pub fn hsv_shift(c: Vec3, hue_deg: f32, sat: f32, val: f32) -> Vec3 {
    let c = c.clamp(Vec3::ZERO, Vec3::ONE);
    let max = c.max_element();
    let min = c.min_element();
    let d = max - min;
    let mut h = if d <= 0.0 {
        0.0
    } else if max == c.x {
        60.0 * ((c.y - c.z) / d).rem_euclid(6.0)
    } else if max == c.y {
        60.0 * ((c.z - c.x) / d + 2.0)
    } else {
        60.0 * ((c.x - c.y) / d + 4.0)
    };
    let s = if max > 0.0 { d / max } else { 0.0 };
    h = (h + hue_deg).rem_euclid(360.0);
    let s = (s * sat).clamp(0.0, 1.0);
    let v = (max * val).clamp(0.0, 1.0);
    let cc = v * s;
    let x = cc * (1.0 - ((h / 60.0).rem_euclid(2.0) - 1.0).abs());
    let m = v - cc;
    let (r, g, b) = match (h / 60.0) as u32 {
        0 => (cc, x, 0.0),
        1 => (x, cc, 0.0),
        2 => (0.0, cc, x),
        3 => (0.0, x, cc),
        4 => (x, 0.0, cc),
        _ => (cc, 0.0, x),
    };
    Vec3::new(r + m, g + m, b + m)
}

/// Applies `ops` where `mask` is set.
pub fn apply_ops(maps: &MaterialMaps, mask: &Image<bool>, ops: &EditOps) -> MaterialMaps {
    let mut out = maps.clone();
    for i in 0..mask.data.len() {
        if !mask.data[i] {
            continue;
        }
        let r = ops.roughness.unwrap_or(out.roughness.data[i]) * ops.roughness_scale;
        out.roughness.data[i] = r.clamp(0.0, 1.0);
        let m = ops.metallic.unwrap_or(out.metallic.data[i]) * ops.metallic_scale;
        out.metallic.data[i] = m.clamp(0.0, 1.0);
        let a = out.albedo.data[i];
        let enc = ops.albedo.unwrap_or(Vec3::new(
            linear_to_gamma(a.x),
            linear_to_gamma(a.y),
            linear_to_gamma(a.z),
        ));
        let enc = hsv_shift(
            enc,
            ops.hue_shift_deg,
            ops.saturation_scale,
            ops.value_scale,
        );
        out.albedo.data[i] = Vec3::new(
            gamma_to_linear(enc.x),
            gamma_to_linear(enc.y),
            gamma_to_linear(enc.z),
        );
    }
    out
}

/// Pixels 4-connected to `seed` whose γ-encoded albedo differs from the
/// seed's by at most `tol` in every channel.
pub fn flood_mask(albedo: &RgbImage, seed: (usize, usize), tol: f32) -> Image<bool> {
    let (w, h) = (albedo.width, albedo.height);
    let mut m = Image::new(w, h, false);
    if seed.0 >= w || seed.1 >= h {
        return m;
    }
    let enc = |v: Vec3| {
        Vec3::new(
            linear_to_gamma(v.x),
            linear_to_gamma(v.y),
            linear_to_gamma(v.z),
        )
    };
    let c0 = enc(albedo.get(seed.0, seed.1));
    let mut q = VecDeque::from([seed]);
    m.set(seed.0, seed.1, true);
    while let Some((x, y)) = q.pop_front() {
        let nb = [
            (x.wrapping_sub(1), y),
            (x + 1, y),
            (x, y.wrapping_sub(1)),
            (x, y + 1),
        ];
        for (nx, ny) in nb {
            if nx < w
                && ny < h
                && !m.get(nx, ny)
                && (enc(albedo.get(nx, ny)) - c0).abs().max_element() <= tol
            {
                m.set(nx, ny, true);
                q.push_back((nx, ny));
            }
        }
    }
    m
}

pub struct EditNode;

const MASKS: [&str; 3] = ["mask_png", "mask_rect", "mask_flood"];
const OPS: [&str; 8] = [
    "roughness",
    "roughness_scale",
    "metallic",
    "metallic_scale",
    "albedo",
    "hue_shift",
    "saturation_scale",
    "value_scale",
];

impl EditNode {
    fn ops(p: &Params) -> EditOps {
        EditOps {
            roughness: p.opt_f64("roughness").map(|x| x as f32),
            roughness_scale: p.f32("roughness_scale"),
            metallic: p.opt_f64("metallic").map(|x| x as f32),
            metallic_scale: p.f32("metallic_scale"),
            albedo: p
                .floats("albedo")
                .map(|v| Vec3::new(v[0] as f32, v[1] as f32, v[2] as f32)),
            hue_shift_deg: p.f32("hue_shift"),
            saturation_scale: p.f32("saturation_scale"),
            value_scale: p.f32("value_scale"),
        }
    }

    fn mask(p: &Params, maps: &MaterialMaps) -> Result<Image<bool>, NodeError> {
        let (w, h) = (maps.width(), maps.height());
        let m = if let Some(path) = p.path("mask_png") {
            let m = io::read_mask(&path).map_err(err)?;
            if m.width != w || m.height != h {
                return Err(err(format!(
                    "{}: the mask is {}x{} but the materials are {w}x{h}",
                    path.display(),
                    m.width,
                    m.height
                )));
            }
            m
        } else if let Some(r) = p.floats("mask_rect") {
            let (x0, y0) = (r[0].max(0.0) as usize, r[1].max(0.0) as usize);
            let (x1, y1) = ((r[2] as usize).min(w), (r[3] as usize).min(h));
            Image::from_fn(w, h, |x, y| x >= x0 && x < x1 && y >= y0 && y < y1)
        } else {
            let s = p.floats("mask_flood").unwrap_or_default();
            let (x, y) = (s[0] as usize, s[1] as usize);
            if x >= w || y >= h {
                return Err(err(format!(
                    "mask_flood: seed pixel ({x}, {y}) is outside the {w}x{h} image"
                )));
            }
            flood_mask(&maps.albedo, (x, y), p.f32("flood_tolerance"))
        };
        if !m.data.iter().any(|&b| b) {
            return Err(err("the mask selects no pixels"));
        }
        Ok(m)
    }
}

const EDIT_INFO: NodeInfo = NodeInfo {
    kind: "edit",
    version: 1,
    doc: "Edits materials inside a mask: set or scale roughness and metallic, set the albedo \
         colour or shift its hue, saturation and value (on γ-encoded albedo, as a colour \
         picker shows it). Exactly one of mask_png, mask_rect, mask_flood; order: set, \
         then scale, then the HSV shift.",
    params: &[
        ParamSpec {
            name: "materials",
            ty: ParamType::Ref(&["materials", "scene"]),
            default: None,
            unit: "",
            doc: "the materials to edit (a scene gives its predictions)",
        },
        ParamSpec {
            name: "mask_png",
            ty: ParamType::InPath,
            default: Some("~"),
            unit: "",
            doc: "a PNG of the image's size; white (and opaque) pixels are edited",
        },
        ParamSpec {
            name: "mask_rect",
            ty: ParamType::Floats {
                len: 4,
                min: 0.0,
                max: 65536.0,
            },
            default: Some("~"),
            unit: "px",
            doc: "[x0, y0, x1, y1], x1 and y1 exclusive, origin top left",
        },
        ParamSpec {
            name: "mask_flood",
            ty: ParamType::Floats {
                len: 2,
                min: 0.0,
                max: 65536.0,
            },
            default: Some("~"),
            unit: "px",
            doc: "[x, y] seed pixel; the region grows over similar albedo",
        },
        ParamSpec {
            name: "flood_tolerance",
            ty: ParamType::Float { min: 0.0, max: 1.0 },
            default: Some("0.08"),
            unit: "γ-encoded",
            doc: "largest per-channel albedo difference from the seed that joins the region",
        },
        ParamSpec {
            name: "roughness",
            ty: ParamType::Float { min: 0.0, max: 1.0 },
            default: Some("~"),
            unit: "",
            doc: "set roughness",
        },
        ParamSpec {
            name: "roughness_scale",
            ty: ParamType::Float {
                min: 0.0,
                max: 100.0,
            },
            default: Some("1"),
            unit: "×",
            doc: "scale roughness (clamped to [0, 1])",
        },
        ParamSpec {
            name: "metallic",
            ty: ParamType::Float { min: 0.0, max: 1.0 },
            default: Some("~"),
            unit: "",
            doc: "set metallic",
        },
        ParamSpec {
            name: "metallic_scale",
            ty: ParamType::Float {
                min: 0.0,
                max: 100.0,
            },
            default: Some("1"),
            unit: "×",
            doc: "scale metallic (clamped to [0, 1])",
        },
        ParamSpec {
            name: "albedo",
            ty: ParamType::Floats {
                len: 3,
                min: 0.0,
                max: 1.0,
            },
            default: Some("~"),
            unit: "γ-encoded RGB",
            doc: "set the albedo colour",
        },
        ParamSpec {
            name: "hue_shift",
            ty: ParamType::Float {
                min: -360.0,
                max: 360.0,
            },
            default: Some("0"),
            unit: "degrees",
            doc: "rotate the albedo's hue",
        },
        ParamSpec {
            name: "saturation_scale",
            ty: ParamType::Float {
                min: 0.0,
                max: 100.0,
            },
            default: Some("1"),
            unit: "×",
            doc: "scale the albedo's saturation",
        },
        ParamSpec {
            name: "value_scale",
            ty: ParamType::Float {
                min: 0.0,
                max: 100.0,
            },
            default: Some("1"),
            unit: "×",
            doc: "scale the albedo's value (brightness)",
        },
    ],
    outputs: &[
        OutputSpec {
            name: "materials",
            ty: "materials",
            doc: "the edited materials",
        },
        OutputSpec {
            name: "mask",
            ty: "mask",
            doc: "the edited pixels (1) as a single-channel image",
        },
    ],
};

impl Node for EditNode {
    fn info(&self) -> &'static NodeInfo {
        &EDIT_INFO
    }
    fn check(&self, p: &Params) -> Result<(), String> {
        let masks: Vec<&str> = MASKS.iter().copied().filter(|m| p.is_set(m)).collect();
        if masks.len() != 1 {
            return Err(format!(
                "give exactly one of mask_png, mask_rect, mask_flood (got {})",
                if masks.is_empty() {
                    "none".to_string()
                } else {
                    masks.join(", ")
                }
            ));
        }
        let changes = OPS.iter().any(|o| match *o {
            "roughness_scale" | "metallic_scale" | "saturation_scale" | "value_scale" => {
                p.f64(o) != 1.0
            }
            "hue_shift" => p.f64(o) != 0.0,
            _ => p.is_set(o),
        });
        if !changes {
            return Err(
                "the edit changes nothing: set roughness, metallic, albedo, or a \
                        scale or shift"
                    .into(),
            );
        }
        Ok(())
    }
    fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
        let maps = materials_from(ctx.input("materials")?)?;
        let mask = Self::mask(ctx.params, &maps)?;
        let edited = apply_ops(&maps, &mask, &Self::ops(ctx.params));
        let mut m = Artifact::new("mask");
        m.put_gray("mask", &mask.map(|b| if b { 1.0 } else { 0.0 }));
        Ok([
            ("materials".to_string(), encode_materials(&edited)),
            ("mask".to_string(), m.encode()),
        ]
        .into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hsv_shift_known_answers() {
        let red = Vec3::new(1.0, 0.0, 0.0);
        let g = hsv_shift(red, 120.0, 1.0, 1.0);
        assert!(
            (g - Vec3::new(0.0, 1.0, 0.0)).abs().max_element() < 1e-5,
            "{g}"
        );
        let grey = hsv_shift(Vec3::new(0.8, 0.4, 0.2), 0.0, 0.0, 1.0);
        assert!(
            (grey - Vec3::splat(0.8)).abs().max_element() < 1e-5,
            "{grey}"
        );
        let c = Vec3::new(0.3, 0.6, 0.9);
        assert!((hsv_shift(c, 0.0, 1.0, 1.0) - c).abs().max_element() < 1e-5);
        assert!(
            (hsv_shift(c, 360.0, 1.0, 0.5) - c * 0.5)
                .abs()
                .max_element()
                < 1e-5
        );
    }

    #[test]
    fn flood_fill_stops_at_colour_edges() {
        let img = Image::from_fn(6, 4, |x, _| {
            if x < 3 {
                Vec3::splat(0.2)
            } else {
                Vec3::splat(0.8)
            }
        });
        let m = flood_mask(&img, (0, 0), 0.05);
        assert_eq!(m.data.iter().filter(|&&b| b).count(), 12);
        assert!(m.get(2, 3) && !m.get(3, 0));
    }

    #[test]
    fn ops_touch_only_the_mask_and_apply_in_order() {
        let maps = MaterialMaps::uniform(4, 4, Vec3::splat(0.5), 0.5, 0.2);
        let mask = Image::from_fn(4, 4, |x, y| x == 1 && y == 2);
        let ops = EditOps {
            roughness: Some(0.3),
            roughness_scale: 2.0,
            metallic: None,
            metallic_scale: 10.0,
            albedo: None,
            hue_shift_deg: 0.0,
            saturation_scale: 1.0,
            value_scale: 1.0,
        };
        let out = apply_ops(&maps, &mask, &ops);
        assert!((out.roughness.get(1, 2) - 0.6).abs() < 1e-6);
        assert_eq!(out.metallic.get(1, 2), 1.0);
        assert_eq!(out.roughness.get(0, 0), 0.5);
        assert!(
            (out.albedo.get(1, 2) - Vec3::splat(0.5))
                .abs()
                .max_element()
                < 1e-5
        );
    }
}
