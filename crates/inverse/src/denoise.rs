//! Edge-aware denoising of the per-pixel tables.
//!
//! A pixel's table is a Monte Carlo estimate of the light reaching its
//! primary vertex (weighted by BRDF terms), from a few dozen frozen paths.
//! Fitting a free albedo per pixel against it would bake that noise into
//! the albedo (the fit looks perfect, an independent render does not), so
//! before a material stage the tables are filtered the way real-time path
//! tracers filter demodulated irradiance (SVGF, Schied et al. 2017): an
//! à-trous wavelet (5×5 B3-spline taps at spacings 1, 2, 4, …) whose
//! weights stop at
//!
//! * normal changes: `max(0, n_p·n_q)^SIGMA_N`;
//! * leaving the pixel's plane: `exp(−|(x_q − x_p)·n_p| / (2·footprint·|o|))`,
//!   footprint = the pixel's size at its depth, |o| = the tap offset;
//! * irradiance changes beyond the noise (shadow edges):
//!   `exp(−|l_p − l_q| / (SIGMA_L·σ_p))`, l the luminance of the diffuse
//!   coefficient and σ_p its estimated standard error, itself filtered.
//!
//! Every table entry is linear in the incident light, so a weighted mean
//! of tables is the table of a weighted mean of the light: the filter is
//! spatial reuse of neighbours' paths. Pure gathers in a fixed order: the
//! result does not depend on the thread count.

use glam::{Vec2, Vec3};
use matflow_render::RenderScene;
use rayon::prelude::*;

use crate::tables::PixelTable;

pub const SIGMA_N: i32 = 32;
pub const SIGMA_L: f32 = 4.0;
const B3: [f32; 5] = [1.0 / 16.0, 1.0 / 4.0, 3.0 / 8.0, 1.0 / 4.0, 1.0 / 16.0];

/// Geometry of each pixel's primary hit (through the pixel centre).
#[derive(Clone, Debug)]
pub struct Guide {
    pub width: usize,
    pub height: usize,
    /// Camera-space position, normal facing the camera, and the world size
    /// of one pixel there; `None` where the centre ray misses.
    pub hits: Vec<Option<(Vec3, Vec3, f32)>>,
}

impl Guide {
    pub fn build(scene: &RenderScene) -> Guide {
        let (w, h) = (scene.camera.width, scene.camera.height);
        let focal = scene.camera.focal().max(1e-6);
        let hits = (0..w * h)
            .into_par_iter()
            .with_min_len(1024)
            .map(|i| {
                let film = Vec2::new((i % w) as f32 + 0.5, (i / w) as f32 + 0.5);
                let d = scene.camera_ray(film);
                let hit = scene.bvh.intersect(Vec3::ZERO, d, 0.0, f32::INFINITY)?;
                let p = d * hit.t;
                let mut n = scene.face_normals[hit.prim as usize];
                if n.dot(d) > 0.0 {
                    n = -n;
                }
                let foot = (-p.z).max(1e-6) / focal;
                (p.is_finite() && n.is_finite()).then_some((p, n, foot))
            })
            .collect();
        Guide {
            width: w,
            height: h,
            hits,
        }
    }
}

/// Luminance of the diffuse coefficient at R = 0 (a proxy for irradiance).
#[inline]
pub fn table_luminance(t: &PixelTable) -> f32 {
    lum(t.c[0])
}

#[inline]
fn lum(v: Vec3) -> f32 {
    0.2126 * v.x + 0.7152 * v.y + 0.0722 * v.z
}

fn scale_add(acc: &mut PixelTable, t: &PixelTable, w: f32) {
    acc.base += t.base * w;
    for k in 0..3 {
        acc.c[k] += t.c[k] * w;
    }
    for (a, b) in acc.spec.iter_mut().zip(t.spec.iter()) {
        for k in 0..4 {
            a[k] += b[k] * w;
        }
    }
}

fn scaled(t: &PixelTable, s: f32) -> PixelTable {
    let mut out = PixelTable::default();
    scale_add(&mut out, t, s);
    out
}

/// Filters `tables` in place with `iterations` à-trous passes. `variance`
/// is the per-pixel variance of [`table_luminance`]'s estimate; `valid`
/// marks pixels whose table models their own primary vertex (others are
/// neither changed nor used).
pub fn denoise_tables(
    tables: &mut [PixelTable],
    variance: &[f32],
    valid: &[bool],
    guide: &Guide,
    iterations: usize,
) {
    let (w, h) = (guide.width, guide.height);
    assert_eq!(tables.len(), w * h);
    let mut var: Vec<f32> = variance
        .iter()
        .map(|v| if v.is_finite() { v.max(0.0) } else { 0.0 })
        .collect();
    for it in 0..iterations {
        let step = 1isize << it;
        let lums: Vec<f32> = tables.iter().map(table_luminance).collect();
        // σ from a 3×3 blur of the variance, as SVGF does.
        let sigma: Vec<f32> = (0..w * h)
            .into_par_iter()
            .with_min_len(1024)
            .map(|i| {
                let (x, y) = ((i % w) as isize, (i / w) as isize);
                let (mut s, mut n) = (0f32, 0f32);
                for dy in -1..=1 {
                    for dx in -1..=1 {
                        let (qx, qy) = (x + dx, y + dy);
                        if qx < 0 || qy < 0 || qx >= w as isize || qy >= h as isize {
                            continue;
                        }
                        let q = qy as usize * w + qx as usize;
                        if valid[q] {
                            s += var[q];
                            n += 1.0;
                        }
                    }
                }
                if n > 0.0 {
                    (s / n).sqrt()
                } else {
                    0.0
                }
            })
            .collect();
        // One output pixel of this pass, from the pass's input.
        let filtered = |tables: &[PixelTable], var: &[f32], i: usize| -> (PixelTable, f32) {
            let Some((xp, np, foot)) = guide.hits[i].filter(|_| valid[i]) else {
                return (tables[i], var[i]);
            };
            let (x, y) = ((i % w) as isize, (i / w) as isize);
            let lp = lums[i];
            let inv_l = 1.0 / (SIGMA_L * sigma[i] + 1e-6 * lp.abs() + 1e-12);
            let mut acc = PixelTable::default();
            let (mut wsum, mut vsum) = (0f32, 0f32);
            for (j, hy) in B3.iter().enumerate() {
                let qy = y + (j as isize - 2) * step;
                if qy < 0 || qy >= h as isize {
                    continue;
                }
                for (k, hx) in B3.iter().enumerate() {
                    let qx = x + (k as isize - 2) * step;
                    if qx < 0 || qx >= w as isize {
                        continue;
                    }
                    let q = qy as usize * w + qx as usize;
                    if !valid[q] {
                        continue;
                    }
                    let Some((xq, nq, _)) = guide.hits[q] else {
                        continue;
                    };
                    let wn = np.dot(nq).max(0.0).powi(SIGMA_N);
                    let off =
                        ((j as f32 - 2.0).powi(2) + (k as f32 - 2.0).powi(2)).sqrt() * step as f32;
                    let wz = if q == i {
                        1.0
                    } else {
                        (-((xq - xp).dot(np)).abs() / (2.0 * foot * off)).exp()
                    };
                    let wl = (-(lums[q] - lp).abs() * inv_l).exp();
                    let wt = hx * hy * wn * wz * wl;
                    if !(wt > 0.0) || !wt.is_finite() {
                        continue;
                    }
                    scale_add(&mut acc, &tables[q], wt);
                    wsum += wt;
                    vsum += wt * wt * var[q];
                }
            }
            if wsum > 0.0 {
                (scaled(&acc, 1.0 / wsum), vsum / (wsum * wsum))
            } else {
                (tables[i], var[i])
            }
        };
        // Bands of rows are filtered in turn (each in parallel) and
        // written back once no later band reads them (`reach` rows below
        // a band's first row): the pass holds a few bands of output, not
        // a second copy of every table (214 MB at 512²). Each output is
        // the same gather as before, so the result does not change.
        let reach = 2 * step as usize;
        let mut pending: std::collections::VecDeque<(usize, Vec<(PixelTable, f32)>)> =
            Default::default();
        let mut y0 = 0;
        while y0 < h {
            let y1 = (y0 + BAND).min(h);
            let out: Vec<(PixelTable, f32)> = (y0 * w..y1 * w)
                .into_par_iter()
                .with_min_len(256)
                .map(|i| filtered(tables, &var, i))
                .collect();
            pending.push_back((y0, out));
            // The next band reads rows from y1 - reach on.
            while let Some((a, out)) = pending.front() {
                let b = a + out.len() / w;
                if y1 < h && b + reach > y1 {
                    break;
                }
                let start = a * w;
                for (k, (t, v)) in out.iter().enumerate() {
                    tables[start + k] = *t;
                    var[start + k] = *v;
                }
                pending.pop_front();
            }
            y0 = y1;
        }
        debug_assert!(pending.is_empty());
    }
}

/// Rows filtered at once by [`denoise_tables`].
const BAND: usize = 16;

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
                .map(|((a, b), _)| (lum(a.c[0]) - lum(b.c[0])).abs() as f64)
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
