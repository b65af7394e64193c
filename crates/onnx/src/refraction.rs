//! The refraction-length network's input and output, exactly as
//! `train/refraction/train.py` prepares them:
//!
//! - a square crop around the object's mask (its bounding box's longest
//!   side × [`CROP_PAD`], centred on the box), sampled at [`CROP`]²
//!   points by nearest neighbour (crop pixel j reads source column
//!   ⌊x0 + (j + ½)·side/CROP⌋);
//! - 8 channels: the photograph in sRGB [0, 1] (quantised to 8 bits, as
//!   the dataset's PNGs are), the mask, depth relative to the object
//!   ((z − z̄)/s, clipped to [−2, 2]) and camera-space normals, zero
//!   outside the mask;
//! - 3 outputs per crop pixel: the eq. 24 length, d1 and d2, in units of
//!   s = (the box's longest side in pixels) · z̄ / f, the object's extent
//!   in scene units, with z̄ the mean depth over the mask.
//!
//! [`expand`] brings the outputs back to every pixel of the mask (bilinear
//! in the crop) in scene units.

use glam::Vec3;
use matflow_scene::color::{linear_to_srgb, to_u8};
use matflow_scene::{GrayImage, Image, RgbImage};

pub const CROP: usize = 64;
pub const CROP_PAD: f64 = 1.2;
pub const IN_CH: usize = 8;
pub const OUT_CH: usize = 3;

/// The crop's place in the image: its top-left corner and side, in
/// pixels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Window {
    pub x0: f64,
    pub y0: f64,
    pub side: f64,
}

/// One object's network input.
#[derive(Clone, Debug, PartialEq)]
pub struct Prepared {
    /// [IN_CH, CROP, CROP], row-major.
    pub input: Vec<f32>,
    pub window: Window,
    /// s: scene units per output unit.
    pub scale: f32,
}

/// Why an object cannot be prepared.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum PrepareError {
    #[error("the mask is empty")]
    EmptyMask,
    #[error("the depth under the mask is not positive and finite (mean {0})")]
    BadDepth(f32),
    #[error("the image, mask, depth and normals differ in size")]
    Sizes,
}

/// The network input for the object under `mask` in a photograph
/// (`linear` RGB), with camera-space `depth` (z) and `normals`, seen with
/// focal length `focal` pixels.
pub fn prepare(
    linear: &RgbImage,
    mask: &Image<bool>,
    depth: &GrayImage,
    normals: &RgbImage,
    focal: f32,
) -> Result<Prepared, PrepareError> {
    let (w, h) = (mask.width, mask.height);
    if !(linear.same_size(mask) && depth.same_size(mask) && normals.same_size(mask)) {
        return Err(PrepareError::Sizes);
    }
    let (mut bx0, mut bx1, mut by0, mut by1) = (usize::MAX, 0, usize::MAX, 0);
    let mut zsum = 0.0f64;
    let mut n = 0usize;
    for y in 0..h {
        for x in 0..w {
            if mask.get(x, y) {
                bx0 = bx0.min(x);
                bx1 = bx1.max(x + 1);
                by0 = by0.min(y);
                by1 = by1.max(y + 1);
                zsum += depth.get(x, y) as f64;
                n += 1;
            }
        }
    }
    if n == 0 {
        return Err(PrepareError::EmptyMask);
    }
    let z_mean = (zsum / n as f64) as f32;
    if !(z_mean.is_finite() && z_mean > 0.0 && focal.is_finite() && focal > 0.0) {
        return Err(PrepareError::BadDepth(z_mean));
    }
    let extent = (bx1 - bx0).max(by1 - by0);
    let side = extent as f64 * CROP_PAD;
    let (cx, cy) = ((bx0 + bx1) as f64 / 2.0, (by0 + by1) as f64 / 2.0);
    let window = Window {
        x0: cx - side / 2.0,
        y0: cy - side / 2.0,
        side,
    };
    let scale = extent as f32 * z_mean / focal;
    let src = |o: f64, j: usize, len: usize| -> Option<usize> {
        let v = (o + (j as f64 + 0.5) * side / CROP as f64).floor();
        (v >= 0.0 && v < len as f64).then_some(v as usize)
    };
    let plane = CROP * CROP;
    let mut input = vec![0.0f32; IN_CH * plane];
    for i in 0..CROP {
        let Some(r) = src(window.y0, i, h) else {
            continue;
        };
        for j in 0..CROP {
            let Some(c) = src(window.x0, j, w) else {
                continue;
            };
            let q = i * CROP + j;
            let lin = linear.get(c, r);
            let srgb = |v: f32| to_u8(linear_to_srgb(v.clamp(0.0, 1.0))) as f32 / 255.0;
            input[q] = srgb(lin.x);
            input[plane + q] = srgb(lin.y);
            input[2 * plane + q] = srgb(lin.z);
            if mask.get(c, r) {
                input[3 * plane + q] = 1.0;
                let dz = (depth.get(c, r) - z_mean) / scale;
                input[4 * plane + q] = if dz.is_finite() {
                    dz.clamp(-2.0, 2.0)
                } else {
                    0.0
                };
                let nv = normals.get(c, r);
                let nv = if nv.is_finite() { nv } else { Vec3::ZERO };
                input[5 * plane + q] = nv.x;
                input[6 * plane + q] = nv.y;
                input[7 * plane + q] = nv.z;
            }
        }
    }
    Ok(Prepared {
        input,
        window,
        scale,
    })
}

/// The network's output ([OUT_CH, CROP, CROP]) at every pixel of `mask`,
/// bilinear between crop pixel centres, times the scale: (length, d1,
/// d2) in scene units, 0 outside the mask.
pub fn expand(out: &[f32], p: &Prepared, mask: &Image<bool>) -> [GrayImage; OUT_CH] {
    let plane = CROP * CROP;
    let sample = |ch: usize, x: usize, y: usize| -> f32 {
        let k = CROP as f64 / p.window.side;
        let u = ((x as f64 + 0.5 - p.window.x0) * k - 0.5).clamp(0.0, (CROP - 1) as f64);
        let v = ((y as f64 + 0.5 - p.window.y0) * k - 0.5).clamp(0.0, (CROP - 1) as f64);
        let (j0, i0) = (u.floor() as usize, v.floor() as usize);
        let (j1, i1) = ((j0 + 1).min(CROP - 1), (i0 + 1).min(CROP - 1));
        let (fu, fv) = ((u - j0 as f64) as f32, (v - i0 as f64) as f32);
        let at = |i: usize, j: usize| out[ch * plane + i * CROP + j];
        let a = at(i0, j0) * (1.0 - fu) + at(i0, j1) * fu;
        let b = at(i1, j0) * (1.0 - fu) + at(i1, j1) * fu;
        let v = (a * (1.0 - fv) + b * fv) * p.scale;
        if v.is_finite() {
            v.max(0.0)
        } else {
            0.0
        }
    };
    std::array::from_fn(|ch| {
        Image::from_fn(mask.width, mask.height, |x, y| {
            if mask.get(x, y) {
                sample(ch, x, y)
            } else {
                0.0
            }
        })
    })
}

/// Camera-space normals of the surface under `mask` from its depth map:
/// the cross product of the back-projected neighbours' differences
/// (central where both neighbours are in the mask, one-sided at its
/// edge), turned towards the camera; +z where no neighbour is.
pub fn normals_from_depth(
    depth: &GrayImage,
    mask: &Image<bool>,
    camera: &matflow_scene::Camera,
) -> RgbImage {
    let (w, h) = (mask.width, mask.height);
    let point = |x: usize, y: usize| camera.backproject(x as f32, y as f32, depth.get(x, y));
    let inside = |x: i64, y: i64| {
        x >= 0
            && y >= 0
            && (x as usize) < w
            && (y as usize) < h
            && mask.get(x as usize, y as usize)
            && depth.get(x as usize, y as usize) > 0.0
    };
    let diff = |x: usize, y: usize, dx: i64, dy: i64| -> Vec3 {
        let (xi, yi) = (x as i64, y as i64);
        let fwd = inside(xi + dx, yi + dy);
        let back = inside(xi - dx, yi - dy);
        let at = |k: i64| point((xi + k * dx) as usize, (yi + k * dy) as usize);
        match (back, fwd) {
            (true, true) => at(1) - at(-1),
            (false, true) => at(1) - at(0),
            (true, false) => at(0) - at(-1),
            (false, false) => Vec3::ZERO,
        }
    };
    Image::from_fn(w, h, |x, y| {
        if !inside(x as i64, y as i64) {
            return Vec3::Z;
        }
        // Image x runs along +x, image y along −y: (dx × dy) points away
        // from the camera for a surface facing it.
        let n = diff(x, y, 0, 1).cross(diff(x, y, 1, 0));
        let n = n.normalize_or(Vec3::Z);
        if n.dot(-point(x, y)) < 0.0 {
            -n
        } else {
            n
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn disk(n: usize, c: (f32, f32), r: f32) -> Image<bool> {
        Image::from_fn(n, n, |x, y| {
            let (dx, dy) = (x as f32 + 0.5 - c.0, y as f32 + 0.5 - c.1);
            dx * dx + dy * dy <= r * r
        })
    }

    #[test]
    fn the_crop_covers_the_mask_and_the_scale_is_the_extent() {
        let n = 100;
        let mask = disk(n, (40.0, 60.0), 20.0);
        let depth = Image::new(n, n, 5.0f32);
        let normals = Image::new(n, n, Vec3::Z);
        let img = Image::new(n, n, Vec3::splat(0.2));
        let p = prepare(&img, &mask, &depth, &normals, 100.0).unwrap();
        // Box 40 px wide: side 48, centred on (40, 60).
        assert_eq!(
            p.window,
            Window {
                x0: 16.0,
                y0: 36.0,
                side: 48.0
            }
        );
        assert!((p.scale - 40.0 * 5.0 / 100.0).abs() < 1e-6);
        let plane = CROP * CROP;
        let inside: f32 = p.input[3 * plane..4 * plane].iter().sum();
        // The disk fills π/4 of its box, the box (1/1.2)² of the crop.
        let want = std::f32::consts::FRAC_PI_4 / 1.44 * plane as f32;
        assert!((inside - want).abs() < 0.03 * want, "{inside} vs {want}");
        // Flat depth: the relative depth is 0; normals +z inside only.
        assert!(p.input[4 * plane..5 * plane].iter().all(|&v| v == 0.0));
        let c = (CROP / 2) * CROP + CROP / 2;
        assert_eq!((p.input[7 * plane + c], p.input[7 * plane]), (1.0, 0.0));
        // sRGB of 0.2, quantised.
        assert!((p.input[c] - 124.0 / 255.0).abs() < 1e-6, "{}", p.input[c]);
        // An output of 1 everywhere comes back as the scale inside the mask.
        let out = vec![1.0f32; OUT_CH * plane];
        let [l, d1, _] = expand(&out, &p, &mask);
        assert!((l.get(40, 60) - p.scale).abs() < 1e-6 && d1.get(0, 0) == 0.0);
        assert!(matches!(
            prepare(&img, &Image::new(n, n, false), &depth, &normals, 100.0),
            Err(PrepareError::EmptyMask)
        ));
    }

    #[test]
    fn normals_from_the_depth_of_a_ball_are_its_normals() {
        let n = 64;
        let cam = matflow_scene::Camera::new(n, n);
        let (c, r) = (Vec3::new(0.2, -0.1, -4.0), 1.0f32);
        let mut mask = Image::new(n, n, false);
        let mut depth = Image::new(n, n, 0.0f32);
        let mut truth = Image::new(n, n, Vec3::Z);
        for y in 0..n {
            for x in 0..n {
                let d = cam.film_to_dir(glam::Vec2::new(x as f32 + 0.5, y as f32 + 0.5));
                let d = d.normalize();
                let b = d.dot(c);
                let disc = b * b - (c.length_squared() - r * r);
                if disc > 0.0 {
                    let p = d * (b - disc.sqrt());
                    mask.set(x, y, true);
                    depth.set(x, y, -p.z);
                    truth.set(x, y, (p - c) / r);
                }
            }
        }
        let got = normals_from_depth(&depth, &mask, &cam);
        let (mut worst, mut sum, mut k) = (0.0f32, 0.0f32, 0);
        for q in 0..n * n {
            if mask.data[q] {
                let e = got.data[q]
                    .dot(truth.data[q])
                    .clamp(-1.0, 1.0)
                    .acos()
                    .to_degrees();
                sum += e;
                k += 1;
                // Away from the silhouette the estimate is close.
                if truth.data[q].z > 0.8 {
                    worst = worst.max(e);
                }
            }
        }
        assert!(worst < 3.0, "{worst} degrees");
        assert!(
            sum / (k as f32) < 6.0,
            "{} degrees on average",
            sum / k as f32
        );
    }
}
