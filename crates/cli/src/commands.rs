use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use matflow_geom::mesh_for_view;
use matflow_render::{
    render as render_scene, scene_from_depth, EnvMap, PixelFilter, RenderOptions, RenderOutput,
    RenderScene,
};
use matflow_scene::metrics::psnr_gamma;
use matflow_scene::{io, Bundle, MaterialSource, RgbImage};

#[derive(Args, Clone)]
pub struct RenderArgs {
    /// Scene bundle folder (reference layout).
    #[arg(long)]
    pub bundle: PathBuf,
    /// Render even when estimated to take more than an hour (on the
    /// reference 2-core machine).
    #[arg(long)]
    pub allow_expensive: bool,
    /// Material maps: best_results, pred or ground_truth.
    #[arg(long, default_value = "best_results")]
    pub materials: MaterialSource,
    /// Environment map (.hdr or .exr); default: the bundle's best_results/envmap.hdr
    /// (or ground_truth/envmap.hdr).
    #[arg(long)]
    pub envmap: Option<PathBuf>,
    /// Samples per pixel.
    #[arg(long, default_value_t = 64)]
    pub spp: u32,
    /// Maximum path depth in ray segments (Mitsuba's max_depth).
    #[arg(long, default_value_t = 4)]
    pub depth: u32,
    /// Random seed.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Pixel filter: gaussian (Mitsuba's default) or box.
    #[arg(long, default_value = "gaussian")]
    pub filter: PixelFilter,
    /// Mesh boundary angle threshold in degrees.
    #[arg(long, default_value_t = 6.0)]
    pub mesh_angle: f64,
    /// Reproduce the reference renderer's sampling-frame defect and its
    /// optimisation-time envmap layout (for comparing with its stored
    /// renders; physically incorrect).
    #[arg(long)]
    pub reference_compat: bool,
    /// Print PSNR (sRGB, γ 2.2) against this linear EXR.
    #[arg(long)]
    pub compare: Option<PathBuf>,
    /// Output EXR (linear); a gamma-encoded PNG is written beside it.
    #[arg(long)]
    pub out: PathBuf,
}

#[derive(Args)]
pub struct MeshArgs {
    #[arg(long)]
    pub bundle: PathBuf,
    /// Boundary angle threshold in degrees (the reference's code uses 6).
    #[arg(long, default_value_t = 6.0)]
    pub angle: f64,
    #[arg(long)]
    pub out: PathBuf,
}

#[derive(Args)]
pub struct SynthArgs {
    /// Scene seed (layout, objects, materials, lighting).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Image side in pixels.
    #[arg(long, default_value_t = 512)]
    pub size: usize,
    /// Samples per pixel for the input image.
    #[arg(long, default_value_t = 256)]
    pub spp: u32,
    /// Output bundle folder.
    #[arg(long)]
    pub out: PathBuf,
    /// Write MatNet-like predictions (blurred, biased, noisy albedo; wrong
    /// roughness and metallic) instead of the ground truth.
    #[arg(long)]
    pub degrade: bool,
    /// Also write a relighting test: ground_truth/relight_envmap.hdr (a
    /// different sky) and ground_truth/relit_image.exr rendered under it
    /// with this many samples per pixel (0: none).
    #[arg(long, default_value_t = 0)]
    pub relight_spp: u32,
}

pub struct LoadedScene {
    pub scene: RenderScene,
    /// Building mesh and BVH.
    pub seconds: f64,
}

/// Builds mesh, BVH, materials and envmap for a bundle.
pub fn load_scene(
    bundle_dir: &Path,
    materials: MaterialSource,
    envmap: Option<&Path>,
    mesh_angle: f64,
    reference_compat: bool,
) -> Result<LoadedScene> {
    let bundle = Bundle::open(bundle_dir)?;
    let depth = bundle.load_depth()?;
    let maps = bundle.load_materials(materials)?;
    let env_path = match envmap {
        Some(p) => p.to_path_buf(),
        None => bundle.envmap_path().with_context(|| {
            format!(
                "{}: no best_results/envmap.hdr or ground_truth/envmap.hdr; pass --envmap FILE.hdr (or .exr)",
                bundle_dir.display()
            )
        })?,
    };
    let mut env_img = io::read_envmap(&env_path)?;
    if reference_compat {
        env_img = matflow_render::envmap::merge_seam_columns(&env_img);
    }
    let env = EnvMap::new(&env_img).with_context(|| format!("{}", env_path.display()))?;
    let t0 = Instant::now();
    let (scene, _) = scene_from_depth(&depth, &maps, env, mesh_angle)
        .with_context(|| format!("{}: building the scene", bundle_dir.display()))?;
    Ok(LoadedScene {
        scene,
        seconds: t0.elapsed().as_secs_f64(),
    })
}

pub fn progress_bar(total: u64, msg: &str) -> ProgressBar {
    let pb = ProgressBar::new(total);
    pb.set_style(
        ProgressStyle::with_template(
            "{msg} [{bar:40}] {pos}/{len} tiles, {elapsed} elapsed, eta {eta}",
        )
        .unwrap()
        .progress_chars("=> "),
    );
    pb.set_message(msg.to_string());
    pb
}

/// Renders with a progress bar; returns the output and its wall time in
/// seconds.
pub fn render_with_progress(
    scene: &RenderScene,
    opts: &RenderOptions,
    label: &str,
) -> (RenderOutput, f64) {
    let ts = opts.tile_size.max(1);
    let tiles = scene.camera.width.div_ceil(ts) * scene.camera.height.div_ceil(ts);
    let pb = progress_bar(tiles as u64, label);
    let t0 = Instant::now();
    let out = render_scene(scene, opts, &|d, _| pb.set_position(d as u64));
    pb.finish_and_clear();
    (out, t0.elapsed().as_secs_f64())
}

/// Writes `out` (EXR) and a PNG with the same stem.
pub fn write_outputs(out: &Path, img: &RgbImage) -> Result<PathBuf> {
    io::write_exr_rgb(out, img)?;
    let png = out.with_extension("png");
    io::write_png_gamma(&png, img)?;
    Ok(png)
}

pub fn render(a: RenderArgs) -> Result<()> {
    let t_all = Instant::now();
    let loaded = load_scene(
        &a.bundle,
        a.materials,
        a.envmap.as_deref(),
        a.mesh_angle,
        a.reference_compat,
    )?;
    let opts = RenderOptions {
        spp: a.spp,
        max_depth: a.depth,
        seed: a.seed,
        filter: a.filter,
        reference_compat: a.reference_compat,
        ..Default::default()
    };
    let est = matflow_nodes::render_seconds(
        Some((loaded.scene.camera.width, loaded.scene.camera.height)),
        a.spp as i64,
        a.depth as i64,
    );
    if !a.allow_expensive && est > matflow_engine::spec::EXPENSIVE_SECONDS {
        bail!(
            "{}: this render is estimated at {} on the reference 2-core machine; the limit \
             without --allow-expensive is {}. Lower --spp, or pass --allow-expensive",
            a.bundle.display(),
            crate::run::duration(est),
            crate::run::duration(matflow_engine::spec::EXPENSIVE_SECONDS)
        );
    }
    let (out, seconds) = render_with_progress(&loaded.scene, &opts, "render");
    let png = write_outputs(&a.out, &out.image)?;
    let s = out.stats;
    outln!(
        "rendered {}x{} at {} spp, depth {} in {:.2} s (mesh and BVH {:.2} s, total {:.2} s): {:.1} M rays, {:.2} Mrays/s -> {}, {}",
        loaded.scene.camera.width,
        loaded.scene.camera.height,
        a.spp,
        a.depth,
        seconds,
        loaded.seconds,
        t_all.elapsed().as_secs_f64(),
        s.total_rays() as f64 / 1e6,
        s.total_rays() as f64 / 1e6 / seconds.max(1e-9),
        a.out.display(),
        png.display()
    );
    if s.discarded_samples > 0 {
        eprintln!(
            "warning: {} sample(s) with NaN/Inf radiance were dropped",
            s.discarded_samples
        );
    }
    if let Some(c) = &a.compare {
        let reference = io::read_exr_rgb(c)?;
        if !reference.same_size(&out.image) {
            bail!("{}: size differs from the render", c.display());
        }
        outln!(
            "PSNR (sRGB, gamma 2.2) against {}: {:.2} dB",
            c.display(),
            psnr_gamma(&out.image, &reference)
        );
    }
    Ok(())
}

pub fn mesh(a: MeshArgs) -> Result<()> {
    let bundle = Bundle::open(&a.bundle)?;
    let depth = bundle.load_depth()?;
    let t0 = Instant::now();
    let (cam, m) = mesh_for_view(&depth, a.angle)?;
    let secs = t0.elapsed().as_secs_f64();
    let mut buf = Vec::new();
    m.mesh.write_ply(&mut buf, cam.width, cam.height)?;
    io::write_atomic(&a.out, &buf)?;
    outln!(
        "mesh: {} vertices, {} triangles in {:.3} s ({} boundary pixels moved, {} copies, {} direct, {} after 1 copy, {} after 2, {} dropped) -> {}",
        m.mesh.vertex_count(),
        m.mesh.triangle_count(),
        secs,
        m.stats.boundary_pixels,
        m.stats.copies,
        m.stats.emitted_direct,
        m.stats.emitted_one_copy,
        m.stats.emitted_two_copies,
        m.stats.dropped,
        a.out.display()
    );
    Ok(())
}

pub fn synth(a: SynthArgs) -> Result<()> {
    if a.size < 8 || a.size > 8192 {
        bail!("--size {} is out of range (8..=8192)", a.size);
    }
    let t0 = Instant::now();
    let s = matflow_scene::synthetic::generate(a.seed, a.size, a.size);
    let bundle = Bundle::create(&a.out)?;
    bundle.write_depth(&s.depth)?;
    if a.degrade {
        bundle.write_predictions(&matflow_scene::synthetic::degrade(&s.maps, a.seed))?;
    } else {
        bundle.write_predictions(&s.maps)?;
    }
    bundle.write_materials("ground_truth", &s.maps)?;
    io::write_hdr(&bundle.path("ground_truth/envmap.hdr"), &s.envmap)?;
    // Render the input photo with the true materials and lighting.
    let loaded = load_scene(&a.out, MaterialSource::GroundTruth, None, 6.0, false)?;
    let opts = RenderOptions {
        spp: a.spp,
        seed: a.seed,
        ..Default::default()
    };
    let (out, seconds) = render_with_progress(&loaded.scene, &opts, "render gt_image");
    io::write_exr_rgb(&bundle.path("gt_image.exr"), &out.image)?;
    io::write_png_gamma(&bundle.path("gt_image.png"), &out.image)?;
    if a.relight_spp > 0 {
        let env_path = bundle.path("ground_truth/relight_envmap.hdr");
        io::write_hdr(
            &env_path,
            &matflow_scene::synthetic::relight_sky(a.seed, 32, 16),
        )?;
        let relit = load_scene(
            &a.out,
            MaterialSource::GroundTruth,
            Some(&env_path),
            6.0,
            false,
        )?;
        let opts = RenderOptions {
            spp: a.relight_spp,
            seed: a.seed ^ 0x7e11,
            ..Default::default()
        };
        let (img, _) = render_with_progress(&relit.scene, &opts, "render relit_image");
        io::write_exr_rgb(&bundle.path("ground_truth/relit_image.exr"), &img.image)?;
        io::write_png_gamma(&bundle.path("ground_truth/relit_image.png"), &img.image)?;
    }
    outln!(
        "synthetic scene {} ({}x{}): {} triangles, gt_image at {} spp in {:.2} s (total {:.2} s) -> {}",
        a.seed,
        a.size,
        a.size,
        loaded.scene.mesh.triangle_count(),
        a.spp,
        seconds,
        t0.elapsed().as_secs_f64(),
        a.out.display()
    );
    Ok(())
}
