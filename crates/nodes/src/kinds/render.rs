//! `render`: a path-traced render of a scene's mesh with given materials
//! and lighting, or an edit's render from a `trace` stage's kept paths.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use matflow_engine::node::{Bytes, Params};
use matflow_engine::{Node, NodeError, NodeInfo, OutputSpec, ParamSpec, ParamType, RunContext};
use matflow_render::RenderOptions;
use matflow_scene::{io, MaterialMaps, RgbImage};

use crate::artifact::Artifact;
use crate::data::{encode_image, envmap_from, materials_from, Kept, MESH};
use crate::err;

pub struct RenderNode;

/// The files a render with `output` = `path` writes: the EXR and the PNG
/// beside it.
pub(crate) fn pair(path: &Path) -> [PathBuf; 2] {
    [path.to_path_buf(), path.with_extension("png")]
}

/// Writes `img` to `path` (EXR, linear) and a γ-encoded PNG beside it,
/// each through a temporary file renamed into place; a file that already
/// holds the same bytes is not rewritten (a cached run changes nothing on
/// disk).
pub(crate) fn write_pair(
    path: &Path,
    img: &matflow_scene::RgbImage,
) -> Result<Vec<PathBuf>, NodeError> {
    let [exr, png] = pair(path);
    io::write_if_changed(&exr, &io::encode_exr_rgb(&exr, img).map_err(err)?).map_err(err)?;
    io::write_if_changed(&png, &io::encode_png_gamma(&png, img).map_err(err)?).map_err(err)?;
    Ok(vec![exr, png])
}

/// Samples per pixel, as the renders take them.
pub(crate) const SPP: ParamSpec = ParamSpec {
    name: "spp",
    ty: ParamType::Int { min: 1, max: 65536 },
    default: Some("64"),
    unit: "samples/px",
    doc: "samples per pixel",
};

/// The longest path, as the renders take it.
pub(crate) const DEPTH: ParamSpec = ParamSpec {
    name: "depth",
    ty: ParamType::Int { min: 1, max: 64 },
    default: Some("4"),
    unit: "segments",
    doc: "maximum path length (Mitsuba's max_depth)",
};

/// The pixel filter, as the renders take it.
pub(crate) const FILTER: ParamSpec = ParamSpec {
    name: "filter",
    ty: ParamType::Choice(&["gaussian", "box"]),
    default: Some("gaussian"),
    unit: "",
    doc: "pixel filter: Mitsuba's Gaussian (σ 0.5 px, radius 2) or box",
};

const RENDER_INFO: NodeInfo = NodeInfo {
    kind: "render",
    version: 4,
    doc: "Path-traces the mesh with the given materials under the given envmap (unidirectional, \
         next-event estimation with MIS, GGX + Lambert as the reference). Writes an EXR \
         (linear) and a PNG (γ 2.2) when `output` is set. With `paths` and `photo`, an edit \
         keeps the photo: only the change the edit makes to the render enters it, and pixels \
         the edit does not reach are the photo's exactly.",
    params: &[
        MESH,
        ParamSpec {
            name: "paths",
            ty: ParamType::Ref(&["paths"]),
            default: Some("~"),
            unit: "",
            doc: "a `trace` stage of the same mesh: re-trace only what the materials' \
                      changes reach (its envmap, spp and seed; box filter)",
        },
        ParamSpec {
            name: "materials",
            ty: ParamType::Ref(&["materials", "scene"]),
            default: None,
            unit: "",
            doc: "materials (a scene gives its predictions)",
        },
        ParamSpec {
            name: "envmap",
            ty: ParamType::Ref(&["envmap"]),
            default: Some("~"),
            unit: "",
            doc: "lighting (with `mesh`)",
        },
        SPP,
        DEPTH,
        FILTER,
        ParamSpec {
            name: "seed",
            ty: ParamType::Int {
                min: 0,
                max: i64::MAX,
            },
            default: Some("0"),
            unit: "",
            doc: "extra seed (the stage's parameters seed it already)",
        },
        ParamSpec {
            name: "output",
            ty: ParamType::OutPath,
            default: Some("~"),
            unit: "",
            doc: "EXR path to write (a PNG is written beside it)",
        },
        ParamSpec {
            name: "denoise",
            ty: ParamType::Bool,
            default: Some("false"),
            unit: "",
            doc: "denoise the render for viewing (as `invert` does its re-render): two halves of \
                  the samples, divided by the pixels' albedo, edge-aware à-trous filtered, \
                  multiplied back; `output` and its PNG are the denoised image, and the same \
                  samples unfiltered are written beside them (X_raw.exr) and output as `raw`. \
                  Needs spp 2 or more; not with `paths`",
        },
        ParamSpec {
            name: "photo",
            ty: ParamType::Ref(&["image", "scene"]),
            default: Some("~"),
            unit: "",
            doc: "with `paths`: the photo the edit's change is composited into (a scene gives its \
                  input image), instead of the plain render",
        },
        ParamSpec {
            name: "composite",
            ty: ParamType::Choice(&COMPOSITES),
            default: Some("auto"),
            unit: "",
            doc: "with `photo`: ratio (photo × edited / unedited render: a change of reflectance \
                  scales the photo's own shading), differential (photo + edited − unedited \
                  render), or auto (ratio where the edit changed the albedo alone, else \
                  differential)",
        },
    ],
    outputs: &[
        OutputSpec {
            name: "image",
            ty: "image",
            doc: "the render (or, with `photo`, the photo with the edit), linear RGB; \
                  denoised with `denoise`",
        },
        OutputSpec {
            name: "raw",
            ty: "image",
            doc: "with `denoise`: the same samples unfiltered (otherwise the image again)",
        },
    ],
};

/// The raw render's file beside `output` (`X.exr` → `X_raw.exr`).
fn raw_path(path: &Path) -> PathBuf {
    let stem = path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    path.with_file_name(format!("{stem}_raw.exr"))
}

/// `composite`'s values.
const COMPOSITES: [&str; 3] = ["auto", "ratio", "differential"];

/// How an edit's change enters the photo ([`composite_edit`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Composite {
    /// photo × edited / unedited.
    Ratio,
    /// photo + edited − unedited.
    Differential,
}

/// Below this (linear, per channel) an unedited render gives the ratio
/// no footing: the pixel takes the difference instead.
const RATIO_FLOOR: f32 = 1e-4;

/// The photo with an edit's change: where `edited` equals `unedited` (the
/// same sample streams, pixels the edit does not reach) the photo exactly;
/// elsewhere the change as a ratio or a difference, clamped at 0, never
/// NaN or Inf.
pub fn composite_edit(
    photo: &RgbImage,
    edited: &RgbImage,
    unedited: &RgbImage,
    how: Composite,
) -> RgbImage {
    let data = (0..photo.data.len())
        .map(|k| {
            let (p, e, u) = (photo.data[k], edited.data[k], unedited.data[k]);
            if e == u {
                return p;
            }
            let v = glam::Vec3::from_array(std::array::from_fn(|c| {
                let diff = p[c] + (e[c] - u[c]);
                match how {
                    Composite::Ratio if u[c] > RATIO_FLOOR => p[c] * (e[c] / u[c]),
                    _ => diff,
                }
            }));
            // A non-finite render is no change to add (f32::max would
            // turn a NaN into 0).
            if v.is_finite() {
                v.max(glam::Vec3::ZERO)
            } else {
                p
            }
        })
        .collect();
    RgbImage::from_vec(photo.width, photo.height, data)
}

/// The composite `auto` takes: ratio when the edit changed albedo alone
/// (a change of reflectance, which scales the light a surface returns),
/// else differential.
fn composite_for(asked: &str, before: &MaterialMaps, after: &MaterialMaps) -> Composite {
    match asked {
        "ratio" => Composite::Ratio,
        "differential" => Composite::Differential,
        _ => {
            let same_brdf = before.roughness == after.roughness
                && before.metallic == after.metallic
                && before.transparency == after.transparency;
            if same_brdf {
                Composite::Ratio
            } else {
                Composite::Differential
            }
        }
    }
}

/// The render of `scene`, stopped between tiles when the stage's run no
/// longer wants it ([`RunContext::cancelled`]).
pub(crate) fn render_or_stop(
    ctx: &RunContext,
    scene: &matflow_render::RenderScene,
    opts: &RenderOptions,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<matflow_render::RenderOutput, NodeError> {
    matflow_render::render_until(scene, opts, progress, ctx.cancelled)
        .ok_or_else(NodeError::cancelled)
}

/// An `output` parameter must name an EXR (a PNG is written beside it).
pub(crate) fn check_exr_output(p: &Params) -> Result<(), String> {
    if let Some(out) = p.path("output") {
        let ext = out.extension().map(|e| e.to_string_lossy().to_lowercase());
        if ext.as_deref() != Some("exr") {
            return Err(format!(
                "`output` {} must end in .exr: the stage writes linear EXR there and a \
                 γ-encoded PNG beside it (same name, .png)",
                out.display()
            ));
        }
    }
    Ok(())
}

/// The image of a `trace` stage's scene with its materials edited to
/// `edited`: the base render, re-traced where the kept paths say the edit
/// reaches ([`matflow_inverse::paths::Reach::rerender_changed`]). The
/// trace's objects stay in the scene as they were.
pub(crate) fn edited_image(
    k: &Kept,
    mesh: &[u8],
    edited: &MaterialMaps,
) -> Result<RgbImage, NodeError> {
    let scene = if k.objects.is_empty() {
        crate::memo::scene(mesh, edited, &k.envmap)?
    } else {
        let (cam, tri) = crate::data::decode_mesh(mesh)?;
        crate::data::scene_of(cam, tri, edited, &k.envmap, &k.objects)?
    };
    rerender_kept(k, &scene, edited, &k.objects)
}

/// The base render of `k` re-traced in `scene` (the trace's geometry with
/// materials `edited` and objects `objs`, placed as the trace's) where the
/// kept paths meet a changed pixel material or object surface.
pub(crate) fn rerender_kept(
    k: &Kept,
    scene: &matflow_render::RenderScene,
    edited: &MaterialMaps,
    objs: &[matflow_render::SceneObject],
) -> Result<RgbImage, NodeError> {
    if edited.width() != k.reach.width || edited.height() != k.reach.height {
        return Err(err(format!(
            "the materials are {}x{} but the kept paths are {}x{}",
            edited.width(),
            edited.height(),
            k.reach.width,
            k.reach.height
        )));
    }
    let mut changed = k.materials.changed_texels(edited);
    changed.extend(
        k.objects
            .iter()
            .zip(objs)
            .map(|(a, b)| a.surface != b.surface || a.uvs != b.uvs || a.texture != b.texture),
    );
    // Background vertices (seen through transparent regions) come last.
    changed.extend(k.materials.changed_background(edited));
    Ok(k.reach
        .rerender_changed(&k.image, scene, &k.render_options(), &changed))
}

impl Node for RenderNode {
    fn info(&self) -> &'static NodeInfo {
        &RENDER_INFO
    }
    fn estimate_seconds(&self, p: &Params, film: Option<(usize, usize)>) -> f64 {
        crate::data::render_seconds(film, p.i64("spp"), p.i64("depth"))
    }
    fn check(&self, p: &Params) -> Result<(), String> {
        check_exr_output(p)?;
        if p.bool("denoise") && (p.is_set("paths") || p.i64("spp") < 2) {
            return Err(
                "`denoise` needs a plain render (not `paths`: an edit's re-trace keeps the \
                 trace's samples) with spp 2 or more (two halves of the samples)"
                    .into(),
            );
        }
        if p.is_set("photo") && !p.is_set("paths") {
            return Err(
                "`photo` keeps the photo and adds the edit's change to it, which needs \
                        the unedited render on the same paths: give `paths` (a `trace` stage of \
                        the unedited materials)"
                    .into(),
            );
        }
        match (p.is_set("paths"), p.is_set("mesh"), p.is_set("envmap")) {
            (_, false, _) => Err("give `mesh`".into()),
            (true, true, false) | (false, true, true) => Ok(()),
            (true, true, true) => {
                Err("`paths` brings its envmap (the one it was traced under): drop `envmap`".into())
            }
            (false, true, false) => Err("give `envmap` (or `paths`, a `trace` stage)".into()),
        }
    }
    fn output_files(&self, p: &Params) -> Vec<PathBuf> {
        let Some(o) = p.path("output") else {
            return vec![];
        };
        let mut files = pair(&o).to_vec();
        if p.bool("denoise") {
            files.push(raw_path(&o));
        }
        files
    }
    fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
        let p = ctx.params;
        let maps = materials_from(ctx.input("materials")?)?;
        if let Some(b) = ctx.opt_input("paths") {
            let kept = crate::memo::kept(b)?;
            let mut img = edited_image(&kept, ctx.input("mesh")?, &maps)?;
            if let Some(photo) = ctx.opt_input("photo") {
                let photo = crate::kinds::insert::photo_from(photo)?;
                if !photo.same_size(&img) {
                    return Err(err(format!(
                        "the photo is {}x{} but the render is {}x{}",
                        photo.width, photo.height, img.width, img.height
                    )));
                }
                let how = composite_for(p.str("composite"), &kept.materials, &maps);
                img = composite_edit(&photo, &img, &kept.image, how);
            }
            let image = encode_image("image", "image", &img);
            return Ok([
                ("raw".to_string(), image.clone()),
                ("image".to_string(), image),
            ]
            .into());
        }
        let env = envmap_from(ctx.input("envmap")?)?;
        let scene = crate::memo::scene(ctx.input("mesh")?, &maps, &env)?;
        // Seeded from the stage's parameters, not its inputs: an edit
        // upstream keeps the noise pattern, so before/after differ only
        // where the edit acts.
        let opts = RenderOptions {
            spp: p.i64("spp") as u32,
            max_depth: p.i64("depth") as u32,
            seed: ctx.seed ^ p.i64("seed") as u64,
            filter: p.parse("filter").map_err(err)?,
            ..Default::default()
        };
        let progress = |d: usize, t: usize| (ctx.progress)(d as u64, t as u64);
        let (image, raw) = if p.bool("denoise") {
            let guide = matflow_render::denoise::Guide::build(&scene);
            let passes = matflow_render::denoise::RENDER_PASSES;
            let d =
                matflow_render::denoise::render_denoised(&scene, &guide, &opts, passes, &progress)
                    .ok_or_else(|| err("denoising needs at least 2 samples per pixel"))?;
            let raw = encode_image("image", "image", &d.raw);
            (encode_image("image", "image", &d.image), raw)
        } else {
            let out = render_or_stop(ctx, &scene, &opts, &progress)?;
            let image = encode_image("image", "image", &out.image);
            (image.clone(), image)
        };
        Ok([("image".to_string(), image), ("raw".to_string(), raw)].into())
    }
    fn materialize(
        &self,
        params: &Params,
        outputs: &BTreeMap<String, Bytes>,
    ) -> Result<Vec<PathBuf>, NodeError> {
        let mut written = write_output_image(params, outputs)?;
        if let (Some(path), true) = (params.path("output"), params.bool("denoise")) {
            let b = outputs
                .get("raw")
                .ok_or_else(|| err("the stage made no raw image"))?;
            let img = Artifact::decode(&b[..], "image")?.rgb("image")?;
            let raw = raw_path(&path);
            io::write_if_changed(&raw, &io::encode_exr_rgb(&raw, &img).map_err(err)?)
                .map_err(err)?;
            written.push(raw);
        }
        Ok(written)
    }
}

/// Writes the `image` output to the `output` path (EXR and PNG), when
/// one is given: what the image-producing kinds materialise.
pub(crate) fn write_output_image(
    params: &Params,
    outputs: &BTreeMap<String, Bytes>,
) -> Result<Vec<PathBuf>, NodeError> {
    let Some(path) = params.path("output") else {
        return Ok(vec![]);
    };
    let b = outputs
        .get("image")
        .ok_or_else(|| err("the stage made no image"))?;
    let img = Artifact::decode(&b[..], "image")?.rgb("image")?;
    write_pair(&path, &img)
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    fn img(v: &[Vec3]) -> RgbImage {
        RgbImage::from_vec(v.len(), 1, v.to_vec())
    }

    #[test]
    fn an_edit_keeps_the_photo_where_it_does_not_reach_and_adds_its_change_elsewhere() {
        let photo = img(&[
            Vec3::new(0.3, 0.2, 0.1),
            Vec3::new(0.4, 0.4, 0.4),
            Vec3::splat(0.5),
        ]);
        // Pixel 0 untouched (the same samples), pixel 1 twice as bright,
        // pixel 2 darker than the unedited render by 0.2.
        let unedited = img(&[
            Vec3::new(0.25, 0.21, 0.12),
            Vec3::splat(0.3),
            Vec3::splat(0.6),
        ]);
        let edited = img(&[
            Vec3::new(0.25, 0.21, 0.12),
            Vec3::splat(0.6),
            Vec3::splat(0.4),
        ]);
        for how in [Composite::Ratio, Composite::Differential] {
            let out = composite_edit(&photo, &edited, &unedited, how);
            assert_eq!(out.data[0], photo.data[0], "{how:?}: bit for bit");
        }
        let r = composite_edit(&photo, &edited, &unedited, Composite::Ratio);
        assert!((r.data[1] - Vec3::splat(0.8)).abs().max_element() < 1e-6);
        assert!(
            (r.data[2] - Vec3::splat(0.5 * 0.4 / 0.6))
                .abs()
                .max_element()
                < 1e-6
        );
        let d = composite_edit(&photo, &edited, &unedited, Composite::Differential);
        assert!((d.data[1] - Vec3::splat(0.7)).abs().max_element() < 1e-6);
        assert!((d.data[2] - Vec3::splat(0.3)).abs().max_element() < 1e-6);
    }

    #[test]
    fn a_ratio_without_footing_falls_back_to_the_difference_and_nothing_goes_negative() {
        let photo = img(&[Vec3::splat(0.2), Vec3::splat(0.05), Vec3::splat(0.5)]);
        // An unedited render of zero (no ratio), a change darker than the
        // photo (clamped at 0), and a non-finite render (the photo kept).
        let unedited = img(&[Vec3::ZERO, Vec3::splat(0.5), Vec3::splat(0.5)]);
        let edited = img(&[Vec3::splat(0.1), Vec3::ZERO, Vec3::splat(f32::NAN)]);
        let out = composite_edit(&photo, &edited, &unedited, Composite::Ratio);
        assert!((out.data[0] - Vec3::splat(0.3)).abs().max_element() < 1e-6);
        assert_eq!(out.data[1], Vec3::ZERO);
        let d = composite_edit(&photo, &edited, &unedited, Composite::Differential);
        assert_eq!(d.data[1], Vec3::ZERO);
        assert_eq!(d.data[2], photo.data[2]);
        assert!(out.data.iter().chain(&d.data).all(|v| v.is_finite()));
    }

    #[test]
    fn auto_takes_the_ratio_for_a_change_of_albedo_alone() {
        let before = MaterialMaps::uniform(2, 2, Vec3::splat(0.5), 0.5, 0.0);
        let mut albedo = before.clone();
        albedo.albedo.data[0] = Vec3::new(0.9, 0.1, 0.1);
        assert_eq!(composite_for("auto", &before, &albedo), Composite::Ratio);
        let mut metal = albedo.clone();
        metal.metallic.data[0] = 1.0;
        assert_eq!(
            composite_for("auto", &before, &metal),
            Composite::Differential
        );
        assert_eq!(composite_for("ratio", &before, &metal), Composite::Ratio);
        assert_eq!(
            composite_for("differential", &before, &albedo),
            Composite::Differential
        );
    }

    /// `denoise`: the image is the two halves' samples filtered, `raw` the
    /// same samples as they came; the filtered one is nearer a render of
    /// many samples, and the stage refuses what it cannot denoise.
    #[test]
    fn a_denoised_render_is_nearer_the_converged_one_and_keeps_its_raw_samples() {
        use crate::data::{encode_materials, encode_mesh};
        use crate::testutil::{params_of, small_room};
        use matflow_engine::Value;
        use std::sync::Arc;
        let n = 32;
        let (s, _, tri) = small_room(n);
        let inputs: BTreeMap<String, Arc<Vec<u8>>> = [
            ("mesh".to_string(), Arc::new(encode_mesh(n, n, &tri))),
            ("materials".to_string(), Arc::new(encode_materials(&s.maps))),
            (
                "envmap".to_string(),
                Arc::new(encode_image("envmap", "envmap", &s.envmap)),
            ),
        ]
        .into();
        let run = |extra: &[(&str, Value)]| {
            let mut given = vec![
                ("mesh", Value::Str("m".into())),
                ("materials", Value::Str("x".into())),
                ("envmap", Value::Str("e".into())),
            ];
            given.extend(extra.iter().cloned());
            let p = params_of(&RENDER_INFO, &given);
            let out = crate::testutil::run_node(&RenderNode, &p, inputs.clone(), 3).unwrap();
            let rgb = |k: &str| {
                Artifact::decode(&out[k], "image")
                    .unwrap()
                    .rgb("image")
                    .unwrap()
            };
            (rgb("image"), rgb("raw"))
        };
        let (truth, same) = run(&[("spp", Value::Int(512))]);
        assert_eq!(truth.data, same.data, "without denoise, raw is the image");
        let (image, raw) = run(&[("spp", Value::Int(8)), ("denoise", Value::Bool(true))]);
        let err = |a: &RgbImage| {
            a.data
                .iter()
                .zip(&truth.data)
                .map(|(x, y)| (*x - *y).length_squared() as f64)
                .sum::<f64>()
        };
        assert_ne!(image.data, raw.data);
        assert!(image.data.iter().all(|v| v.is_finite()));
        assert!(
            err(&image) < 0.5 * err(&raw),
            "{} vs {}",
            err(&image),
            err(&raw)
        );
        let check = |extra: &[(&str, Value)]| {
            let mut given = vec![
                ("mesh", Value::Str("m".into())),
                ("materials", Value::Str("x".into())),
                ("denoise", Value::Bool(true)),
            ];
            given.extend(extra.iter().cloned());
            RenderNode.check(&params_of(&RENDER_INFO, &given))
        };
        assert!(check(&[("envmap", Value::Str("e".into()))]).is_ok());
        let one = check(&[("envmap", Value::Str("e".into())), ("spp", Value::Int(1))]);
        assert!(one.unwrap_err().contains("spp 2 or more"));
        let kept = check(&[("paths", Value::Str("t".into()))]);
        assert!(kept.unwrap_err().contains("not `paths`"));
    }
}
