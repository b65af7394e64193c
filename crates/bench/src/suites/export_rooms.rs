//! `matflow-bench export-rooms`: a `rooms` dataset's scenes written for
//! another renderer, beside their unpacked bundles, so that the same
//! scenes can be photographed by Mitsuba 3 (`scripts/mitsuba_rooms.py`)
//! and the prediction network scored on both photographs of each
//! (`matflow-bench matnet --scenes`): what of its gap on other renderers'
//! scenes is the renderer's look, and what is the scenes' content.
//!
//! Each sample's scene is rebuilt from its manifest entry (kind and
//! `room_seed`: the generator is a pure function of them) and written as
//! `KEY/mitsuba/`:
//!
//! * `scene.json`: image size, horizontal field of view, the exposure
//!   (EV) the dataset's photo got, the objects and the lamps;
//! * `obj-NNN.ply`: each object's triangles in camera space (camera at the
//!   origin looking down −z, +y up), binary little-endian, with the
//!   object's vertex normals where it has them and, for textured objects,
//!   texture coordinates with v = 0 at the texture's top row (Mitsuba's;
//!   matflow's textures have v = 0 at the bottom);
//! * `tex-NNN.exr`: a textured object's texture times its albedo (linear);
//! * `envmap.exr`: the sky in the camera's frame (matflow's lat-long
//!   layout, which is Mitsuba's), unexposed, at the dataset's width.
//!
//! `KEY/` itself is the sample's bundle (`matflow dataset unpack`) less
//! `gt_image.png`, so that both photographs of a scene reach the network
//! the same way (the linear EXR written as 8-bit sRGB), and `validation.json`
//! lists the kinds.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::Args;
use glam::{Vec2, Vec3};
use matflow_procgen::envgen::procedural_envmap;
use matflow_procgen::framing::Framing;
use matflow_procgen::rooms::{scene_framed, SceneKind};
use matflow_render::envmap::rotated;
use matflow_render::scene::Surface;
use matflow_scene::lamps::LampAt;
use matflow_scene::{io, Camera, RgbImage};

use crate::suites::ply::write_ply;

#[derive(Args)]
pub struct ExportRoomsArgs {
    /// A `rooms` dataset folder (`matflow dataset ... --out DIR`).
    #[arg(long)]
    pub dataset: PathBuf,
    /// Where the bundles and the scenes go.
    #[arg(long)]
    pub out: PathBuf,
    /// Export only the first N samples.
    #[arg(long)]
    pub samples: Option<usize>,
}

pub fn export_rooms(a: ExportRoomsArgs) -> Result<()> {
    let desc_path = a.dataset.join("dataset.json");
    let desc: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(&desc_path).with_context(|| desc_path.display().to_string())?,
    )
    .with_context(|| desc_path.display().to_string())?;
    if desc["generator"].as_str() != Some("rooms") {
        bail!(
            "{}: generator {:?}, not rooms",
            desc_path.display(),
            desc["generator"]
        );
    }
    let ew = desc["params"]["envmap_width"]
        .as_u64()
        .unwrap_or(128)
        .max(8) as usize;
    let manifest = a.dataset.join("manifest.jsonl");
    let text =
        std::fs::read_to_string(&manifest).with_context(|| manifest.display().to_string())?;
    std::fs::create_dir_all(&a.out).with_context(|| a.out.display().to_string())?;
    let mut kinds = serde_json::Map::new();
    for (line_no, line) in text.lines().enumerate() {
        if a.samples.is_some_and(|n| kinds.len() >= n) {
            break;
        }
        let at = || format!("{}:{}", manifest.display(), line_no + 1);
        let v: serde_json::Value = serde_json::from_str(line).with_context(at)?;
        let key = v["key"]
            .as_str()
            .with_context(|| format!("{}: no key", at()))?;
        let kind_name = v["params"]["kind"].as_str().unwrap_or("open");
        let kind = SceneKind::from_name(kind_name)
            .with_context(|| format!("{}: kind {kind_name:?}", at()))?;
        let seed = v["params"]["room_seed"]
            .as_u64()
            .with_context(|| format!("{}: no params.room_seed", at()))?;
        let size = v["params"]["size"].as_u64().unwrap_or(256) as usize;
        let framing_name = v["params"]["framing"].as_str().unwrap_or("drawn");
        let framing = Framing::from_name(framing_name)
            .with_context(|| format!("{}: framing {framing_name:?}", at()))?;
        let dir = a.out.join(key);
        matflow_dataset::shards::unpack(&a.dataset, key, &dir)
            .with_context(|| format!("unpacking {key}"))?;
        let png = dir.join("gt_image.png");
        if png.is_file() {
            std::fs::remove_file(&png).with_context(|| png.display().to_string())?;
        }
        export_scene(kind, seed, framing, size, ew, &dir.join("mitsuba"))
            .with_context(|| format!("exporting {key}"))?;
        kinds.insert(key.to_string(), kind_name.into());
    }
    let n = kinds.len();
    let index = serde_json::json!({
        "generator": "matflow-bench export-rooms",
        "dataset": a.dataset.display().to_string(),
        "kinds": kinds,
    });
    io::write_atomic(
        &a.out.join("validation.json"),
        serde_json::to_string_pretty(&index)?.as_bytes(),
    )?;
    outln!("{n} scenes exported to {}", a.out.display());
    Ok(())
}

/// Writes the scene of (kind, seed, framing) as `scene.json`, PLY meshes, textures
/// and the sky into `to`.
fn export_scene(
    kind: SceneKind,
    seed: u64,
    framing: Framing,
    size: usize,
    ew: usize,
    to: &Path,
) -> Result<()> {
    std::fs::create_dir_all(to)?;
    let r = scene_framed(kind, seed, framing);
    let world = procedural_envmap(r.env_kind, r.env_seed, ew, (ew / 2).max(2));
    io::write_exr_rgb(&to.join("envmap.exr"), &rotated(&world, r.to_world))?;
    let mut objects = vec![];
    for (k, o) in r.objects.iter().enumerate() {
        let ply = format!("obj-{k:03}.ply");
        let textured = o.texture.is_some() && o.uvs.len() == o.mesh.positions.len();
        let normals: Vec<Vec3> = o.normals.iter().map(|n| n.normalize_or(Vec3::Z)).collect();
        // Mitsuba's v runs down the texture, matflow's up.
        let uvs: Vec<Vec2> = if textured {
            o.uvs.iter().map(|uv| Vec2::new(uv.x, 1.0 - uv.y)).collect()
        } else {
            vec![]
        };
        write_ply(&to.join(&ply), &o.mesh, &normals, &uvs)?;
        let mut obj = serde_json::json!({
            "ply": ply,
            "vertex_normals": o.normals.len() == o.mesh.positions.len(),
            "surface": surface_json(&o.surface),
        });
        if let (true, Some(t)) = (textured, &o.texture) {
            let tex = format!("tex-{k:03}.exr");
            let tint = match o.surface {
                Surface::Principled(m) => m.albedo,
                Surface::Diffuse(a) => a,
                Surface::Glass(_) => Vec3::ONE,
            };
            let baked = RgbImage {
                width: t.width,
                height: t.height,
                data: t.data.iter().map(|&c| c * tint).collect(),
            };
            io::write_exr_rgb(&to.join(&tex), &baked)?;
            obj["texture"] = tex.into();
        }
        objects.push(obj);
    }
    let lamps: Vec<serde_json::Value> = r
        .lamps
        .iter()
        .filter(|l| l.is_valid())
        .map(|l| {
            let i = l.intensity.to_array();
            match l.at {
                LampAt::Point(p) => serde_json::json!({"point": p.to_array(), "intensity": i}),
                LampAt::Distant(d) => serde_json::json!({"distant": d.to_array(), "irradiance": i}),
            }
        })
        .collect();
    let cam = Camera::new(size, size);
    let desc = serde_json::json!({
        "kind": kind.name(),
        "room_seed": seed,
        "size": size,
        "fov_x_deg": cam.fov_x_deg,
        "exposure_ev": r.exposure,
        "envmap": "envmap.exr",
        "objects": objects,
        "lamps": lamps,
    });
    io::write_atomic(
        &to.join("scene.json"),
        serde_json::to_string_pretty(&desc)?.as_bytes(),
    )?;
    Ok(())
}

fn surface_json(s: &Surface) -> serde_json::Value {
    match s.sanitized() {
        Surface::Principled(m) => serde_json::json!({
            "type": "principled",
            "albedo": m.albedo.to_array(),
            "roughness": m.roughness,
            "metallic": m.metallic,
        }),
        Surface::Diffuse(a) => serde_json::json!({"type": "diffuse", "albedo": a.to_array()}),
        Surface::Glass(g) => serde_json::json!({
            "type": "glass",
            "eta": g.eta,
            "transmission": g.transmission,
            "tint": g.tint.to_array(),
            "roughness": g.roughness,
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The vertex count, the float properties per vertex and the face
    /// count of a PLY this module wrote, and the vertices.
    fn read_ply(path: &Path) -> (usize, Vec<String>, usize, Vec<f32>) {
        let b = std::fs::read(path).unwrap();
        let end = b.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
        let head = std::str::from_utf8(&b[..end]).unwrap();
        let count = |what: &str| -> usize {
            head.lines()
                .find_map(|l| l.strip_prefix(&format!("element {what} ")))
                .unwrap()
                .parse()
                .unwrap()
        };
        let props: Vec<String> = head
            .lines()
            .filter_map(|l| l.strip_prefix("property float "))
            .map(str::to_string)
            .collect();
        let (nv, nf) = (count("vertex"), count("face"));
        let floats = b[end..end + 4 * nv * props.len()]
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        assert_eq!(b.len(), end + 4 * nv * props.len() + 13 * nf, "size");
        (nv, props, nf, floats)
    }

    #[test]
    fn an_exported_scene_is_the_generators_scene() {
        let d = std::env::temp_dir().join(format!("matflow-export-rooms-{}", std::process::id()));
        let mut textured = 0;
        for (kind, seed, framing) in [
            (SceneKind::Closed, 5, Framing::Drawn),
            (SceneKind::Stage, 8, Framing::Drawn),
            (SceneKind::Open, 2, Framing::Near),
        ] {
            let to = d.join(format!("{}-{seed}", kind.name()));
            export_scene(kind, seed, framing, 32, 16, &to).unwrap();
            let r = scene_framed(kind, seed, framing);
            let desc: serde_json::Value =
                serde_json::from_str(&std::fs::read_to_string(to.join("scene.json")).unwrap())
                    .unwrap();
            let objs = desc["objects"].as_array().unwrap();
            assert_eq!(objs.len(), r.objects.len());
            assert_eq!(desc["lamps"].as_array().unwrap().len(), r.lamps.len());
            assert_eq!(desc["exposure_ev"].as_f64().unwrap() as f32, r.exposure);
            let env = io::read_exr_rgb(&to.join("envmap.exr")).unwrap();
            assert_eq!((env.width, env.height), (16, 8));
            for (o, j) in r.objects.iter().zip(objs) {
                let (nv, props, nf, v) = read_ply(&to.join(j["ply"].as_str().unwrap()));
                assert_eq!((nv, nf), (o.mesh.positions.len(), o.mesh.indices.len()));
                let k = props.len();
                assert_eq!(
                    k,
                    3 + 3 * (j["vertex_normals"] == true) as usize
                        + 2 * j.get("texture").is_some() as usize
                );
                for (i, p) in o.mesh.positions.iter().enumerate() {
                    assert_eq!(&v[i * k..i * k + 3], &p.to_array()[..]);
                }
                if let Some(t) = j.get("texture") {
                    textured += 1;
                    assert!(to.join(t.as_str().unwrap()).is_file());
                    // Mitsuba's v runs down the texture: 1 − matflow's.
                    assert_eq!(v[k - 1], 1.0 - o.uvs[0].y);
                }
            }
        }
        assert!(textured > 0, "no textured object to check");
        std::fs::remove_dir_all(&d).ok();
    }
}
