//! `transparency`: a region of the photo made transparent, as the paper
//! does it without back-side geometry (§3.3, eqs. 22–23). The region's
//! front surface becomes a glass interface; what shows through it is the
//! background behind it, whose albedo (A_BG) is inpainted — harmonic
//! (membrane) inpainting, a documented classical method, in place of the
//! paper's Stable Diffusion — or given as an image. A refracted path goes
//! d1 into the object, leaves through a back surface parallel to the front
//! one, and reaches the background d2 further on; the pixel that point
//! projects to gives A_BG (`render`'s integrator does this). d1 and d2
//! come from a refraction-distance map (what the paper's refraction-length
//! network outputs, normalised to [0, 1], times `refraction_scale`) when
//! one is given, else from the thickness rule: `thickness` (scene units,
//! a slab), or the chord of a round object whose silhouette is the mask
//! (`matflow_scene::transparency::thickness_rule`), and d2 = `gap` (default
//! d1: the background one object-thickness behind).
//!
//! The result is a `materials` artifact with a transparency layer: a
//! `trace`/`render` pair re-edits T or η incrementally like any material.

use std::collections::BTreeMap;

use glam::{Vec2, Vec3};
use matflow_engine::node::Params;
use matflow_engine::{Node, NodeError, NodeInfo, OutputSpec, ParamSpec, ParamType, RunContext};
use matflow_geom::Bvh;
use matflow_scene::transparency::{
    inpaint_harmonic_gray, inpaint_harmonic_rgb, thickness_rule, Transparency,
};
use matflow_scene::{io, GrayImage, Image, MaterialMaps};

use crate::artifact::Artifact;
use crate::data::{decode_mesh, encode_materials, materials_from, MESH};
use crate::err;
use crate::kinds::edit::{
    check_mask_choice, check_mask_film, preflight_mask, EditNode, FLOOD_TOLERANCE, MASKS,
    MASK_FLOOD, MASK_PNG, MASK_RECT,
};

pub struct TransparencyNode;

const TRANSPARENCY_INFO: NodeInfo = NodeInfo {
    kind: "transparency",
    version: 2,
    doc: "Makes a region of the photo transparent (the paper's single-view transparency, eqs. \
         22–23): its surface becomes glass (ior, transmission T, roughness, tint); a refracted \
         path goes d1 into it, leaves through a back surface parallel to the front one and \
         shows the background d2 further on, whose albedo is inpainted (harmonic) or given. \
         d1, d2 from a refraction-distance map, or the thickness rule. Exactly one of \
         mask_png, mask_rect, mask_flood.",
    params: &[
        ParamSpec {
            name: "materials",
            ty: ParamType::Ref(&["materials", "scene"]),
            default: None,
            unit: "",
            doc: "the materials (a scene gives its predictions)",
        },
        MESH,
        MASK_PNG,
        MASK_RECT,
        MASK_FLOOD,
        FLOOD_TOLERANCE,
        ParamSpec {
            name: "ior",
            ty: ParamType::Float { min: 1.0, max: 4.0 },
            default: Some("1.5"),
            unit: "",
            doc: "index of refraction",
        },
        ParamSpec {
            name: "transmission",
            ty: ParamType::Float { min: 0.0, max: 1.0 },
            default: Some("1"),
            unit: "",
            doc: "specular transmission T",
        },
        ParamSpec {
            name: "roughness",
            ty: ParamType::Float { min: 0.0, max: 1.0 },
            default: Some("0"),
            unit: "",
            doc: "glass roughness (GGX α = roughness²)",
        },
        ParamSpec {
            name: "tint",
            ty: ParamType::Floats {
                len: 3,
                min: 0.0,
                max: 1.0,
            },
            default: Some("[1, 1, 1]"),
            unit: "linear RGB",
            doc: "colour of transmitted light",
        },
        ParamSpec {
            name: "background",
            ty: ParamType::Ref(&["image"]),
            default: Some("~"),
            unit: "",
            doc: "the background's albedo A_BG (linear) instead of inpainting it",
        },
        ParamSpec {
            name: "refraction_map",
            ty: ParamType::InPath,
            default: Some("~"),
            unit: "",
            doc: "EXR of the image's size: d1 in R, d2 in G, normalised to [0, 1] as the \
                  refraction-length network outputs them",
        },
        ParamSpec {
            name: "refraction",
            ty: ParamType::Ref(&["image"]),
            default: Some("~"),
            unit: "",
            doc: "a stage giving the same map as an image (d1 in R, d2 in G, normalised): where \
                  a refraction-length network's output comes in",
        },
        ParamSpec {
            name: "refraction_scale",
            ty: ParamType::Float { min: 0.0, max: 1e6 },
            default: Some("1"),
            unit: "scene units",
            doc: "what 1 in `refraction_map` means",
        },
        ParamSpec {
            name: "thickness",
            ty: ParamType::Float { min: 0.0, max: 1e6 },
            default: Some("~"),
            unit: "scene units",
            doc: "d1 everywhere in the region (a slab); default: the round-object rule",
        },
        ParamSpec {
            name: "thickness_scale",
            ty: ParamType::Float {
                min: 0.0,
                max: 100.0,
            },
            default: Some("1"),
            unit: "×",
            doc: "scales the round-object rule's d1",
        },
        ParamSpec {
            name: "gap",
            ty: ParamType::Float { min: 0.0, max: 1e6 },
            default: Some("~"),
            unit: "scene units",
            doc: "d2 everywhere (default: d1, the background one thickness behind)",
        },
    ],
    outputs: &[
        OutputSpec {
            name: "materials",
            ty: "materials",
            doc: "the materials with the region transparent",
        },
        OutputSpec {
            name: "background",
            ty: "image",
            doc: "the background albedo A_BG (linear)",
        },
    ],
};

/// Pixels within this distance of the region are inpainted too, so the
/// object's own rim does not bleed into its background.
const INPAINT_MARGIN: usize = 2;

fn dilate(mask: &Image<bool>, r: usize) -> Image<bool> {
    let (w, h) = (mask.width, mask.height);
    Image::from_fn(w, h, |x, y| {
        let (x0, x1) = (x.saturating_sub(r), (x + r).min(w - 1));
        let (y0, y1) = (y.saturating_sub(r), (y + r).min(h - 1));
        (y0..=y1).any(|yy| (x0..=x1).any(|xx| mask.get(xx, yy)))
    })
}

/// Camera-space depth z of the depth mesh seen through each pixel centre
/// inside `mask` (0 elsewhere or on the sky).
fn depth_in(mask: &Image<bool>, mesh: &[u8]) -> Result<(GrayImage, f32), NodeError> {
    let (cam, tri) = decode_mesh(mesh)?;
    if (cam.width, cam.height) != (mask.width, mask.height) {
        return Err(err(format!(
            "the mesh's camera is {}x{} but the materials are {}x{}",
            cam.width, cam.height, mask.width, mask.height
        )));
    }
    let bvh = Bvh::build(&tri);
    let f = cam.focal();
    let pp = cam.principal_point();
    let z = Image::from_fn(cam.width, cam.height, |x, y| {
        if !mask.get(x, y) {
            return 0.0;
        }
        let film = Vec2::new(x as f32 + 0.5, y as f32 + 0.5);
        let d = Vec3::new((film.x - 0.5 - pp.x) / f, -(film.y - 0.5 - pp.y) / f, -1.0).normalize();
        bvh.intersect(Vec3::ZERO, d, 0.0, f32::INFINITY)
            .map_or(0.0, |h| -(d * h.t).z)
    });
    Ok((z, f))
}

impl Node for TransparencyNode {
    fn info(&self) -> &'static NodeInfo {
        &TRANSPARENCY_INFO
    }
    fn check(&self, p: &Params) -> Result<(), String> {
        check_mask_choice(p, &MASKS[..3])?;
        if p.is_set("refraction_map") && p.is_set("refraction") {
            return Err(
                "give `refraction_map` (a file) or `refraction` (a stage), not both".into(),
            );
        }
        let given = if p.is_set("refraction_map") {
            Some("refraction_map")
        } else if p.is_set("refraction") {
            Some("refraction")
        } else {
            None
        };
        if let Some(g) = given {
            if p.is_set("thickness") || p.is_set("gap") {
                return Err(format!("`{g}` gives d1 and d2: drop `thickness` and `gap`"));
            }
        }
        Ok(())
    }
    fn check_film(&self, p: &Params, size: (usize, usize)) -> Result<(), String> {
        check_mask_film(p, size)?;
        if let Some(path) = p.path("refraction_map") {
            if let Ok((w, h)) = io::exr_size(&path) {
                if (w, h) != size {
                    return Err(format!(
                        "{}: the refraction map is {w}x{h} but the image is {}x{}",
                        path.display(),
                        size.0,
                        size.1
                    ));
                }
            }
        }
        Ok(())
    }
    fn preflight(&self, p: &Params) -> Result<(), String> {
        preflight_mask(p)?;
        if let Some(path) = p.path("refraction_map") {
            let m = io::read_exr_rgb(&path).map_err(|e| e.to_string())?;
            io::ensure_finite_rgb(&path, &m).map_err(|e| e.to_string())?;
            if m.data.iter().any(|v| v.x < 0.0 || v.y < 0.0) {
                return Err(format!(
                    "{}: refraction distances must not be negative",
                    path.display()
                ));
            }
        }
        Ok(())
    }
    fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
        let p = ctx.params;
        let maps = materials_from(ctx.input("materials")?)?;
        let mask = EditNode::mask(p, &maps, None)?;
        let (w, h) = (maps.width(), maps.height());
        let f32p = |n: &str| p.f64(n) as f32;
        let tint = p
            .floats("tint")
            .map(|v| Vec3::new(v[0] as f32, v[1] as f32, v[2] as f32))
            .unwrap_or(Vec3::ONE);
        // The background: the current one (earlier regions' included),
        // inpainted over this region and a small margin, or given.
        let current = |k: usize| maps.background_at(k);
        let bg_a = Image::from_vec(w, h, (0..w * h).map(|k| current(k).0).collect());
        let bg_r = Image::from_vec(w, h, (0..w * h).map(|k| current(k).1).collect());
        let bg_m = Image::from_vec(w, h, (0..w * h).map(|k| current(k).2).collect());
        let hole = dilate(&mask, INPAINT_MARGIN);
        let bg_albedo = match ctx.opt_input("background") {
            Some(b) => {
                let img = Artifact::decode(b, "image")?.rgb("image")?;
                if (img.width, img.height) != (w, h) {
                    return Err(err(format!(
                        "the background image is {}x{} but the materials are {w}x{h}",
                        img.width, img.height
                    )));
                }
                img.map(|v| v.clamp(Vec3::ZERO, Vec3::ONE))
            }
            None => inpaint_harmonic_rgb(&bg_a, &hole),
        };
        let (bg_roughness, bg_metallic) = rayon::join(
            || inpaint_harmonic_gray(&bg_r, &hole),
            || inpaint_harmonic_gray(&bg_m, &hole),
        );
        // Refraction distances.
        let map = match (p.path("refraction_map"), ctx.opt_input("refraction")) {
            (Some(path), _) => Some((
                io::read_exr_rgb(&path).map_err(err)?,
                path.display().to_string(),
            )),
            (None, Some(b)) => Some((
                Artifact::decode(b, "image")?.rgb("image")?,
                "the `refraction` stage's image".to_string(),
            )),
            _ => None,
        };
        let (d1, d2) = if let Some((m, what)) = map {
            if (m.width, m.height) != (w, h) {
                return Err(err(format!(
                    "{what}: the refraction map is {}x{} but the materials are {w}x{h}",
                    m.width, m.height
                )));
            }
            if m.data
                .iter()
                .any(|v| !v.is_finite() || v.x < 0.0 || v.y < 0.0)
            {
                return Err(err(format!(
                    "{what}: refraction distances must be finite and not negative"
                )));
            }
            let s = f32p("refraction_scale");
            (m.map(|v| v.x.max(0.0) * s), m.map(|v| v.y.max(0.0) * s))
        } else {
            let d1 = match p.opt_f64("thickness") {
                Some(t) => mask.map(|b| if b { t as f32 } else { 0.0 }),
                None => {
                    let (z, focal) = depth_in(&mask, ctx.input("mesh")?)?;
                    thickness_rule(&mask, &z, focal, f32p("thickness_scale"))
                }
            };
            let d2 = match p.opt_f64("gap") {
                Some(g) => mask.map(|b| if b { g as f32 } else { 0.0 }),
                None => d1.clone(),
            };
            (d1, d2)
        };
        let mut t = maps
            .transparency
            .clone()
            .unwrap_or_else(|| Transparency::none(&maps.albedo, &maps.roughness, &maps.metallic));
        for k in 0..w * h {
            if mask.data[k] {
                t.ior.data[k] = f32p("ior");
                t.transmission.data[k] = f32p("transmission");
                t.roughness.data[k] = f32p("roughness");
                t.tint.data[k] = tint;
                t.d1.data[k] = d1.data[k];
                t.d2.data[k] = d2.data[k];
            }
            // The background under this region (and its margin) is the
            // new one; elsewhere it stays.
            if hole.data[k] {
                t.bg_albedo.data[k] = bg_albedo.data[k];
                t.bg_roughness.data[k] = bg_roughness.data[k];
                t.bg_metallic.data[k] = bg_metallic.data[k];
            }
        }
        let out = MaterialMaps {
            transparency: Some(t),
            ..maps
        };
        let bg = out
            .transparency
            .as_ref()
            .map(|t| t.bg_albedo.clone())
            .expect("set above");
        Ok([
            ("materials".to_string(), encode_materials(&out)),
            (
                "background".to_string(),
                crate::data::encode_image("image", "image", &bg),
            ),
        ]
        .into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinds::render::rerender_kept;
    use crate::testutil::{check_retrace, opts, small_room, trace_kept};
    use matflow_render::{render, EnvMap, RenderScene};

    /// Re-editing a transparent region's T re-traces what its kept paths
    /// reach, bit-identical there to a full render; so does making a
    /// region transparent in the first place.
    #[test]
    fn transmission_re_edits_retrace_bit_identically() {
        let n = 24;
        let (s, cam, tri) = small_room(n);
        let mask = Image::from_fn(n, n, |x, y| (8..16).contains(&x) && (12..20).contains(&y));
        let glassy = |t_value: f32| {
            let mut t = Transparency::none(&s.maps.albedo, &s.maps.roughness, &s.maps.metallic);
            let bg = inpaint_harmonic_rgb(&s.maps.albedo, &mask);
            for k in 0..n * n {
                if mask.data[k] {
                    t.ior.data[k] = 1.5;
                    t.transmission.data[k] = t_value;
                    t.d1.data[k] = 0.2;
                    t.d2.data[k] = 0.2;
                    t.bg_albedo.data[k] = bg.data[k];
                }
            }
            MaterialMaps {
                transparency: Some(t),
                ..s.maps.clone()
            }
        };
        let env = EnvMap::new(&s.envmap).unwrap();
        let scene = |m: &MaterialMaps| RenderScene::new(cam, tri.clone(), m, env.clone()).unwrap();
        for (base_maps, edited) in [(glassy(1.0), glassy(0.4)), (s.maps.clone(), glassy(1.0))] {
            let kept = trace_kept(&scene(&base_maps), &base_maps, &s.envmap, &[], None);
            assert!(
                kept.materials.transparency == base_maps.transparency,
                "the transparency layer round-trips"
            );
            let escene = scene(&edited);
            let got = rerender_kept(&kept, &escene, &edited, &[]).unwrap();
            let full = render(&escene, &opts(), &|_, _| {}).image;
            let mut changed = base_maps.changed_texels(&edited);
            changed.extend(base_maps.changed_background(&edited));
            let (hit, missed) = check_retrace(&kept, &changed, &got, &full);
            assert!(hit >= 64 && hit < n * n, "{hit}");
            assert!(missed * 10 < n * n, "{missed} pixels missed");
        }
    }
}

#[cfg(test)]
mod node_tests {
    use super::*;
    use crate::data::{encode_image, encode_mesh};
    use matflow_engine::Value;
    use matflow_scene::Camera;

    fn params(extra: &[(&str, Value)]) -> Params {
        let mut m = BTreeMap::new();
        for p in TRANSPARENCY_INFO.params {
            let v = match p.default {
                Some(d) => matflow_engine::value::parse_override(d).unwrap(),
                None => Value::Null,
            };
            let v = p.ty.normalize(&v).unwrap_or(v);
            m.insert(p.name.to_string(), v);
        }
        for (k, v) in extra {
            m.insert(k.to_string(), v.clone());
        }
        Params(m)
    }

    #[test]
    fn the_region_gets_glass_distances_and_a_background() {
        let n = 20;
        let cam = Camera::new(n, n);
        let tri =
            matflow_geom::mesh_from_depth(&GrayImage::new(n, n, 4.0), &cam, &Default::default())
                .unwrap()
                .mesh;
        let grey = Vec3::new(0.4, 0.3, 0.2);
        let maps = MaterialMaps::uniform(n, n, grey, 0.6, 0.1);
        let rect = Value::List([5.0, 5.0, 15.0, 15.0].map(Value::Float).to_vec());
        let run = |extra: &[(&str, Value)], bg: Option<Vec<u8>>| {
            let p = params(extra);
            let mut inputs = BTreeMap::new();
            inputs.insert("materials".to_string(), encode_materials(&maps).into());
            inputs.insert("mesh".to_string(), encode_mesh(n, n, &tri).into());
            if let Some(b) = bg {
                inputs.insert("background".to_string(), b.into());
            }
            let ctx = RunContext {
                stage: "t",
                params: &p,
                inputs,
                seed: 0,
                progress: &|_, _| {},
                metric: &|_, _| {},
                cancelled: &matflow_engine::node::never_cancelled,
                image: None,
            };
            let out = TransparencyNode.run(&ctx).unwrap();
            crate::data::materials_from(&out["materials"]).unwrap()
        };
        // Inpainted: the surroundings are uniform, so is the background.
        let m = run(&[("mask_rect", rect.clone())], None);
        let t = m.transparency.as_ref().unwrap();
        let c = 10 * n + 10;
        assert!(t.is_glass(c) && !t.is_glass(0));
        assert_eq!(t.ior.data[c], 1.5);
        assert!((t.bg_albedo.data[c] - grey).abs().max_element() < 1e-4);
        assert!((t.bg_roughness.data[c] - 0.6).abs() < 1e-4);
        // The round-object rule: thickest in the middle, about the region's
        // width (10 px at depth 4, focal n/2/tan 17.5°).
        let width = 10.0 * 4.0 / cam.focal();
        assert!(
            t.d1.data[c] > 0.6 * width && t.d1.data[c] < 1.2 * width,
            "{}",
            t.d1.data[c]
        );
        assert!(t.d1.data[5 * n + 10] < t.d1.data[c]);
        assert_eq!(t.d2.data[c], t.d1.data[c], "the gap defaults to d1");
        assert_eq!(
            (m.albedo, m.roughness),
            (maps.albedo.clone(), maps.roughness.clone())
        );
        // Given: the background image is used inside the region.
        let green = Vec3::new(0.1, 0.8, 0.2);
        let img = encode_image("image", "image", &matflow_scene::RgbImage::new(n, n, green));
        let m = run(
            &[
                ("mask_rect", rect.clone()),
                ("thickness", Value::Float(0.5)),
                ("gap", Value::Float(2.0)),
                ("transmission", Value::Float(0.3)),
            ],
            Some(img),
        );
        let t = m.transparency.as_ref().unwrap();
        assert_eq!(t.bg_albedo.data[c], green);
        assert_eq!(
            (t.d1.data[c], t.d2.data[c], t.transmission.data[c]),
            (0.5, 2.0, 0.3)
        );
        assert_eq!(t.d1.data[0], 0.0);
    }
}
