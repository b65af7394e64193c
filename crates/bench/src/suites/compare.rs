//! The side-by-side comparison with Mitsuba 3 (benchmarks only; Mitsuba is
//! never a dependency of matflow). `export_scene` writes exactly the scene
//! matflow renders — mesh, envmap texels, screen-space material maps and
//! camera — to a folder that `crates/bench/scripts/mitsuba_render.py` turns into a Mitsuba
//! scene with the same BRDF, sampling and filter, and the ray sets that
//! `crates/bench/scripts/embree_rays.c` traces with Embree. Both run only when installed
//! (`pip install mitsuba` with `apt-get install libllvm19`;
//! `apt-get install libembree-dev`).

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use anyhow::{bail, Context, Result};
use matflow_render::{Crop, RenderScene};
use matflow_scene::{Image, RgbImage};
use serde::Deserialize;

/// Writes `mesh.ply` (binary little-endian, camera space), `envmap.exr`
/// (the texels matflow samples, Mitsuba's `envmap` orientation), the
/// material maps as raw little-endian f32 (`albedo.f32` H×W×3,
/// `roughness.f32` and `metallic.f32` H×W, already sanitised) and
/// `scene.json` (resolution, focal length and principal point in pixels).
pub fn export_scene(scene: &RenderScene, dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let mesh = &scene.mesh;
    let mut ply = Vec::with_capacity(64 + mesh.positions.len() * 12 + mesh.indices.len() * 13);
    write!(
        ply,
        "ply\nformat binary_little_endian 1.0\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nelement face {}\nproperty list uchar int vertex_indices\nend_header\n",
        mesh.positions.len(),
        mesh.indices.len()
    )?;
    for p in &mesh.positions {
        for c in [p.x, p.y, p.z] {
            ply.extend_from_slice(&c.to_le_bytes());
        }
    }
    for t in &mesh.indices {
        ply.push(3);
        for k in t {
            ply.extend_from_slice(&(*k as i32).to_le_bytes());
        }
    }
    std::fs::write(dir.join("mesh.ply"), ply)?;

    let env = &scene.env;
    let env_img = Image::from_vec(env.width(), env.height(), env.texels().to_vec());
    matflow_scene::io::write_exr_rgb(&dir.join("envmap.exr"), &env_img)?;

    let mut albedo = Vec::with_capacity(scene.materials.len() * 12);
    let mut rough = Vec::with_capacity(scene.materials.len() * 4);
    let mut metal = Vec::with_capacity(scene.materials.len() * 4);
    for m in &scene.materials {
        for c in [m.albedo.x, m.albedo.y, m.albedo.z] {
            albedo.extend_from_slice(&c.to_le_bytes());
        }
        rough.extend_from_slice(&m.roughness.to_le_bytes());
        metal.extend_from_slice(&m.metallic.to_le_bytes());
    }
    std::fs::write(dir.join("albedo.f32"), albedo)?;
    std::fs::write(dir.join("roughness.f32"), rough)?;
    std::fs::write(dir.join("metallic.f32"), metal)?;

    let cam = &scene.camera;
    let pp = cam.principal_point();
    let json = format!(
        "{{\"width\": {}, \"height\": {}, \"focal\": {}, \"cx\": {}, \"cy\": {}, \"fov_x_deg\": {}}}\n",
        cam.width,
        cam.height,
        cam.focal(),
        pp.x,
        pp.y,
        (2.0 * ((cam.width as f64 * 0.5) / cam.focal() as f64).atan()).to_degrees()
    );
    std::fs::write(dir.join("scene.json"), json)?;
    Ok(())
}

/// Rays as little-endian f32 records (ox, oy, oz, dx, dy, dz), for the
/// Embree throughput program.
pub fn write_rays(path: &Path, rays: &[(glam::Vec3, glam::Vec3)]) -> Result<()> {
    let mut b = Vec::with_capacity(rays.len() * 24);
    for (o, d) in rays {
        for c in [o.x, o.y, o.z, d.x, d.y, d.z] {
            b.extend_from_slice(&c.to_le_bytes());
        }
    }
    std::fs::write(path, b).with_context(|| format!("writing {}", path.display()))
}

/// Where the comparison programs live: this crate's `scripts/`.
pub fn default_bench_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts")
}

/// Whether `python3` can import Mitsuba (the comparison runs only then).
pub fn mitsuba_installed() -> bool {
    Command::new("python3")
        .args(["-c", "import mitsuba"])
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success())
}

/// Timings of `crates/bench/scripts/mitsuba_render.py`.
#[derive(Debug, Deserialize)]
pub struct MitsubaRun {
    pub renderer: String,
    pub median_s: f64,
    pub first_s: f64,
}

/// Renders the exported scene with Mitsuba: `runs` timed renders after a
/// first (compiling) one; the last image is written to `out` when given.
#[allow(clippy::too_many_arguments)]
pub fn run_mitsuba(
    bench_dir: &Path,
    scene_dir: &Path,
    spp: u32,
    depth: u32,
    runs: usize,
    threads: usize,
    seed: u64,
    crop: Option<Crop>,
    out: Option<&Path>,
) -> Result<MitsubaRun> {
    let script = bench_dir.join("mitsuba_render.py");
    // Dr.Jit 1.5 hangs in its first kernel with `set_thread_count(1)`
    // (seen here: both threads asleep on a futex); one core is given as
    // two threads pinned to CPU 0 instead.
    let mut cmd = if threads == 1 {
        let mut c = Command::new("taskset");
        c.args(["-c", "0", "python3"]);
        c
    } else {
        Command::new("python3")
    };
    cmd.arg(&script)
        .arg(scene_dir)
        .args(["--spp", &spp.to_string()])
        .args(["--depth", &depth.to_string()])
        .args(["--runs", &runs.to_string()])
        .args(["--threads", &threads.max(2).to_string()])
        .args(["--seed", &seed.to_string()]);
    if let Some(c) = crop {
        cmd.arg("--crop");
        for v in [c.x, c.y, c.width, c.height] {
            cmd.arg(v.to_string());
        }
    }
    if let Some(o) = out {
        cmd.arg("--out").arg(o);
    }
    json_of(cmd, &script)
}

/// Embree's numbers from `crates/bench/scripts/embree_rays.c`.
#[derive(Debug, Deserialize)]
pub struct EmbreeRun {
    pub embree: String,
    pub build_ms: f64,
    pub primary_hit_mrays: f64,
    pub incoherent_hit_mrays: f64,
    pub incoherent_occl_mrays: f64,
    /// The incoherent rays as streams of 1024 (rtcIntersect1M /
    /// rtcOccluded1M, incoherent flag).
    pub incoherent_hit_stream_mrays: f64,
    pub incoherent_occl_stream_mrays: f64,
}

/// Compiles and runs the Embree throughput program on the exported mesh
/// and ray sets; `None` when Embree's headers are not installed
/// (`apt-get install libembree-dev`).
pub fn run_embree(
    bench_dir: &Path,
    scene_dir: &Path,
    work: &Path,
    threads: usize,
    runs: usize,
) -> Result<Option<EmbreeRun>> {
    if !Path::new("/usr/include/embree3/rtcore.h").is_file() {
        return Ok(None);
    }
    let src = bench_dir.join("embree_rays.c");
    let exe = work.join("embree_rays");
    let st = Command::new("cc")
        .args(["-O3", "-march=native", "-o"])
        .arg(&exe)
        .arg(&src)
        .args(["-lembree3", "-lpthread"])
        .status()
        .with_context(|| format!("compiling {} with cc", src.display()))?;
    if !st.success() {
        bail!("compiling {} failed ({st})", src.display());
    }
    let mut cmd = Command::new(&exe);
    cmd.arg(scene_dir)
        .args(["--threads", &threads.to_string()])
        .args(["--runs", &runs.to_string()]);
    json_of(cmd, &exe).map(Some)
}

/// Runs a comparison program and parses the JSON line it ends its output
/// with.
fn json_of<T: for<'de> Deserialize<'de>>(mut cmd: Command, what: &Path) -> Result<T> {
    let out = cmd
        .stderr(Stdio::piped())
        .output()
        .with_context(|| format!("running {}", what.display()))?;
    if !out.status.success() {
        let err = String::from_utf8_lossy(&out.stderr);
        let tail: Vec<&str> = err.lines().rev().take(12).collect();
        bail!(
            "{} failed ({}):\n{}",
            what.display(),
            out.status,
            tail.into_iter().rev().collect::<Vec<_>>().join("\n")
        );
    }
    let text = String::from_utf8_lossy(&out.stdout);
    let line = text
        .lines()
        .rev()
        .find(|l| l.trim_start().starts_with('{'))
        .with_context(|| format!("{} printed no JSON line", what.display()))?;
    serde_json::from_str(line).with_context(|| format!("{}: bad JSON {line}", what.display()))
}

/// Root-mean-square difference of two images over the pixels at least
/// `margin` from the border (crops differ from full renders there).
pub fn rmse_interior(a: &RgbImage, b: &RgbImage, margin: usize) -> f64 {
    let (w, h) = (a.width.min(b.width), a.height.min(b.height));
    let (mut s, mut n) = (0.0f64, 0usize);
    for y in margin..h.saturating_sub(margin) {
        for x in margin..w.saturating_sub(margin) {
            let d = a.data[y * a.width + x] - b.data[y * b.width + x];
            s += (d.x as f64).powi(2) + (d.y as f64).powi(2) + (d.z as f64).powi(2);
            n += 3;
        }
    }
    (s / n.max(1) as f64).sqrt()
}

/// Time to reach `target` error, interpolating log(time) against
/// log(error) between the measured (seconds, error) points (extrapolating
/// from the nearest two, with the Monte Carlo slope −2 when there is one).
pub fn time_to_error(points: &[(f64, f64)], target: f64) -> f64 {
    let mut p: Vec<(f64, f64)> = points
        .iter()
        .copied()
        .filter(|(t, e)| *t > 0.0 && *e > 0.0)
        .collect();
    p.sort_by(|a, b| b.1.total_cmp(&a.1));
    match p.len() {
        0 => f64::NAN,
        1 => p[0].0 * (p[0].1 / target).powi(2),
        _ => {
            let k = p
                .windows(2)
                .position(|w| w[0].1 >= target && target >= w[1].1)
                .unwrap_or(if target > p[0].1 { 0 } else { p.len() - 2 });
            let ((t0, e0), (t1, e1)) = (p[k], p[k + 1]);
            let slope = (t1.ln() - t0.ln()) / (e1.ln() - e0.ln());
            (t0.ln() + slope * (target.ln() - e0.ln())).exp()
        }
    }
}
