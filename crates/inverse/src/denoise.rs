//! Edge-aware denoising of the per-pixel tables.
//!
//! A pixel's table is a Monte Carlo estimate of the light reaching its
//! primary vertex (weighted by BRDF terms), from a few dozen frozen paths.
//! Fitting a free albedo per pixel against it would bake that noise into
//! the albedo (the fit looks perfect, an independent render does not), so
//! before a material stage the tables are filtered the way real-time path
//! tracers filter demodulated irradiance: the à-trous filter of
//! [`matflow_render::denoise`], on the luminance of the diffuse
//! coefficient. Every table entry is linear in the incident light, so a
//! weighted mean of tables is the table of a weighted mean of the light.

use matflow_render::denoise::{atrous, Filterable};
pub use matflow_render::denoise::{Guide, SIGMA_L, SIGMA_N};
use matflow_scene::color::luminance;

use crate::tables::PixelTable;

/// Luminance of the diffuse coefficient at R = 0 (a proxy for irradiance).
#[inline]
pub fn table_luminance(t: &PixelTable) -> f32 {
    luminance(t.c[0])
}

impl Filterable for PixelTable {
    #[inline]
    fn luminance(&self) -> f32 {
        table_luminance(self)
    }

    fn scale_add(&mut self, t: &PixelTable, w: f32) {
        self.base += t.base * w;
        for k in 0..3 {
            self.c[k] += t.c[k] * w;
        }
        for (a, b) in self.spec.iter_mut().zip(t.spec.iter()) {
            for k in 0..4 {
                a[k] += b[k] * w;
            }
        }
    }
}

/// Filters `tables` in place with `iterations` à-trous passes
/// ([`matflow_render::denoise::atrous`]). `variance` is the per-pixel
/// variance of [`table_luminance`]'s estimate; `valid` marks pixels whose
/// table models their own primary vertex (others are neither changed nor
/// used).
pub fn denoise_tables(
    tables: &mut [PixelTable],
    variance: &[f32],
    valid: &[bool],
    guide: &Guide,
    iterations: usize,
) {
    atrous(tables, variance, valid, guide, iterations);
}

/// The frozen paths' image as a person watching the recovery sees it:
/// with a few paths per pixel it is mostly noise (pixels whose paths all
/// died are black), so the light (the image over `albedo`) is filtered by
/// [`atrous`] with `passes` passes, each pixel's variance taken from its
/// 3×3 neighbourhood, and multiplied back. Only pixels on the view's own
/// mesh are filtered. For viewing only: no fit reads it.
pub fn viewable(
    raw: &[glam::Vec3],
    albedo: &[glam::Vec3],
    guide: &Guide,
    passes: usize,
) -> Vec<glam::Vec3> {
    use glam::Vec3;
    let (w, h) = (guide.width, guide.height);
    if raw.len() != w * h || albedo.len() != w * h {
        return raw.to_vec();
    }
    let floor = Vec3::splat(matflow_render::denoise::DEMODULATE_FLOOR);
    let demod: Vec<Vec3> = albedo.iter().map(|a| a.max(floor)).collect();
    let valid: Vec<bool> = (0..w * h)
        .map(|i| guide.screen[i] && raw[i].is_finite())
        .collect();
    let mut light: Vec<Vec3> = (0..w * h)
        .map(|i| if valid[i] { raw[i] / demod[i] } else { raw[i] })
        .collect();
    let lum: Vec<f32> = light.iter().map(|v| luminance(*v)).collect();
    let var: Vec<f32> = (0..w * h)
        .map(|i| {
            let (x, y) = ((i % w) as isize, (i / w) as isize);
            let (mut s, mut s2, mut n) = (0f64, 0f64, 0f64);
            for dy in -1..=1isize {
                for dx in -1..=1isize {
                    let (qx, qy) = (x + dx, y + dy);
                    if qx < 0 || qy < 0 || qx >= w as isize || qy >= h as isize {
                        continue;
                    }
                    let q = qy as usize * w + qx as usize;
                    if valid[q] {
                        let l = lum[q] as f64;
                        s += l;
                        s2 += l * l;
                        n += 1.0;
                    }
                }
            }
            if n < 2.0 {
                return 0.0;
            }
            let m = s / n;
            ((s2 / n - m * m).max(0.0) * n / (n - 1.0)) as f32
        })
        .collect();
    atrous(&mut light, &var, &valid, guide, passes);
    (0..w * h)
        .map(|i| {
            let v = if valid[i] {
                light[i] * demod[i]
            } else {
                raw[i]
            };
            if v.is_finite() {
                v.max(Vec3::ZERO)
            } else {
                Vec3::ZERO
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::paths::{CacheOptions, PathCache};
    use crate::tables::build_tables_with_variance;
    use crate::testutil::{materials_of, room, texels};

    /// Frozen paths of the test room at `spp` paths per pixel.
    fn opts(spp: u32, seed: u64) -> CacheOptions {
        CacheOptions {
            spp,
            max_depth: 3,
            seed,
            env_width: 32,
            env_height: 16,
            lamp_scale: 1.0,
        }
    }

    /// On a scene lit by a constant envmap, filtering must bring the
    /// tables closer to a high-sample estimate than the raw ones are.
    #[test]
    fn filtering_reduces_table_error() {
        let t = room(3, 48);
        let scene = &t.scene;
        let mats = materials_of(&t.maps);
        let env = texels(&t.env);
        let noisy = PathCache::build(scene, &opts(4, 1), &|_, _| {}).unwrap();
        let truth = PathCache::build(scene, &opts(256, 2), &|_, _| {}).unwrap();
        let (mut t, var, valid) = build_tables_with_variance(&noisy, &mats, &env);
        let (tr, _, _) = build_tables_with_variance(&truth, &mats, &env);
        let err = |t: &[PixelTable]| -> f64 {
            t.iter()
                .zip(tr.iter())
                .zip(valid.iter())
                .filter(|(_, v)| **v)
                .map(|((a, b), _)| (luminance(a.c[0]) - luminance(b.c[0])).abs() as f64)
                .sum::<f64>()
        };
        let before = err(&t);
        let guide = Guide::build(scene);
        denoise_tables(&mut t, &var, &valid, &guide, 3);
        let after = err(&t);
        assert!(after < 0.6 * before, "before {before}, after {after}");
        assert!(t.iter().all(|t| t.c[0].is_finite() && t.base.is_finite()));
    }

    /// The frozen paths' image at 2 paths per pixel, filtered for viewing,
    /// is nearer the 256-path image than the raw one, and has no black
    /// pixels where the raw one's paths all died.
    #[test]
    fn the_viewable_fit_is_nearer_the_converged_image() {
        let t = room(3, 48);
        let mats = materials_of(&t.maps);
        let env = texels(&t.env);
        let noisy = PathCache::build(&t.scene, &opts(2, 1), &|_, _| {}).unwrap();
        let truth = PathCache::build(&t.scene, &opts(256, 2), &|_, _| {}).unwrap();
        let raw = crate::transport::render(&noisy, &mats, &env);
        let good = crate::transport::render(&truth, &mats, &env);
        let guide = Guide::build(&t.scene);
        let albedo: Vec<glam::Vec3> = mats.iter().map(|m| m.albedo).collect();
        let shown = viewable(&raw, &albedo, &guide, 3);
        let err = |img: &[glam::Vec3]| -> f64 {
            img.iter()
                .zip(&good)
                .map(|(a, b)| (*a - *b).abs().element_sum() as f64)
                .sum()
        };
        let (before, after) = (err(&raw), err(&shown));
        assert!(after < 0.6 * before, "before {before}, after {after}");
        let black = |img: &[glam::Vec3]| {
            (0..img.len())
                .filter(|&i| guide.screen[i] && img[i] == glam::Vec3::ZERO)
                .count()
        };
        assert!(
            black(&raw) > 0 && black(&shown) <= black(&raw) / 10,
            "{} {}",
            black(&raw),
            black(&shown)
        );
        assert!(shown
            .iter()
            .all(|v| v.is_finite() && v.min_element() >= 0.0));
    }
}
