//! Re-evaluating the frozen paths: the rendered image for given materials
//! and envmap, and its exact reverse-mode gradient with respect to every
//! envmap texel and every pixel's albedo, roughness and metallic —
//! including their effect through the indirect bounces.
//!
//! A path's radiance is evaluated back to front: at vertex k,
//! L_k = Σ_sky f_k·w·E(ω) + f_k(ω_c)·w_c·L_{k+1}. The adjoint runs front to
//! back. Gradients for vertices that use other pixels' materials scatter
//! anywhere in the image, so work is split into a fixed number of row bands
//! with private accumulators that are summed in band order: the result does
//! not depend on the thread count.

use glam::Vec3;
use matflow_render::Material;
use rayon::prelude::*;

use crate::brdf::eval;
#[cfg(test)]
use crate::brdf::eval_grad;
#[cfg(test)]
use crate::paths::taps;
use crate::paths::{sky, PathCache, Record, Vertex, MAX_DEPTH, NO_MATERIAL};

/// Number of row bands gradient accumulation is split into (fixed so that
/// results do not depend on the machine).
#[cfg(test)]
pub const BANDS: usize = 16;

/// Gradients of a scalar loss through every path vertex (the reference
/// for the per-pixel tables and the envmap transport production uses;
/// kept for the finite-difference checks).
#[cfg(test)]
#[derive(Clone, Debug)]
pub struct Gradients {
    pub albedo: Vec<Vec3>,
    pub roughness: Vec<f32>,
    pub metallic: Vec<f32>,
    pub env: Vec<Vec3>,
}

#[cfg(test)]
impl Gradients {
    pub fn zeros(npix: usize, ntex: usize) -> Gradients {
        Gradients {
            albedo: vec![Vec3::ZERO; npix],
            roughness: vec![0.0; npix],
            metallic: vec![0.0; npix],
            env: vec![Vec3::ZERO; ntex],
        }
    }
}

/// Splits a pixel's vertex list into paths: calls `f(first, end, rec0)`.
#[inline]
pub(crate) fn for_each_path(verts: &[Vertex], mut f: impl FnMut(usize, usize, usize)) {
    let mut i = 0;
    let mut r = 0;
    while i < verts.len() {
        let start = i;
        let r0 = r;
        r += verts[i].n_records();
        i += 1;
        while i < verts.len() && !verts[i].is_start() {
            r += verts[i].n_records();
            i += 1;
        }
        f(start, i, r0);
    }
}

/// Radiance of each vertex of one path, back to front: `l[k]` for vertex
/// `first + k`. Returns the number of vertices.
#[inline]
pub(crate) fn path_radiance(
    verts: &[Vertex],
    recs: &[Record],
    first: usize,
    end: usize,
    r0: usize,
    mats: &[Material],
    env: &[Vec3],
    ew: usize,
    l: &mut [Vec3; MAX_DEPTH as usize],
    rstart: &mut [usize; MAX_DEPTH as usize],
) -> usize {
    let n = (end - first).min(MAX_DEPTH as usize);
    let mut r = r0;
    for k in 0..n {
        rstart[k] = r;
        r += verts[first + k].n_records();
    }
    let mut next = Vec3::ZERO;
    for k in (0..n).rev() {
        let v = verts[first + k];
        let rs = &recs[rstart[k]..rstart[k] + v.n_records()];
        let mut acc = Vec3::ZERO;
        if v.q == NO_MATERIAL {
            for rec in &rs[..v.n_env as usize] {
                acc += sky(rec, env, ew) * rec.w;
            }
        } else {
            let m = mats[v.q as usize];
            for rec in &rs[..v.n_env as usize] {
                acc += eval(&rec.geo.decode(), &m) * (rec.w) * sky(rec, env, ew);
            }
            if v.has_cont() {
                let rec = &rs[v.n_env as usize];
                acc += eval(&rec.geo.decode(), &m) * rec.w * next;
            }
        }
        l[k] = acc;
        next = acc;
    }
    n
}

/// Radiance of pixel (x, y) summed over its paths (not yet divided by spp).
#[inline]
pub fn pixel_sum(cache: &PathCache, x: usize, y: usize, mats: &[Material], env: &[Vec3]) -> Vec3 {
    let (verts, recs) = cache.pixel(x, y);
    let mut l = [Vec3::ZERO; MAX_DEPTH as usize];
    let mut rs = [0usize; MAX_DEPTH as usize];
    let mut sum = Vec3::ZERO;
    for_each_path(verts, |a, b, r0| {
        path_radiance(
            verts,
            recs,
            a,
            b,
            r0,
            mats,
            env,
            cache.env_width,
            &mut l,
            &mut rs,
        );
        sum += l[0];
    });
    sum
}

/// The frozen estimator's image (linear RGB, row-major).
pub fn render(cache: &PathCache, mats: &[Material], env: &[Vec3]) -> Vec<Vec3> {
    let inv = 1.0 / cache.spp as f32;
    let w = cache.width;
    let rows: Vec<Vec<Vec3>> = (0..cache.height)
        .into_par_iter()
        .map(|y| {
            (0..w)
                .map(|x| sanitize(pixel_sum(cache, x, y, mats, env) * inv))
                .collect()
        })
        .collect();
    rows.into_iter().flatten().collect()
}

#[inline]
pub(crate) fn sanitize(v: Vec3) -> Vec3 {
    let f = |x: f32| if x.is_finite() { x.max(0.0) } else { 0.0 };
    Vec3::new(f(v.x), f(v.y), f(v.z))
}

#[cfg(test)]
struct BandAcc {
    albedo: Vec<Vec3>,
    rough: Vec<f32>,
    metal: Vec<f32>,
    env: Vec<[f64; 3]>,
}

#[cfg(test)]
/// Reverse mode: given ∂loss/∂I per pixel (`adj`), the gradient with
/// respect to all materials and envmap texels.
pub fn backward(cache: &PathCache, mats: &[Material], env: &[Vec3], adj: &[Vec3]) -> Gradients {
    let npix = cache.npix();
    let ntex = env.len();
    let (w, h) = (cache.width, cache.height);
    let ew = cache.env_width;
    let inv = 1.0 / cache.spp as f32;
    let bands = BANDS.min(h).max(1);
    let band_rows = h.div_ceil(bands);
    let accs: Vec<BandAcc> = (0..bands)
        .into_par_iter()
        .map(|b| {
            let mut acc = BandAcc {
                albedo: vec![Vec3::ZERO; npix],
                rough: vec![0.0; npix],
                metal: vec![0.0; npix],
                env: vec![[0.0; 3]; ntex],
            };
            let mut l = [Vec3::ZERO; MAX_DEPTH as usize];
            let mut rst = [0usize; MAX_DEPTH as usize];
            for y in b * band_rows..((b + 1) * band_rows).min(h) {
                for x in 0..w {
                    let a_p = adj[y * w + x] * inv;
                    if a_p == Vec3::ZERO || !a_p.is_finite() {
                        continue;
                    }
                    let (verts, recs) = cache.pixel(x, y);
                    for_each_path(verts, |first, end, r0| {
                        let n = path_radiance(
                            verts, recs, first, end, r0, mats, env, ew, &mut l, &mut rst,
                        );
                        let mut a = a_p;
                        for k in 0..n {
                            let v = verts[first + k];
                            let rs = &recs[rst[k]..rst[k] + v.n_records()];
                            if v.q == NO_MATERIAL {
                                for rec in &rs[..v.n_env as usize] {
                                    add_env(&mut acc.env, rec, ew, a * rec.w);
                                }
                                break;
                            }
                            let q = v.q as usize;
                            let m = mats[q];
                            let mut da = Vec3::ZERO;
                            let mut dr = 0.0f32;
                            let mut dm = 0.0f32;
                            for rec in &rs[..v.n_env as usize] {
                                let g = eval_grad(&rec.geo.decode(), &m);
                                let e = sky(rec, env, ew);
                                let c = a * e * rec.w;
                                da += c * g.da;
                                dr += (c * g.dr).element_sum();
                                dm += (c * g.dm).element_sum();
                                add_env(&mut acc.env, rec, ew, a * g.f * rec.w);
                            }
                            if v.has_cont() && k + 1 < n {
                                let rec = &rs[v.n_env as usize];
                                let g = eval_grad(&rec.geo.decode(), &m);
                                let c = a * l[k + 1] * rec.w;
                                da += c * g.da;
                                dr += (c * g.dr).element_sum();
                                dm += (c * g.dm).element_sum();
                                a *= g.f * rec.w;
                            } else {
                                a = Vec3::ZERO;
                            }
                            acc.albedo[q] += da;
                            acc.rough[q] += dr;
                            acc.metal[q] += dm;
                            if a == Vec3::ZERO {
                                break;
                            }
                        }
                    });
                }
            }
            acc
        })
        .collect();
    let mut g = Gradients::zeros(npix, ntex);
    let mut env_acc = vec![[0f64; 3]; ntex];
    for acc in &accs {
        for i in 0..npix {
            g.albedo[i] += acc.albedo[i];
            g.roughness[i] += acc.rough[i];
            g.metallic[i] += acc.metal[i];
        }
        for t in 0..ntex {
            for c in 0..3 {
                env_acc[t][c] += acc.env[t][c];
            }
        }
    }
    for t in 0..ntex {
        g.env[t] = Vec3::new(
            env_acc[t][0] as f32,
            env_acc[t][1] as f32,
            env_acc[t][2] as f32,
        );
    }
    g
}

#[inline]
#[cfg(test)]
fn add_env(env: &mut [[f64; 3]], rec: &Record, ew: usize, c: Vec3) {
    let (i, wt) = taps(rec, ew);
    for k in 0..4 {
        let e = &mut env[i[k]];
        e[0] += (c.x * wt[k]) as f64;
        e[1] += (c.y * wt[k]) as f64;
        e[2] += (c.z * wt[k]) as f64;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::paths::{CacheOptions, PathCache};
    use crate::testutil::{hash01, materials_of, room, texels};

    fn setup() -> (PathCache, Vec<Material>, Vec<Vec3>, usize) {
        let t = room(3, 12);
        let cache = PathCache::build(
            &t.scene,
            &CacheOptions {
                spp: 4,
                max_depth: 4,
                seed: 7,
                ..Default::default()
            },
            &|_, _| {},
        )
        .unwrap();
        // Keep parameters away from the clamps so derivatives exist.
        let mats: Vec<Material> = materials_of(&t.maps)
            .into_iter()
            .enumerate()
            .map(|(i, m)| Material {
                albedo: m.albedo.clamp(Vec3::splat(0.1), Vec3::splat(0.9)),
                roughness: 0.3 + 0.6 * hash01(i as u64 * 3 + 1),
                metallic: 0.1 + 0.8 * hash01(i as u64 * 3 + 2),
            })
            .collect();
        (cache, mats, texels(&t.env), 12 * 12)
    }

    /// Σ_p c_p·(I⁺_p − I⁻_p) in f64; unaffected pixels cancel exactly.
    fn fd(
        cache: &PathCache,
        c: &[Vec3],
        plus: (&[Material], &[Vec3]),
        minus: (&[Material], &[Vec3]),
        h: f64,
    ) -> f64 {
        let a = render(cache, plus.0, plus.1);
        let b = render(cache, minus.0, minus.1);
        let mut s = 0.0f64;
        for p in 0..a.len() {
            for k in 0..3 {
                s += c[p][k] as f64 * (a[p][k] as f64 - b[p][k] as f64);
            }
        }
        s / (2.0 * h)
    }

    fn close(an: f64, num: f64, what: &str) {
        let err = (an - num).abs();
        assert!(
            err <= 1e-3 * an.abs().max(num.abs()),
            "{what}: analytic {an:e} vs finite difference {num:e} (rel {:.2e})",
            err / an.abs().max(num.abs())
        );
    }

    /// Reverse-mode gradients of Σ c·I with respect to envmap texels and
    /// materials agree with central differences to 1e-3 relative, including
    /// a pixel whose own value is excluded from the loss, so that only its
    /// effect through indirect bounces remains.
    #[test]
    fn gradients_match_central_differences() {
        let (cache, mats, env, npix) = setup();
        let mut c: Vec<Vec3> = (0..npix)
            .map(|p| {
                Vec3::new(
                    hash01(p as u64 * 7 + 100),
                    hash01(p as u64 * 7 + 101),
                    hash01(p as u64 * 7 + 102),
                )
            })
            .collect();
        // Drop from the loss the pixel that deeper path vertices land on
        // most often, so that only its indirect effect remains.
        let mut visits = vec![0usize; npix];
        for y in 0..12 {
            for x in 0..12 {
                for v in cache.pixel(x, y).0 {
                    if !v.is_start() && (v.q as usize) < npix {
                        visits[v.q as usize] += 1;
                    }
                }
            }
        }
        let hidden = (0..npix).max_by_key(|&p| (visits[p], p)).unwrap();
        assert!(visits[hidden] > 0);
        c[hidden] = Vec3::ZERO;
        let g = backward(&cache, &mats, &env, &c);

        // Envmap: the five texels with the largest gradient (linear in E).
        let mut order: Vec<usize> = (0..env.len()).collect();
        order.sort_by(|&a, &b| g.env[b].x.abs().total_cmp(&g.env[a].x.abs()));
        for &t in order.iter().take(5) {
            let h = 0.05 * env[t].x.abs().max(0.1);
            let mut ep = env.clone();
            ep[t].x += h;
            let mut em = env.clone();
            em[t].x -= h;
            let num = fd(&cache, &c, (&mats, &ep), (&mats, &em), h as f64);
            close(g.env[t].x as f64, num, &format!("env texel {t}"));
        }

        // Materials of a few pixels, and of the hidden one.
        for &p in &[hidden, 3 * 12 + 4, 7 * 12 + 9, 11 * 12 + 1] {
            for what in 0..5 {
                let (an, h) = match what {
                    0 => (g.albedo[p].x, 0.05),
                    1 => (g.albedo[p].y, 0.05),
                    2 => (g.albedo[p].z, 0.05),
                    3 => (g.roughness[p], 0.003),
                    _ => (g.metallic[p], 0.05),
                };
                let pert = |s: f32| {
                    let mut m = mats.clone();
                    match what {
                        0 => m[p].albedo.x += s,
                        1 => m[p].albedo.y += s,
                        2 => m[p].albedo.z += s,
                        3 => m[p].roughness += s,
                        _ => m[p].metallic += s,
                    }
                    m
                };
                let (mp, mm) = (pert(h), pert(-h));
                let num = fd(&cache, &c, (&mp, &env), (&mm, &env), h as f64);
                if an == 0.0 && num == 0.0 {
                    continue;
                }
                close(an as f64, num, &format!("pixel {p} parameter {what}"));
            }
        }
        // The hidden pixel's albedo does influence the loss (indirectly).
        assert!(g.albedo[hidden].max_element() > 0.0);
    }

    /// The frozen estimator is the path tracer: with the materials and the
    /// envmap it was traced with, its mean agrees with an independent
    /// render of the forward integrator (box filter) at the same spp.
    #[test]
    fn frozen_estimator_matches_the_forward_renderer() {
        same_as_forward(room(5, 16), 256);
    }

    /// Likewise in a closed room whose assumed walls and ceiling let part
    /// of the light through (their share enters the recorded weights).
    #[test]
    fn frozen_estimator_matches_the_forward_renderer_through_partly_open_walls() {
        let t = crate::testutil::partly_open_room(4, 16, 0.3);
        assert!(t.scene.has_openness());
        // Two independent estimates: at 256 spp their difference was 1.0 %
        // of the image's energy for some meshes of the same room.
        same_as_forward(t, 512);
    }

    /// The same in a room closed with solid walls, lit through the
    /// windows of its assumed walls, which light samples aim at as
    /// portals (their density enters the recorded weights).
    #[test]
    fn frozen_estimator_matches_the_forward_renderer_through_portals() {
        let t = crate::testutil::partly_open_room(4, 16, 0.0);
        assert!(!t.scene.has_openness());
        assert!(!t.scene.portals.is_empty());
        // Closed, the room's light has more variance between seeds
        // (measured: ±0.4 % of the mean at 256 spp).
        same_as_forward(t, 1024);
    }

    fn same_as_forward(t: crate::testutil::TestScene, spp: u32) {
        let opts = CacheOptions {
            spp,
            ..Default::default()
        };
        let cache = PathCache::build(&t.scene, &opts, &|_, _| {}).unwrap();
        let mats = materials_of(&t.maps);
        let a = render(&cache, &mats, &texels(&t.env));
        let ro = matflow_render::RenderOptions {
            spp,
            seed: 99,
            filter: matflow_render::PixelFilter::Box,
            ..Default::default()
        };
        let b = matflow_render::render(&t.scene, &ro, &|_, _| {}).image.data;
        let sa: f64 = a.iter().map(|v| v.element_sum() as f64).sum();
        let sb: f64 = b.iter().map(|v| v.element_sum() as f64).sum();
        assert!((sa / sb - 1.0).abs() < 0.01, "mean {sa} vs {sb}");
        let mut err = 0.0f64;
        let mut norm = 0.0f64;
        for (x, y) in a.iter().zip(&b) {
            err += (*x - *y).length_squared() as f64;
            norm += y.length_squared() as f64;
        }
        assert!(err / norm < 0.01, "relative squared error {}", err / norm);
    }
}
