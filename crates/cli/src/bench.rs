//! `matflow bench …`: benchmarks that print numbers (never timed tests).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Result;
use clap::{Args, Subcommand};
use glam::{Vec2, Vec3};
use matflow_geom::Bvh;
use matflow_render::rng::Pcg32;
use matflow_render::warp::{square_to_cosine_hemisphere, Frame};
use matflow_render::{render, RenderOptions};
use matflow_scene::metrics::psnr_gamma;
use matflow_scene::{io, MaterialSource};
use rayon::prelude::*;

use crate::commands::load_scene;

#[derive(Subcommand)]
pub enum BenchCmd {
    /// BVH build time, ray throughput and wall time of a full render.
    Render(BenchRenderArgs),
    /// Inverse rendering: wall time against rerender error per budget,
    /// route and skip.
    Invert(crate::bench_invert::BenchInvertArgs),
    /// Inverse rendering on procedural scenes with known truth: envmap,
    /// material and relighting errors per budget and route.
    Synthetic(crate::bench_synthetic::BenchSyntheticArgs),
    /// The pipeline engine: first run, re-edit of one material and a
    /// no-change re-run, over the binary.
    Pipeline(crate::bench_pipeline::BenchPipelineArgs),
}

#[derive(Args)]
pub struct BenchRenderArgs {
    /// Bundle to benchmark (e.g. ../shared/data/materialist/indoor).
    #[arg(long)]
    pub bundle: PathBuf,
    #[arg(long, default_value = "best_results")]
    pub materials: MaterialSource,
    #[arg(long, default_value_t = 64)]
    pub spp: u32,
    #[arg(long, default_value_t = 4)]
    pub depth: u32,
    /// Repetitions; medians are reported.
    #[arg(long, default_value_t = 3)]
    pub runs: usize,
    /// Also compare against the bundle's stored best_results/rendered_img.exr
    /// with the reference-compatible sampling frame.
    #[arg(long)]
    pub reference_compat: bool,
    /// Only write the scene as rendered (mesh, envmap, material maps,
    /// camera) to this folder for `bench/mitsuba_render.py`, then stop.
    #[arg(long)]
    pub export: Option<PathBuf>,
}

pub fn run(b: BenchCmd) -> Result<()> {
    match b {
        BenchCmd::Render(a) => bench_render(a),
        BenchCmd::Invert(a) => crate::bench_invert::bench_invert(a),
        BenchCmd::Synthetic(a) => crate::bench_synthetic::bench_synthetic(a),
        BenchCmd::Pipeline(a) => crate::bench_pipeline::bench_pipeline(a),
    }
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.partial_cmp(b).unwrap());
    let n = v.len();
    if n == 0 {
        return f64::NAN;
    }
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

fn bench_render(a: BenchRenderArgs) -> Result<()> {
    let runs = a.runs.max(1);
    let threads = rayon::current_num_threads();
    let loaded = load_scene(&a.bundle, a.materials, None, 6.0, a.reference_compat)?;
    let scene = &loaded.scene;
    let cam = scene.camera;
    println!(
        "bench render: {} ({}x{}, {} triangles), {} thread(s), {} run(s), medians",
        a.bundle.display(),
        cam.width,
        cam.height,
        scene.mesh.triangle_count(),
        threads,
        runs
    );

    // Meshing and BVH build.
    let depth = matflow_scene::Bundle::open(&a.bundle)?.load_depth()?;
    let mesh_t = median(
        (0..runs)
            .map(|_| {
                let t = Instant::now();
                let _ = matflow_geom::mesh_from_depth(&depth, &cam, &Default::default());
                t.elapsed().as_secs_f64()
            })
            .collect(),
    );
    let build_t = median(
        (0..runs)
            .map(|_| {
                let t = Instant::now();
                let b = Bvh::build(&scene.mesh);
                std::hint::black_box(b.node_count());
                t.elapsed().as_secs_f64()
            })
            .collect(),
    );
    println!("  mesh from depth       {:8.1} ms", mesh_t * 1e3);
    println!("  BVH build             {:8.1} ms", build_t * 1e3);

    // Ray sets: primary (one per pixel, jittered), incoherent (cosine
    // directions from the primary hits), occlusion (the same incoherent rays).
    let (w, h) = (cam.width, cam.height);
    let primary: Vec<(Vec3, Vec3)> = (0..w * h)
        .map(|k| {
            let mut r = Pcg32::for_sample(1, k as u64, 0);
            let (jx, jy) = r.next_2d();
            (
                Vec3::ZERO,
                scene.camera_ray(Vec2::new((k % w) as f32 + jx, (k / w) as f32 + jy)),
            )
        })
        .collect();
    let hits: Vec<Option<matflow_geom::Hit>> = primary
        .par_iter()
        .map(|(o, d)| scene.bvh.intersect(*o, *d, 0.0, f32::INFINITY))
        .collect();
    let incoherent: Vec<(Vec3, Vec3)> = primary
        .iter()
        .zip(hits.iter())
        .enumerate()
        .filter_map(|(k, ((o, d), h))| {
            let h = (*h)?;
            let p = *o + *d * h.t;
            let n = scene.face_normals[h.prim as usize];
            let mut r = Pcg32::for_sample(2, k as u64, 0);
            let l = Frame::from_normal(n)
                .to_world(square_to_cosine_hemisphere(r.next_f32(), r.next_f32()));
            Some((p + n * 1e-5 * (1.0 + p.abs().max_element()), l))
        })
        .collect();
    if let Some(dir) = &a.export {
        crate::bench_mitsuba::export_scene(scene, dir)?;
        crate::bench_mitsuba::write_rays(&dir.join("primary.rays"), &primary)?;
        crate::bench_mitsuba::write_rays(&dir.join("incoherent.rays"), &incoherent)?;
        println!("wrote {}", dir.display());
        return Ok(());
    }
    let time_rays = |rays: &[(Vec3, Vec3)], occl: bool| -> f64 {
        median(
            (0..runs)
                .map(|_| {
                    let t = Instant::now();
                    let c: usize = rays
                        .par_chunks(1024)
                        .map(|ch| {
                            ch.iter()
                                .filter(|(o, d)| {
                                    if occl {
                                        scene.bvh.occluded(*o, *d, 0.0, f32::INFINITY)
                                    } else {
                                        scene.bvh.intersect(*o, *d, 0.0, f32::INFINITY).is_some()
                                    }
                                })
                                .count()
                        })
                        .sum();
                    std::hint::black_box(c);
                    rays.len() as f64 / t.elapsed().as_secs_f64() / 1e6
                })
                .collect(),
        )
    };
    println!(
        "  primary closest-hit   {:8.2} Mrays/s ({} rays)",
        time_rays(&primary, false),
        primary.len()
    );
    println!(
        "  incoherent closest-hit{:8.2} Mrays/s ({} rays)",
        time_rays(&incoherent, false),
        incoherent.len()
    );
    println!(
        "  incoherent occlusion  {:8.2} Mrays/s ({} rays)",
        time_rays(&incoherent, true),
        incoherent.len()
    );

    // Full renders.
    let opts = RenderOptions {
        spp: a.spp,
        max_depth: a.depth,
        reference_compat: a.reference_compat,
        ..Default::default()
    };
    let mut times = Vec::new();
    let mut mrays = Vec::new();
    let mut last = None;
    for r in 0..runs {
        let o = RenderOptions {
            seed: r as u64,
            ..opts
        };
        let out = render(scene, &o, &|_, _| {});
        times.push(out.stats.seconds);
        mrays.push(out.stats.total_rays() as f64 / out.stats.seconds / 1e6);
        last = Some(out);
    }
    let out = last.unwrap();
    println!(
        "  render {} spp, depth {} {:8.2} s wall ({:.2} Mrays/s overall, {:.1} M rays)",
        a.spp,
        a.depth,
        median(times),
        median(mrays),
        out.stats.total_rays() as f64 / 1e6
    );
    let stored = a.bundle.join("best_results/rendered_img.exr");
    if stored.is_file() && !matflow_scene::Bundle::open(&a.bundle)?.rendered_img_is_gamma_encoded()
    {
        let reference = io::read_exr_rgb(&stored)?;
        if reference.same_size(&out.image) {
            println!(
                "  PSNR vs stored rendered_img.exr (sRGB, gamma 2.2): {:.2} dB{}",
                psnr_gamma(&out.image, &reference),
                if a.reference_compat {
                    " (reference-compatible frame)"
                } else {
                    ""
                }
            );
        }
    }
    Ok(())
}
