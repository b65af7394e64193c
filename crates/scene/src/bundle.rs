//! The Materialist scene bundle: a folder in the reference implementation's
//! layout.
//!
//! ```text
//! gt_image.exr          linear input photo (or gt_image.png, sRGB, power 2.2)
//! albedoPred.exr        MatNet albedo (RGB)
//! normalPred.exr        camera-space unit normals, +z towards the camera
//! depthPred.exr         disparity-like map (channel Y): z = 2·max − d
//! depth.exr             optional: camera-space z directly; wins over depthPred
//! roughnessPred.png     sRGB-encoded 8-bit map
//! metallicPred.png      sRGB-encoded 8-bit map
//! mesh_mask.png         optional: set pixels carry no geometry (z = 0)
//! best_results/         optimised albedo, roughness, metallic, normal EXRs,
//!                       envmap.hdr and rendered_img.exr
//! ground_truth/         synthetic scenes only: the true maps and envmap
//! ```

use std::path::{Path, PathBuf};

use glam::Vec3;

use crate::color::srgb_to_linear;
use crate::error::{Result, SceneError};
use crate::image::{GrayImage, Image, RgbImage};
use crate::io;
use crate::transparency::Transparency;

/// Which material maps to use.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MaterialSource {
    /// MatNet's predictions (`*Pred.*`).
    Pred,
    /// The optimised maps in `best_results/`.
    BestResults,
    /// The true maps of a synthetic scene in `ground_truth/`.
    GroundTruth,
}

impl MaterialSource {
    pub fn folder(self) -> Option<&'static str> {
        match self {
            MaterialSource::Pred => None,
            MaterialSource::BestResults => Some("best_results"),
            MaterialSource::GroundTruth => Some("ground_truth"),
        }
    }
}

impl std::str::FromStr for MaterialSource {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "pred" => Ok(MaterialSource::Pred),
            "best_results" | "best" => Ok(MaterialSource::BestResults),
            "ground_truth" | "gt" => Ok(MaterialSource::GroundTruth),
            _ => Err(format!(
                "unknown material source '{s}' (expected pred, best_results or ground_truth)"
            )),
        }
    }
}

/// Per-pixel material maps in screen space.
#[derive(Clone, Debug, PartialEq)]
pub struct MaterialMaps {
    pub albedo: RgbImage,
    pub roughness: GrayImage,
    pub metallic: GrayImage,
    /// Camera-space normals, when the source has them.
    pub normal: Option<RgbImage>,
    /// Regions made transparent, when there are any.
    pub transparency: Option<Transparency>,
}

impl MaterialMaps {
    /// Per texel, whether albedo, roughness or metallic — or the glass of
    /// a transparent region — differ from `other`'s (maps of the same
    /// size).
    pub fn changed_texels(&self, other: &MaterialMaps) -> Vec<bool> {
        (0..self.albedo.data.len())
            .map(|i| {
                self.albedo.data[i] != other.albedo.data[i]
                    || self.roughness.data[i] != other.roughness.data[i]
                    || self.metallic.data[i] != other.metallic.data[i]
                    || match (&self.transparency, &other.transparency) {
                        (None, None) => false,
                        (Some(a), Some(b)) => a.glass_differs(b, i),
                        (Some(t), None) | (None, Some(t)) => t.is_glass(i),
                    }
            })
            .collect()
    }

    /// Per texel, whether the material of the background seen through it
    /// differs from `other`'s: inside a transparent region its own
    /// background material, elsewhere the texel's ordinary one.
    pub fn changed_background(&self, other: &MaterialMaps) -> Vec<bool> {
        (0..self.albedo.data.len())
            .map(|i| {
                fn glass(m: &MaterialMaps, i: usize) -> Option<&Transparency> {
                    m.transparency.as_ref().filter(|t| t.is_glass(i))
                }
                match (glass(self, i), glass(other, i)) {
                    (None, None) => {
                        self.albedo.data[i] != other.albedo.data[i]
                            || self.roughness.data[i] != other.roughness.data[i]
                            || self.metallic.data[i] != other.metallic.data[i]
                    }
                    (Some(a), Some(b)) => a.background_differs(b, i),
                    _ => true,
                }
            })
            .collect()
    }

    /// The material of the background at texel `i`: (albedo, roughness,
    /// metallic).
    pub fn background_at(&self, i: usize) -> (Vec3, f32, f32) {
        match self.transparency.as_ref().filter(|t| t.is_glass(i)) {
            Some(t) => (
                t.bg_albedo.data[i],
                t.bg_roughness.data[i],
                t.bg_metallic.data[i],
            ),
            None => (
                self.albedo.data[i],
                self.roughness.data[i],
                self.metallic.data[i],
            ),
        }
    }
}

impl MaterialMaps {
    pub fn width(&self) -> usize {
        self.albedo.width
    }
    pub fn height(&self) -> usize {
        self.albedo.height
    }
    /// Uniform maps (handy for tests and procedural scenes).
    pub fn uniform(w: usize, h: usize, albedo: Vec3, roughness: f32, metallic: f32) -> Self {
        MaterialMaps {
            albedo: Image::new(w, h, albedo),
            roughness: Image::new(w, h, roughness),
            metallic: Image::new(w, h, metallic),
            normal: None,
            transparency: None,
        }
    }
}

#[derive(Clone, Debug)]
pub struct Bundle {
    pub dir: PathBuf,
}

fn exists(p: &Path) -> bool {
    p.is_file()
}

impl Bundle {
    /// Opens a bundle folder (it must exist; files are read on demand).
    pub fn open(dir: impl Into<PathBuf>) -> Result<Bundle> {
        let dir = dir.into();
        if !dir.is_dir() {
            return Err(SceneError::invalid(&dir, "bundle folder does not exist"));
        }
        Ok(Bundle { dir })
    }

    /// Creates the folder if needed (for writing).
    pub fn create(dir: impl Into<PathBuf>) -> Result<Bundle> {
        let dir = dir.into();
        std::fs::create_dir_all(&dir).map_err(|e| SceneError::io(&dir, e))?;
        Ok(Bundle { dir })
    }

    pub fn path(&self, name: &str) -> PathBuf {
        self.dir.join(name)
    }

    fn missing(&self, what: &str, looked_for: &str) -> SceneError {
        SceneError::Missing {
            dir: self.dir.clone(),
            what: what.into(),
            looked_for: looked_for.into(),
        }
    }

    /// The linear input image: `gt_image.exr`, else `gt_image.png` decoded
    /// with power 2.2.
    pub fn load_gt_image(&self) -> Result<RgbImage> {
        let exr = self.path("gt_image.exr");
        if exists(&exr) {
            let img = io::read_exr_rgb(&exr)?;
            io::ensure_finite_rgb(&exr, &img)?;
            return Ok(img);
        }
        let png = self.path("gt_image.png");
        if exists(&png) {
            let raw = io::read_ldr_raw(&png)?;
            return Ok(raw.map(|v| v.powf(crate::color::GAMMA)));
        }
        Err(self.missing("input image", "gt_image.exr, gt_image.png"))
    }

    /// Camera-space depth z > 0 per pixel; 0 means "no geometry here".
    ///
    /// `depth.exr` (z directly) wins; otherwise `depthPred.exr` is converted
    /// as the reference does, z = 2·max(d) − d. Pixels set in
    /// `mesh_mask.png` get z = 0.
    /// The size of the depth map [`Bundle::load_depth`] reads, from its
    /// header alone.
    pub fn depth_size(&self) -> Result<(usize, usize)> {
        let direct = self.path("depth.exr");
        if exists(&direct) {
            return io::exr_size(&direct);
        }
        let pred = self.path("depthPred.exr");
        if !exists(&pred) {
            return Err(self.missing("depth", "depth.exr, depthPred.exr"));
        }
        io::exr_size(&pred)
    }

    pub fn load_depth(&self) -> Result<GrayImage> {
        let direct = self.path("depth.exr");
        let from = if exists(&direct) {
            direct.clone()
        } else {
            self.path("depthPred.exr")
        };
        let mut z = if exists(&direct) {
            let z = io::read_exr_gray(&direct)?;
            io::ensure_finite_gray(&direct, &z)?;
            if let Some(i) = z.data.iter().position(|&v| v < 0.0) {
                return Err(SceneError::invalid(
                    &direct,
                    format!(
                        "negative depth {} at x={}, y={} (depth.exr holds camera-space z >= 0)",
                        z.data[i],
                        i % z.width,
                        i / z.width
                    ),
                ));
            }
            z
        } else {
            let pred = self.path("depthPred.exr");
            if !exists(&pred) {
                return Err(self.missing("depth", "depth.exr, depthPred.exr"));
            }
            let d = io::read_exr_gray(&pred)?;
            io::ensure_finite_gray(&pred, &d)?;
            disparity_to_depth(&d)
        };
        let mask_path = self.path("mesh_mask.png");
        if exists(&mask_path) {
            let mask = io::read_mask(&mask_path)?;
            self.check_size(&mask_path, &mask, z.width, z.height)?;
            for (v, &m) in z.data.iter_mut().zip(mask.data.iter()) {
                if m {
                    *v = 0.0;
                }
            }
        }
        check_depth_range(&from, &z)?;
        Ok(z)
    }

    fn check_size<T>(&self, path: &Path, img: &Image<T>, w: usize, h: usize) -> Result<()> {
        if img.width != w || img.height != h {
            return Err(SceneError::SizeMismatch {
                path: path.into(),
                got_w: img.width,
                got_h: img.height,
                want_w: w,
                want_h: h,
            });
        }
        Ok(())
    }

    fn read_rgb_checked(&self, rel: &str) -> Result<RgbImage> {
        let p = self.path(rel);
        if !exists(&p) {
            return Err(self.missing(rel, rel));
        }
        let img = io::read_exr_rgb(&p)?;
        io::ensure_finite_rgb(&p, &img)?;
        Ok(img)
    }

    fn read_gray_exr_checked(&self, rel: &str) -> Result<GrayImage> {
        let p = self.path(rel);
        if !exists(&p) {
            return Err(self.missing(rel, rel));
        }
        let img = io::read_exr_rgb(&p)?.mean_channel();
        io::ensure_finite_gray(&p, &img)?;
        Ok(img)
    }

    fn read_srgb_png_map(&self, rel: &str) -> Result<GrayImage> {
        let p = self.path(rel);
        if !exists(&p) {
            return Err(self.missing(rel, rel));
        }
        Ok(io::read_ldr_raw(&p)?.map(|v| srgb_to_linear(v.x)))
    }

    /// Loads albedo, roughness, metallic (and normals when present).
    /// Values are checked finite; sizes must agree.
    pub fn load_materials(&self, src: MaterialSource) -> Result<MaterialMaps> {
        let maps = match src.folder() {
            None => {
                let normal_p = self.path("normalPred.exr");
                MaterialMaps {
                    albedo: self.read_rgb_checked("albedoPred.exr")?,
                    roughness: if exists(&self.path("roughnessPred.exr")) {
                        self.read_gray_exr_checked("roughnessPred.exr")?
                    } else {
                        self.read_srgb_png_map("roughnessPred.png")?
                    },
                    metallic: if exists(&self.path("metallicPred.exr")) {
                        self.read_gray_exr_checked("metallicPred.exr")?
                    } else {
                        self.read_srgb_png_map("metallicPred.png")?
                    },
                    normal: if exists(&normal_p) {
                        Some(self.read_rgb_checked("normalPred.exr")?)
                    } else {
                        None
                    },
                    transparency: None,
                }
            }
            Some(f) => {
                let normal_rel = format!("{f}/normal.exr");
                MaterialMaps {
                    albedo: self.read_rgb_checked(&format!("{f}/albedo.exr"))?,
                    roughness: self.read_gray_exr_checked(&format!("{f}/roughness.exr"))?,
                    metallic: self.read_gray_exr_checked(&format!("{f}/metallic.exr"))?,
                    normal: if exists(&self.path(&normal_rel)) {
                        Some(self.read_rgb_checked(&normal_rel)?)
                    } else {
                        None
                    },
                    transparency: None,
                }
            }
        };
        let (w, h) = (maps.albedo.width, maps.albedo.height);
        let folder = src.folder().unwrap_or(".");
        self.check_size(
            &self.dir.join(folder).join("roughness"),
            &maps.roughness,
            w,
            h,
        )?;
        self.check_size(
            &self.dir.join(folder).join("metallic"),
            &maps.metallic,
            w,
            h,
        )?;
        if let Some(n) = &maps.normal {
            self.check_size(&self.dir.join(folder).join("normal"), n, w, h)?;
        }
        Ok(maps)
    }

    /// The bundle's environment map: `best_results/envmap.hdr`, else
    /// `ground_truth/envmap.hdr`.
    pub fn envmap_path(&self) -> Option<PathBuf> {
        ["best_results/envmap.hdr", "ground_truth/envmap.hdr"]
            .iter()
            .map(|r| self.path(r))
            .find(|p| exists(p))
    }

    /// The reference stores `rendered_img.exr` linear on its MLP path but
    /// gamma-encoded (power 1/2.2) on its direct path (`"model_name":
    /// "none"` in `config.json`), e.g. for `jinjya`.
    pub fn rendered_img_is_gamma_encoded(&self) -> bool {
        std::fs::read_to_string(self.path("config.json"))
            .map(|s| {
                s.split("\"model_name\"")
                    .nth(1)
                    .map(|rest| {
                        let v = rest.trim_start_matches([' ', ':', '\t', '\n']);
                        v.starts_with("\"none\"")
                    })
                    .unwrap_or(false)
            })
            .unwrap_or(false)
    }

    /// Writes maps in the `best_results/` (or `ground_truth/`) layout.
    pub fn write_materials(&self, folder: &str, maps: &MaterialMaps) -> Result<()> {
        let d = self.dir.join(folder);
        let d = &d;
        let mut jobs: Vec<Job> = vec![
            Box::new(move || io::write_exr_rgb(&d.join("albedo.exr"), &maps.albedo)),
            Box::new(move || io::write_exr_rgb(&d.join("roughness.exr"), &maps.roughness.to_rgb())),
            Box::new(move || io::write_exr_rgb(&d.join("metallic.exr"), &maps.metallic.to_rgb())),
        ];
        if let Some(n) = &maps.normal {
            jobs.push(Box::new(move || {
                io::write_exr_rgb(&d.join("normal.exr"), n)
            }));
        }
        write_all(jobs)
    }

    /// Writes maps as MatNet-style predictions (`*Pred.*`).
    pub fn write_predictions(&self, maps: &MaterialMaps) -> Result<()> {
        let mut jobs: Vec<Job> = vec![
            Box::new(|| io::write_exr_rgb(&self.path("albedoPred.exr"), &maps.albedo)),
            Box::new(|| io::write_png_srgb_map(&self.path("roughnessPred.png"), &maps.roughness)),
            Box::new(|| io::write_png_srgb_map(&self.path("metallicPred.png"), &maps.metallic)),
        ];
        if let Some(n) = &maps.normal {
            jobs.push(Box::new(|| {
                io::write_exr_rgb(&self.path("normalPred.exr"), n)
            }));
        }
        write_all(jobs)
    }

    /// Writes camera-space z as `depth.exr` (channel Y).
    pub fn write_depth(&self, z: &GrayImage) -> Result<()> {
        io::write_exr_gray(&self.path("depth.exr"), z)
    }

    /// Writes the input photograph as `gt_image.exr` (linear) and
    /// `gt_image.png` (sRGB).
    pub fn write_gt_image(&self, image: &RgbImage) -> Result<()> {
        write_all(vec![
            Box::new(|| io::write_exr_rgb(&self.path("gt_image.exr"), image)),
            Box::new(|| io::write_png_gamma(&self.path("gt_image.png"), image)),
        ])
    }

    /// Writes a recovery's `best_results/`: the maps, `envmap.hdr`,
    /// `lamps.json` (removed when there are none), the independent
    /// re-render (`rendered_img`, and `rendered_raw.exr` when it was
    /// denoised, else removed), the fitted image (`fit_img`) and a
    /// viewable `albedo.png`. A file an earlier run left where this one
    /// writes nothing is removed, so the folder never mixes two runs.
    pub fn write_best_results(&self, r: &BestResults) -> Result<()> {
        self.write_materials("best_results", r.maps)?;
        write_all(vec![
            Box::new(|| io::write_hdr(&self.path("best_results/envmap.hdr"), r.envmap)),
            Box::new(|| {
                let lamps = self.path(crate::lamps::LAMPS_FILE);
                if r.lamps.is_empty() {
                    remove_stale(&lamps)
                } else {
                    crate::lamps::write_lamps(&lamps, r.lamps)
                }
            }),
            Box::new(|| io::write_exr_rgb(&self.path("best_results/rendered_img.exr"), r.rendered)),
            Box::new(|| {
                io::write_png_gamma(&self.path("best_results/rendered_img.png"), r.rendered)
            }),
            Box::new(|| {
                let raw = self.path("best_results/rendered_raw.exr");
                match r.rendered_raw {
                    Some(im) => io::write_exr_rgb(&raw, im),
                    None => remove_stale(&raw),
                }
            }),
            Box::new(|| io::write_exr_rgb(&self.path("best_results/fit_img.exr"), r.fit_image)),
            Box::new(|| io::write_png_gamma(&self.path("best_results/fit_img.png"), r.fit_image)),
            Box::new(|| io::write_png_gamma(&self.path("best_results/albedo.png"), &r.maps.albedo)),
        ])
    }
}

/// What a recovery writes to `best_results/` ([`Bundle::write_best_results`]).
pub struct BestResults<'a> {
    /// Albedo, roughness, metallic (and the normals it was recovered with).
    pub maps: &'a MaterialMaps,
    pub envmap: &'a RgbImage,
    pub lamps: &'a [crate::lamps::Lamp],
    /// The independent re-render of the result, as written.
    pub rendered: &'a RgbImage,
    /// The same samples unfiltered, when `rendered` was denoised.
    pub rendered_raw: Option<&'a RgbImage>,
    /// What the optimiser fitted: the frozen paths' image of the result.
    pub fit_image: &'a RgbImage,
}

/// One file's write, for [`write_all`].
pub type Job<'a> = Box<dyn FnOnce() -> Result<()> + Send + 'a>;

/// Runs independent file writes side by side (EXR compression is most of
/// a bundle's writing, one core per file); of several failures, the first
/// in the order given is the one reported.
pub fn write_all(jobs: Vec<Job<'_>>) -> Result<()> {
    use rayon::prelude::*;
    let done: Vec<Result<()>> = jobs.into_par_iter().map(|job| job()).collect();
    done.into_iter().collect()
}

/// Removes `path`, left by an earlier run, where this run writes nothing.
fn remove_stale(path: &Path) -> Result<()> {
    match std::fs::remove_file(path) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(SceneError::io(path, e)),
        _ => Ok(()),
    }
}

/// Nearest and farthest depth a scene may have, in the depth map's units:
/// outside them the geometry is degenerate in f32 (ray offsets swamp a
/// scene of 1e-30; squared lengths overflow at 1e30).
pub const DEPTH_RANGE: (f32, f32) = (1e-4, 1e7);

/// A depth map is usable when its positive pixels (0 marks "no geometry")
/// lie in [`DEPTH_RANGE`] and are not all equal: all zeros, or one
/// constant however large or small, is what a broken depth predictor
/// writes and would render as sky alone.
pub fn check_depth_range(path: &Path, z: &GrayImage) -> Result<()> {
    let (mut lo, mut hi, mut n) = (f32::INFINITY, 0f32, 0usize);
    for &v in &z.data {
        if v > 0.0 && v.is_finite() {
            lo = lo.min(v);
            hi = hi.max(v);
            n += 1;
        }
    }
    let why = if n == 0 {
        "no pixel has a positive depth".to_string()
    } else if lo < DEPTH_RANGE.0 || hi > DEPTH_RANGE.1 {
        format!(
            "depths run from {lo:e} to {hi:e}; matflow needs them within [{:e}, {:e}] (rescale the map)",
            DEPTH_RANGE.0, DEPTH_RANGE.1
        )
    } else if hi <= lo {
        format!("every pixel has the same depth {lo}: the map has no spread")
    } else {
        return Ok(());
    };
    Err(SceneError::invalid(path, format!("unusable depth: {why}")))
}

/// The reference's conversion of its stored disparity-like map to
/// camera-space depth: z = 2·max(d) − d.
pub fn disparity_to_depth(d: &GrayImage) -> GrayImage {
    let m = d.max_value();
    d.map(|v| 2.0 * m - v)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn disparity_conversion_flips_order() {
        let d = Image::from_vec(2, 1, vec![1.0, 3.0]);
        let z = disparity_to_depth(&d);
        assert_eq!(z.data, vec![5.0, 3.0]);
    }

    #[test]
    fn write_then_read_materials_and_depth() {
        let dir = tempfile::tempdir().unwrap();
        let b = Bundle::create(dir.path()).unwrap();
        let mut maps = MaterialMaps::uniform(6, 4, Vec3::new(0.2, 0.5, 0.8), 0.3, 1.0);
        maps.normal = Some(Image::new(6, 4, Vec3::Z));
        b.write_materials("best_results", &maps).unwrap();
        assert_eq!(b.load_materials(MaterialSource::BestResults).unwrap(), maps);
        b.write_predictions(&maps).unwrap();
        let pred = b.load_materials(MaterialSource::Pred).unwrap();
        assert!((pred.roughness.get(0, 0) - 0.3).abs() < 0.01);
        assert_eq!(pred.metallic.get(5, 3), 1.0);
        let z = Image::from_fn(6, 4, |x, y| 1.0 + x as f32 + y as f32 * 0.5);
        b.write_depth(&z).unwrap();
        assert_eq!(b.load_depth().unwrap(), z);
    }

    #[test]
    fn missing_files_are_named() {
        let dir = tempfile::tempdir().unwrap();
        let b = Bundle::open(dir.path()).unwrap();
        let e = b.load_depth().unwrap_err().to_string();
        assert!(e.contains("depthPred.exr"), "{e}");
        let e = b
            .load_materials(MaterialSource::Pred)
            .unwrap_err()
            .to_string();
        assert!(e.contains("albedoPred.exr"), "{e}");
    }

    #[test]
    fn nan_in_prediction_is_rejected_with_pixel_count() {
        let dir = tempfile::tempdir().unwrap();
        let b = Bundle::create(dir.path()).unwrap();
        let mut maps = MaterialMaps::uniform(4, 4, Vec3::splat(0.5), 0.5, 0.0);
        maps.albedo.set(1, 2, Vec3::new(f32::NAN, 0.0, 0.0));
        b.write_predictions(&maps).unwrap();
        let e = b
            .load_materials(MaterialSource::Pred)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("albedoPred.exr") && e.contains("1 pixel") && e.contains("x=1, y=2"),
            "{e}"
        );
    }
}
