//! A studio session: a pipeline in a folder of its own (`session.yaml`),
//! run by the same engine and cache as `matflow run`, and what its scene
//! stage made, as images a page can show.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use matflow_engine::exec::Silent;
use matflow_engine::{run_pipeline, LocalExecutor, Store, Tiered};
use matflow_nodes::SceneData;
use matflow_scene::{GrayImage, RgbImage};

/// What went wrong opening or running a session.
#[derive(Debug, thiserror::Error)]
pub enum SessionError {
    #[error("{0}: not a photo (.png, .jpg, .jpeg, .exr), a bundle folder or a pipeline (.yaml)")]
    Input(PathBuf),
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{0}")]
    Pipeline(String),
}

/// The pipeline a session starts from: a photo is predicted (`matnet`), a
/// bundle read as it is (`bundle`, its predictions), a pipeline file taken
/// whole. Its scene stage is named `scene`.
pub fn starting_pipeline(input: &Path) -> Result<String, SessionError> {
    let quoted = serde_json::to_string(&input.display().to_string()).unwrap_or_default();
    let ext = input
        .extension()
        .map(|e| e.to_string_lossy().to_lowercase())
        .unwrap_or_default();
    if input.is_dir() {
        return Ok(format!(
            "pipeline: studio\noutputs: [scene]\nstages:\n  scene:\n    kind: bundle\n    path: {quoted}\n    materials: pred\n"
        ));
    }
    match ext.as_str() {
        "png" | "jpg" | "jpeg" | "exr" => Ok(format!(
            "pipeline: studio\noutputs: [scene]\nstages:\n  scene:\n    kind: matnet\n    photo: {quoted}\n"
        )),
        "yaml" | "yml" => std::fs::read_to_string(input).map_err(|source| SessionError::Io {
            path: input.to_path_buf(),
            source,
        }),
        _ => Err(SessionError::Input(input.to_path_buf())),
    }
}

/// A session's images: the photo and the scene's maps, each as a PNG.
#[derive(Default)]
pub struct Maps {
    pub images: Vec<(&'static str, Vec<u8>)>,
    pub width: usize,
    pub height: usize,
}

/// The names of the images a session shows, in the page's order.
pub const MAP_NAMES: [&str; 6] = [
    "photo",
    "albedo",
    "roughness",
    "metallic",
    "normal",
    "depth",
];

/// Runs the session's pipeline (`session.yaml` in `dir`) with `cache`
/// and returns its scene's images and the run's one-line summary.
pub fn run(dir: &Path, cache: &Path) -> Result<(Maps, String), SessionError> {
    let file = dir.join("session.yaml");
    let reg = matflow_nodes::registry();
    let p = matflow_engine::spec::load(&file, &reg, &[])
        .map_err(|e| SessionError::Pipeline(e.to_string()))?;
    let store = Arc::new(Tiered::new(
        Store::open(cache).map_err(|e| SessionError::Pipeline(e.to_string()))?,
        None,
    ));
    let reg = Arc::new(reg);
    let exec = LocalExecutor::new(reg.clone(), store.clone(), 1);
    let report = run_pipeline(&p, &reg, &store, &exec, &Silent);
    if let Some(f) = report.failure() {
        return Err(SessionError::Pipeline(f));
    }
    let scene = report
        .stages
        .iter()
        .find(|s| s.name == "scene")
        .and_then(|s| s.outputs.get("scene"))
        .ok_or_else(|| SessionError::Pipeline("the pipeline has no `scene` stage".into()))?;
    let digest = matflow_engine::store::Digest::from_hex(scene)
        .ok_or_else(|| SessionError::Pipeline(format!("bad digest {scene}")))?;
    let bytes = store
        .get(&digest)
        .map_err(|e| SessionError::Pipeline(e.to_string()))?
        .ok_or_else(|| SessionError::Pipeline("the scene is not in the cache".into()))?;
    let s = SceneData::decode(&bytes).map_err(|e| SessionError::Pipeline(e.0))?;
    let summary = format!(
        "{}: {} executed, {} cached in {:.2} s",
        report.pipeline,
        report
            .stages
            .iter()
            .filter(|s| s.status == matflow_engine::Status::Executed)
            .count(),
        report
            .stages
            .iter()
            .filter(|s| s.status == matflow_engine::Status::Cached)
            .count(),
        report.seconds
    );
    Ok((maps(&s), summary))
}

/// The scene's images for display: the photo and albedo γ-encoded,
/// roughness and metallic as their values, normals as (n + 1) / 2, depth
/// as nearness (the nearest surface white, the sky black).
fn maps(s: &SceneData) -> Maps {
    let (w, h) = (s.depth.width, s.depth.height);
    let gamma = |img: &RgbImage| {
        matflow_scene::io::encode_png_gamma(Path::new("image"), img).unwrap_or_default()
    };
    let mut images = Vec::new();
    if let Some(photo) = &s.target {
        images.push(("photo", gamma(photo)));
    }
    images.push(("albedo", gamma(&s.pred.albedo)));
    images.push(("roughness", values(&s.pred.roughness.to_rgb())));
    images.push(("metallic", values(&s.pred.metallic.to_rgb())));
    if let Some(n) = &s.pred.normal {
        let shown = RgbImage::from_vec(
            n.width,
            n.height,
            n.data.iter().map(|v| (*v + 1.0) * 0.5).collect(),
        );
        images.push(("normal", values(&shown)));
    }
    images.push(("depth", values(&nearness(&s.depth).to_rgb())));
    Maps {
        images,
        width: w,
        height: h,
    }
}

/// Depth as nearness in [0, 1]: the nearest surface 1, the farthest a
/// tenth, the sky (z ≤ 0 or not finite) 0.
fn nearness(depth: &GrayImage) -> GrayImage {
    let seen = |z: f32| z.is_finite() && z > 0.0;
    let (lo, hi) = depth
        .data
        .iter()
        .copied()
        .filter(|&z| seen(z))
        .fold((f32::INFINITY, 0.0f32), |(lo, hi), z| {
            (lo.min(z), hi.max(z))
        });
    let data = depth
        .data
        .iter()
        .map(|&z| {
            if !seen(z) || hi <= 0.0 {
                0.0
            } else if hi - lo <= f32::EPSILON {
                1.0
            } else {
                1.0 - 0.9 * (z - lo) / (hi - lo)
            }
        })
        .collect();
    GrayImage::from_vec(depth.width, depth.height, data)
}

/// Values in [0, 1] (clipped; NaN as 0) as an 8-bit PNG, no curve.
fn values(img: &RgbImage) -> Vec<u8> {
    let to8 = |c: f32| {
        if c.is_finite() {
            (c.clamp(0.0, 1.0) * 255.0).round() as u8
        } else {
            0
        }
    };
    let mut out = image::RgbImage::new(img.width as u32, img.height as u32);
    for (o, v) in out.pixels_mut().zip(img.data.iter()) {
        *o = image::Rgb([to8(v.x), to8(v.y), to8(v.z)]);
    }
    let mut buf = std::io::Cursor::new(Vec::new());
    let _ = out.write_to(&mut buf, image::ImageFormat::Png);
    buf.into_inner()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn depth_shows_near_as_bright_and_sky_as_black() {
        let d = GrayImage::from_vec(4, 1, vec![1.0, 3.0, 0.0, f32::NAN]);
        let n = nearness(&d);
        assert_eq!(n.data[0], 1.0);
        assert!((n.data[1] - 0.1).abs() < 1e-6);
        assert_eq!(n.data[2], 0.0);
        assert_eq!(n.data[3], 0.0);
    }

    #[test]
    fn inputs_become_pipelines_by_what_they_are() {
        let d = std::env::temp_dir().join(format!("matflow-studio-in-{}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        let bundle = starting_pipeline(&d).unwrap();
        assert!(bundle.contains("kind: bundle"), "{bundle}");
        let photo = starting_pipeline(&d.join("x.JPG")).unwrap();
        assert!(photo.contains("kind: matnet"), "{photo}");
        // A path with quotes or a colon stays one YAML string.
        let odd = starting_pipeline(Path::new("a \"b\": c.png")).unwrap();
        assert!(odd.contains(r#"photo: "a \"b\": c.png""#), "{odd}");
        assert!(matches!(
            starting_pipeline(&d.join("notes.txt")),
            Err(SessionError::Input(_))
        ));
        let _ = std::fs::remove_dir_all(&d);
    }
}
