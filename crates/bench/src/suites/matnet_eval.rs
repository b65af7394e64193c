//! `matflow-bench matnet`'s accuracy tables: a MatNet-contract model on
//! scenes with ground truth, per scene and per kind of scene, against the
//! predictors that need no network.
//!
//! Scenes come from two places, each skipped when absent:
//!
//! - a held-out `rooms` dataset (`train/matnet/kinds-heldout.yaml`: seeds
//!   training never sees, every kind), its kind read from each sample's
//!   parameters;
//! - a folder of bundles made by another renderer
//!   (`crates/bench/scripts/relight_scenes.py --kinds …`, Mitsuba 3), its
//!   kinds in `validation.json`.
//!
//! Each photo goes in as a new user's would: 8-bit sRGB. Per scene:
//!
//! - albedo: PSNR after the best single gain (least squares over the
//!   pixels with geometry; albedo's scale is what a photo cannot tell),
//!   for the model, the linear photo itself as albedo, a constant grey,
//!   and an oracle constant (the truth's own mean colour);
//! - normals: mean angle, for the model and for every normal facing the
//!   camera;
//! - depth: R² of the best affine map from the prediction to the true z
//!   (to 1/z for a disparity model: the target's form), and of the pixel
//!   row's (the layout prior "lower is nearer"); beside it the same fit
//!   in the other form (a z model's 1/output to 1/z; a disparity model's
//!   output to z), so that models of both kinds compare. In z a far
//!   floor or ground near the horizon (z of 50–200 beside a near 3–10)
//!   holds most of the variance; in 1/z the near surfaces do;
//! - the depth's own surface normals (what the mesh stage shades with: the
//!   back-projected depth's facets under matflow's camera, the depth taken
//!   as z as the mesh stage takes it) against the true depth's, mean
//!   angle over smooth surfaces (where the true depth's facet is within
//!   ~25° of the true normal map: not across an edge), for the model and
//!   for a flat wall facing the camera;
//! - silhouettes: the share of the true depth's steps (ln z changing by
//!   more than 0.1 between neighbours: objects against what is behind
//!   them) where the model's depth also steps (by more than 0.03, within
//!   2 pixels); a depth of the average layout, with no objects, scores
//!   near 0 (a noisy depth scores high here and badly on its normals);
//! - false steps: the share of the frame where the model's depth steps
//!   (by more than 0.1) with no step of the true depth (by more than
//!   0.03) within 2 pixels — recall's counterpart, what a relight shows
//!   as lit slivers inside a face or where a floor meets a wall;
//! - roughness and metallic: mean absolute error, model and oracle
//!   constant (the truth's means).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use glam::Vec3;
use matflow_nodes::{matnet_predict, read_matnet_photo, MatnetModel, MatnetPrediction};
use matflow_onnx::matnet::DepthKind;
use matflow_scene::io::{Photo, PhotoPixels};
use matflow_scene::{Bundle, GrayImage, MaterialMaps, MaterialSource, RgbImage};

use crate::harness::median;

/// One scene to evaluate: its name, kind and bundle folder.
pub struct Scene {
    pub name: String,
    pub kind: String,
    pub dir: PathBuf,
}

/// A scene's scores (see the module's documentation).
#[derive(Clone, Debug, Default)]
pub struct Scores {
    pub albedo_model: f64,
    pub albedo_photo: f64,
    pub albedo_grey: f64,
    pub albedo_oracle: f64,
    pub normal_model: f64,
    pub normal_facing: f64,
    /// R² in the target's form: z for a z model, 1/z for a disparity one.
    pub depth_model: f64,
    /// R² in the other form (see the module's documentation).
    pub depth_other: f64,
    pub depth_row: f64,
    pub mesh_model: f64,
    pub mesh_facing: f64,
    /// `None` where the truth has fewer than 16 steps.
    pub silhouettes: Option<f64>,
    pub false_steps: f64,
    pub rough_model: f64,
    pub rough_oracle: f64,
    pub metal_model: f64,
    pub metal_oracle: f64,
}

impl Scores {
    pub fn normal_ratio(&self) -> f64 {
        self.normal_model / self.normal_facing.max(1e-9)
    }
}

/// Pixels where ln z steps by more than `step` to the right or lower
/// neighbour (both with depth).
fn depth_steps(z: &GrayImage, step: f32) -> Vec<bool> {
    let (w, h) = (z.width, z.height);
    let lz: Vec<Option<f32>> = z
        .data
        .iter()
        .map(|&v| (v > 0.0 && v.is_finite()).then(|| v.ln()))
        .collect();
    let mut e = vec![false; w * h];
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            let Some(a) = lz[i] else { continue };
            let mut near = |j: usize| {
                if let Some(b) = lz[j] {
                    if (a - b).abs() > step {
                        e[i] = true;
                    }
                }
            };
            if x + 1 < w {
                near(i + 1);
            }
            if y + 1 < h {
                near(i + w);
            }
        }
    }
    e
}

/// Whether `mask` (w × h) is set within 2 pixels (a 5 × 5 square) of
/// (x, y).
fn within_2px(mask: &[bool], w: usize, h: usize, x: usize, y: usize) -> bool {
    let (x0, y0) = (x.saturating_sub(2), y.saturating_sub(2));
    (y0..(y + 3).min(h)).any(|yy| (x0..(x + 3).min(w)).any(|xx| mask[yy * w + xx]))
}

/// Share of the true depth's silhouettes (ln z steps by > 0.1) where
/// `pred` (the same size) also steps (by > 0.03) within 2 pixels; `None`
/// where the truth has fewer than 16 such pixels.
fn silhouette_recall(pred: &GrayImage, truth: &GrayImage) -> Option<f64> {
    let (w, h) = (truth.width, truth.height);
    let (t, p) = (depth_steps(truth, 0.1), depth_steps(pred, 0.03));
    let (mut hit, mut all) = (0usize, 0usize);
    for y in 0..h {
        for x in 0..w {
            if t[y * w + x] {
                all += 1;
                hit += within_2px(&p, w, h, x, y) as usize;
            }
        }
    }
    (all >= 16).then(|| hit as f64 / all as f64)
}

/// Share of the frame where `pred` steps (ln z by > 0.1) with no step
/// of `truth` (the same size; by > 0.03) within 2 pixels.
fn false_steps(pred: &GrayImage, truth: &GrayImage) -> f64 {
    let (w, h) = (truth.width, truth.height);
    let (p, t) = (depth_steps(pred, 0.1), depth_steps(truth, 0.03));
    let mut false_px = 0usize;
    for y in 0..h {
        for x in 0..w {
            if p[y * w + x] && !within_2px(&t, w, h, x, y) {
                false_px += 1;
            }
        }
    }
    false_px as f64 / (w * h).max(1) as f64
}

/// PSNR of `gain · p` against `t` (clamped to [0, 1]) over `valid`, the
/// gain fitted by least squares.
fn gain_fitted_psnr(p: &[Vec3], t: &[Vec3], valid: &[usize]) -> f64 {
    let (mut pt, mut pp) = (0.0f64, 0.0f64);
    for &i in valid {
        let (a, b) = (
            p[i].as_dvec3(),
            t[i].clamp(Vec3::ZERO, Vec3::ONE).as_dvec3(),
        );
        pt += a.dot(b);
        pp += a.dot(a);
    }
    let g = if pp > 1e-12 { pt / pp } else { 0.0 };
    let mut se = 0.0f64;
    for &i in valid {
        let d = p[i].as_dvec3() * g - t[i].clamp(Vec3::ZERO, Vec3::ONE).as_dvec3();
        se += d.length_squared();
    }
    let mse = se / (3.0 * valid.len().max(1) as f64);
    matflow_scene::metrics::psnr_from_mse(mse.max(1e-12))
}

/// R² of the least-squares affine fit of `y` from `x`.
fn affine_r2(x: &[f64], y: &[f64]) -> f64 {
    let n = x.len().max(1) as f64;
    let (mx, my) = (x.iter().sum::<f64>() / n, y.iter().sum::<f64>() / n);
    let (mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0);
    for (a, b) in x.iter().zip(y) {
        sxx += (a - mx) * (a - mx);
        sxy += (a - mx) * (b - my);
        syy += (b - my) * (b - my);
    }
    if syy <= 0.0 || sxx <= 0.0 {
        return 0.0;
    }
    // The fitted line's residual: syy − sxy²/sxx.
    1.0 - (syy - sxy * sxy / sxx) / syy
}

/// Unit camera-space normals (+z towards the camera) of the facets depth
/// `z` makes under matflow's camera: at pixel (i, j) the cross product of
/// the back-projected point's forward differences to (i+1, j) and
/// (i, j+1); `None` where any of the three has no depth or the facet is
/// degenerate, and on the last row and column.
fn facet_normals(z: &GrayImage) -> Vec<Option<Vec3>> {
    let (w, h) = (z.width, z.height);
    let cam = matflow_scene::Camera::new(w, h);
    let p = |i: usize, j: usize| {
        let d = z.data[j * w + i];
        (d > 0.0).then(|| cam.backproject(i as f32, j as f32, d))
    };
    (0..w * h)
        .map(|k| {
            let (i, j) = (k % w, k / w);
            if i + 1 >= w || j + 1 >= h {
                return None;
            }
            let (o, a, b) = (p(i, j)?, p(i + 1, j)?, p(i, j + 1)?);
            let n = (b - o).cross(a - o);
            let len = n.length();
            (len.is_finite() && len > 1e-12).then(|| n / len)
        })
        .collect()
}

/// Mean angle (degrees) of the facets of `pred` to those of `truth` over
/// the pixels where the true facet is within ~25° of `normal` (a smooth
/// surface), and of a camera-facing wall's; `(NaN, NaN)` with no such
/// pixel.
fn mesh_normal_angles(pred: &GrayImage, truth: &GrayImage, normal: &RgbImage) -> (f64, f64) {
    let (np, nt) = (facet_normals(pred), facet_normals(truth));
    let (mut model, mut facing, mut n) = (0.0f64, 0.0f64, 0usize);
    for k in 0..nt.len() {
        let Some(t) = nt[k] else { continue };
        if t.dot(normal.data[k].normalize_or_zero()) <= 0.9 {
            continue;
        }
        let angle = |a: Vec3| (a.dot(t).clamp(-1.0, 1.0) as f64).acos().to_degrees();
        // A prediction with no facet here (no depth) counts as facing.
        model += angle(np[k].unwrap_or(Vec3::Z));
        facing += angle(Vec3::Z);
        n += 1;
    }
    if n == 0 {
        return (f64::NAN, f64::NAN);
    }
    (model / n as f64, facing / n as f64)
}

/// The 8-bit sRGB photo a camera would have written of a linear image.
fn srgb_photo(img: &RgbImage) -> Photo {
    let f = |c: f32| {
        matflow_scene::color::to_u8(matflow_scene::color::linear_to_srgb(c.clamp(0.0, 1.0)))
    };
    let data = img
        .data
        .iter()
        .flat_map(|v| [f(v.x), f(v.y), f(v.z)])
        .collect();
    Photo {
        width: img.width,
        height: img.height,
        pixels: PhotoPixels::U8 { channels: 3, data },
    }
}

/// A scene's photo: its `gt_image.png` when it has one, else its linear
/// `gt_image.exr` written as 8-bit sRGB.
fn photo_of(dir: &Path, b: &Bundle) -> Result<Photo> {
    let png = dir.join("gt_image.png");
    if png.is_file() {
        return read_matnet_photo(&png).map_err(anyhow::Error::msg);
    }
    Ok(srgb_photo(&b.load_gt_image()?))
}

/// Scores of `m` on the scene in `dir`.
pub fn score(dir: &Path, m: &MatnetModel) -> Result<Scores> {
    let b = Bundle::open(dir)?;
    let truth = b.load_materials(MaterialSource::GroundTruth)?;
    let tz = b.load_depth()?;
    let photo = photo_of(dir, &b)?;
    let p = matnet_predict(&photo, m).map_err(anyhow::Error::msg)?;
    Ok(scores_of(&p, &truth, &tz))
}

fn scores_of(p: &MatnetPrediction, truth: &MaterialMaps, tz: &GrayImage) -> Scores {
    let (w, h) = (tz.width, tz.height);
    let valid: Vec<usize> = (0..w * h).filter(|&i| tz.data[i] > 0.0).collect();
    let resize = |img: &RgbImage| matflow_scene::io::resize_bilinear(img, w, h);
    let pm = p.materials();
    let albedo = resize(&pm.albedo);
    let rough = resize(&pm.roughness.to_rgb());
    let metal = resize(&pm.metallic.to_rgb());
    let normal = resize(pm.normal.as_ref().expect("predictions carry normals"));
    let photo = resize(&p.photo);
    let n = valid.len().max(1) as f64;
    let ta = &truth.albedo.data;
    let mean_a = valid.iter().map(|&i| ta[i]).sum::<Vec3>() / n as f32;
    let grey = vec![Vec3::splat(0.5); w * h];
    let oracle = vec![mean_a; w * h];
    let mut s = Scores {
        albedo_model: gain_fitted_psnr(&albedo.data, ta, &valid),
        albedo_photo: gain_fitted_psnr(&photo.data, ta, &valid),
        albedo_grey: gain_fitted_psnr(&grey, ta, &valid),
        albedo_oracle: gain_fitted_psnr(&oracle, ta, &valid),
        ..Scores::default()
    };
    let tn = truth.normal.as_ref();
    let (mr, mm) = (
        valid
            .iter()
            .map(|&i| truth.roughness.data[i] as f64)
            .sum::<f64>()
            / n,
        valid
            .iter()
            .map(|&i| truth.metallic.data[i] as f64)
            .sum::<f64>()
            / n,
    );
    for &i in &valid {
        if let Some(tn) = tn {
            let t = tn.data[i].normalize_or_zero();
            let a = normal.data[i].normalize_or_zero();
            s.normal_model += (a.dot(t).clamp(-1.0, 1.0) as f64).acos().to_degrees();
            s.normal_facing += (t.z.clamp(-1.0, 1.0) as f64).acos().to_degrees();
        }
        let (r, m) = (
            truth.roughness.data[i] as f64,
            truth.metallic.data[i] as f64,
        );
        s.rough_model += (rough.data[i].x as f64 - r).abs();
        s.metal_model += (metal.data[i].x as f64 - m).abs();
        s.rough_oracle += (mr - r).abs();
        s.metal_oracle += (mm - m).abs();
    }
    for v in [
        &mut s.normal_model,
        &mut s.normal_facing,
        &mut s.rough_model,
        &mut s.metal_model,
        &mut s.rough_oracle,
        &mut s.metal_oracle,
    ] {
        *v /= n;
    }
    // Depth: the raw output (z or disparity), resized, against z or 1/z.
    let raw = resize(&p.depth_raw().to_rgb());
    let t: Vec<f64> = valid
        .iter()
        .map(|&i| match p.depth_kind {
            DepthKind::Z => tz.data[i] as f64,
            DepthKind::Disparity => 1.0 / tz.data[i] as f64,
        })
        .collect();
    let x: Vec<f64> = valid.iter().map(|&i| raw.data[i].x as f64).collect();
    s.depth_model = affine_r2(&x, &t);
    // The other form: a z model's 1/output against 1/z; a disparity
    // model's output against z (the mesh's 2·max − d is affine in it).
    let (xo, to): (Vec<f64>, Vec<f64>) = valid
        .iter()
        .map(|&i| {
            let (r, z) = (raw.data[i].x as f64, tz.data[i] as f64);
            match p.depth_kind {
                DepthKind::Z => (1.0 / r.max(1e-6), 1.0 / z),
                DepthKind::Disparity => (r, z),
            }
        })
        .unzip();
    s.depth_other = affine_r2(&xo, &to);
    let rows: Vec<f64> = valid.iter().map(|&i| (i / w) as f64).collect();
    let tzv: Vec<f64> = valid.iter().map(|&i| tz.data[i] as f64).collect();
    s.depth_row = affine_r2(&rows, &tzv);
    // The depth as the mesh stage takes it (z, or the reference's
    // 2·max − d for disparity, which commutes with the resize above), at
    // the truth's size: its facets and its silhouettes.
    let z: Vec<f32> = match p.depth_kind {
        DepthKind::Z => raw.data.iter().map(|v| v.x).collect(),
        DepthKind::Disparity => {
            let m = p.depth_raw().max_value();
            raw.data.iter().map(|v| 2.0 * m - v.x).collect()
        }
    };
    let z = GrayImage::from_vec(w, h, z);
    if let Some(tn) = tn {
        (s.mesh_model, s.mesh_facing) = mesh_normal_angles(&z, tz, tn);
    }
    s.silhouettes = silhouette_recall(&z, tz);
    s.false_steps = false_steps(&z, tz);
    s
}

/// The held-out `rooms` dataset's samples (unpacked under `tmp`) with
/// their kinds; empty when `dir` holds none.
pub fn dataset_scenes(dir: &Path, tmp: &Path) -> Result<Vec<Scene>> {
    let desc = dir.join("dataset.json");
    if !desc.is_file() {
        return Ok(vec![]);
    }
    let d: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&desc)?)?;
    let name = d["name"].as_str().unwrap_or("");
    let mut kinds = BTreeMap::new();
    let manifest = dir.join("manifest.jsonl");
    for line in std::fs::read_to_string(&manifest)
        .with_context(|| manifest.display().to_string())?
        .lines()
    {
        let v: serde_json::Value = serde_json::from_str(line)?;
        let key = v["key"].as_str().unwrap_or("").to_string();
        let kind = v["params"]["kind"].as_str().unwrap_or("open").to_string();
        kinds.insert(key, kind);
    }
    let mut out = vec![];
    for i in 0..d["samples"].as_u64().unwrap_or(0) {
        let key = matflow_dataset::shards::key(i);
        let to = tmp.join(&key);
        matflow_dataset::shards::unpack(dir, &key, &to)?;
        out.push(Scene {
            name: format!("{name}/{key}"),
            kind: kinds.get(&key).cloned().unwrap_or_else(|| "open".into()),
            dir: to,
        });
    }
    Ok(out)
}

/// The bundles of a `relight_scenes.py` folder with their kinds (every
/// scene, both halves); empty when `dir` holds none.
pub fn bundle_scenes(dir: &Path) -> Result<Vec<Scene>> {
    let index = dir.join("validation.json");
    if !index.is_file() {
        return Ok(vec![]);
    }
    let v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&index)?)
        .with_context(|| index.display().to_string())?;
    let mut out = vec![];
    if let Some(kinds) = v["kinds"].as_object() {
        for (name, kind) in kinds {
            let d = dir.join(name);
            if d.join("gt_image.exr").is_file() {
                out.push(Scene {
                    name: name.clone(),
                    kind: kind.as_str().unwrap_or("closed").to_string(),
                    dir: d,
                });
            }
        }
    }
    Ok(out)
}

/// A share as a percentage, or "–" where there is none.
fn share(v: Option<f64>) -> String {
    v.map_or_else(|| "–".to_string(), |v| format!("{:.0} %", 100.0 * v))
}

/// Prints the per-scene table, the per-kind medians and the targets.
pub fn print_tables(title: &str, rows: &[(Scene, Scores)]) {
    println!("\n{title}: per scene");
    println!(
        "| scene | kind | albedo PSNR: model / photo / grey / oracle | normals: model / facing | \
         depth R²: model / other form / row | depth's normals: model / facing | silhouettes | roughness MAE: model / oracle | \
         metallic MAE: model / oracle | false steps |\n\
         |---|---|---|---|---|---|---|---|---|---|"
    );
    for (sc, s) in rows {
        println!(
            "| {} | {} | {:.2} / {:.2} / {:.2} / {:.2} dB | {:.1}° / {:.1}° | {:.2} / {:.2} / {:.2} | {:.1}° / {:.1}° | {} | {:.3} / {:.3} | {:.3} / {:.3} | {:.1} % |",
            sc.name,
            sc.kind,
            s.albedo_model,
            s.albedo_photo,
            s.albedo_grey,
            s.albedo_oracle,
            s.normal_model,
            s.normal_facing,
            s.depth_model,
            s.depth_other,
            s.depth_row,
            s.mesh_model,
            s.mesh_facing,
            share(s.silhouettes),
            s.rough_model,
            s.rough_oracle,
            s.metal_model,
            s.metal_oracle,
            100.0 * s.false_steps
        );
    }
    let mut kinds: BTreeMap<&str, Vec<&Scores>> = BTreeMap::new();
    for (sc, s) in rows {
        kinds.entry(sc.kind.as_str()).or_default().push(s);
        kinds.entry("all").or_default().push(s);
    }
    println!("\n{title}: medians per kind, and the scenes that meet each target");
    println!(
        "| kind | scenes | albedo PSNR: model / photo / oracle | ≥ photo + 2 dB | normals: model / facing | ≤ 0.7× facing | depth R²: model / other form | ≥ 0.7 | depth's normals: model / facing | silhouettes | false steps |\n\
         |---|---|---|---|---|---|---|---|---|---|---|"
    );
    for (k, v) in &kinds {
        let med = |f: &dyn Fn(&Scores) -> f64| median(v.iter().map(|s| f(s)).collect());
        let count = |f: &dyn Fn(&Scores) -> bool| v.iter().filter(|s| f(s)).count();
        println!(
            "| {k} | {} | {:.2} / {:.2} / {:.2} dB | {} | {:.1}° / {:.1}° | {} | {:.2} / {:.2} | {} | {:.1}° / {:.1}° | {} | {:.1} % |",
            v.len(),
            med(&|s| s.albedo_model),
            med(&|s| s.albedo_photo),
            med(&|s| s.albedo_oracle),
            count(&|s| s.albedo_model >= s.albedo_photo + 2.0),
            med(&|s| s.normal_model),
            med(&|s| s.normal_facing),
            count(&|s| s.normal_ratio() <= 0.7),
            med(&|s| s.depth_model),
            med(&|s| s.depth_other),
            count(&|s| s.depth_model >= 0.7),
            med(&|s| s.mesh_model),
            med(&|s| s.mesh_facing),
            share({
                let v: Vec<f64> = v.iter().filter_map(|s| s.silhouettes).collect();
                (!v.is_empty()).then(|| median(v))
            }),
            100.0 * med(&|s| s.false_steps),
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn affine_r2_is_one_for_an_affine_map_and_small_for_noise() {
        let x: Vec<f64> = (0..50).map(|i| i as f64).collect();
        let y: Vec<f64> = x.iter().map(|v| 3.0 - 0.5 * v).collect();
        assert!((affine_r2(&x, &y) - 1.0).abs() < 1e-12);
        let z: Vec<f64> = (0..50).map(|i| ((i * 37) % 11) as f64).collect();
        assert!(affine_r2(&x, &z) < 0.2);
        assert_eq!(affine_r2(&[1.0, 1.0], &[2.0, 3.0]), 0.0);
    }

    #[test]
    fn facets_of_a_tilted_plane_are_its_normal_whatever_the_depth_scale() {
        // The plane m·p = d seen by matflow's camera: z = d / (m·dir).
        let (w, h) = (24, 16);
        let cam = matflow_scene::Camera::new(w, h);
        let m = Vec3::new(0.3, 0.4, 0.75f32.sqrt());
        let plane = |scale: f32| {
            let z = (0..w * h).map(|k| {
                let dir = cam.backproject((k % w) as f32, (k / w) as f32, 1.0);
                scale * -3.0 / m.dot(dir)
            });
            GrayImage::from_vec(w, h, z.collect())
        };
        let normal = RgbImage::from_vec(w, h, vec![m; w * h]);
        for n in facet_normals(&plane(1.0)).into_iter().flatten() {
            assert!((n - m).length() < 1e-4, "{n} against {m}");
        }
        let (model, facing) = mesh_normal_angles(&plane(7.0), &plane(1.0), &normal);
        assert!(model < 0.05, "{model}");
        assert!((facing - 30.0).abs() < 0.05, "{facing}");
        // Noise in depth tilts the facets.
        let mut noisy = plane(1.0);
        for (k, v) in noisy.data.iter_mut().enumerate() {
            *v *= 1.0 + 0.02 * ((k * 37 % 11) as f32 / 10.0 - 0.5);
        }
        assert!(mesh_normal_angles(&noisy, &plane(1.0), &normal).0 > 5.0);
    }

    #[test]
    fn silhouettes_are_found_in_a_depth_with_the_object_and_not_in_one_without() {
        // A box at z = 2 in front of a wall at z = 5.
        let (w, h) = (32, 24);
        let scene = |boxed: bool, scale: f32| {
            let z = (0..w * h).map(|k| {
                let (x, y) = (k % w, k / w);
                let inside = boxed && (10..20).contains(&x) && (8..16).contains(&y);
                scale * if inside { 2.0 } else { 5.0 + 0.01 * y as f32 }
            });
            GrayImage::from_vec(w, h, z.collect())
        };
        let truth = scene(true, 1.0);
        assert_eq!(silhouette_recall(&scene(true, 3.0), &truth), Some(1.0));
        assert_eq!(silhouette_recall(&scene(false, 1.0), &truth), Some(0.0));
        // A box drawn 2 pixels off still counts; a wall alone has no silhouettes.
        let mut moved = scene(false, 1.0);
        for y in 10..18 {
            for x in 12..22 {
                moved.data[y * w + x] = 2.0;
            }
        }
        assert_eq!(silhouette_recall(&moved, &truth), Some(1.0));
        assert_eq!(silhouette_recall(&truth, &scene(false, 1.0)), None);
        // False steps: none in the truth itself, in a depth missing the
        // box, or in one with the box 2 pixels off; a 6 × 4 box the truth
        // lacks makes 19 (its left and upper neighbours, its right column
        // and bottom row, the corner once).
        assert_eq!(false_steps(&truth, &truth), 0.0);
        assert_eq!(false_steps(&scene(false, 1.0), &truth), 0.0);
        assert_eq!(false_steps(&moved, &truth), 0.0);
        let mut elsewhere = scene(false, 1.0);
        for y in 2..6 {
            for x in 2..8 {
                elsewhere.data[y * w + x] = 2.0;
            }
        }
        let edge = false_steps(&elsewhere, &scene(false, 1.0));
        assert_eq!(edge, 19.0 / (w * h) as f64, "{}", edge * (w * h) as f64);
        assert_eq!(false_steps(&elsewhere, &elsewhere), 0.0);
    }

    #[test]
    fn gain_fitted_psnr_ignores_a_gain_and_not_a_pattern() {
        let t: Vec<Vec3> = (0..64)
            .map(|i| Vec3::splat(0.2 + 0.01 * i as f32))
            .collect();
        let valid: Vec<usize> = (0..64).collect();
        let scaled: Vec<Vec3> = t.iter().map(|v| *v * 1.7).collect();
        assert!(gain_fitted_psnr(&scaled, &t, &valid) >= 100.0);
        let flat = vec![Vec3::splat(0.5); 64];
        assert!(gain_fitted_psnr(&flat, &t, &valid) < 25.0);
    }
}
