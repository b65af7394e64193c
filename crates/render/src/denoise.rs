//! Edge-aware à-trous filtering in screen space (SVGF, Schied et al.
//! 2017), shared by the inverse stages' per-pixel light tables and by
//! renders of screen-space materials.
//!
//! A value per pixel (anything linear in the light: a table of light
//! integrals, or a render's radiance divided by the pixel's albedo) is
//! filtered by an à-trous wavelet (5×5 B3-spline taps at spacings 1, 2,
//! 4, …) whose weights stop at
//!
//! * normal changes: `max(0, n_p·n_q)^SIGMA_N`;
//! * leaving the pixel's plane: `exp(−|(x_q − x_p)·n_p| / (2·footprint·|o|))`,
//!   footprint = the pixel's size at its depth, |o| = the tap offset;
//! * changes beyond the noise (shadow edges):
//!   `exp(−|l_p − l_q| / (SIGMA_L·σ_p))`, l the value's luminance and σ_p
//!   its estimated standard error, itself filtered.
//!
//! A weighted mean of values linear in the light is the value of a
//! weighted mean of the light: the filter is spatial reuse of the
//! neighbours' paths. Pure gathers in a fixed order: the result does not
//! depend on the thread count.

use glam::{Vec2, Vec3};
use matflow_scene::color::luminance;
use matflow_scene::RgbImage;
use rayon::prelude::*;

use crate::RenderScene;

pub const SIGMA_N: i32 = 32;
pub const SIGMA_L: f32 = 4.0;
const B3: [f32; 5] = [1.0 / 16.0, 1.0 / 4.0, 3.0 / 8.0, 1.0 / 4.0, 1.0 / 16.0];
/// Rows filtered at once by [`atrous`].
const BAND: usize = 16;

/// Geometry of each pixel's primary hit (through the pixel centre).
#[derive(Clone, Debug)]
pub struct Guide {
    pub width: usize,
    pub height: usize,
    /// Camera-space position, normal facing the camera, and the world size
    /// of one pixel there; `None` where the centre ray misses.
    pub hits: Vec<Option<(Vec3, Vec3, f32)>>,
    /// Whether the centre ray meets geometry carrying the screen-space
    /// material of its pixel (the view's mesh, not an inserted object).
    pub screen: Vec<bool>,
}

impl Guide {
    pub fn build(scene: &RenderScene) -> Guide {
        let (w, h) = (scene.camera.width, scene.camera.height);
        let focal = scene.camera.focal().max(1e-6);
        let (hits, screen) = (0..w * h)
            .into_par_iter()
            .with_min_len(1024)
            .map(|i| {
                let film = Vec2::new((i % w) as f32 + 0.5, (i / w) as f32 + 0.5);
                let d = scene.camera_ray(film);
                let Some(hit) = scene.bvh.intersect(Vec3::ZERO, d, 0.0, f32::INFINITY) else {
                    return (None, false);
                };
                let p = d * hit.t;
                let mut n = scene.face_normals[hit.prim as usize];
                if n.dot(d) > 0.0 {
                    n = -n;
                }
                let foot = (-p.z).max(1e-6) / focal;
                let ok = p.is_finite() && n.is_finite();
                (
                    ok.then_some((p, n, foot)),
                    ok && (hit.prim as usize) < scene.screen_prims,
                )
            })
            .unzip();
        Guide {
            width: w,
            height: h,
            hits,
            screen,
        }
    }
}

/// A per-pixel value [`atrous`] can filter: linear (weighted sums) with a
/// luminance for the edge-stopping weight.
pub trait Filterable: Copy + Default + Send + Sync {
    fn luminance(&self) -> f32;
    /// `self += o · w`.
    fn scale_add(&mut self, o: &Self, w: f32);
}

impl Filterable for Vec3 {
    #[inline]
    fn luminance(&self) -> f32 {
        luminance(*self)
    }
    #[inline]
    fn scale_add(&mut self, o: &Self, w: f32) {
        *self += *o * w;
    }
}

/// Filters `values` in place with `iterations` à-trous passes. `variance`
/// is the per-pixel variance of the estimate of their luminance; `valid`
/// marks the pixels to filter (others are neither changed nor used).
pub fn atrous<T: Filterable>(
    values: &mut [T],
    variance: &[f32],
    valid: &[bool],
    guide: &Guide,
    iterations: usize,
) {
    let (w, h) = (guide.width, guide.height);
    assert_eq!(values.len(), w * h);
    let mut var: Vec<f32> = variance
        .iter()
        .map(|v| if v.is_finite() { v.max(0.0) } else { 0.0 })
        .collect();
    for it in 0..iterations {
        let step = 1isize << it;
        let lums: Vec<f32> = values.iter().map(T::luminance).collect();
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
        let filtered = |values: &[T], var: &[f32], i: usize| -> (T, f32) {
            let Some((xp, np, foot)) = guide.hits[i].filter(|_| valid[i]) else {
                return (values[i], var[i]);
            };
            let (x, y) = ((i % w) as isize, (i / w) as isize);
            let lp = lums[i];
            let inv_l = 1.0 / (SIGMA_L * sigma[i] + 1e-6 * lp.abs() + 1e-12);
            let mut acc = T::default();
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
                    acc.scale_add(&values[q], wt);
                    wsum += wt;
                    vsum += wt * wt * var[q];
                }
            }
            if wsum > 0.0 {
                let mut out = T::default();
                out.scale_add(&acc, 1.0 / wsum);
                (out, vsum / (wsum * wsum))
            } else {
                (values[i], var[i])
            }
        };
        // Bands of rows are filtered in turn (each in parallel) and
        // written back once no later band reads them (`reach` rows below
        // a band's first row): the pass holds a few bands of output, not
        // a second copy of every value (214 MB of tables at 512²). Each
        // output is the same gather as before, so the result does not
        // change.
        let reach = 2 * step as usize;
        let mut pending: std::collections::VecDeque<(usize, Vec<(T, f32)>)> = Default::default();
        let mut y0 = 0;
        while y0 < h {
            let y1 = (y0 + BAND).min(h);
            let out: Vec<(T, f32)> = (y0 * w..y1 * w)
                .into_par_iter()
                .with_min_len(256)
                .map(|i| filtered(values, &var, i))
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
                    values[start + k] = *t;
                    var[start + k] = *v;
                }
                pending.pop_front();
            }
            y0 = y1;
        }
        debug_assert!(pending.is_empty());
    }
}

/// Passes of [`denoise_render`] (spacings 1, 2 and 4 pixels).
pub const RENDER_PASSES: usize = 3;
/// Smallest albedo a render is divided by (per channel), so that dark
/// pixels' radiance is not blown up before filtering.
pub const DEMODULATE_FLOOR: f32 = 0.02;

/// What [`render_denoised`] gives: the denoised image, the same samples
/// unfiltered and what tracing them took.
pub struct Denoised {
    pub image: RgbImage,
    pub raw: RgbImage,
    pub stats: crate::RenderStats,
}

/// Seed of a denoised render's second half (xor the options' seed).
pub const SECOND_HALF_SEED: u64 = 0x0005_eedb;

/// Renders `scene` with `opts` as two independent halves of its samples
/// (seeds `opts.seed` and `opts.seed ^ SECOND_HALF_SEED`) and denoises
/// them ([`denoise_render`], guided by `guide`, the scene's
/// [`Guide::build`]); `progress(done, total)` counts the tiles of both.
/// `None` below 2 samples per pixel or with a crop (nothing to tell the
/// noise from, or no whole view to filter).
pub fn render_denoised(
    scene: &RenderScene,
    guide: &Guide,
    opts: &crate::RenderOptions,
    passes: usize,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Option<Denoised> {
    if opts.spp < 2 || opts.crop.is_some() {
        return None;
    }
    let (na, nb) = (opts.spp.div_ceil(2), opts.spp / 2);
    let half = |k: usize, spp: u32, seed: u64| {
        let o = crate::RenderOptions { spp, seed, ..*opts };
        crate::render(scene, &o, &|d, t| progress(k * t + d, 2 * t))
    };
    let a = half(0, na, opts.seed);
    let b = half(1, nb, opts.seed ^ SECOND_HALF_SEED);
    let image = denoise_render(scene, guide, &a.image, na, &b.image, nb, passes);
    let mut stats = a.stats;
    stats.add(&b.stats);
    Some(Denoised {
        image,
        raw: mean_of_halves(&a.image, na, &b.image, nb),
        stats,
    })
}

/// The render that `na` samples per pixel in `a` and `nb` in `b` make
/// together: their mean weighted by sample counts (`a`'s size; `b` must
/// have as many pixels).
pub fn mean_of_halves(a: &RgbImage, na: u32, b: &RgbImage, nb: u32) -> RgbImage {
    let total = (na + nb).max(1) as f32;
    let (wa, wb) = (na as f32 / total, nb as f32 / total);
    RgbImage {
        width: a.width,
        height: a.height,
        data: a
            .data
            .iter()
            .zip(&b.data)
            .map(|(&x, &y)| x * wa + y * wb)
            .collect(),
    }
}

/// The render of `scene` from two independent halves of its samples, `a`
/// (`na` samples per pixel) and `b` (`nb`), denoised: their weighted mean,
/// divided by each pixel's albedo (screen-space materials, at least
/// [`DEMODULATE_FLOOR`]), filtered by [`atrous`] with `passes` passes
/// and multiplied back. The variance of each pixel's estimate comes from
/// the halves' difference (`(l_a − l_b)² / 4` for equal halves). Only
/// pixels whose centre ray meets the view's own mesh are filtered; sky
/// and inserted objects are kept as rendered, and so is everything when
/// `a` and `b` are not the scene's size.
pub fn denoise_render(
    scene: &RenderScene,
    guide: &Guide,
    a: &RgbImage,
    na: u32,
    b: &RgbImage,
    nb: u32,
    passes: usize,
) -> RgbImage {
    let (w, h) = (guide.width, guide.height);
    if scene.materials.len() != w * h {
        return mean_of_halves(a, na, b, nb);
    }
    let albedo: Vec<Vec3> = scene.materials.iter().map(|m| m.albedo).collect();
    denoise_halves(guide, &guide.screen, &albedo, a, na, b, nb, passes)
}

/// [`denoise_render`] for a scene of objects: every pixel whose centre
/// ray meets geometry is filtered, divided by `albedo` (the albedo seen
/// through each pixel's centre, textures included, at least
/// [`DEMODULATE_FLOOR`]); the sky is kept as rendered.
pub fn denoise_objects(
    guide: &Guide,
    albedo: &RgbImage,
    a: &RgbImage,
    na: u32,
    b: &RgbImage,
    nb: u32,
    passes: usize,
) -> RgbImage {
    let (w, h) = (guide.width, guide.height);
    if albedo.width != w || albedo.height != h {
        return mean_of_halves(a, na, b, nb);
    }
    let hit: Vec<bool> = guide.hits.iter().map(|h| h.is_some()).collect();
    denoise_halves(guide, &hit, &albedo.data, a, na, b, nb, passes)
}

/// The halves' mean, demodulated by `albedo` where `filter` is set,
/// filtered there by [`atrous`] and multiplied back; elsewhere the mean.
#[allow(clippy::too_many_arguments)]
fn denoise_halves(
    guide: &Guide,
    filter: &[bool],
    albedo: &[Vec3],
    a: &RgbImage,
    na: u32,
    b: &RgbImage,
    nb: u32,
    passes: usize,
) -> RgbImage {
    let (w, h) = (guide.width, guide.height);
    let mean = mean_of_halves(a, na, b, nb);
    let sized = |im: &RgbImage| im.width == w && im.height == h;
    if !sized(a) || !sized(b) || albedo.len() != w * h || na == 0 || nb == 0 {
        return mean;
    }
    let total = (na + nb) as f32;
    let mean = mean.data;
    let demod: Vec<Vec3> = albedo
        .iter()
        .map(|a| a.max(Vec3::splat(DEMODULATE_FLOOR)))
        .collect();
    let valid: Vec<bool> = (0..w * h)
        .map(|i| filter[i] && mean[i].is_finite())
        .collect();
    let mut light: Vec<Vec3> = (0..w * h)
        .map(|i| {
            if valid[i] {
                mean[i] / demod[i]
            } else {
                mean[i]
            }
        })
        .collect();
    // Var(wa·A + wb·B) with Var(A) ∝ 1/na: the squared difference of the
    // halves estimates Var(A) + Var(B) = σ²(1/na + 1/nb), and the mean's
    // variance is σ²/(na + nb).
    let share = 1.0 / (total * (1.0 / na as f32 + 1.0 / nb as f32));
    let var: Vec<f32> = (0..w * h)
        .map(|i| {
            let d = luminance(a.data[i] / demod[i]) - luminance(b.data[i] / demod[i]);
            d * d * share
        })
        .collect();
    atrous(&mut light, &var, &valid, guide, passes);
    let data = (0..w * h)
        .map(|i| {
            let v = if valid[i] {
                light[i] * demod[i]
            } else {
                mean[i]
            };
            if v.is_finite() {
                v
            } else {
                mean[i]
            }
        })
        .collect();
    RgbImage {
        width: w,
        height: h,
        data,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{scene_from_depth, EnvMap, RenderOptions};
    use matflow_scene::{GrayImage, Image, MaterialMaps};

    /// A wall at depth 6 with a block at depth 4 in front of it (shadow
    /// and occlusion around it, depth edges), a strip of sky along the
    /// top, a checkerboard albedo, under a sky with a bright patch.
    fn block_scene(n: usize) -> RenderScene {
        let depth = GrayImage::from_fn(n, n, |x, y| {
            let block = (n / 3..2 * n / 3).contains(&x) && (n / 3..2 * n / 3).contains(&y);
            if y < n / 8 {
                0.0
            } else if block {
                4.0
            } else {
                6.0
            }
        });
        let mut maps = MaterialMaps::uniform(n, n, Vec3::splat(0.5), 0.6, 0.0);
        maps.albedo = Image::from_fn(n, n, |x, y| {
            if (x / 4 + y / 4) % 2 == 0 {
                Vec3::new(0.8, 0.6, 0.3)
            } else {
                Vec3::new(0.1, 0.2, 0.4)
            }
        });
        let sky = Image::from_fn(32, 16, |x, y| {
            let base = Vec3::new(0.3, 0.4, 0.6) * (1.0 - y as f32 / 20.0);
            if (12..15).contains(&x) && (3..5).contains(&y) {
                base + Vec3::splat(30.0)
            } else {
                base
            }
        });
        scene_from_depth(
            &depth,
            &maps,
            EnvMap::new(&sky).unwrap(),
            matflow_geom::MeshParams::default(),
            None,
        )
        .unwrap()
        .0
    }

    fn render(scene: &RenderScene, spp: u32, seed: u64) -> RgbImage {
        let o = RenderOptions {
            spp,
            seed,
            filter: crate::PixelFilter::Box,
            ..Default::default()
        };
        crate::render(scene, &o, &|_, _| {}).image
    }

    fn rmse(a: &RgbImage, b: &RgbImage, keep: impl Fn(usize) -> bool) -> f64 {
        let (mut s, mut n) = (0f64, 0usize);
        for (i, (x, y)) in a.data.iter().zip(&b.data).enumerate() {
            if keep(i) {
                s += (*x - *y).length_squared() as f64;
                n += 1;
            }
        }
        (s / n.max(1) as f64).sqrt()
    }

    /// The block scene at `n`², its guide, and two halves rendered with
    /// `spp_a` and `spp_b` samples per pixel (seeds 1 and 2).
    fn halves(n: usize, spp_a: u32, spp_b: u32) -> (RenderScene, Guide, RgbImage, RgbImage) {
        let scene = block_scene(n);
        let guide = Guide::build(&scene);
        let (a, b) = (render(&scene, spp_a, 1), render(&scene, spp_b, 2));
        (scene, guide, a, b)
    }

    /// Known answer: against a 1024-spp render, the denoised 8-spp render
    /// (two halves of 4) is far closer than the same samples unfiltered,
    /// both over the whole view and along the block's edges and the
    /// albedo's checker edges (the filter stops at depth and normal edges,
    /// and the albedo is divided out before filtering).
    #[test]
    fn denoised_render_is_closer_to_the_converged_one() {
        let n = 48;
        let (scene, guide, a, b) = halves(n, 4, 4);
        let reference = render(&scene, 1024, 99);
        let raw = mean_of_halves(&a, 4, &b, 4);
        let den = denoise_render(&scene, &guide, &a, 4, &b, 4, RENDER_PASSES);
        assert!(den.data.iter().all(|v| v.is_finite()));
        let all = |_| true;
        let (e_raw, e_den) = (rmse(&raw, &reference, all), rmse(&den, &reference, all));
        assert!(e_den < 0.5 * e_raw, "raw {e_raw}, denoised {e_den}");
        // Pixels next to the block's silhouette.
        let edge = |i: usize| {
            let (x, y) = (i % n, i / n);
            let near = |v: usize| {
                (v as isize - (n / 3) as isize).abs() <= 1
                    || (v as isize - (2 * n / 3) as isize).abs() <= 1
            };
            y >= n / 8 && (near(x) || near(y))
        };
        let (r_edge, d_edge) = (rmse(&raw, &reference, edge), rmse(&den, &reference, edge));
        assert!(
            d_edge < 0.8 * r_edge,
            "edges: raw {r_edge}, denoised {d_edge}"
        );
    }

    /// Denoising a scene of objects is the same filter: given the albedo
    /// each pixel sees, it gives exactly what the screen-space path gives
    /// where every hit is the view's mesh (and leaves the sky as it is).
    #[test]
    fn objects_denoise_as_the_screen_space_path_does() {
        let n = 32;
        let (scene, guide, a, b) = halves(n, 3, 3);
        let albedo = RgbImage {
            width: n,
            height: n,
            data: scene.materials.iter().map(|m| m.albedo).collect(),
        };
        let screen = denoise_render(&scene, &guide, &a, 3, &b, 3, RENDER_PASSES);
        let objects = denoise_objects(&guide, &albedo, &a, 3, &b, 3, RENDER_PASSES);
        assert_eq!(screen.data, objects.data);
        // A wrongly sized albedo is refused: the plain mean comes back.
        let small = RgbImage::new(4, 4, Vec3::ONE);
        let mean = mean_of_halves(&a, 3, &b, 3);
        assert_eq!(
            denoise_objects(&guide, &small, &a, 3, &b, 3, 2).data,
            mean.data
        );
    }

    /// The sky seen through the top strip is left as rendered; the mean of
    /// halves weights them by their sample counts.
    #[test]
    fn sky_is_kept_and_halves_are_weighted_by_samples() {
        let n = 24;
        let (scene, guide, a, b) = halves(n, 3, 1);
        let mean = mean_of_halves(&a, 3, &b, 1);
        for i in 0..n * n {
            let want = a.data[i] * 0.75 + b.data[i] * 0.25;
            assert!((mean.data[i] - want).abs().max_element() < 1e-6);
        }
        let den = denoise_render(&scene, &guide, &a, 3, &b, 1, RENDER_PASSES);
        for i in 0..n * n / 8 {
            assert!(!guide.screen[i]);
            assert_eq!(den.data[i], mean.data[i], "sky pixel {i}");
        }
        assert!(den.data[n * n / 2..]
            .iter()
            .zip(&mean.data[n * n / 2..])
            .any(|(x, y)| x != y));
    }

    /// The same halves give the same denoised image on 1 and 2 threads.
    #[test]
    fn denoising_does_not_depend_on_the_thread_count() {
        let (scene, guide, a, b) = halves(40, 2, 2);
        let on = |threads| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| denoise_render(&scene, &guide, &a, 2, &b, 2, RENDER_PASSES))
        };
        assert_eq!(on(1).data, on(2).data);
    }
}
