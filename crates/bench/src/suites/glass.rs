//! `matflow-bench glass`: glass against Mitsuba 3. A glass jug (smooth,
//! then rough) standing on a Lambertian floor under a procedural sky with a
//! sun, rendered by matflow and by Mitsuba's own `dielectric` /
//! `roughdielectric`, `diffuse` and `path` (`crates/bench/scripts/mitsuba_glass.py`), both
//! with a box filter and paths long enough that neither truncates what
//! matters. Each renderer also renders a second seed, so the comparison
//! says how much of the difference is noise: matflow vs Mitsuba PSNR next
//! to each renderer's seed-to-seed PSNR, and the mean radiance ratio.

use std::path::PathBuf;
use std::process::Command;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::Args;
use glam::Vec3;
use matflow_geom::TriMesh;
use matflow_procgen::shapes;
use matflow_render::{
    render, Dielectric, EnvMap, PixelFilter, RenderOptions, RenderScene, SceneObject, Surface,
};
use matflow_scene::metrics::psnr_gamma;
use matflow_scene::{io, Camera, Image, MaterialMaps, RgbImage};

use crate::suites::compare::{default_bench_dir, mitsuba_installed};
use crate::suites::ply::write_ply;

#[derive(Args)]
pub struct BenchGlassArgs {
    /// Image side in pixels.
    #[arg(long, default_value_t = 128)]
    pub size: usize,
    /// Samples per pixel of every render.
    #[arg(long, default_value_t = 1024)]
    pub spp: u32,
    /// Working folder (scene export and renders).
    #[arg(long, default_value = "/tmp/matflow-bench-glass")]
    pub work: PathBuf,
}

fn mean(img: &RgbImage) -> Vec3 {
    let s: glam::DVec3 = img.data.iter().map(|v| v.as_dvec3()).sum();
    (s / img.data.len() as f64).as_vec3()
}

pub fn bench_glass(a: BenchGlassArgs) -> Result<()> {
    if !mitsuba_installed() {
        bail!("bench glass compares with Mitsuba 3: pip install mitsuba (and apt-get install libllvm19)");
    }
    let n = a.size;
    std::fs::create_dir_all(&a.work)?;
    let cam = Camera::new(n, n);
    let env_img = matflow_procgen::synthetic::generate(1, 16, 16).envmap;
    let env = EnvMap::new(&env_img)?;
    io::write_exr_rgb(
        &a.work.join("envmap.exr"),
        &Image::from_vec(env.width(), env.height(), env.texels().to_vec()),
    )?;
    // The floor: a quad at y = −1 under the camera.
    let floor = TriMesh {
        positions: vec![
            Vec3::new(-30.0, -1.0, 2.0),
            Vec3::new(30.0, -1.0, 2.0),
            Vec3::new(30.0, -1.0, -60.0),
            Vec3::new(-30.0, -1.0, -60.0),
        ],
        indices: vec![[0, 1, 2], [0, 2, 3]],
        ..Default::default()
    };
    let jug = shapes::jug(96).transformed(1.8, Vec3::new(0.0, -1.0, -5.5));
    write_ply(&a.work.join("floor.ply"), &floor, &[], &[])?;
    write_ply(&a.work.join("jug.ply"), &jug.mesh, &jug.normals, &[])?;
    let threads = rayon::current_num_threads();
    outln!(
        "bench glass: a glass jug on a Lambertian floor under a sky with a sun, {n}x{n}, {} spp, box filter, {threads} thread(s)",
        a.spp
    );
    outln!("| jug | matflow s | Mitsuba s | PSNR matflow vs Mitsuba | PSNR matflow seed 0 vs 1 | PSNR Mitsuba seed 0 vs 1 | mean ratio matflow/Mitsuba (R, G, B) |");
    outln!("|---|---|---|---|---|---|---|");
    for (label, roughness) in [
        ("smooth glass (η 1.5)", 0.0f32),
        ("rough glass (η 1.5, roughness 0.3)", 0.3),
    ] {
        let glass = Dielectric {
            eta: 1.5,
            roughness,
            ..Default::default()
        };
        let objects = [
            SceneObject {
                mesh: floor.clone(),
                normals: Vec::new(),
                surface: Surface::Diffuse(Vec3::splat(0.6)),
                uvs: Vec::new(),
                texture: None,
            },
            SceneObject {
                mesh: jug.mesh.clone(),
                normals: jug.normals.clone(),
                surface: Surface::Glass(glass),
                uvs: Vec::new(),
                texture: None,
            },
        ];
        let maps = MaterialMaps::uniform(n, n, Vec3::splat(0.5), 1.0, 0.0);
        let scene =
            RenderScene::with_objects(cam, TriMesh::default(), &maps, env.clone(), &objects)?;
        let mut ours = Vec::new();
        let mut our_s = 0.0;
        for seed in [0u64, 1] {
            let opts = RenderOptions {
                spp: a.spp,
                max_depth: 32,
                glass_depth: 64,
                seed,
                filter: PixelFilter::Box,
                ..Default::default()
            };
            let t = Instant::now();
            ours.push(render(&scene, &opts, &|_, _| {}).image);
            our_s += t.elapsed().as_secs_f64() / 2.0;
        }
        let bsdf = if roughness == 0.0 {
            r#"{"type": "dielectric", "ior": 1.5, "transmittance": [1, 1, 1]}"#.to_string()
        } else {
            format!(
                r#"{{"type": "roughdielectric", "ior": 1.5, "alpha": {}, "transmittance": [1, 1, 1]}}"#,
                roughness * roughness
            )
        };
        let json = format!(
            r#"{{"width": {n}, "height": {n}, "fov_x_deg": {}, "objects": [{{"ply": "floor.ply", "bsdf": {{"type": "diffuse", "albedo": [0.6, 0.6, 0.6]}}}}, {{"ply": "jug.ply", "vertex_normals": true, "bsdf": {bsdf}}}]}}"#,
            cam.fov_x_deg
        );
        std::fs::write(a.work.join("scene.json"), json)?;
        let mut theirs = Vec::new();
        let mut their_s = 0.0;
        for seed in [0u64, 1] {
            let out = a.work.join(format!("mitsuba-{roughness}-{seed}.exr"));
            let script = default_bench_dir().join("mitsuba_glass.py");
            let o = Command::new("python3")
                .arg(&script)
                .arg(&a.work)
                .args([
                    "--spp",
                    &a.spp.to_string(),
                    "--depth",
                    "96",
                    "--seed",
                    &seed.to_string(),
                ])
                .args(["--threads", &threads.to_string()])
                .arg("--out")
                .arg(&out)
                .output()
                .with_context(|| format!("running {}", script.display()))?;
            if !o.status.success() {
                bail!(
                    "{} failed:\n{}",
                    script.display(),
                    String::from_utf8_lossy(&o.stderr)
                );
            }
            let line = String::from_utf8_lossy(&o.stdout);
            let v: serde_json::Value = serde_json::from_str(line.lines().last().unwrap_or("{}"))
                .with_context(|| format!("{}: no JSON line", script.display()))?;
            their_s += v["render_s"].as_f64().unwrap_or(f64::NAN) / 2.0;
            theirs.push(io::read_exr_rgb(&out)?);
        }
        io::write_exr_rgb(&a.work.join(format!("matflow-{roughness}.exr")), &ours[0])?;
        io::write_png_gamma(&a.work.join(format!("matflow-{roughness}.png")), &ours[0])?;
        io::write_png_gamma(&a.work.join(format!("mitsuba-{roughness}.png")), &theirs[0])?;
        let (m, t) = (mean(&ours[0]), mean(&theirs[0]));
        let r = m / t;
        outln!(
            "| {label} | {our_s:.2} | {their_s:.2} | {:.2} dB | {:.2} dB | {:.2} dB | {:.4}, {:.4}, {:.4} |",
            psnr_gamma(&ours[0], &theirs[0]),
            psnr_gamma(&ours[0], &ours[1]),
            psnr_gamma(&theirs[0], &theirs[1]),
            r.x,
            r.y,
            r.z
        );
    }
    outln!("images: {}", a.work.display());
    Ok(())
}
