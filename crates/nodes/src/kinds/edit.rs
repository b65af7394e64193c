//! `edit`: a material edit, a mask (a PNG, a rectangle, a region grown
//! from a seed pixel over the albedo, or the object under a pixel, grown
//! over the scene's albedo, depth and normals as the studio's click
//! selects it) and operations on the masked pixels
//! ([`matflow_scene::edit`]).

use std::collections::BTreeMap;

use glam::Vec3;
use matflow_engine::node::Params;
use matflow_engine::{Node, NodeError, NodeInfo, OutputSpec, ParamSpec, ParamType, RunContext};
use matflow_scene::edit::{apply_ops, flood_mask, EditOps};
use matflow_scene::select::{grow_object_within_edges, Grow};
use matflow_scene::{io, Camera, Image, MaterialMaps};

use crate::artifact::Artifact;
use crate::data::{encode_materials, materials_from, SceneData};
use crate::err;

pub struct EditNode;

/// The masks of `edit`; the stages that share its masks offer the first three.
pub(crate) const MASKS: [&str; 4] = ["mask_png", "mask_rect", "mask_flood", "mask_object"];
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

    /// The mask; `scene` is needed by `mask_object` alone.
    pub(crate) fn mask(
        p: &Params,
        maps: &MaterialMaps,
        scene: Option<&SceneData>,
    ) -> Result<Image<bool>, NodeError> {
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
        } else if let Some(s) = p.floats("mask_object") {
            let scene = scene.ok_or_else(|| err("mask_object needs `scene`"))?;
            let (x, y) = (s[0] as usize, s[1] as usize);
            if x >= w || y >= h {
                return Err(err(format!(
                    "mask_object: seed pixel ({x}, {y}) is outside the {w}x{h} image"
                )));
            }
            let pred = &scene.pred;
            if !scene.depth.same_size(&pred.albedo)
                || (pred.albedo.width, pred.albedo.height) != (w, h)
            {
                return Err(err(format!(
                    "mask_object: the scene is {}x{} but the materials are {w}x{h}",
                    scene.depth.width, scene.depth.height
                )));
            }
            let g = Grow {
                albedo_tol: p.f32("object_tolerance"),
                ..Grow::default()
            };
            let normals = match p.str("object_normals") {
                "predicted" => pred.normal.as_ref(),
                _ => None,
            };
            let cam = Camera::new(w, h);
            let step = p.f32("object_edges");
            let edges = scene
                .target
                .as_ref()
                .filter(|_| step > 0.0)
                .map(|p| (p, step));
            grow_object_within_edges(&pred.albedo, &scene.depth, normals, edges, &cam, (x, y), &g)
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

pub(crate) const MASK_PNG: ParamSpec = ParamSpec {
    name: "mask_png",
    ty: ParamType::InPath,
    default: Some("~"),
    unit: "",
    doc: "a PNG of the image's size; white (and opaque) pixels are edited",
};

pub(crate) const MASK_RECT: ParamSpec = ParamSpec {
    name: "mask_rect",
    ty: ParamType::Floats {
        len: 4,
        min: 0.0,
        max: 65536.0,
    },
    default: Some("~"),
    unit: "px",
    doc: "[x0, y0, x1, y1], x1 and y1 exclusive, origin top left",
};

/// A `[x, y]` pixel of the image, as the masks grown from a seed take it.
const fn seed_pixel(name: &'static str, doc: &'static str) -> ParamSpec {
    ParamSpec {
        name,
        ty: ParamType::Floats {
            len: 2,
            min: 0.0,
            max: 65536.0,
        },
        default: Some("~"),
        unit: "px",
        doc,
    }
}

pub(crate) const MASK_FLOOD: ParamSpec = seed_pixel(
    "mask_flood",
    "[x, y] seed pixel; the region grows over similar albedo",
);

const MASK_OBJECT: ParamSpec = seed_pixel(
    "mask_object",
    "[x, y] a pixel of the object to edit: the region grows from it over the scene's \
     predicted albedo, depth and normals (object_normals) and stops at occlusion edges, \
     inward folds (where the object meets its support) and the photo's own edges \
     (object_edges) (needs `scene`)",
);

const OBJECT_EDGES: ParamSpec = ParamSpec {
    name: "object_edges",
    ty: ParamType::Float { min: 0.0, max: 1.0 },
    default: Some("0.03"),
    unit: "γ-encoded",
    doc: "with mask_object: the region also stops where the photo steps by more than this \
          between neighbours (3×3 means, any channel), and does not enter a pixel on a \
          strong edge (a step of 3× this to a neighbour; the outline's ring joins after): \
          an object's outline, where blurred predictions run smoothly into what is behind \
          it (0: the predictions alone; the studio's click takes the default)",
};

const OBJECT_NORMALS: ParamSpec = ParamSpec {
    name: "object_normals",
    ty: ParamType::Choice(&["depth", "predicted"]),
    default: Some("predicted"),
    unit: "",
    doc: "with mask_object: the normals the region grows over: predicted (the model's own, \
          where the scene has them; else estimated from the depth) or depth (estimated from \
          the depth: for a model whose normal map is blotchy, which breaks a curved object \
          into patches)",
};

const OBJECT_TOLERANCE: ParamSpec = ParamSpec {
    name: "object_tolerance",
    ty: ParamType::Float { min: 0.0, max: 1.0 },
    default: Some("0.2"),
    unit: "γ-encoded",
    doc: "with mask_object: largest per-channel difference of the predicted albedo (3×3 mean) \
          from the seed's that joins the region",
};

pub(crate) const FLOOD_TOLERANCE: ParamSpec = ParamSpec {
    name: "flood_tolerance",
    ty: ParamType::Float { min: 0.0, max: 1.0 },
    default: Some("0.08"),
    unit: "γ-encoded",
    doc: "largest per-channel albedo difference from the seed that joins the region",
};

const EDIT_INFO: NodeInfo = NodeInfo {
    kind: "edit",
    version: 4,
    doc: "Edits materials inside a mask: set or scale roughness and metallic, set the albedo \
         colour or shift its hue, saturation and value (on γ-encoded albedo, as a colour \
         picker shows it). Exactly one of mask_png, mask_rect, mask_flood, mask_object; \
         order: set, then scale, then the HSV shift.",
    params: &[
        ParamSpec {
            name: "materials",
            ty: ParamType::Ref(&["materials", "scene"]),
            default: None,
            unit: "",
            doc: "the materials to edit (a scene gives its predictions)",
        },
        MASK_PNG,
        MASK_RECT,
        MASK_FLOOD,
        FLOOD_TOLERANCE,
        MASK_OBJECT,
        OBJECT_EDGES,
        OBJECT_TOLERANCE,
        OBJECT_NORMALS,
        ParamSpec {
            name: "scene",
            ty: ParamType::Ref(&["scene"]),
            default: Some("~"),
            unit: "",
            doc: "the scene whose predicted albedo, depth and normals mask_object grows over",
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
    fn check_film(&self, p: &Params, size: (usize, usize)) -> Result<(), String> {
        check_mask_film(p, size)
    }
    /// A mask file is decoded before any stage runs: a corrupt or empty
    /// one must not cost the upstream stages first.
    fn preflight(&self, p: &Params) -> Result<(), String> {
        preflight_mask(p)
    }
    fn check(&self, p: &Params) -> Result<(), String> {
        check_mask_choice(p, &MASKS)?;
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
        let scene = ctx.opt_input("scene").map(SceneData::decode).transpose()?;
        let mask = Self::mask(ctx.params, &maps, scene.as_ref())?;
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

/// Pixel positions and mask sizes against the image size.
pub(crate) fn check_mask_film(p: &Params, (w, h): (usize, usize)) -> Result<(), String> {
    if let Some(r) = p.floats("mask_rect") {
        if r[0] >= w as f64 || r[1] >= h as f64 || r[2] <= 0.0 || r[3] <= 0.0 {
            return Err(format!(
                "mask_rect [{}, {}, {}, {}] lies outside the {w}x{h} image",
                r[0], r[1], r[2], r[3]
            ));
        }
    }
    if let Some(s) = p.floats("mask_flood") {
        if s[0] >= w as f64 || s[1] >= h as f64 {
            return Err(format!(
                "mask_flood: seed pixel ({}, {}) is outside the {w}x{h} image",
                s[0], s[1]
            ));
        }
    }
    if let Some(s) = p.floats("mask_object") {
        if s[0] >= w as f64 || s[1] >= h as f64 {
            return Err(format!(
                "mask_object: seed pixel ({}, {}) is outside the {w}x{h} image",
                s[0], s[1]
            ));
        }
    }
    if let Some(path) = p.path("mask_png") {
        if let Ok(m) = io::read_mask(&path) {
            if (m.width, m.height) != (w, h) {
                return Err(format!(
                    "{}: the mask is {}x{} but the image is {w}x{h}",
                    path.display(),
                    m.width,
                    m.height
                ));
            }
        }
    }
    Ok(())
}

/// Decodes a mask file before anything runs.
pub(crate) fn preflight_mask(p: &Params) -> Result<(), String> {
    if let Some(path) = p.path("mask_png") {
        let m = io::read_mask(&path).map_err(|e| e.to_string())?;
        if !m.data.iter().any(|&b| b) {
            return Err(format!(
                "{}: the mask selects no pixels (white, opaque pixels are edited)",
                path.display()
            ));
        }
    }
    Ok(())
}

/// Exactly one of the masks `offered`, and a non-empty rectangle.
pub(crate) fn check_mask_choice(p: &Params, offered: &[&str]) -> Result<(), String> {
    if let Some(r) = p.floats("mask_rect") {
        if r[2] <= r[0] || r[3] <= r[1] {
            return Err(format!(
                "mask_rect [{}, {}, {}, {}] is empty: give [x0, y0, x1, y1] with x1 > x0 and y1 > y0",
                r[0], r[1], r[2], r[3]
            ));
        }
    }
    if p.is_set("mask_object") && !p.is_set("scene") {
        return Err(
            "mask_object needs `scene`: the stage whose depth and predictions it \
                    grows over"
                .into(),
        );
    }
    let masks: Vec<&str> = offered.iter().copied().filter(|m| p.is_set(m)).collect();
    if masks.len() != 1 {
        return Err(format!(
            "give exactly one of {} (got {})",
            offered.join(", "),
            if masks.is_empty() {
                "none".to_string()
            } else {
                masks.join(", ")
            }
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The studio's click and the stage's default stop at the same edges.
    #[test]
    fn object_edges_defaults_to_the_shared_step() {
        let d: f32 = OBJECT_EDGES.default.unwrap().parse().unwrap();
        assert_eq!(d, matflow_scene::select::PHOTO_EDGE_STEP);
    }
}
