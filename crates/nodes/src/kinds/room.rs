//! `room_sample`: one sample of the `rooms` dataset — a synthetic
//! interior (`matflow_procgen::rooms`) path-traced by matflow's renderer,
//! with its ground-truth maps, as the files of a reference bundle: the
//! linear photograph and its sRGB PNG, camera-space depth, the sky mask,
//! true albedo, roughness, metallic, normals and the lighting.

use std::collections::BTreeMap;

use glam::Vec3;
use matflow_engine::node::Params;
use matflow_engine::{Node, NodeError, NodeInfo, OutputSpec, ParamSpec, ParamType, RunContext};
use matflow_geom::TriMesh;
use matflow_procgen::envgen::procedural_envmap;
use matflow_procgen::framing::Framing;
use matflow_procgen::rooms::{ground_truth, scene_framed, SceneKind};
use matflow_render::denoise::{denoise_objects, Guide, RENDER_PASSES, SECOND_HALF_SEED};
use matflow_render::envmap::rotated;
use matflow_render::{render, EnvMap, RenderOptions, RenderScene};
use matflow_scene::{io, Camera, MaterialMaps};

use crate::data::put_file;
use crate::failed;

pub struct RoomSampleNode;

const ROOM_INFO: NodeInfo = NodeInfo {
    kind: "room_sample",
    version: 4,
    doc: "One synthetic scene of the `rooms` dataset (an open or closed room, a stage or an \
         outdoor scene; furniture, matte, glossy and metal materials, camera placement, sky, \
         room lighting, windows and lamps), path-traced, with its ground truth in the reference \
         bundle's files (`matflow dataset` makes these).",
    params: &[
        ParamSpec {
            name: "scene",
            ty: ParamType::Choice(SceneKind::NAMES),
            default: Some("open"),
            unit: "",
            doc: "the kind of scene: a room open to the sky, a closed room, a stage, outdoors",
        },
        ParamSpec {
            name: "seed",
            ty: ParamType::Int {
                min: 0,
                max: i64::MAX,
            },
            default: Some("0"),
            unit: "",
            doc: "the room, its materials, camera and lighting",
        },
        ParamSpec {
            name: "framing",
            ty: ParamType::Choice(Framing::NAMES),
            default: Some("drawn"),
            unit: "",
            doc:
                "where the camera stands: drawn (where the kind's layout puts it) or near (walked \
                  up to one of the scene's objects, looking at it; before a stage, at times its \
                  front row)",
        },
        ParamSpec {
            name: "size",
            ty: ParamType::Int { min: 8, max: 4096 },
            default: Some("256"),
            unit: "px",
            doc: "image side",
        },
        ParamSpec {
            name: "spp",
            ty: ParamType::Int { min: 1, max: 65536 },
            default: Some("64"),
            unit: "samples/px",
            doc: "samples per pixel of the photograph",
        },
        ParamSpec {
            name: "denoise",
            ty: ParamType::Bool,
            default: Some("true"),
            unit: "",
            doc: "render the photograph as two halves of its samples and filter them (à-trous, \
                  guided by the true albedo, normals and depth), as a clean photo looks",
        },
        ParamSpec {
            name: "envmap_width",
            ty: ParamType::Int { min: 8, max: 8192 },
            default: Some("128"),
            unit: "px",
            doc: "the lighting's width (height: half)",
        },
    ],
    outputs: &[
        OutputSpec {
            name: "gt_image.exr",
            ty: "file",
            doc: "the photograph, linear RGB (exposed)",
        },
        OutputSpec {
            name: "gt_image.png",
            ty: "file",
            doc: "the photograph, 8-bit sRGB",
        },
        OutputSpec {
            name: "depth.exr",
            ty: "file",
            doc: "camera-space z (channel Y; 0 where nothing is seen)",
        },
        OutputSpec {
            name: "mesh_mask.png",
            ty: "file",
            doc: "255 where nothing is seen (no geometry)",
        },
        OutputSpec {
            name: "albedo.exr",
            ty: "file",
            doc: "true albedo, linear RGB",
        },
        OutputSpec {
            name: "roughness.exr",
            ty: "file",
            doc: "true roughness (grey: R = G = B, as the bundle's ground_truth/)",
        },
        OutputSpec {
            name: "metallic.exr",
            ty: "file",
            doc: "true metallic (grey: R = G = B)",
        },
        OutputSpec {
            name: "normal.exr",
            ty: "file",
            doc: "true normals, camera space, +z towards the camera",
        },
        OutputSpec {
            name: "envmap.hdr",
            ty: "file",
            doc: "the true lighting in the camera's frame (lat-long, exposed like the image)",
        },
    ],
};

impl Node for RoomSampleNode {
    fn info(&self) -> &'static NodeInfo {
        &ROOM_INFO
    }
    fn film_size(&self, p: &Params) -> Option<(usize, usize)> {
        let n = p.i64("size") as usize;
        Some((n, n))
    }
    fn estimate_seconds(&self, p: &Params, film: Option<(usize, usize)>) -> f64 {
        crate::data::render_seconds(film, p.i64("spp"), 4)
    }
    fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
        let p = ctx.params;
        let n = p.i64("size") as usize;
        let kind = SceneKind::from_name(p.str("scene")).unwrap_or(SceneKind::Open);
        let framing = Framing::from_name(p.str("framing")).unwrap_or(Framing::Drawn);
        let r = scene_framed(kind, p.i64("seed") as u64, framing);
        let ew = p.i64("envmap_width") as usize;
        let world = procedural_envmap(r.env_kind, r.env_seed, ew, (ew / 2).max(2));
        let env_img = rotated(&world, r.to_world);
        let camera = Camera::new(n, n);
        let maps = MaterialMaps::uniform(n, n, Vec3::splat(0.5), 0.5, 0.0);
        let env = EnvMap::new(&env_img).map_err(failed)?;
        let mut scene =
            RenderScene::with_objects(camera, TriMesh::default(), &maps, env, &r.objects)
                .map_err(failed)?;
        scene.set_lamps(r.lamps.clone()).map_err(failed)?;
        scene.set_portals(&r.portals).map_err(failed)?;
        let opts = RenderOptions {
            spp: p.i64("spp") as u32,
            seed: ctx.seed,
            ..RenderOptions::default()
        };
        let progress = |d: usize, t: usize| (ctx.progress)(d as u64, t as u64);
        let gt = ground_truth(&scene, &camera);
        let raw = if p.bool("denoise") && opts.spp >= 2 {
            let (na, nb) = (opts.spp.div_ceil(2), opts.spp / 2);
            let half = |k: usize, spp: u32, seed: u64| {
                let o = RenderOptions { spp, seed, ..opts };
                render(&scene, &o, &|d, t| progress(k * t + d, 2 * t)).image
            };
            let a = half(0, na, opts.seed);
            let b = half(1, nb, opts.seed ^ SECOND_HALF_SEED);
            let guide = Guide::build(&scene);
            denoise_objects(&guide, &gt.albedo, &a, na, &b, nb, RENDER_PASSES + 1)
        } else {
            render(&scene, &opts, &progress).image
        };
        // Exposed like a photograph (the image is linear in the lighting,
        // so the lighting is scaled alike): the log-average to 0.18, then
        // the room's own exposure.
        let k = (matflow_scene::color::exposure_to_key(&raw, 0.18) * 2f64.powf(r.exposure as f64))
            as f32;
        let img = raw.map(|c| c * k);
        let env_img = env_img.map(|c| c * k);
        let mut out = BTreeMap::new();
        put_file(&mut out, "gt_image.exr", |p| io::encode_exr_rgb(p, &img))?;
        put_file(&mut out, "gt_image.png", |_| io::png_srgb_bytes(&img))?;
        put_file(&mut out, "depth.exr", |p| io::encode_exr_gray(p, &gt.depth))?;
        put_file(&mut out, "mesh_mask.png", |_| io::png_mask_bytes(&gt.sky))?;
        put_file(&mut out, "albedo.exr", |p| {
            io::encode_exr_rgb(p, &gt.albedo)
        })?;
        put_file(&mut out, "roughness.exr", |p| {
            io::encode_exr_rgb(p, &gt.roughness.to_rgb())
        })?;
        put_file(&mut out, "metallic.exr", |p| {
            io::encode_exr_rgb(p, &gt.metallic.to_rgb())
        })?;
        put_file(&mut out, "normal.exr", |p| {
            io::encode_exr_rgb(p, &gt.normal)
        })?;
        put_file(&mut out, "envmap.hdr", |p| io::encode_hdr(p, &env_img))?;
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testutil::params_of;
    use matflow_engine::Value;

    #[test]
    fn a_room_sample_is_a_readable_bundle_with_consistent_truth() {
        let p = params_of(
            &ROOM_INFO,
            &[
                ("seed", Value::Int(4)),
                ("size", Value::Int(32)),
                ("spp", Value::Int(4)),
            ],
        );
        let run = || {
            RoomSampleNode
                .run(&RunContext {
                    stage: "r",
                    params: &p,
                    inputs: BTreeMap::new(),
                    seed: 9,
                    progress: &|_, _| {},
                    metric: &|_, _| {},
                    cancelled: &matflow_engine::node::never_cancelled,
                    image: None,
                })
                .unwrap()
        };
        let out = run();
        assert_eq!(out, run(), "not deterministic");
        let names: Vec<&str> = out.keys().map(|k| k.as_str()).collect();
        let want: Vec<&str> = ROOM_INFO.outputs.iter().map(|o| o.name).collect();
        let mut sorted = want.clone();
        sorted.sort();
        assert_eq!(names, sorted);
        // Written out, the files read back as a bundle's would.
        let d = tempfile::tempdir().unwrap();
        for (k, b) in &out {
            std::fs::write(d.path().join(k), b).unwrap();
        }
        let depth = io::read_exr_gray(&d.path().join("depth.exr")).unwrap();
        let mask = io::read_mask(&d.path().join("mesh_mask.png")).unwrap();
        let img = io::read_exr_rgb(&d.path().join("gt_image.exr")).unwrap();
        assert_eq!((depth.width, img.width), (32, 32));
        for k in 0..32 * 32 {
            assert_eq!(depth.data[k] == 0.0, mask.data[k], "pixel {k}");
            assert!(img.data[k].is_finite() && img.data[k].min_element() >= 0.0);
        }
        let rough = io::read_exr_rgb(&d.path().join("roughness.exr"))
            .unwrap()
            .channel(0);
        assert!(rough.data.iter().all(|r| (0.0..=1.0).contains(r)));
    }
}
