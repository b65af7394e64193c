//! Per-pixel exact material solves on the tables.
//!
//! With the envmap and the light arriving from deeper bounces held fixed
//! (what a [`PixelTable`] models) and the exposure factor k held fixed, the
//! loss L_re + δ·L_cons is a sum of independent per-pixel terms, so it can
//! be minimised pixel by pixel to (near) global optimality instead of by
//! gradient steps on all pixels at once:
//!
//! * albedo stage: R, M fixed, each channel is I_c = P_c + A_c·Q_c, and the
//!   1-D objective h(γ(k·I_c) − γ(T_c)) + δ·|A_c − Â_c| (h = |e| + e²) has
//!   its minimum between the exact-fit albedo and the prediction, found by
//!   golden-section search there;
//! * roughness/metallic stage: A fixed, a grid over (R, M) followed by a
//!   compass search with halving steps.
//!
//! k (the reference's `ratio`, see [`crate::matfit::MatFitOptions::rescale`])
//! is refreshed between rounds from the solved image. Each pixel's work is
//! a pure function of its inputs: deterministic for any thread count.

use glam::Vec3;
use matflow_render::bsdf::MIN_ROUGHNESS;
use matflow_render::Material;
use rayon::prelude::*;

use crate::envfit::FitTrace;
use crate::loss::{exposure_ratio, gamma, gamma_inv, pixel_loss, Target};
use crate::matfit::{MatFit, Parts};
use crate::tables::PixelTable;

#[derive(Clone, Copy, Debug)]
pub struct SolveOptions {
    pub delta: f32,
    pub zeta: f32,
    pub parts: Parts,
    /// Rounds of (solve every pixel, refresh k).
    pub rounds: usize,
    pub rescale: bool,
    /// Weight the squared term as the reference does, 3·(L1/L2)·L2 + L1
    /// with the ratio held constant (refreshed between rounds), instead of
    /// the paper's plain L1 + L2.
    pub reference_weighting: bool,
    /// Lowest roughness the solve may choose below the prediction (the
    /// floor is min(this, predicted R)). A lobe narrower than the
    /// spacing of a pixel's frozen directions is estimated from a handful
    /// of them, and a per-pixel minimum would exploit that noise (mirror
    /// "fixes" that an independent render does not reproduce).
    pub min_roughness: f32,
    /// Start from the current R, M (a compass search with fine steps)
    /// instead of a grid over their whole range: for stages after the
    /// first, whose starting materials are already a solve's answer.
    /// Rounds after a stage's first are always warm.
    pub warm: bool,
}

/// Feasible interval of a parameter: within ζ of the prediction and inside
/// its physical range.
#[inline]
fn bounds(pred: f32, zeta: f32, lo: f32) -> (f32, f32) {
    let a = (pred - zeta).max(lo);
    let b = (pred + zeta).min(1.0);
    if a <= b {
        (a, b)
    } else {
        (lo, 1.0)
    }
}

/// h(e) = |e| + c·e² for one channel, one-sided where the target is
/// saturated.
#[inline]
pub(crate) fn channel_loss(i: f32, t: f32, sat: bool, c2: f32) -> f32 {
    let mut e = gamma(i).0 - t;
    if sat && e > 0.0 {
        e = 0.0;
    }
    e.abs() + c2 * e * e
}

const GOLDEN: f32 = 0.618_034;

/// Minimises a function that is unimodal on [a, b] (golden section),
/// returning the best of the search and the two ends.
pub(crate) fn golden(mut a: f32, mut b: f32, iters: usize, f: impl Fn(f32) -> f32) -> f32 {
    let (a0, b0) = (a, b);
    let mut c = b - GOLDEN * (b - a);
    let mut d = a + GOLDEN * (b - a);
    let (mut fc, mut fd) = (f(c), f(d));
    for _ in 0..iters {
        if fc <= fd {
            b = d;
            d = c;
            fd = fc;
            c = b - GOLDEN * (b - a);
            fc = f(c);
        } else {
            a = c;
            c = d;
            fc = fd;
            d = a + GOLDEN * (b - a);
            fd = f(d);
        }
    }
    let mut best = (if fc <= fd { c } else { d }, fc.min(fd));
    for x in [a0, b0] {
        let v = f(x);
        if v < best.1 {
            best = (x, v);
        }
    }
    best.0
}

/// Albedo of one pixel with R, M fixed.
fn solve_albedo(
    t: &PixelTable,
    m: &Material,
    pred: &Material,
    tg: Vec3,
    sat: [bool; 3],
    k: f32,
    c2: f32,
    o: &SolveOptions,
) -> Vec3 {
    let e = t.eval(m);
    let q = e.da;
    let p = e.i - m.albedo * q;
    let mut out = m.albedo;
    for c in 0..3 {
        let (lo, hi) = bounds(pred.albedo[c], o.zeta, 0.0);
        let pa = pred.albedo[c].clamp(lo, hi);
        if !(q[c] > 0.0) || !(k > 0.0) {
            out[c] = pa;
            continue;
        }
        // Exact fit: k(P + aQ) = γ⁻¹(T).
        let a0 = ((gamma_inv(tg[c]) / k - p[c]) / q[c]).clamp(lo, hi);
        let f = |a: f32| {
            channel_loss(k * (p[c] + a * q[c]), tg[c], sat[c], c2) + o.delta * (a - pa).abs()
        };
        let (s0, s1) = if a0 <= pa { (a0, pa) } else { (pa, a0) };
        out[c] = if s1 - s0 < 1e-6 {
            s0
        } else {
            golden(s0, s1, 16, f)
        };
    }
    out
}

/// Roughness and metallic of one pixel; with A fixed, or, when the stage
/// also solves albedo, with A at its exact-fit value for each candidate
/// (R, M) (clamped to its bounds), so that the search is over all three.
fn solve_rm(
    t: &PixelTable,
    m: &Material,
    pred: &Material,
    tg: Vec3,
    sat: [bool; 3],
    k: f32,
    c2: f32,
    o: &SolveOptions,
) -> (f32, f32) {
    let (rlo, rhi) = if o.parts.roughness {
        bounds(
            pred.roughness,
            o.zeta,
            o.min_roughness.min(pred.roughness).max(MIN_ROUGHNESS),
        )
    } else {
        (m.roughness, m.roughness)
    };
    let (mlo, mhi) = if o.parts.metallic {
        bounds(pred.metallic, o.zeta, 0.0)
    } else {
        (m.metallic, m.metallic)
    };
    let tl = Vec3::new(gamma_inv(tg.x), gamma_inv(tg.y), gamma_inv(tg.z));
    let abounds: [(f32, f32); 3] = std::array::from_fn(|c| bounds(pred.albedo[c], o.zeta, 0.0));
    let f = |r: f32, mm: f32| -> f32 {
        let mut x = Material {
            albedo: m.albedo,
            roughness: r,
            metallic: mm,
        };
        let mut cons = 0.0;
        // The pixel is affine in A for fixed R, M: I = P + A ⊙ Q.
        let e = t.eval(&x);
        let q = e.da;
        let p = e.i - x.albedo * q;
        if o.parts.albedo {
            for c in 0..3 {
                let (lo, hi) = abounds[c];
                x.albedo[c] = if q[c] > 0.0 && k > 0.0 {
                    ((tl[c] / k - p[c]) / q[c]).clamp(lo, hi)
                } else {
                    pred.albedo[c].clamp(lo, hi)
                };
                cons += (x.albedo[c] - pred.albedo[c]).abs();
            }
        }
        let i = (p + x.albedo * q) * k;
        let mut l = 0.0;
        for c in 0..3 {
            l += channel_loss(i[c], tg[c], sat[c], c2);
        }
        if o.parts.roughness {
            cons += 3.0 * (r - pred.roughness).abs();
        }
        if o.parts.metallic {
            cons += 3.0 * (mm - pred.metallic).abs();
        }
        l + o.delta * cons
    };
    const GR: usize = 10;
    const GM: usize = 8;
    let lerp = |a: f32, b: f32, i: usize, n: usize| a + (b - a) * i as f32 / (n - 1) as f32;
    let mut best = (
        m.roughness.clamp(rlo, rhi),
        m.metallic.clamp(mlo, mhi),
        f32::INFINITY,
    );
    best.2 = f(best.0, best.1);
    let mut sr = (rhi - rlo) / (GR - 1) as f32;
    let mut sm = (mhi - mlo) / (GM - 1) as f32;
    if o.warm {
        sr *= 0.25;
        sm *= 0.25;
    } else {
        for i in 0..GR {
            // Denser grid at low roughness, where the lobe changes fastest.
            let u = i as f32 / (GR - 1) as f32;
            let r = rlo + (rhi - rlo) * u * u;
            for j in 0..GM {
                let mm = lerp(mlo, mhi, j, GM);
                let v = f(r, mm);
                if v < best.2 {
                    best = (r, mm, v);
                }
            }
        }
    }
    for _ in 0..14 {
        if sr.max(sm) < 2e-4 {
            break;
        }
        let mut moved = false;
        for (dr, dm) in [(sr, 0.0), (-sr, 0.0), (0.0, sm), (0.0, -sm)] {
            if dr == 0.0 && dm == 0.0 {
                continue;
            }
            let r = (best.0 + dr).clamp(rlo, rhi);
            let mm = (best.1 + dm).clamp(mlo, mhi);
            let v = f(r, mm);
            if v < best.2 {
                best = (r, mm, v);
                moved = true;
            }
        }
        if !moved {
            sr *= 0.5;
            sm *= 0.5;
        }
    }
    (best.0, best.1)
}

/// Solves the stage's parts for every pixel; `start` holds the current
/// materials (parts not solved stay as they are).
pub fn solve_pixels(
    tables: &[PixelTable],
    target: &Target,
    pred: &[Material],
    start: &[Material],
    o: &SolveOptions,
    progress: &(dyn Fn(usize, f64) + Sync),
) -> MatFit {
    let n = tables.len();
    let target_sum = target.exposure_sum();
    let mut k = 1f32;
    let mut mats: Vec<Material> = start.iter().map(|m| m.sanitized()).collect();
    let mut trace = FitTrace::default();
    let rounds = o.rounds.max(1);
    // (L1 + L2 mean, Σ unscaled render, L1 sum, L2 sum)
    let measure = |mats: &[Material], k: f32| -> (f64, f64, f64, f64) {
        let parts: Vec<(f64, f64, f64)> = mats
            .par_chunks(4096)
            .enumerate()
            .map(|(c, ms)| {
                let (mut a, mut b, mut s) = (0f64, 0f64, 0f64);
                for (j, m) in ms.iter().enumerate() {
                    let p = c * 4096 + j;
                    let i = tables[p].eval(m).i;
                    s += target.exposure_part(p, i);
                    let (l1, l2, _) = pixel_loss(i * k, target.gamma[p], target.saturated[p]);
                    a += l1 as f64;
                    b += l2 as f64;
                }
                (a, b, s)
            })
            .collect();
        let (a, b, s) = parts.iter().fold((0.0, 0.0, 0.0), |(a, b, c), (x, y, z)| {
            (a + x, b + y, c + z)
        });
        ((a + b) / (3.0 * n.max(1) as f64), s, a, b)
    };
    let weight = |l1: f64, l2: f64| -> f32 {
        if o.reference_weighting && l2 > 0.0 {
            ((3.0 * l1 / l2) as f32).clamp(1.0, 1e4)
        } else {
            1.0
        }
    };
    let (l, s, l1, l2) = measure(&mats, k);
    let mut c2 = weight(l1, l2);
    trace.losses.push(l);
    progress(0, l);
    let update_k = |s: f64, k: f32| -> f32 {
        match exposure_ratio(target_sum, s) {
            Some(r) if o.rescale => r,
            _ => k,
        }
    };
    k = update_k(s, k);
    let mut k_used = k;
    for round in 0..rounds {
        k_used = k;
        let o = &SolveOptions {
            warm: o.warm || round > 0,
            ..*o
        };
        mats = mats
            .par_iter()
            .enumerate()
            .with_min_len(512)
            .map(|(p, m)| {
                let (tg, sat) = (target.gamma[p], target.saturated[p]);
                let mut m = *m;
                if o.parts.roughness || o.parts.metallic {
                    let (r, mm) = solve_rm(&tables[p], &m, &pred[p], tg, sat, k, c2, o);
                    m.roughness = r;
                    m.metallic = mm;
                }
                if o.parts.albedo {
                    m.albedo = solve_albedo(&tables[p], &m, &pred[p], tg, sat, k, c2, o);
                }
                m.sanitized()
            })
            .collect();
        let (l, s, l1, l2) = measure(&mats, k);
        trace.losses.push(l);
        trace.steps = round + 1;
        progress(round + 1, l);
        k = update_k(s, k);
        c2 = weight(l1, l2);
    }
    MatFit {
        materials: mats,
        scale: if o.rescale { k_used } else { 1.0 },
        trace,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testutil::{hash01, table_problem, TableProblem};

    /// One cold round with plain L1 + L2 and no exposure ratio.
    fn one_round(parts: Parts, delta: f32) -> SolveOptions {
        SolveOptions {
            delta,
            zeta: 1.3,
            parts,
            rounds: 1,
            rescale: false,
            reference_weighting: false,
            min_roughness: MIN_ROUGHNESS,
            warm: false,
        }
    }

    /// A warm solve (compass search from the previous answer, no grid)
    /// started at a cold solve's answer keeps its fit: the re-rendering
    /// loss stays within 1 % (each pixel minimises loss + consistency,
    /// and the albedo search has finite precision, so the reported loss
    /// alone may move a hair either way).
    #[test]
    fn warm_solve_never_loses_ground() {
        let TableProblem {
            tables,
            truth,
            target,
            ..
        } = table_problem(9, 24);
        let pred: Vec<Material> = truth
            .iter()
            .map(|t| Material {
                albedo: t.albedo * 0.8,
                roughness: 0.7,
                metallic: 0.05,
            })
            .collect();
        let o = one_round(Parts::ARM, 0.1);
        let cold = solve_pixels(&tables, &target, &pred, &pred, &o, &|_, _| {});
        let warm = solve_pixels(
            &tables,
            &target,
            &pred,
            &cold.materials,
            &SolveOptions { warm: true, ..o },
            &|_, _| {},
        );
        let (lc, lw) = (
            *cold.trace.losses.last().unwrap(),
            *warm.trace.losses.last().unwrap(),
        );
        assert!(lc < cold.trace.losses[0], "cold solve did not descend");
        assert!(lw <= lc * 1.01, "warm {lw} vs cold {lc}");
    }

    /// Known answer: the target is the tables' own image for the true
    /// materials; from perturbed predictions the albedo solve recovers the
    /// true albedo wherever light reaches the pixel, and the
    /// roughness/metallic solve drives the loss to (nearly) zero.
    #[test]
    fn solves_recover_the_materials_that_made_the_image() {
        let TableProblem {
            tables: tabs,
            truth,
            image: img,
            target,
        } = table_problem(5, 24);
        let pred: Vec<Material> = truth
            .iter()
            .enumerate()
            .map(|(p, m)| Material {
                albedo: (m.albedo + Vec3::splat(0.4 * hash01(p as u64) - 0.2))
                    .clamp(Vec3::ZERO, Vec3::ONE),
                roughness: (m.roughness + 0.3 * hash01(p as u64 + 99) - 0.15).clamp(0.07, 1.0),
                metallic: (m.metallic + 0.3 * hash01(p as u64 + 7) - 0.15).clamp(0.0, 1.0),
            })
            .collect();
        let opts = |parts| one_round(parts, 0.01);
        // Albedo with R, M at the truth.
        let start: Vec<Material> = pred
            .iter()
            .zip(&truth)
            .map(|(p, t)| Material {
                albedo: p.albedo,
                ..*t
            })
            .collect();
        let fit = solve_pixels(&tabs, &target, &pred, &start, &opts(Parts::A), &|_, _| {});
        let mut checked = 0;
        for p in 0..truth.len() {
            let q = tabs[p].eval(&truth[p]).da;
            for c in 0..3 {
                if q[c] > 0.05 && img[p][c] > 1e-3 && img[p][c] < 0.99 {
                    let (a, b) = (fit.materials[p].albedo[c], truth[p].albedo[c]);
                    assert!((a - b).abs() < 2e-3, "pixel {p} channel {c}: {a} vs {b}");
                    checked += 1;
                }
            }
        }
        assert!(checked > truth.len(), "only {checked} channels checked");
        assert!(*fit.trace.losses.last().unwrap() < 1e-4);
        // Roughness and metallic with A at the truth.
        let start: Vec<Material> = pred
            .iter()
            .zip(&truth)
            .map(|(p, t)| Material {
                albedo: t.albedo,
                ..*p
            })
            .collect();
        let fit = solve_pixels(&tabs, &target, &pred, &start, &opts(Parts::RM), &|_, _| {});
        let l = &fit.trace.losses;
        assert!(l[1] < 0.05 * l[0], "loss {} -> {}", l[0], l[1]);
        assert!(fit
            .materials
            .iter()
            .all(|m| m.albedo.is_finite() && m.roughness >= 0.07 && m.metallic <= 1.0));
    }

    #[test]
    fn golden_finds_the_minimum_of_a_unimodal_function() {
        let x = golden(0.0, 1.0, 30, |x| (x - 0.3).abs() + 0.1 * x);
        assert!((x - 0.3).abs() < 1e-4);
        // Minimum at an end.
        let x = golden(0.0, 1.0, 30, |x| x);
        assert_eq!(x, 0.0);
    }
}
