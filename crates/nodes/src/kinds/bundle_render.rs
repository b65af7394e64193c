//! `bundle_render`: `matflow render` as a stage: a bundle folder's scene
//! (its depth meshed and completed past the frame, its maps, its envmap or
//! a new one, its maps' lamps) path-traced, optionally with objects
//! inserted and composited into its photo.

use std::collections::BTreeMap;
use std::path::PathBuf;

use matflow_engine::node::{Bytes, Params};
use matflow_engine::{Node, NodeError, NodeInfo, OutputSpec, ParamSpec, ParamType, RunContext};
use matflow_geom::{MeshParams, Silhouettes};
use matflow_render::{PixelFilter, RenderOptions, RenderOutput, RenderScene};
use matflow_scene::metrics::psnr_gamma;
use matflow_scene::{Bundle, MaterialSource, RgbImage};

use crate::bundle_scene::{load_scene, photo_psnr_lines, LoadedScene};
use crate::completion::{
    from_invert, render_completion, render_filter, CompleteArg, CompletionDecision, EvidenceRender,
};
use crate::data::encode_image;
use crate::kinds::bundle_mesh::{complete_arg, on_off, BUNDLE};
use crate::kinds::render::{pair, write_output_image, DEPTH, FILTER, SPP};
use crate::{err, Context};

pub struct BundleRenderNode;

const INFO: NodeInfo = NodeInfo {
    kind: "bundle_render",
    version: 2,
    doc: "`matflow render` as a stage: a bundle folder's scene path-traced (its depth meshed \
          and completed past the frame, its maps, its envmap or a new one, its maps' lamps), \
          optionally with objects inserted; writes an EXR (linear), a PNG (γ 2.2) and a JSON \
          report (the completion and the photo's evidence, how well the render explains the \
          photo) beside it. Settings left unset follow what `matflow invert` recovered the \
          maps with (its summary.json), else the bundle's own geometry.json.",
    params: &[
        BUNDLE,
        ParamSpec {
            name: "materials",
            ty: ParamType::Choice(&["best_results", "pred", "ground_truth"]),
            default: Some("best_results"),
            unit: "",
            doc: "material maps: best_results, pred or ground_truth",
        },
        ParamSpec {
            name: "envmap",
            ty: ParamType::InPath,
            default: Some("~"),
            unit: "",
            doc: "environment map (.hdr or .exr); default: the bundle's best_results/envmap.hdr \
                  (or ground_truth/envmap.hdr)",
        },
        SPP,
        DEPTH,
        crate::kinds::bundle_mesh::SEED,
        ParamSpec {
            default: Some("~"),
            doc: "pixel filter: gaussian (Mitsuba's default) or box. Default: for best_results \
                  written by `matflow invert`, the filter it fitted with (its summary.json says \
                  which: box); otherwise gaussian",
            ..FILTER
        },
        ParamSpec {
            name: "mesh_angle",
            ..crate::kinds::mesh::ANGLE
        },
        ParamSpec {
            default: Some("~"),
            doc: "the near side of a depth discontinuity: kept (an object's edge keeps its \
                  depth and reaches the pixel border; a solid's unseen back is its front \
                  mirrored about its silhouettes) or reference (every boundary pixel takes the \
                  background's depth, as the reference implementation). Default: for \
                  best_results written by `matflow invert`, the one it recovered them with; \
                  else reference with reference_compat; otherwise kept",
            ..crate::kinds::mesh::SILHOUETTES
        },
        ParamSpec {
            name: "complete",
            ty: ParamType::Choice(&CompleteArg::NAMES),
            default: Some("~"),
            unit: "",
            doc: "geometry past the frame, so that unseen parts of the scene block and reflect \
                  light: room extends the view's floor, walls and ceiling and closes the room \
                  with assumed ones where the view shows a room; closed the same without \
                  windows; planes only extends the planes seen; none renders the depth mesh \
                  alone; auto renders each of them cheaply under the light the photo was taken \
                  in (the bundle's own envmap, else `envmap`) and takes the least assuming whose \
                  render agrees with the bundle's photo within 0.5 dB of the best's (none \
                  without a photo). Default: for best_results written by `matflow invert`, the \
                  completion it recovered them with (its summary.json's `options.complete`); \
                  else none with reference_compat; else the one the bundle declares for its own \
                  geometry (geometry.json, which `matflow synth` writes: none); otherwise auto",
        },
        ParamSpec {
            name: "reference_compat",
            ty: ParamType::Bool,
            default: Some("false"),
            unit: "",
            doc: "reproduce the reference renderer's sampling-frame defect and its \
                  optimisation-time envmap layout (for comparing with its stored renders; \
                  physically incorrect)",
        },
        ParamSpec {
            name: "denoise",
            ty: ParamType::Bool,
            default: Some("false"),
            unit: "",
            doc: "denoise the render (as `invert` does its re-render): two halves of the \
                  samples, divided by the pixels' albedo, edge-aware à-trous filtered, \
                  multiplied back. Needs spp 2 or more; not with objects",
        },
        ParamSpec {
            name: "objects",
            ty: crate::objects::OBJECTS,
            default: Some("~"),
            unit: "",
            doc: "objects to insert (as `insert` takes them; `matflow render --insert FILE` \
                  reads them from a YAML file, mesh paths relative to it)",
        },
        ParamSpec {
            name: "composite",
            ty: ParamType::Choice(&["differential", "full"]),
            default: Some("differential"),
            unit: "",
            doc: "with objects: differential (the bundle's input image plus the change the \
                  objects make) or full (the render with the objects)",
        },
        crate::kinds::insert::GLASS_DEPTH,
        on_off(
            "light_guide",
            "on",
            "guide light samples by what each region of the scene sees of the sky (on), \
                  or sample the envmap by radiance alone (off). Either converges to the same \
                  image; on is less noisy where walls block most of the sky",
        ),
        on_off(
            "portals",
            "on",
            "aim light samples at the windows of a closed room's assumed walls too \
                  (portals; on), or follow the envmap's density alone (off). Either converges \
                  to the same image; on is less noisy in a closed room",
        ),
        on_off(
            "lamps",
            "on",
            "light the scene with the lamps of the maps: those `matflow invert` fitted \
                  (best_results/lamps.json) or the true ones (ground_truth/lamps.json): on, or \
                  off (e.g. to relight a room by a new envmap alone). A sun among them lights \
                  the scene only under the envmap it came with: `envmap` is a new sky",
        ),
        ParamSpec {
            name: "output",
            ty: ParamType::OutPath,
            default: None,
            unit: "",
            doc: "output EXR (linear); a γ-encoded PNG and the JSON report (same name, .png \
                  and .json) are written beside it",
        },
    ],
    outputs: &[
        OutputSpec {
            name: "image",
            ty: "image",
            doc: "the render (with objects: composited into the photo, or the full render)",
        },
        OutputSpec {
            name: "report",
            ty: "report",
            doc: "the completion, why, the photo's evidence, and how well the render explains \
                  the photo",
        },
        OutputSpec {
            name: "note",
            ty: "note",
            doc: "what was rendered and how (the run's report has its seconds)",
        },
    ],
};

impl Node for BundleRenderNode {
    fn info(&self) -> &'static NodeInfo {
        &INFO
    }

    fn check(&self, p: &Params) -> Result<(), String> {
        crate::kinds::render::check_exr_output(p)?;
        if p.bool("denoise") && (p.is_set("objects") || p.i64("spp") < 2) {
            return Err(
                "`denoise` needs spp 2 or more (two halves of the samples) and a plain \
                        render (no objects)"
                    .into(),
            );
        }
        Ok(())
    }

    fn preflight(&self, p: &Params) -> Result<(), String> {
        crate::kinds::bundle_mesh::bundle_preflight(p)
    }

    fn film_size(&self, p: &Params) -> Option<(usize, usize)> {
        crate::kinds::bundle_mesh::bundle_film_size(p)
    }

    fn estimate_seconds(&self, p: &Params, film: Option<(usize, usize)>) -> f64 {
        let renders = if p.is_set("objects") && p.str("composite") == "differential" {
            2.0
        } else {
            1.0
        };
        renders * crate::data::render_seconds(film, p.i64("spp"), p.i64("depth"))
    }

    fn output_files(&self, p: &Params) -> Vec<PathBuf> {
        match p.path("output") {
            Some(out) => {
                let json = out.with_extension("json");
                pair(&out).into_iter().chain([json]).collect()
            }
            None => vec![],
        }
    }

    fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
        let a = Asked::of(ctx.params)?;
        let (filter, why) = render_filter(&a.bundle, a.materials, a.filter)?;
        let mesh = render_mesh(&a)?;
        let decision = render_completion(
            &a.bundle,
            a.materials,
            a.complete,
            a.reference_compat,
            a.envmap.as_deref(),
            EvidenceRender {
                mesh,
                filter,
                max_depth: a.opts.max_depth,
            },
        )?;
        let mut lines = decision.lines();
        let mut loaded = load_scene(
            &a.bundle,
            a.materials,
            a.envmap.as_deref(),
            mesh,
            a.reference_compat,
            decision.params(),
            ctx.params.str("lamps") == "on",
        )?;
        if ctx.params.str("light_guide") != "on" {
            loaded.scene.set_light_guide(None);
        }
        if ctx.params.str("portals") != "on" {
            loaded.scene.portals = Default::default();
        }
        let opts = RenderOptions { filter, ..a.opts };
        let progress = |done: usize, total: usize| (ctx.progress)(done as u64, total as u64);
        let (image, photo_psnr) = if ctx.params.is_set("objects") {
            let image = render_inserted(&a, ctx, loaded, &opts, &mut lines, &progress)?;
            (image, None)
        } else {
            let out = if a.denoise {
                render_denoised(&loaded.scene, &opts, &progress)?
            } else {
                matflow_render::render(&loaded.scene, &opts, &|d, t| progress(d, t))
            };
            lines.push(rendered_line(
                &a,
                &loaded.scene,
                &out,
                filter,
                why,
                &decision,
            ));
            if out.stats.discarded_samples > 0 {
                lines.push(format!(
                    "warning: {} sample(s) with NaN/Inf radiance were dropped",
                    out.stats.discarded_samples
                ));
            }
            let psnr = explains_photo(&a, &out.image);
            if let Some(p) = psnr {
                lines.extend(photo_psnr_lines("the render", p));
            }
            (out.image, psnr)
        };
        let report = serde_json::json!({
            "completion": decision.to_json(),
            "photo_psnr": photo_psnr,
        });
        Ok([
            ("image".to_string(), encode_image("image", "image", &image)),
            (
                "report".to_string(),
                serde_json::to_vec_pretty(&report).node_err()?,
            ),
            ("note".to_string(), lines.join("\n").into_bytes()),
        ]
        .into())
    }

    fn materialize(
        &self,
        params: &Params,
        outputs: &BTreeMap<String, Bytes>,
    ) -> Result<Vec<PathBuf>, NodeError> {
        let mut written = write_output_image(params, outputs)?;
        if let Some(out) = params.path("output") {
            let json = out.with_extension("json");
            crate::files::write_file(&json, outputs.get("report"))?;
            written.push(json);
        }
        Ok(written)
    }
}

/// What the stage was asked, in the render's terms.
struct Asked {
    bundle: PathBuf,
    materials: MaterialSource,
    envmap: Option<PathBuf>,
    filter: Option<PixelFilter>,
    silhouettes: Option<Silhouettes>,
    mesh_angle: f64,
    complete: Option<CompleteArg>,
    reference_compat: bool,
    denoise: bool,
    /// Everything but the filter, which may come from the bundle.
    opts: RenderOptions,
}

impl Asked {
    fn of(p: &Params) -> Result<Asked, NodeError> {
        let reference_compat = p.bool("reference_compat");
        Ok(Asked {
            bundle: p.path("bundle").unwrap_or_default(),
            materials: p.parse("materials")?,
            envmap: p.path("envmap"),
            filter: match p.is_set("filter") {
                true => Some(p.parse("filter")?),
                false => None,
            },
            silhouettes: match p.is_set("silhouettes") {
                true => Some(crate::kinds::bundle_mesh::silhouettes(p)?),
                false => None,
            },
            mesh_angle: p.f64("mesh_angle"),
            complete: complete_arg(p)?,
            reference_compat,
            denoise: p.bool("denoise"),
            opts: RenderOptions {
                spp: p.i64("spp") as u32,
                max_depth: p.i64("depth") as u32,
                glass_depth: p.i64("glass_depth") as u32,
                seed: p.i64("seed") as u64,
                reference_compat,
                ..Default::default()
            },
        })
    }
}

/// The mesh the render builds: its angle, and the silhouettes asked for,
/// else those `matflow invert` recovered the maps with, else the
/// reference's with reference_compat, else kept.
fn render_mesh(a: &Asked) -> Result<MeshParams, NodeError> {
    let (recovered, _) = from_invert(
        &a.bundle,
        a.materials,
        a.silhouettes.map(Some),
        "silhouettes",
        "the one matflow invert recovered these maps with",
        |name| name.parse::<Silhouettes>().map(Some),
    )?;
    let silhouettes = recovered.unwrap_or(if a.reference_compat {
        Silhouettes::Reference
    } else {
        Silhouettes::Kept
    });
    Ok(MeshParams {
        min_angle_deg: a.mesh_angle,
        silhouettes,
    })
}

/// The render in two halves, denoised.
fn render_denoised(
    scene: &RenderScene,
    opts: &RenderOptions,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<RenderOutput, NodeError> {
    let guide = matflow_render::denoise::Guide::build(scene);
    let d = matflow_render::denoise::render_denoised(
        scene,
        &guide,
        opts,
        matflow_render::denoise::RENDER_PASSES,
        progress,
    )
    .ok_or_else(|| err("denoising needs at least 2 samples per pixel"))?;
    Ok(RenderOutput {
        image: d.image,
        stats: d.stats,
    })
}

/// What a render says of itself (no timings: the note is an output,
/// which must not depend on the clock; the run's report has the stage's
/// seconds).
fn rendered_line(
    a: &Asked,
    scene: &RenderScene,
    out: &RenderOutput,
    filter: PixelFilter,
    why: &str,
    decision: &CompletionDecision,
) -> String {
    format!(
        "rendered {}x{} at {} spp{}, depth {}, {} filter ({why}), completion {}, {} lamp(s), {} sun(s), {} portal(s), {}: {:.1} M rays",
        scene.camera.width,
        scene.camera.height,
        a.opts.spp,
        if a.denoise { " (denoised)" } else { "" },
        a.opts.max_depth,
        filter.name(),
        decision.mode.name(),
        scene.lamps.iter().filter(|l| !l.is_distant()).count(),
        scene.lamps.iter().filter(|l| l.is_distant()).count(),
        scene.portals.len(),
        crate::bundle_scene::light_guide_note(scene),
        out.stats.total_rays() as f64 / 1e6,
    )
}

/// A plain render in the light of the bundle's photo (no `envmap`, or
/// none of the bundle's own to tell it from) against that photo: the
/// PSNR; `None` when the render is a relighting or the bundle has no
/// photo.
fn explains_photo(a: &Asked, image: &RgbImage) -> Option<f64> {
    let bundle = Bundle::open(&a.bundle).ok()?;
    if a.envmap.is_some() && bundle.envmap_path().is_some() {
        return None;
    }
    let photo = bundle.load_gt_image().ok()?;
    if !photo.same_size(image) {
        return None;
    }
    Some(psnr_gamma(image, &photo))
}

/// The bundle with the objects, composited into its input image (or the
/// full render).
fn render_inserted(
    a: &Asked,
    ctx: &RunContext,
    loaded: LoadedScene,
    opts: &RenderOptions,
    lines: &mut Vec<String>,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<RgbImage, NodeError> {
    let specs = crate::objects::specs(ctx.params.get("objects"))?;
    crate::objects::check_specs(&specs).map_err(err)?;
    let cam = loaded.scene.camera;
    let objs = crate::objects::place(&specs, &cam, &loaded.scene.mesh)?;
    let differential = ctx.params.str("composite") == "differential";
    let photo = if differential {
        let b = Bundle::open(&a.bundle).node_err()?;
        let img = b.load_gt_image().context(|| {
            "differential compositing adds the objects to the bundle's input image; use \
             composite full for the plain render"
                .to_string()
        })?;
        if (img.width, img.height) != (cam.width, cam.height) {
            return Err(err(format!(
                "{}: the input image is {}x{} but the scene is {}x{}",
                a.bundle.display(),
                img.width,
                img.height,
                cam.width,
                cam.height
            )));
        }
        Some(img)
    } else {
        None
    };
    let with_scene = RenderScene::with_objects(
        cam,
        loaded.scene.mesh.clone(),
        &loaded.maps,
        loaded.env.clone(),
        &objs,
    )
    .node_err()?;
    let with = matflow_render::render(&with_scene, opts, &|d, t| progress(d, t));
    let image = match &photo {
        Some(photo) => {
            let without = matflow_render::render(&loaded.scene, opts, &|d, t| progress(d, t));
            let alpha = with_scene.object_coverage(4);
            crate::composite_differential(photo, &with.image, &without.image, &alpha)
        }
        None => with.image.clone(),
    };
    lines.push(format!(
        "inserted {} object(s) ({} triangles) into {}x{} at {} spp: {}",
        specs.len(),
        objs.iter().map(|o| o.mesh.triangle_count()).sum::<usize>(),
        cam.width,
        cam.height,
        opts.spp,
        if photo.is_some() {
            "rendered with and without them, composited differentially"
        } else {
            "the full render with them"
        },
    ));
    Ok(image)
}
