//! `matflow-bench render`: BVH build, ray throughput and a full render
//! against Embree and Mitsuba 3.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Result;
use clap::Args;
use glam::{Vec2, Vec3};
use matflow_geom::Bvh;
use matflow_render::rng::Pcg32;
use matflow_render::warp::{square_to_cosine_hemisphere, Frame};
use matflow_render::{render, Crop, RenderOptions, RenderScene};
use matflow_scene::metrics::psnr_gamma;
use matflow_scene::{io, MaterialSource};
use rayon::prelude::*;

use crate::harness::median;
use matflow_nodes::bundle_scene::load_scene;

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
    /// camera) and the ray sets to this folder for `crates/bench/scripts/mitsuba_render.py`
    /// and `crates/bench/scripts/embree_rays.c`, then stop.
    #[arg(long)]
    pub export: Option<PathBuf>,
    /// Skip the side-by-side runs of Embree and Mitsuba 3 (they run when
    /// installed: libembree-dev; pip mitsuba with libllvm19).
    #[arg(long)]
    pub no_compare: bool,
    /// Also measure time to equal error against each renderer's own
    /// converged render of a window of the image.
    #[arg(long)]
    pub equal_error: bool,
    /// Samples per pixel of the converged renders of --equal-error.
    #[arg(long, default_value_t = 4096)]
    pub reference_spp: u32,
    /// Window of --equal-error: X Y W H (default: the central 128×128).
    #[arg(long, num_args = 4)]
    pub window: Option<Vec<usize>>,
    /// Folder of the comparison programs (default: the repository's bench/).
    #[arg(long)]
    pub bench_dir: Option<PathBuf>,
    /// Scratch folder for the exported scene and compiled programs.
    #[arg(long, default_value = "target/bench-render")]
    pub work_dir: PathBuf,
    /// Only time the full render at each of these shading lane widths
    /// (1, 4, 8, 16; runs interleaved, the same seed) and check that
    /// every width gives the same image bytes
    #[arg(long, value_delimiter = ',')]
    pub widths: Vec<usize>,
    /// Only measure how the render's time grows with resolution (the
    /// scene resampled to 256², 512², 1024², 16 spp), spp (16 to 1024 on
    /// the central 128² window), triangles (the mesh as built and each
    /// triangle split in 4, central 256², 64 spp) and threads (1, 2;
    /// central 256², 64 spp), with Mitsuba 3 on the same scenes and
    /// windows when installed (for one thread: on one core, as Dr.Jit
    /// hangs with one thread)
    #[arg(long)]
    pub scaling: bool,
}

pub fn bench_render(a: BenchRenderArgs) -> Result<()> {
    let runs = a.runs.max(1);
    let threads = rayon::current_num_threads();
    let loaded = load_scene(
        &a.bundle,
        a.materials,
        None,
        if a.reference_compat {
            matflow_geom::MeshParams::reference(6.0)
        } else {
            matflow_geom::MeshParams::default()
        },
        a.reference_compat,
        None,
        false,
    )?;
    let scene = &loaded.scene;
    let cam = scene.camera;
    outln!(
        "bench render: {} ({}x{}, {} triangles), {} thread(s), {} run(s), medians",
        a.bundle.display(),
        cam.width,
        cam.height,
        scene.mesh.triangle_count(),
        threads,
        runs
    );
    if !a.widths.is_empty() {
        return lane_widths(&a, scene, runs);
    }
    if a.scaling {
        return scaling(&a, &loaded, runs);
    }
    let depth = matflow_scene::Bundle::open(&a.bundle)?.load_depth()?;
    let build_t = build_times(scene, &depth, runs);
    let (primary, incoherent) = ray_sets(scene);
    let export = |dir: &std::path::Path| -> Result<()> {
        crate::suites::compare::export_scene(scene, dir)?;
        crate::suites::compare::write_rays(&dir.join("primary.rays"), &primary)?;
        crate::suites::compare::write_rays(&dir.join("incoherent.rays"), &incoherent)
    };
    if let Some(dir) = &a.export {
        export(dir)?;
        outln!("wrote {}", dir.display());
        return Ok(());
    }
    let ours = throughput(scene, &primary, &incoherent, runs);
    outln!(
        "  primary closest-hit   {:8.2} Mrays/s ({} rays)",
        ours[0],
        primary.len()
    );
    let spp = a.spp.max(1) as usize;
    let packet_t = packet_seconds(scene, spp, runs);
    outln!(
        "  camera packets        {:8.2} Mrays/s ({} per pixel, as the renderer traces them)",
        (cam.width * cam.height * spp) as f64 / packet_t / 1e6,
        spp
    );
    for (name, v) in [
        ("incoherent closest-hit", ours[1]),
        ("incoherent occlusion", ours[2]),
        ("  as streams", ours[3]),
        ("  occlusion as streams", ours[4]),
    ] {
        outln!("  {name:<22}{v:8.2} Mrays/s ({} rays)", incoherent.len());
    }
    let (render_s, image) = full_renders(&a, scene, runs);
    stored_psnr(&a, &image)?;
    if a.no_compare {
        return Ok(());
    }
    compare(&a, scene, &export, build_t, ours, render_s, threads, runs)
}

/// Meshing the depth and building the BVH, medians of `runs` (printed);
/// returns the BVH build's seconds.
fn build_times(
    scene: &matflow_render::RenderScene,
    depth: &matflow_scene::GrayImage,
    runs: usize,
) -> f64 {
    let cam = scene.camera;
    // Meshing and BVH build.
    let mesh_t = median(
        (0..runs)
            .map(|_| {
                let t = Instant::now();
                let _ = matflow_geom::mesh_from_depth(depth, &cam, &Default::default());
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
    outln!("  mesh from depth       {:8.1} ms", mesh_t * 1e3);
    outln!("  BVH build             {:8.1} ms", build_t * 1e3);

    build_t
}

/// The ray sets: primary (one per pixel, jittered) and incoherent (cosine
/// directions from the primary hits; also the occlusion set).
#[allow(clippy::type_complexity)]
fn ray_sets(scene: &matflow_render::RenderScene) -> (Vec<(Vec3, Vec3)>, Vec<(Vec3, Vec3)>) {
    let cam = scene.camera;
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
    (primary, incoherent)
}

/// Median Mrays/s, one ray at a time (primary and incoherent closest hit,
/// incoherent occlusion) and as the renderer traces its shadow and
/// continuation rays: streams (of 1024, as chunked).
fn throughput(
    scene: &matflow_render::RenderScene,
    primary: &[(Vec3, Vec3)],
    incoherent: &[(Vec3, Vec3)],
    runs: usize,
) -> [f64; 5] {
    // Median Mrays/s of `count`, which answers a chunk of 1024 rays and
    // counts its hits, over the chunks in parallel.
    type Rays<'a> = &'a [(Vec3, Vec3)];
    let time = |rays: Rays, count: &(dyn Fn(Rays) -> usize + Sync)| {
        median(
            (0..runs)
                .map(|_| {
                    let t = Instant::now();
                    let c: usize = rays.par_chunks(1024).map(count).sum();
                    std::hint::black_box(c);
                    rays.len() as f64 / t.elapsed().as_secs_f64() / 1e6
                })
                .collect(),
        )
    };
    let bvh = &scene.bvh;
    let inf = f32::INFINITY;
    let hits = |ch: &[(Vec3, Vec3)]| {
        ch.iter()
            .filter(|(o, d)| bvh.intersect(*o, *d, 0.0, inf).is_some())
            .count()
    };
    let blocked = |ch: &[(Vec3, Vec3)]| {
        ch.iter()
            .filter(|(o, d)| bvh.occluded(*o, *d, 0.0, inf))
            .count()
    };
    let stream_hits = |ch: &[(Vec3, Vec3)]| {
        let mut out = vec![None; ch.len()];
        bvh.intersect_stream(ch, 0.0, inf, &mut out);
        out.iter().filter(|h| h.is_some()).count()
    };
    let stream_blocked = |ch: &[(Vec3, Vec3)]| {
        let mut out = vec![false; ch.len()];
        bvh.occluded_stream(ch, 0.0, inf, &mut out);
        out.iter().filter(|&&b| b).count()
    };
    [
        time(primary, &hits),
        time(incoherent, &hits),
        time(incoherent, &blocked),
        time(incoherent, &stream_hits),
        time(incoherent, &stream_blocked),
    ]
}

/// The renderer's own route for camera rays: each pixel's `spp` samples
/// as one packet; median seconds over `runs`.
fn packet_seconds(scene: &matflow_render::RenderScene, spp: usize, runs: usize) -> f64 {
    let (w, h) = (scene.camera.width, scene.camera.height);
    median(
        (0..runs)
            .map(|_| {
                let t = Instant::now();
                let c: usize = (0..w * h)
                    .into_par_iter()
                    .map_init(
                        || (Vec::with_capacity(spp), vec![None; spp]),
                        |(dirs, out), k| {
                            dirs.clear();
                            for s in 0..spp {
                                let mut r = Pcg32::for_sample(3, k as u64, s as u64);
                                let (jx, jy) = r.next_2d();
                                let film = Vec2::new((k % w) as f32 + jx, (k / w) as f32 + jy);
                                dirs.push(scene.camera_ray(film));
                            }
                            scene
                                .bvh
                                .intersect_packet(Vec3::ZERO, dirs, 0.0, f32::INFINITY, out);
                            out.iter().filter(|h| h.is_some()).count()
                        },
                    )
                    .sum();
                std::hint::black_box(c);
                t.elapsed().as_secs_f64()
            })
            .collect(),
    )
}

/// Full renders at the bench's spp and depth, one per seed: the median
/// wall time (printed with the rays) and the last image.
fn full_renders(
    a: &BenchRenderArgs,
    scene: &matflow_render::RenderScene,
    runs: usize,
) -> (f64, matflow_scene::RgbImage) {
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
        let t0 = Instant::now();
        let out = render(scene, &o, &|_, _| {});
        let seconds = t0.elapsed().as_secs_f64();
        times.push(seconds);
        mrays.push(out.stats.total_rays() as f64 / seconds / 1e6);
        last = Some(out);
    }
    let out = last.unwrap();
    let render_s = median(times);
    outln!(
        "  render {} spp, depth {} {:8.2} s wall ({:.2} Mrays/s overall, {:.1} M rays)",
        a.spp,
        a.depth,
        render_s,
        median(mrays),
        out.stats.total_rays() as f64 / 1e6
    );
    (render_s, out.image)
}

/// The full render at each lane width of `--widths`, runs interleaved
/// (width after width, `runs` rounds) so that a machine's drift falls on
/// all of them alike; fails unless every width gives the same bytes.
fn lane_widths(
    a: &BenchRenderArgs,
    scene: &matflow_render::RenderScene,
    runs: usize,
) -> Result<()> {
    let opts = RenderOptions {
        spp: a.spp,
        max_depth: a.depth,
        reference_compat: a.reference_compat,
        ..Default::default()
    };
    let mut times = vec![Vec::new(); a.widths.len()];
    let mut images: Vec<Option<Vec<u32>>> = vec![None; a.widths.len()];
    for _ in 0..runs {
        for (k, &w) in a.widths.iter().enumerate() {
            matflow_render::lanes::force_width(Some(w)).map_err(anyhow::Error::msg)?;
            let t0 = Instant::now();
            let out = render(scene, &opts, &|_, _| {});
            times[k].push(t0.elapsed().as_secs_f64());
            matflow_render::lanes::force_width(None).map_err(anyhow::Error::msg)?;
            let bits = out
                .image
                .data
                .iter()
                .flat_map(|v| [v.x.to_bits(), v.y.to_bits(), v.z.to_bits()])
                .collect();
            images[k].get_or_insert(bits);
        }
    }
    outln!(
        "  render {} spp, depth {}, by shading lane width (CPU's own: {}):",
        a.spp,
        a.depth,
        matflow_render::lanes::native_width()
    );
    for (k, &w) in a.widths.iter().enumerate() {
        let same = images[k] == images[0];
        outln!(
            "    {w:2} lanes {:8.2} s wall (runs: {}){}",
            median(times[k].clone()),
            times[k]
                .iter()
                .map(|t| format!("{t:.2}"))
                .collect::<Vec<_>>()
                .join(" "),
            if same { "" } else { "  IMAGE DIFFERS" }
        );
    }
    anyhow::ensure!(
        images.iter().all(|i| *i == images[0]),
        "the lane widths {:?} gave different images",
        a.widths
    );
    outln!("    every width gave the same image bytes");
    Ok(())
}

/// `--scaling`: matflow's and Mitsuba 3's render times (medians of
/// `runs`) as resolution, spp, triangle count and threads grow.
fn scaling(
    a: &BenchRenderArgs,
    loaded: &matflow_nodes::bundle_scene::LoadedScene,
    runs: usize,
) -> Result<()> {
    use crate::suites::compare::*;
    let base = &loaded.scene;
    let bench_dir = a.bench_dir.clone().unwrap_or_else(default_bench_dir);
    let mitsuba = mitsuba_installed() && !a.reference_compat;
    let threads_now = rayon::current_num_threads();
    let centre = |s: usize| {
        let c = base.camera;
        let s = s.min(c.width).min(c.height);
        Crop {
            x: (c.width - s) / 2,
            y: (c.height - s) / 2,
            width: s,
            height: s,
        }
    };
    // One row: matflow's median, then Mitsuba's on the exported scene.
    let row = |what: String,
               scene: &matflow_render::RenderScene,
               dir: &std::path::Path,
               spp: u32,
               crop: Option<Crop>,
               threads: usize|
     -> Result<()> {
        let opts = RenderOptions {
            spp,
            max_depth: a.depth,
            crop,
            ..Default::default()
        };
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()?;
        let times: Vec<f64> = (0..runs)
            .map(|r| {
                let o = RenderOptions {
                    seed: r as u64,
                    ..opts
                };
                let t0 = Instant::now();
                pool.install(|| render(scene, &o, &|_, _| {}));
                t0.elapsed().as_secs_f64()
            })
            .collect();
        let ours = median(times);
        if !mitsuba {
            outln!("  {what:<40}{ours:9.3} s");
            return Ok(());
        }
        let mi = run_mitsuba(&bench_dir, dir, spp, a.depth, runs, threads, 0, crop, None)?;
        outln!(
            "  {what:<40}{ours:9.3} s {:9.3} s   matflow/Mitsuba {:.2}",
            mi.median_s,
            ours / mi.median_s
        );
        Ok(())
    };
    let work = &a.work_dir;
    let export = |scene: &matflow_render::RenderScene, name: &str| -> Result<PathBuf> {
        let dir = work.join(name);
        if mitsuba {
            export_scene(scene, &dir)?;
        }
        Ok(dir)
    };
    outln!(
        "scaling: depth {}, medians of {runs}; matflow{}",
        a.depth,
        if mitsuba {
            ", Mitsuba 3 (llvm_ad_rgb) beside it"
        } else {
            " (Mitsuba 3 not installed)"
        }
    );
    let base_dir = export(base, "scaling-base")?;

    // Resolution: depth and maps resampled (bilinear), the mesh rebuilt.
    let bundle = matflow_scene::Bundle::open(&a.bundle)?;
    let depth = bundle.load_depth()?;
    for n in [256usize, 512, 1024] {
        let (scene, dir) = if n == base.camera.width && n == base.camera.height {
            (None, base_dir.clone())
        } else {
            let s = resampled_scene(&depth, &loaded.maps, &loaded.env, n)?;
            let d = export(&s, &format!("scaling-{n}"))?;
            (Some(s), d)
        };
        let scene = scene.as_ref().unwrap_or(base);
        row(
            format!("{n}², 16 spp, {} triangles", scene.mesh.triangle_count()),
            scene,
            &dir,
            16,
            None,
            threads_now,
        )?;
    }
    // Samples per pixel.
    for spp in [16u32, 64, 256, 1024] {
        row(
            format!("central 128², {spp} spp"),
            base,
            &base_dir,
            spp,
            Some(centre(128)),
            threads_now,
        )?;
    }
    // Triangles: each split into four (the same surface).
    let split = RenderScene::new(
        base.camera,
        split_triangles(&base.mesh),
        &loaded.maps,
        loaded.env.clone(),
    )?;
    let split_dir = export(&split, "scaling-split")?;
    for (scene, dir) in [(base, &base_dir), (&split, &split_dir)] {
        row(
            format!(
                "central 256², 64 spp, {} triangles",
                scene.mesh.triangle_count()
            ),
            scene,
            dir,
            64,
            Some(centre(256)),
            threads_now,
        )?;
    }
    drop(split);
    // Threads (one thread: matflow's pool of one; Mitsuba's two threads
    // pinned to one core, see `run_mitsuba`).
    for threads in [1usize, 2] {
        row(
            format!("central 256², 64 spp, {threads} thread(s)"),
            base,
            &base_dir,
            64,
            Some(centre(256)),
            threads,
        )?;
    }
    Ok(())
}

/// The bundle's scene at `n`×`n`: depth and material maps resampled
/// (bilinear), the mesh and BVH rebuilt.
fn resampled_scene(
    depth: &matflow_scene::GrayImage,
    maps: &matflow_scene::MaterialMaps,
    env: &matflow_render::EnvMap,
    n: usize,
) -> Result<RenderScene> {
    let gray = |g: &matflow_scene::GrayImage| {
        let rgb = matflow_scene::Image::from_fn(g.width, g.height, |x, y| Vec3::splat(g.get(x, y)));
        let r = io::resize_bilinear(&rgb, n, n);
        matflow_scene::Image::from_fn(n, n, |x, y| r.get(x, y).x)
    };
    let mut m = maps.clone();
    m.albedo = io::resize_bilinear(&maps.albedo, n, n);
    m.roughness = gray(&maps.roughness);
    m.metallic = gray(&maps.metallic);
    m.normal = None;
    m.transparency = None;
    let (scene, _, _) = matflow_render::scene_from_depth(
        &gray(depth),
        &m,
        env.clone(),
        matflow_geom::MeshParams::default(),
        None,
    )?;
    Ok(scene)
}

/// `mesh` with every triangle split into four at its edges' midpoints:
/// the same surface with four times the triangles (per-triangle
/// attributes copied to the four).
fn split_triangles(mesh: &matflow_geom::TriMesh) -> matflow_geom::TriMesh {
    let mut out = matflow_geom::TriMesh {
        portals: mesh.portals.clone(),
        ..Default::default()
    };
    let film = !mesh.film.is_empty();
    for (t, tri) in mesh.indices.iter().enumerate() {
        let p = tri.map(|i| mesh.positions[i as usize]);
        let base = out.positions.len() as u32;
        out.positions.extend([
            p[0],
            p[1],
            p[2],
            (p[0] + p[1]) * 0.5,
            (p[1] + p[2]) * 0.5,
            (p[2] + p[0]) * 0.5,
        ]);
        if film {
            let f = tri.map(|i| mesh.film[i as usize]);
            out.film.extend([
                f[0],
                f[1],
                f[2],
                (f[0] + f[1]) * 0.5,
                (f[1] + f[2]) * 0.5,
                (f[2] + f[0]) * 0.5,
            ]);
        }
        let [a, b, c, ab, bc, ca] = [0, 1, 2, 3, 4, 5].map(|k| base + k);
        out.indices
            .extend([[a, ab, ca], [ab, b, bc], [ca, bc, c], [ab, bc, ca]]);
        if let Some(&m) = mesh.material_pixel.get(t) {
            out.material_pixel.extend([m; 4]);
        }
        if let Some(&o) = mesh.openness.get(t) {
            out.openness.extend([o; 4]);
        }
    }
    out
}

/// PSNR against the bundle's stored render, when it has a linear one of
/// the same size.
fn stored_psnr(a: &BenchRenderArgs, image: &matflow_scene::RgbImage) -> Result<()> {
    let stored = a.bundle.join("best_results/rendered_img.exr");
    if stored.is_file() && !matflow_scene::Bundle::open(&a.bundle)?.rendered_img_is_gamma_encoded()
    {
        let reference = io::read_exr_rgb(&stored)?;
        if reference.same_size(image) {
            outln!(
                "  PSNR vs stored rendered_img.exr (sRGB, gamma 2.2): {:.2} dB{}",
                psnr_gamma(image, &reference),
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

/// Embree's ray throughput and Mitsuba 3's render time on the same scene,
/// rays, spp and depth, in this run, beside matflow's; then, with
/// `--equal-error`, the time each needs to reach the same error.
#[allow(clippy::too_many_arguments)]
fn compare(
    a: &BenchRenderArgs,
    scene: &matflow_render::RenderScene,
    export: &dyn Fn(&std::path::Path) -> Result<()>,
    build_t: f64,
    ours: [f64; 5],
    render_s: f64,
    threads: usize,
    runs: usize,
) -> Result<()> {
    use crate::suites::compare::*;
    let bench_dir = a.bench_dir.clone().unwrap_or_else(default_bench_dir);
    let work = &a.work_dir;
    let scene_dir = work.join("scene");
    export(&scene_dir)?;
    outln!("side by side ({threads} threads, same rays, scene, spp and depth):");
    let embree = run_embree(&bench_dir, &scene_dir, work, threads, runs)?;
    match &embree {
        None => outln!("  Embree: not installed (apt-get install libembree-dev)"),
        Some(e) => {
            outln!(
                "  {:<26}{:>12}{:>16}",
                "",
                "matflow",
                format!("Embree {}", e.embree)
            );
            outln!(
                "  {:<26}{:>12.1}{:>16.1}",
                "BVH build (ms)",
                build_t * 1e3,
                e.build_ms
            );
            for (name, m, em) in [
                ("primary closest-hit", ours[0], e.primary_hit_mrays),
                ("incoherent closest-hit", ours[1], e.incoherent_hit_mrays),
                ("incoherent occlusion", ours[2], e.incoherent_occl_mrays),
                (
                    "  streams (Embree 1M)",
                    ours[3],
                    e.incoherent_hit_stream_mrays,
                ),
                (
                    "  occlusion streams (1M)",
                    ours[4],
                    e.incoherent_occl_stream_mrays,
                ),
            ] {
                outln!(
                    "  {:<26}{:>12.2}{:>16.2}   Mrays/s, matflow/Embree {:.2}",
                    name,
                    m,
                    em,
                    m / em
                );
            }
        }
    }
    if !mitsuba_installed() {
        outln!("  Mitsuba 3: not installed (pip install mitsuba; apt-get install libllvm19)");
        return Ok(());
    }
    if a.reference_compat {
        outln!("  Mitsuba 3: skipped (--reference-compat renders a different estimator)");
        return Ok(());
    }
    let mi = run_mitsuba(
        &bench_dir, &scene_dir, a.spp, a.depth, runs, threads, 0, None, None,
    )?;
    outln!(
        "  render {} spp, depth {}: matflow {:.2} s, {} {:.2} s (first run {:.2} s); matflow/Mitsuba {:.2}",
        a.spp, a.depth, render_s, mi.renderer, mi.median_s, mi.first_s, render_s / mi.median_s
    );
    if !a.equal_error {
        return Ok(());
    }

    // Equal error: each renderer against its own converged render of a
    // window, at increasing spp; interior pixels only (a window's edge
    // misses the filter splats of samples outside it).
    let cam = scene.camera;
    let crop = match &a.window {
        Some(v) => Crop {
            x: v[0],
            y: v[1],
            width: v[2],
            height: v[3],
        },
        None => {
            let s = 128.min(cam.width).min(cam.height);
            Crop {
                x: (cam.width - s) / 2,
                y: (cam.height - s) / 2,
                width: s,
                height: s,
            }
        }
    };
    let margin = 2;
    outln!(
        "equal error: window {}x{} at ({}, {}), RMSE (linear) against each renderer's own {} spp render",
        crop.width, crop.height, crop.x, crop.y, a.reference_spp
    );
    let ours_at = |spp: u32, seed: u64| {
        let o = RenderOptions {
            spp,
            max_depth: a.depth,
            seed,
            crop: Some(crop),
            ..Default::default()
        };
        let t0 = Instant::now();
        let out = render(scene, &o, &|_, _| {});
        (out.image, t0.elapsed().as_secs_f64())
    };
    let (ref_m, _) = ours_at(a.reference_spp, 1 << 20);
    let ref_path = work.join("mitsuba-reference.exr");
    run_mitsuba(
        &bench_dir,
        &scene_dir,
        a.reference_spp,
        a.depth,
        1,
        threads,
        1 << 20,
        Some(crop),
        Some(&ref_path),
    )?;
    let ref_mi = io::read_exr_rgb(&ref_path)?;
    outln!(
        "  the two converged renders differ by RMSE {:.5} (mean {:.4})",
        rmse_interior(&ref_m, &ref_mi, margin),
        ref_m
            .data
            .iter()
            .map(|v| v.element_sum() as f64)
            .sum::<f64>()
            / (3 * ref_m.data.len()) as f64
    );
    outln!(
        "  {:>6} {:>12} {:>10} {:>12} {:>10}",
        "spp",
        "matflow s",
        "RMSE",
        "Mitsuba s",
        "RMSE"
    );
    let (mut pts_m, mut pts_mi) = (Vec::new(), Vec::new());
    let img_path = work.join("mitsuba-window.exr");
    for spp in [4u32, 16, 64, 256] {
        let mut t = Vec::new();
        let mut last = None;
        for r in 0..runs {
            let (img, secs) = ours_at(spp, r as u64);
            t.push(secs);
            last = Some(img);
        }
        let tm = median(t);
        let err = last.map_or(f64::NAN, |img| rmse_interior(&img, &ref_m, margin));
        let mi = run_mitsuba(
            &bench_dir,
            &scene_dir,
            spp,
            a.depth,
            runs,
            threads,
            0,
            Some(crop),
            Some(&img_path),
        )?;
        let err_mi = rmse_interior(&io::read_exr_rgb(&img_path)?, &ref_mi, margin);
        outln!(
            "  {:>6} {:>12.3} {:>10.5} {:>12.3} {:>10.5}",
            spp,
            tm,
            err,
            mi.median_s,
            err_mi
        );
        pts_m.push((tm, err));
        pts_mi.push((mi.median_s, err_mi));
    }
    // The target: Mitsuba's error at 64 spp.
    let target = pts_mi[2].1;
    let (tm, tmi) = (
        time_to_error(&pts_m, target),
        time_to_error(&pts_mi, target),
    );
    outln!(
        "  time to RMSE {target:.5} (Mitsuba's at 64 spp): matflow {tm:.3} s, Mitsuba {tmi:.3} s; matflow/Mitsuba {:.2}",
        tm / tmi
    );
    Ok(())
}
