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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::paths::{CacheOptions, PathCache};
    use crate::tables::build_tables_with_variance;
    use crate::testutil::{materials_of, room, texels};

    /// On a scene lit by a constant envmap, filtering must bring the
    /// tables closer to a high-sample estimate than the raw ones are.
    #[test]
    fn filtering_reduces_table_error() {
        let t = room(3, 48);
        let scene = &t.scene;
        let mats = materials_of(&t.maps);
        let env = texels(&t.env);
        let opts = |spp, seed| CacheOptions {
            spp,
            max_depth: 3,
            seed,
            env_width: 32,
            env_height: 16,
            lamp_scale: 1.0,
        };
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
}
