//! `insert`: objects placed in the recovered scene and rendered with full
//! geometry — they cast shadows on the depth mesh, receive its bounced
//! light and show the envmap in reflections and refractions — then
//! composited into the photo.
//!
//! Differential compositing (Debevec 1998), the default: the photo keeps
//! its own detail and only the change the objects make is added,
//! final = photo + (with − without) outside the objects, and the render
//! with objects over them, blended by the objects' pixel coverage. Both
//! renders use the same sample streams, so wherever a path never meets an
//! object the two are bit-identical and the difference is exactly zero.
//! `composite: full` gives the plain re-render with objects, as the paper
//! shows.
//!
//! Given `paths` (a `trace` stage of the same mesh and objects), only the
//! pixels whose kept paths meet an object or material that changed are
//! re-traced: re-editing an inserted object's material is incremental.

use std::collections::BTreeMap;
use std::path::PathBuf;

use matflow_engine::node::{Bytes, Params};
use matflow_engine::{Node, NodeError, NodeInfo, OutputSpec, ParamSpec, ParamType, RunContext};
use matflow_render::{RenderOptions, RenderScene, SceneObject};
use matflow_scene::{Image, MaterialMaps, RgbImage};

use crate::artifact::Artifact;
use crate::data::{decode_mesh, encode_image, envmap_from, materials_from, Kept, SceneData, MESH};
use crate::err;
use crate::kinds::render::{pair, render_or_stop};
use crate::objects;

pub struct InsertNode;

/// Glass events beyond the path length, as the renders with glass take them.
pub(crate) const GLASS_DEPTH: ParamSpec = ParamSpec {
    name: "glass_depth",
    ty: ParamType::Int { min: 0, max: 256 },
    default: Some("16"),
    unit: "events",
    doc: "glass surfaces a path may pass or reflect off beyond `depth`",
};

const INSERT_INFO: NodeInfo = NodeInfo {
    kind: "insert",
    version: 5,
    doc: "Inserts objects (OBJ/PLY meshes; diffuse, principled or glass) into the scene and \
         renders them with full geometry (shadows, inter-reflection, refraction of the \
         envmap); composites into the photo differentially (photo + with − without, the \
         objects' pixels from the render) or gives the full re-render. With `paths` (a \
         `trace` of the same objects) only what a material change reaches is re-traced.",
    params: &[
        MESH,
        ParamSpec {
            name: "materials",
            ty: ParamType::Ref(&["materials", "scene"]),
            default: None,
            unit: "",
            doc: "the scene's materials (a scene gives its predictions)",
        },
        ParamSpec {
            name: "envmap",
            ty: ParamType::Ref(&["envmap"]),
            default: Some("~"),
            unit: "",
            doc: "lighting (not with `paths`, which brings its own)",
        },
        ParamSpec {
            name: "paths",
            ty: ParamType::Ref(&["paths"]),
            default: Some("~"),
            unit: "",
            doc:
                "a `trace` stage given the same `objects` (placement): re-trace only what changed \
                  materials reach (its spp, depth, seed; box filter)",
        },
        ParamSpec {
            name: "objects",
            ty: objects::OBJECTS,
            default: Some("~"),
            unit: "",
            doc: "the objects: `mesh`, `translate` or `anchor`, `rotate`, `scale`, `material` \
                  (see *Inserted objects*); with `paths`, absent: the trace's objects as they are",
        },
        ParamSpec {
            name: "photo",
            ty: ParamType::Ref(&["image", "scene"]),
            default: Some("~"),
            unit: "",
            doc: "the photo to composite into (a scene gives its input image); needed for \
                  `composite: differential`",
        },
        ParamSpec {
            name: "composite",
            ty: ParamType::Choice(&["differential", "full"]),
            default: Some("differential"),
            unit: "",
            doc: "differential: photo + (with − without) outside the objects; full: the render \
                  with the objects",
        },
        ParamSpec {
            name: "spp",
            ty: ParamType::Int { min: 1, max: 65536 },
            default: Some("64"),
            unit: "samples/px",
            doc: "samples per pixel (of each render)",
        },
        ParamSpec {
            name: "depth",
            ty: ParamType::Int { min: 1, max: 64 },
            default: Some("4"),
            unit: "segments",
            doc: "maximum path length, not counting segments leaving glass",
        },
        GLASS_DEPTH,
        ParamSpec {
            name: "filter",
            ty: ParamType::Choice(&["gaussian", "box"]),
            default: Some("gaussian"),
            unit: "",
            doc: "pixel filter",
        },
        ParamSpec {
            name: "seed",
            ty: ParamType::Int {
                min: 0,
                max: i64::MAX,
            },
            default: Some("0"),
            unit: "",
            doc: "extra seed",
        },
        ParamSpec {
            name: "output",
            ty: ParamType::OutPath,
            default: Some("~"),
            unit: "",
            doc: "EXR path to write (a PNG is written beside it)",
        },
    ],
    outputs: &[
        OutputSpec {
            name: "image",
            ty: "image",
            doc: "the result (composited, or the full render)",
        },
        OutputSpec {
            name: "render",
            ty: "image",
            doc: "the full render with the objects",
        },
        OutputSpec {
            name: "coverage",
            ty: "image",
            doc: "the objects' pixel coverage (matte), grey",
        },
    ],
};

/// Subsamples per pixel side of the coverage matte.
pub(crate) const COVERAGE_GRID: usize = 4;

/// The photo of an `image` or `scene` artifact.
pub(crate) fn photo_from(b: &[u8]) -> Result<RgbImage, NodeError> {
    match Artifact::decode(b, "image") {
        Ok(a) => a.rgb("image"),
        Err(_) => SceneData::decode(b)?
            .target
            .ok_or_else(|| err("`photo`: the scene has no input image")),
    }
}

/// final = α·with + (1 − α)·(photo + with − without), clamped at 0.
pub fn composite_differential(
    photo: &RgbImage,
    with: &RgbImage,
    without: &RgbImage,
    alpha: &[f32],
) -> RgbImage {
    Image::from_vec(
        photo.width,
        photo.height,
        (0..photo.data.len())
            .map(|k| {
                let a = alpha[k];
                // The difference first: where it is zero the photo is kept exactly.
                let outside = photo.data[k] + (with.data[k] - without.data[k]);
                (with.data[k] * a + outside * (1.0 - a)).max(glam::Vec3::ZERO)
            })
            .collect(),
    )
}

fn coverage_image(alpha: &[f32], w: usize, h: usize) -> RgbImage {
    Image::from_vec(w, h, alpha.iter().map(|&a| glam::Vec3::splat(a)).collect())
}

impl InsertNode {
    fn options(p: &Params, seed: u64) -> Result<RenderOptions, NodeError> {
        Ok(RenderOptions {
            spp: p.i64("spp") as u32,
            max_depth: p.i64("depth") as u32,
            glass_depth: p.i64("glass_depth") as u32,
            seed: seed ^ p.i64("seed") as u64,
            filter: p.parse("filter").map_err(err)?,
            ..Default::default()
        })
    }
}

/// The scene with `objs` added.
fn scene_with(
    cam: &matflow_scene::Camera,
    tri: &matflow_geom::TriMesh,
    maps: &MaterialMaps,
    env: &RgbImage,
    objs: &[SceneObject],
) -> Result<RenderScene, NodeError> {
    crate::data::scene_of(*cam, tri.clone(), maps, env, objs)
}

impl Node for InsertNode {
    fn info(&self) -> &'static NodeInfo {
        &INSERT_INFO
    }
    fn estimate_seconds(&self, p: &Params, film: Option<(usize, usize)>) -> f64 {
        let renders = if p.str("composite") == "differential" {
            2.0
        } else {
            1.0
        };
        renders * crate::data::render_seconds(film, p.i64("spp"), p.i64("depth"))
    }
    fn check(&self, p: &Params) -> Result<(), String> {
        crate::kinds::render::check_exr_output(p)?;
        let specs = objects::specs(p.get("objects")).map_err(|e| e.to_string())?;
        objects::check_specs(&specs)?;
        if p.str("composite") == "differential" && !p.is_set("photo") {
            return Err(
                "`composite: differential` adds the objects' change to a photo: give `photo` \
                 (an image or scene stage), or use `composite: full`"
                    .into(),
            );
        }
        if !p.is_set("objects") && !p.is_set("paths") {
            return Err("give `objects` (or `paths`, a `trace` stage with objects)".into());
        }
        match (p.is_set("paths"), p.is_set("envmap")) {
            (true, true) => Err("`paths` brings its envmap: drop `envmap`".into()),
            (false, false) => Err("give `envmap` (or `paths`, a `trace` stage)".into()),
            _ => Ok(()),
        }
    }
    fn preflight(&self, p: &Params) -> Result<(), String> {
        let specs = objects::specs(p.get("objects")).map_err(|e| e.to_string())?;
        objects::read_all(&specs).map(|_| ())
    }
    fn check_film(&self, p: &Params, size: (usize, usize)) -> Result<(), String> {
        let specs = objects::specs(p.get("objects")).map_err(|e| e.to_string())?;
        objects::check_anchors(&specs, size)
    }
    fn output_files(&self, p: &Params) -> Vec<PathBuf> {
        p.path("output")
            .map(|o| pair(&o).to_vec())
            .unwrap_or_default()
    }
    fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
        let p = ctx.params;
        let maps = materials_from(ctx.input("materials")?)?;
        let (cam, tri) = decode_mesh(ctx.input("mesh")?)?;
        let specs = objects::specs(p.get("objects"))?;
        let kept = ctx.opt_input("paths").map(Kept::decode).transpose()?;
        // Without kept paths: the scene without the objects, its geometry
        // (and BVH, which places anchored objects) from the memo.
        let plain = match &kept {
            None => {
                let env = envmap_from(ctx.input("envmap")?)?;
                Some((crate::memo::scene(ctx.input("mesh")?, &maps, &env)?, env))
            }
            Some(_) => None,
        };
        let objs = match &kept {
            Some(k) if specs.is_empty() => {
                if k.objects.is_empty() {
                    return Err(err("the `paths` stage has no objects: give `objects`"));
                }
                k.objects.clone()
            }
            _ => objects::place_with(&specs, &cam, &tri, plain.as_ref().map(|(s, _)| &*s.bvh))?,
        };
        let differential = p.str("composite") == "differential";
        let progress = |d: usize, t: usize, part: usize, parts: usize| {
            (ctx.progress)((part * t + d) as u64, (parts * t) as u64)
        };
        let parts = if differential { 2 } else { 1 };
        let kept_coverage = kept.as_ref().and_then(|k| k.coverage.clone());
        let (with, without, w_scene) = if let Some(kept) = kept {
            if !objects::same_geometry(&kept.objects, &objs) {
                return Err(err(
                    "the objects are not placed as in the `paths` stage (another mesh, \
                     transform or anchor): give that `trace` the same `objects`, or drop `paths`",
                ));
            }
            let w_scene = scene_with(&cam, &tri, &maps, &kept.envmap, &objs)?;
            let with = crate::kinds::render::rerender_kept(&kept, &w_scene, &maps, &objs)?;
            let without = match &kept.background {
                Some(bg) if kept.materials.changed_texels(&maps).iter().all(|c| !c) => {
                    Some(bg.clone())
                }
                // Edited screen materials change the background too: a
                // full render of it without the objects.
                _ if differential => {
                    let s = scene_with(&cam, &tri, &maps, &kept.envmap, &[])?;
                    Some(
                        render_or_stop(ctx, &s, &kept.render_options(), &|d, t| {
                            progress(d, t, 1, 2)
                        })?
                        .image,
                    )
                }
                _ => None,
            };
            (with, without, w_scene)
        } else {
            let (plain, env) = plain.ok_or_else(|| err("no scene"))?;
            // Seeded without the objects: the render behind them is the
            // same wherever they stand (and shares the objects' render's
            // sample streams), so moving one re-renders only the scene
            // with it.
            let mut without_objects = p.clone();
            without_objects
                .0
                .insert("objects".into(), matflow_engine::Value::Null);
            let seed = matflow_engine::key::node_seed(self, &without_objects);
            let opts = Self::options(p, seed)?;
            // The plain scene's hierarchy with the objects added: a move
            // rebuilds only the objects'.
            let w_scene = RenderScene::with_objects_over(
                &plain,
                &maps,
                matflow_render::EnvMap::new(&env).map_err(err)?,
                &objs,
            )
            .map_err(crate::failed)?;
            let with =
                render_or_stop(ctx, &w_scene, &opts, &|d, t| progress(d, t, 0, parts))?.image;
            let without = if differential {
                let what = format!("{opts:?}");
                let b = crate::memo::render(
                    &[
                        ctx.input("mesh")?,
                        ctx.input("materials")?,
                        ctx.input("envmap")?,
                        what.as_bytes(),
                    ],
                    || {
                        Ok(
                            render_or_stop(ctx, &plain, &opts, &|d, t| progress(d, t, 1, parts))?
                                .image,
                        )
                    },
                )?;
                Some((*b).clone())
            } else {
                None
            };
            (with, without, w_scene)
        };
        let alpha = kept_coverage.unwrap_or_else(|| w_scene.object_coverage(COVERAGE_GRID));
        let image = match (differential, without) {
            (true, Some(without)) => {
                let photo = photo_from(ctx.input("photo")?)?;
                if (photo.width, photo.height) != (with.width, with.height) {
                    return Err(err(format!(
                        "the photo is {}x{} but the render is {}x{}",
                        photo.width, photo.height, with.width, with.height
                    )));
                }
                composite_differential(&photo, &with, &without, &alpha)
            }
            _ => with.clone(),
        };
        Ok([
            ("image".to_string(), encode_image("image", "image", &image)),
            ("render".to_string(), encode_image("image", "image", &with)),
            (
                "coverage".to_string(),
                encode_image(
                    "image",
                    "image",
                    &coverage_image(&alpha, cam.width, cam.height),
                ),
            ),
        ]
        .into())
    }
    fn materialize(
        &self,
        params: &Params,
        outputs: &BTreeMap<String, Bytes>,
    ) -> Result<Vec<PathBuf>, NodeError> {
        crate::kinds::render::write_output_image(params, outputs)
    }
}
