//! The recovered albedo's structure, taken from the photo and the
//! prediction (issue 51).
//!
//! The per-pixel solve makes each pixel's render match the photo, so
//! whatever the frozen paths get wrong about a pixel's shading — a wavy
//! depth mesh's normals, light missing past the frame — it puts into the
//! albedo: swirls and bands the scene does not have, which an edit or a
//! relight then shows. On the `rooms` generator the recovered albedo held
//! 2–14× the true albedo's structure and scored below the prediction it
//! started from.
//!
//! Here the albedo is rebuilt so that its structure comes only from what
//! the photo and the prediction show (the Retinex assumption: within one
//! surface, shading varies slowly, the albedo may vary quickly):
//!
//! * the coarse structure is the prediction's;
//! * the fine structure is the photo's own relative detail, the photo
//!   over its blur of `detail_sigma` within the surface's segment (so no
//!   edge of a neighbouring surface bleeds in);
//! * the level and colour of each segment (connected pixels of similar
//!   predicted albedo without a depth jump, [`crate::segments::segment`])
//!   is the solve's: the median over the segment of the solved albedo
//!   over that product, per channel, in logarithms.
//!
//! So the solve still corrects the prediction's colour per surface, and
//! the photo's texture still reaches the albedo, but a shading error that
//! varies over a surface can no longer be written into it.
//!
//! Everything is a pure function of its inputs (segments grown in scan
//! order, each pixel's filter a serial sum, medians of sorted values): the
//! same bits for any thread count.

use glam::Vec3;
use rayon::prelude::*;

use matflow_render::Material;

use crate::segments::{segment, SegmentParams, NONE};

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StructureParams {
    /// The photo's detail is its ratio to its blur of this σ, as a share
    /// of the image's larger side (1/128: 4 px at 512²).
    pub detail_sigma: f32,
    /// The detail is held within [1/range, range] (a cast shadow's edge
    /// would otherwise leave a dark and a bright line).
    pub detail_range: f32,
    /// How the surfaces are cut (on the predicted albedo and the
    /// distances).
    pub segments: SegmentParams,
}

impl Default for StructureParams {
    /// Chosen on the `rooms` generator, two scenes of each kind
    /// (docs/results/prediction.md, "The recovered albedo"): a tolerance
    /// of 0.1 cut the prediction's blotches into segments of their own,
    /// and 0.2 and 0.3 gave the same structure; σ of 2, 4 and 8 px at
    /// 512² differed by under 0.3 dB.
    fn default() -> Self {
        StructureParams {
            detail_sigma: 1.0 / 128.0,
            detail_range: 4.0,
            segments: SegmentParams {
                albedo_tolerance: 0.2,
                depth_tolerance: 0.05,
            },
        }
    }
}

/// The smallest value a ratio's terms are taken as.
const FLOOR: f32 = 1e-4;

/// Gaussian taps of σ `sigma` px, to 3σ.
fn taps(sigma: f32) -> Vec<f32> {
    let r = (3.0 * sigma).ceil().max(1.0) as i64;
    let k: Vec<f32> = (-r..=r)
        .map(|i| (-0.5 * (i as f32 / sigma).powi(2)).exp())
        .collect();
    let s: f32 = k.iter().sum();
    k.into_iter().map(|v| v / s).collect()
}

/// Blur of `img` (`w`×`h`, row-major) within segments: a separable
/// Gaussian whose taps count only where the label is the centre pixel's
/// (rows first, then columns over the rows' sums and weights), normalised
/// by the taps counted. Pixels labelled [`NONE`] keep their value.
pub fn blur_within(img: &[Vec3], labels: &[u32], w: usize, h: usize, sigma: f32) -> Vec<Vec3> {
    let k = taps(sigma.max(0.3));
    let r = (k.len() / 2) as i64;
    // Rows: the sum of taps times values, and of taps, of each pixel's
    // own segment.
    let rows: Vec<(Vec3, f32)> = (0..w * h)
        .into_par_iter()
        .map(|i| {
            let (x, y) = ((i % w) as i64, i / w);
            let l = labels[i];
            let (mut s, mut ws) = (Vec3::ZERO, 0.0f32);
            for (t, kv) in k.iter().enumerate() {
                let xx = x + t as i64 - r;
                if xx < 0 || xx >= w as i64 {
                    continue;
                }
                let j = y * w + xx as usize;
                if labels[j] == l {
                    s += img[j] * *kv;
                    ws += *kv;
                }
            }
            (s, ws)
        })
        .collect();
    (0..w * h)
        .into_par_iter()
        .map(|i| {
            let l = labels[i];
            if l == NONE {
                return img[i];
            }
            let (x, y) = (i % w, (i / w) as i64);
            let (mut s, mut ws) = (Vec3::ZERO, 0.0f32);
            for (t, kv) in k.iter().enumerate() {
                let yy = y + t as i64 - r;
                if yy < 0 || yy >= h as i64 {
                    continue;
                }
                let j = yy as usize * w + x;
                if labels[j] == l {
                    s += rows[j].0 * *kv;
                    ws += rows[j].1 * *kv;
                }
            }
            if ws > 0.0 {
                s / ws
            } else {
                img[i]
            }
        })
        .collect()
}

/// Per channel, the photo over its blur, held within [1/range, range]; 1
/// where either is dark or not finite.
fn detail(photo: Vec3, blurred: Vec3, range: f32) -> Vec3 {
    let one = |p: f32, b: f32| {
        let d = p.max(0.0) / b;
        if b > FLOOR && d.is_finite() {
            d.clamp(1.0 / range, range)
        } else {
            1.0
        }
    };
    Vec3::new(
        one(photo.x, blurred.x),
        one(photo.y, blurred.y),
        one(photo.z, blurred.z),
    )
}

/// Median of `v` (sorted in place; not empty).
fn median(v: &mut [f32]) -> f32 {
    v.sort_unstable_by(f32::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// The surfaces of a `w`×`h` image: its segments
/// ([`crate::segments::segment`]) on the predicted albedo `pred` and the
/// distances `dist` to the first surface (not finite: the sky).
#[derive(Clone, Debug)]
pub struct Surfaces {
    pub labels: Vec<u32>,
    pub count: usize,
}

impl Surfaces {
    pub fn new(pred: &[Vec3], dist: &[f32], w: usize, h: usize, p: &StructureParams) -> Surfaces {
        let (labels, count) = segment(pred, dist, w, h, &p.segments);
        Surfaces { labels, count }
    }

    /// Per surface, the median of `value(i)` over its pixels (those where
    /// it is finite; 0 where none is).
    fn medians(&self, value: impl Fn(usize) -> f32) -> Vec<f32> {
        let mut per: Vec<Vec<f32>> = vec![Vec::new(); self.count];
        for (i, &l) in self.labels.iter().enumerate() {
            let v = value(i);
            if l != NONE && v.is_finite() {
                per[l as usize].push(v);
            }
        }
        per.into_par_iter()
            .map(|mut v| if v.is_empty() { 0.0 } else { median(&mut v) })
            .collect()
    }
}

/// The albedo rebuilt from `pred` (the predicted albedo), the linear
/// `photo` and the `solved` albedo on `surfaces` of a `w`×`h` image: per
/// pixel, `pred × detail × gain` of its surface, within [0, 1]. Pixels of
/// no surface keep the solved albedo. See the module's documentation.
pub fn photo_structured(
    solved: &[Vec3],
    pred: &[Vec3],
    photo: &[Vec3],
    surfaces: &Surfaces,
    (w, h): (usize, usize),
    p: &StructureParams,
) -> Vec<Vec3> {
    let n = w * h;
    let labels = &surfaces.labels;
    assert!(
        solved.len() == n && pred.len() == n && photo.len() == n && labels.len() == n,
        "photo_structured: sizes differ"
    );
    let photo: Vec<Vec3> = photo
        .iter()
        .map(|v| {
            Vec3::from_array(
                v.to_array()
                    .map(|c| if c.is_finite() { c.max(0.0) } else { 0.0 }),
            )
        })
        .collect();
    let sigma = p.detail_sigma * w.max(h) as f32;
    let blurred = blur_within(&photo, labels, w, h, sigma);
    let base: Vec<Vec3> = (0..n)
        .map(|i| (pred[i] * detail(photo[i], blurred[i], p.detail_range)).max(Vec3::splat(FLOOR)))
        .collect();
    // Each surface's gain per channel: the median log ratio.
    let log_gain = |c: usize| surfaces.medians(|i| (solved[i][c].max(FLOOR) / base[i][c]).ln());
    let (r, g, b) = (log_gain(0), log_gain(1), log_gain(2));
    (0..n)
        .map(|i| match labels[i] {
            NONE => solved[i],
            l => {
                let l = l as usize;
                let gain = Vec3::new(r[l], g[l], b[l]).exp();
                (base[i] * gain).clamp(Vec3::ZERO, Vec3::ONE)
            }
        })
        .collect()
}

/// Roughness and metallic per surface: the prediction's plus the median
/// over the surface of what the solve moved them by, within their ranges
/// (`min_roughness`..1, 0..1). Free per pixel, the solve makes a pixel
/// whose shading it gets wrong shiny or metallic instead of its albedo.
/// Pixels of no surface keep the solve's.
pub fn rm_per_surface(
    solved: &mut [Material],
    pred: &[Material],
    surfaces: &Surfaces,
    min_roughness: f32,
) {
    let dr = surfaces.medians(|i| solved[i].roughness - pred[i].roughness);
    let dm = surfaces.medians(|i| solved[i].metallic - pred[i].metallic);
    for (i, m) in solved.iter_mut().enumerate() {
        let l = surfaces.labels[i];
        if l == NONE {
            continue;
        }
        let l = l as usize;
        m.roughness = (pred[i].roughness + dr[l]).clamp(min_roughness, 1.0);
        m.metallic = (pred[i].metallic + dm[l]).clamp(0.0, 1.0);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 48×32 image of two surfaces (left and right halves, a depth jump
    /// between them), each of one true albedo times a fine texture
    /// (a checker of ±20 %), lit by a smooth shading.
    struct Scene {
        w: usize,
        h: usize,
        truth: Vec<Vec3>,
        shading: Vec<f32>,
        dist: Vec<f32>,
    }

    fn scene() -> Scene {
        let (w, h) = (48, 32);
        let mut truth = Vec::new();
        let mut shading = Vec::new();
        let mut dist = Vec::new();
        for y in 0..h {
            for x in 0..w {
                let left = x < w / 2;
                let base = if left {
                    Vec3::new(0.6, 0.4, 0.3)
                } else {
                    Vec3::new(0.2, 0.5, 0.7)
                };
                let tex = if (x / 2 + y / 2) % 2 == 0 { 1.2 } else { 0.8 };
                truth.push(base * tex);
                shading.push(0.5 + 0.4 * (x as f32 / w as f32) + 0.1 * (y as f32 / h as f32));
                dist.push(if left { 2.0 } else { 3.0 });
            }
        }
        Scene {
            w,
            h,
            truth,
            shading,
            dist,
        }
    }

    fn rms(a: &[Vec3], b: &[Vec3]) -> f32 {
        let s: f32 = a
            .iter()
            .zip(b)
            .map(|(x, y)| (*x - *y).length_squared())
            .sum();
        (s / a.len() as f32).sqrt()
    }

    #[test]
    fn a_shading_error_in_the_solve_does_not_reach_the_albedo() {
        let s = scene();
        let photo: Vec<Vec3> = s
            .truth
            .iter()
            .zip(&s.shading)
            .map(|(a, e)| *a * *e)
            .collect();
        // The prediction: each surface's mean albedo, 30 % too bright and
        // without the texture.
        let pred: Vec<Vec3> = (0..s.w * s.h)
            .map(|i| {
                let left = i % s.w < s.w / 2;
                1.3 * if left {
                    Vec3::new(0.6, 0.4, 0.3)
                } else {
                    Vec3::new(0.2, 0.5, 0.7)
                }
            })
            .collect();
        // The solve explains the photo under a wrong shading (swirls of
        // ±30 %): the truth times the shading error.
        let solved: Vec<Vec3> = (0..s.w * s.h)
            .map(|i| {
                let (x, y) = ((i % s.w) as f32, (i / s.w) as f32);
                let err = 1.0 + 0.3 * (0.5 * x).sin() * (0.4 * y).cos();
                s.truth[i] * err
            })
            .collect();
        let p = StructureParams {
            detail_sigma: 3.0 / s.w as f32,
            ..Default::default()
        };
        let surfaces = Surfaces::new(&pred, &s.dist, s.w, s.h, &p);
        assert_eq!(surfaces.count, 2);
        let out = photo_structured(&solved, &pred, &photo, &surfaces, (s.w, s.h), &p);
        let before = rms(&solved, &s.truth);
        let after = rms(&out, &s.truth);
        assert!(
            after < 0.35 * before,
            "rms against the truth: {before} solved, {after} rebuilt"
        );
        // The texture is the photo's: the checker's contrast survives.
        let (a, b) = (out[2 * s.w + 4], out[2 * s.w + 6]);
        let ratio = a.x / b.x;
        assert!(
            (ratio - 1.5).abs() < 0.2 || (1.0 / ratio - 1.5).abs() < 0.2,
            "checker contrast {ratio}"
        );
        // The level and colour are the solve's (the prediction's 30 %
        // excess is gone).
        let mean = |v: &[Vec3]| v.iter().copied().sum::<Vec3>() / v.len() as f32;
        let (m, t) = (mean(&out), mean(&s.truth));
        assert!((m - t).abs().max_element() < 0.03, "{m} against {t}");
        assert!(out
            .iter()
            .all(|v| v.is_finite() && v.min_element() >= 0.0 && v.max_element() <= 1.0));
    }

    #[test]
    fn the_blur_stays_within_its_segment() {
        let s = scene();
        let labels: Vec<u32> = (0..s.w * s.h)
            .map(|i| (i % s.w >= s.w / 2) as u32)
            .collect();
        let img: Vec<Vec3> = labels.iter().map(|l| Vec3::splat(*l as f32)).collect();
        let out = blur_within(&img, &labels, s.w, s.h, 3.0);
        assert_eq!(out, img, "a constant per segment is its own blur");
        let mut sky = labels.clone();
        sky[5] = NONE;
        let noisy: Vec<Vec3> = (0..s.w * s.h)
            .map(|i| Vec3::splat((i * 7919 % 13) as f32))
            .collect();
        let out = blur_within(&noisy, &sky, s.w, s.h, 2.0);
        assert_eq!(out[5], noisy[5], "a pixel of no segment keeps its value");
    }

    #[test]
    fn dark_and_non_finite_pixels_leave_finite_albedo() {
        let s = scene();
        let mut photo = vec![Vec3::ZERO; s.w * s.h];
        photo[3] = Vec3::splat(f32::NAN);
        photo[4] = Vec3::splat(f32::INFINITY);
        let pred = vec![Vec3::splat(0.5); s.w * s.h];
        let mut solved = vec![Vec3::splat(0.3); s.w * s.h];
        solved[7] = Vec3::ZERO;
        let mut dist = s.dist.clone();
        dist[9] = f32::INFINITY;
        let p = StructureParams::default();
        let surfaces = Surfaces::new(&pred, &dist, s.w, s.h, &p);
        let out = photo_structured(&solved, &pred, &photo, &surfaces, (s.w, s.h), &p);
        assert!(out
            .iter()
            .all(|v| v.is_finite() && v.min_element() >= 0.0 && v.max_element() <= 1.0));
        assert_eq!(out[9], solved[9], "the sky keeps the solve's");
        assert!((out[20] - Vec3::splat(0.3)).abs().max_element() < 1e-5);
    }

    #[test]
    fn roughness_and_metallic_move_per_surface() {
        let s = scene();
        let albedo: Vec<Vec3> = (0..s.w * s.h)
            .map(|i| Vec3::splat(if i % s.w < s.w / 2 { 0.3 } else { 0.7 }))
            .collect();
        let pred: Vec<Material> = albedo
            .iter()
            .map(|a| Material {
                albedo: *a,
                roughness: 0.7,
                metallic: 0.05,
            })
            .collect();
        // The solve made the left surface rougher everywhere, and a few
        // pixels of the right one metallic.
        let mut solved = pred.clone();
        for (i, m) in solved.iter_mut().enumerate() {
            if i % s.w < s.w / 2 {
                m.roughness = 0.9;
            } else if i % 5 == 0 {
                m.metallic = 1.0;
            }
        }
        let surfaces = Surfaces::new(&albedo, &s.dist, s.w, s.h, &StructureParams::default());
        rm_per_surface(&mut solved, &pred, &surfaces, 0.07);
        for (i, m) in solved.iter().enumerate() {
            if i % s.w < s.w / 2 {
                assert!((m.roughness - 0.9).abs() < 1e-6 && (m.metallic - 0.05).abs() < 1e-6);
            } else {
                assert!((m.roughness - 0.7).abs() < 1e-6 && (m.metallic - 0.05).abs() < 1e-6);
            }
        }
    }
}
