//! `render`: a path-traced render of a scene's mesh with given materials
//! and lighting, or an edit's render from a `trace` stage's kept paths.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use matflow_engine::node::{Bytes, Params};
use matflow_engine::{Node, NodeError, NodeInfo, OutputSpec, ParamSpec, ParamType, RunContext};
use matflow_render::{render, RenderOptions};
use matflow_scene::{io, MaterialMaps, RgbImage};

use crate::artifact::Artifact;
use crate::data::{encode_image, envmap_from, materials_from, render_scene, Kept, MESH};
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
fn write_pair(path: &Path, img: &matflow_scene::RgbImage) -> Result<Vec<PathBuf>, NodeError> {
    let [exr, png] = pair(path);
    io::write_if_changed(&exr, &io::encode_exr_rgb(&exr, img).map_err(err)?).map_err(err)?;
    io::write_if_changed(&png, &io::encode_png_gamma(&png, img).map_err(err)?).map_err(err)?;
    Ok(vec![exr, png])
}

const RENDER_INFO: NodeInfo = NodeInfo {
    kind: "render",
    version: 2,
    doc: "Path-traces the mesh with the given materials under the given envmap (unidirectional, \
         next-event estimation with MIS, GGX + Lambert as the reference). Writes an EXR \
         (linear) and a PNG (γ 2.2) when `output` is set.",
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
        ParamSpec {
            name: "spp",
            ty: ParamType::Int { min: 1, max: 65536 },
            default: Some("64"),
            unit: "samples/px",
            doc: "samples per pixel",
        },
        ParamSpec {
            name: "depth",
            ty: ParamType::Int { min: 1, max: 64 },
            default: Some("4"),
            unit: "segments",
            doc: "maximum path length (Mitsuba's max_depth)",
        },
        ParamSpec {
            name: "filter",
            ty: ParamType::Choice(&["gaussian", "box"]),
            default: Some("gaussian"),
            unit: "",
            doc: "pixel filter: Mitsuba's Gaussian (σ 0.5 px, radius 2) or box",
        },
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
    ],
    outputs: &[OutputSpec {
        name: "image",
        ty: "image",
        doc: "the render, linear RGB",
    }],
};

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
/// reaches ([`matflow_inverse::paths::PathCache::rerender_changed`]). The
/// trace's objects stay in the scene as they were.
pub(crate) fn edited_image(
    k: &Kept,
    mesh: &[u8],
    edited: &MaterialMaps,
) -> Result<RgbImage, NodeError> {
    let (cam, tri) = crate::data::decode_mesh(mesh)?;
    let scene = crate::data::scene_of(cam, tri, edited, &k.envmap, &k.objects)?;
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
    if edited.width() != k.cache.width || edited.height() != k.cache.height {
        return Err(err(format!(
            "the materials are {}x{} but the kept paths are {}x{}",
            edited.width(),
            edited.height(),
            k.cache.width,
            k.cache.height
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
    Ok(k.cache
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
        p.path("output")
            .map(|o| pair(&o).to_vec())
            .unwrap_or_default()
    }
    fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
        let p = ctx.params;
        let maps = materials_from(ctx.input("materials")?)?;
        if let Some(b) = ctx.opt_input("paths") {
            let kept = Kept::decode(b)?;
            let img = edited_image(&kept, ctx.input("mesh")?, &maps)?;
            return Ok([("image".to_string(), encode_image("image", "image", &img))].into());
        }
        let env = envmap_from(ctx.input("envmap")?)?;
        let scene = render_scene(ctx.input("mesh")?, &maps, &env)?;
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
        let out = render(&scene, &opts, &|d, t| (ctx.progress)(d as u64, t as u64));
        Ok([(
            "image".to_string(),
            encode_image("image", "image", &out.image),
        )]
        .into())
    }
    fn materialize(
        &self,
        params: &Params,
        outputs: &BTreeMap<String, Bytes>,
    ) -> Result<Vec<PathBuf>, NodeError> {
        write_output_image(params, outputs)
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
