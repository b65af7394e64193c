//! `trace`: a full render of the unedited scene that also keeps which
//! materials its light paths meet, so that a material edit re-traces only
//! the pixels it reaches.
//!
//! Geometry and lighting do not change under a material edit, and every
//! (pixel, sample) of the render has its own random stream, so a pixel's
//! value changes only if one of its paths meets a changed material. The
//! kept paths (`inverse::paths`, a separate set of `path_spp` paths per
//! pixel, of which only the texels each pixel's paths meet are stored)
//! show which pixels' light passes through which material texels:
//! an edit re-traces exactly the pixels that see a changed texel directly
//! or along a kept path, with the base render's own sample streams — so
//! those pixels are bit-identical to a full re-render — and keeps the base
//! value elsewhere. What this misses is light the kept paths never carried
//! from the edited region to a pixel (a rare indirect path); the benchmark
//! measures it against full renders.

use std::collections::BTreeMap;

use matflow_engine::{Node, NodeError, NodeInfo, OutputSpec, ParamSpec, ParamType, RunContext};
use matflow_inverse::paths::{CacheOptions, PathCache};
use matflow_render::{render, PixelFilter, RenderOptions};

use crate::data::{encode_image, envmap_from, materials_from, Kept, MESH};
use crate::failed;
use crate::kinds::insert::COVERAGE_GRID;

pub struct TraceNode;

const TRACE_INFO: NodeInfo = NodeInfo {
    kind: "trace",
    // 2: the kept paths are stored packed (same paths, other bytes).
    // 3: objects (4: with textures). 7: only the texels each pixel's
    // paths meet are stored, not the paths.
    version: 7,
    doc: "A full render of the unedited scene (box pixel filter) that also keeps a set of its \
         light paths: a `render` given these `paths` re-traces only the pixels whose own \
         material changed or whose kept paths meet a changed material, with the base \
         render's sample streams (bit-identical there to a full re-render), and keeps the \
         base elsewhere.",
    params: &[
            MESH,
            ParamSpec {
                name: "materials",
                ty: ParamType::Ref(&["materials", "scene"]),
                default: None,
                unit: "",
                doc: "the unedited materials (they also guide path sampling)",
            },
            ParamSpec {
                name: "envmap",
                ty: ParamType::Ref(&["envmap"]),
                default: None,
                unit: "",
                doc: "lighting (fixed for every edit rendered from these paths)",
            },
            ParamSpec {
                name: "spp",
                ty: ParamType::Int {
                    min: 1,
                    max: 65536,
                },
                default: Some("64"),
                unit: "samples/px",
                doc: "samples per pixel of the full render",
            },
            ParamSpec {
                name: "path_spp",
                ty: ParamType::Int { min: 1, max: 1024 },
                default: Some("8"),
                unit: "paths/px",
                doc: "paths kept per pixel to find which pixels an edit reaches (only the texels they meet are stored: ~0.2 MB per path/px at 512²)",
            },
            ParamSpec {
                name: "depth",
                ty: ParamType::Int { min: 2, max: 8 },
                default: Some("4"),
                unit: "segments",
                doc: "maximum path length (Mitsuba's max_depth)",
            },
            ParamSpec {
                name: "objects",
                ty: crate::objects::OBJECTS,
                default: Some("~"),
                unit: "",
                doc: "objects inserted into the traced scene (as `insert` takes them): an `insert` \
                      given these paths re-traces only what changes to their materials reach",
            },
        ],
    outputs: &[
            OutputSpec {
                name: "paths",
                ty: "paths",
                doc: "kept paths, the unedited materials, envmap and image",
            },
            OutputSpec {
                name: "image",
                ty: "image",
                doc: "the unedited render",
            },
        ],
};

impl Node for TraceNode {
    fn info(&self) -> &'static NodeInfo {
        &TRACE_INFO
    }
    fn estimate_seconds(
        &self,
        p: &matflow_engine::node::Params,
        film: Option<(usize, usize)>,
    ) -> f64 {
        use matflow_inverse::plan::cost;
        crate::data::render_seconds(film, p.i64("spp"), p.i64("depth"))
            * (1.0
                + cost::TRACE_PER_RAY / cost::RENDER_PER_RAY * p.i64("path_spp") as f64
                    / p.i64("spp").max(1) as f64)
    }
    fn check(&self, p: &matflow_engine::node::Params) -> Result<(), String> {
        let specs = crate::objects::specs(p.get("objects")).map_err(|e| e.to_string())?;
        crate::objects::check_specs(&specs)
    }
    fn preflight(&self, p: &matflow_engine::node::Params) -> Result<(), String> {
        let specs = crate::objects::specs(p.get("objects")).map_err(|e| e.to_string())?;
        crate::objects::read_all(&specs).map(|_| ())
    }
    fn check_film(
        &self,
        p: &matflow_engine::node::Params,
        size: (usize, usize),
    ) -> Result<(), String> {
        let specs = crate::objects::specs(p.get("objects")).map_err(|e| e.to_string())?;
        crate::objects::check_anchors(&specs, size)
    }
    fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
        let p = ctx.params;
        let maps = materials_from(ctx.input("materials")?)?;
        let env = envmap_from(ctx.input("envmap")?)?;
        let specs = crate::objects::specs(p.get("objects"))?;
        let (cam, tri) = crate::data::decode_mesh(ctx.input("mesh")?)?;
        let objects = crate::objects::place(&specs, &cam, &tri)?;
        // With objects the depth mesh is needed again for the render
        // without them.
        let plain_mesh = (!objects.is_empty()).then(|| tri.clone());
        let scene = crate::data::scene_of(cam, tri, &maps, &env, &objects)?;
        let depth = p.i64("depth") as u32;
        let spp = p.i64("spp") as u32;
        let parts = if objects.is_empty() { 2 } else { 3 };
        let opts = RenderOptions {
            spp,
            max_depth: depth,
            seed: ctx.seed,
            filter: PixelFilter::Box,
            ..Default::default()
        };
        let image = render(&scene, &opts, &|d, t| {
            (ctx.progress)(d as u64, parts * t as u64)
        })
        .image;
        // With objects, the same render without them, for compositing.
        let background = match plain_mesh {
            None => None,
            Some(tri) => {
                let plain = crate::data::scene_of(cam, tri, &maps, &env, &[])?;
                Some(
                    render(&plain, &opts, &|d, t| {
                        (ctx.progress)((2 * t + d) as u64, parts * t as u64)
                    })
                    .image,
                )
            }
        };
        let cache = PathCache::build(
            &scene,
            &CacheOptions {
                spp: p.i64("path_spp") as u32,
                max_depth: depth,
                seed: ctx.seed ^ 0x7a7a,
                env_width: env.width,
                env_height: env.height,
                lamp_scale: 1.0,
            },
            &|d, t| (ctx.progress)((t + d) as u64, parts * t as u64),
        )
        .map_err(failed)?;
        let kept = Kept {
            spp,
            max_depth: depth,
            seed: ctx.seed,
            reach: cache.reach(),
            materials: maps,
            envmap: env,
            image,
            coverage: (!objects.is_empty()).then(|| scene.object_coverage(COVERAGE_GRID)),
            objects,
            background,
        };
        let img = encode_image("image", "image", &kept.image);
        Ok([
            ("paths".to_string(), kept.encode()),
            ("image".to_string(), img),
        ]
        .into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data::{encode_mesh, render_scene};
    use crate::kinds::render::edited_image;
    use crate::testutil::{check_retrace, opts, small_room, trace_kept};
    use glam::Vec3;

    /// An edit re-traces exactly the pixels it can reach: there the result
    /// equals a full re-render bit for bit, elsewhere the base; and the
    /// kept paths round-trip through their bytes.
    #[test]
    fn edits_retrace_what_they_reach_bit_identically() {
        let n = 24;
        let (s, _, tri) = small_room(n);
        let mesh = encode_mesh(n, n, &tri);
        let scene = render_scene(&mesh, &s.maps, &s.envmap).unwrap();
        let kept = trace_kept(&scene, &s.maps, &s.envmap, &[], None);
        let mut edited = s.maps.clone();
        for y in 14..20 {
            for x in 4..10 {
                edited.albedo.set(x, y, Vec3::new(0.9, 0.1, 0.1));
                edited.roughness.set(x, y, 0.1);
                edited.metallic.set(x, y, 1.0);
            }
        }
        let got = edited_image(&kept, &mesh, &edited).unwrap();
        let full = render(
            &render_scene(&mesh, &edited, &s.envmap).unwrap(),
            &opts(),
            &|_, _| {},
        )
        .image;
        let (hit, differ) =
            check_retrace(&kept, &kept.materials.changed_texels(&edited), &got, &full);
        assert!(hit >= 36 && hit < n * n, "{hit} pixels");
        // What the kept paths miss is rare indirect light.
        assert!(differ * 4 < n * n, "{differ} pixels missed");
        assert!(kept
            .reach
            .pixels_reaching(&kept.materials.changed_texels(&s.maps))
            .is_empty());
    }
}
