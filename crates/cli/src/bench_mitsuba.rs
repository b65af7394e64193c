//! The side-by-side comparison with Mitsuba 3 (benchmarks only; Mitsuba is
//! never a dependency of matflow). `export_scene` writes exactly the scene
//! matflow renders — mesh, envmap texels, screen-space material maps and
//! camera — to a folder that `bench/mitsuba_render.py` turns into a Mitsuba
//! scene with the same BRDF, sampling and filter.

use std::io::Write;
use std::path::Path;

use anyhow::{Context, Result};
use matflow_render::RenderScene;
use matflow_scene::Image;

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
