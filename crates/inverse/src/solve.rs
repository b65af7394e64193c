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
use crate::loss::{exposure_ratio, gamma, gamma_inv, gamma_toe, gamma_value, pixel_loss, Target};
use crate::matfit::{MatFit, Parts};
use crate::tables::PixelTable;
use matflow_render::lanes::{F, M};

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

/// One pixel's inputs to its solve.
struct PixelProblem<'a> {
    t: &'a PixelTable,
    /// The current materials (the start of the search).
    m: Material,
    pred: Material,
    tg: Vec3,
    /// γ⁻¹ of the target, for the exact albedo fits.
    tl: Vec3,
    sat: [bool; 3],
    k: f32,
    c2: f32,
    /// [`gamma_toe`], hoisted.
    toe: f32,
}

impl PixelProblem<'_> {
    /// γ⁻¹ of a target in γ space, per channel.
    fn linear(tg: Vec3) -> Vec3 {
        Vec3::new(gamma_inv(tg.x), gamma_inv(tg.y), gamma_inv(tg.z))
    }
}

matflow_render::lane_kernel!(fn solve_pixel_now = solve_pixel(p: &PixelProblem, o: &SolveOptions, out: &mut Material));

/// One pixel's solve: R and M (with A at its exact fit per candidate when
/// the stage solves A too), then A.
#[inline(always)]
fn solve_pixel<const W: usize>(p: &PixelProblem, o: &SolveOptions, out: &mut Material) {
    let mut m = p.m;
    if o.parts.roughness || o.parts.metallic {
        let (r, mm) = solve_rm::<W>(p, o);
        m.roughness = r;
        m.metallic = mm;
    }
    if o.parts.albedo {
        m.albedo = solve_albedo(p, &m, o);
    }
    *out = m.sanitized();
}

/// [`channel_loss`] in lanes, bit for bit.
#[inline(always)]
fn channel_loss_lanes<const W: usize>(i: F<W>, t: f32, sat: bool, c2: f32, toe: f32) -> F<W> {
    let e = gamma_value(i, toe) - t;
    let e = if sat {
        F::select(e.gt(0.0), F::splat(0.0), e)
    } else {
        e
    };
    e.abs() + c2 * e * e
}

/// Albedo of one pixel with R, M fixed: per channel, a golden-section
/// search between the exact fit and the prediction, the three channels
/// side by side in lanes (each lane the scalar search's steps, bit for
/// bit).
#[inline(always)]
fn solve_albedo(p: &PixelProblem, m: &Material, o: &SolveOptions) -> Vec3 {
    let (i, q) = p.t.eval_value(m);
    let pv = i - m.albedo * q;
    let k = p.k;
    let (mut lo, mut hi, mut pa, mut fixed) = ([0f32; 4], [0f32; 4], [0f32; 4], [true; 4]);
    let mut ends = [(0f32, 0f32); 4];
    for c in 0..3 {
        (lo[c], hi[c]) = bounds(p.pred.albedo[c], o.zeta, 0.0);
        pa[c] = p.pred.albedo[c].clamp(lo[c], hi[c]);
        if !(q[c] > 0.0) || !(k > 0.0) {
            ends[c] = (pa[c], pa[c]);
            continue;
        }
        // Exact fit: k(P + aQ) = γ⁻¹(T).
        let a0 = ((p.tl[c] / k - pv[c]) / q[c]).clamp(lo[c], hi[c]);
        ends[c] = if a0 <= pa[c] {
            (a0, pa[c])
        } else {
            (pa[c], a0)
        };
        fixed[c] = ends[c].1 - ends[c].0 < 1e-6;
    }
    if fixed[..3].iter().all(|&f| f) {
        return Vec3::new(ends[0].0, ends[1].0, ends[2].0);
    }
    // Lane 3 repeats channel 2.
    let lane = |v: [f32; 3]| F::<4>([v[0], v[1], v[2], v[2]]);
    let ch = AlbedoChannels {
        p: lane(pv.to_array()),
        q: lane(q.to_array()),
        pa: lane([pa[0], pa[1], pa[2]]),
        tg: lane(p.tg.to_array()),
        sat: M::from_array([p.sat[0], p.sat[1], p.sat[2], p.sat[2]]),
        k,
        toe: p.toe,
        c2: p.c2,
        delta: o.delta,
    };
    let best = golden_lanes(
        lane([ends[0].0, ends[1].0, ends[2].0]),
        lane([ends[0].1, ends[1].1, ends[2].1]),
        16,
        &ch,
    );
    Vec3::new(
        if fixed[0] { ends[0].0 } else { best.0[0] },
        if fixed[1] { ends[1].0 } else { best.0[1] },
        if fixed[2] { ends[2].0 } else { best.0[2] },
    )
}

/// The albedo objective of a pixel's channels, one per lane.
struct AlbedoChannels {
    p: F<4>,
    q: F<4>,
    pa: F<4>,
    tg: F<4>,
    sat: M<4>,
    k: f32,
    toe: f32,
    c2: f32,
    delta: f32,
}

impl AlbedoChannels {
    /// h(γ(k(P + aQ)) − γ(T)) + δ·|a − â| per lane: [`channel_loss`] plus
    /// consistency, bit for bit.
    #[inline(always)]
    fn loss(&self, a: F<4>) -> F<4> {
        let e = gamma_value(self.k * (self.p + a * self.q), self.toe) - self.tg;
        let e = F::select(self.sat & e.gt(0.0), F::splat(0.0), e);
        (e.abs() + self.c2 * e * e) + self.delta * (a - self.pa).abs()
    }
}

/// [`golden`] in lanes: each lane its own interval and search, the steps
/// of the scalar one, bit for bit.
#[inline(always)]
fn golden_lanes(mut a: F<4>, mut b: F<4>, iters: usize, f: &AlbedoChannels) -> F<4> {
    let (a0, b0) = (a, b);
    let mut c = b - GOLDEN * (b - a);
    let mut d = a + GOLDEN * (b - a);
    let (mut fc, mut fd) = (f.loss(c), f.loss(d));
    for _ in 0..iters {
        let left = fc.le(fd);
        // Left: the minimum is in [a, d]; else in [c, b].
        b = F::select(left, d, b);
        a = F::select(left, a, c);
        let x = F::select(left, b - GOLDEN * (b - a), a + GOLDEN * (b - a));
        let fx = f.loss(x);
        let (oc, ofc, od, ofd) = (c, fc, d, fd);
        c = F::select(left, x, od);
        fc = F::select(left, fx, ofd);
        d = F::select(left, oc, x);
        fd = F::select(left, ofc, fx);
    }
    let left = fc.le(fd);
    let mut best = F::select(left, c, d);
    let mut bv = fc.min(fd);
    for x in [a0, b0] {
        let v = f.loss(x);
        let better = v.lt(bv);
        best = F::select(better, x, best);
        bv = F::select(better, v, bv);
    }
    best
}

/// A pixel's search of R and M: its bounds and what every candidate
/// shares.
struct RmSearch<'a> {
    p: &'a PixelProblem<'a>,
    parts: Parts,
    delta: f32,
    abounds: [(f32, f32); 3],
}

impl RmSearch<'_> {
    /// The objective (re-rendering loss plus δ·consistency) at `W`
    /// candidates (R, M) at once; per lane the same bits as one at a
    /// time.
    #[inline(always)]
    fn losses<const W: usize>(&self, r: F<W>, mm: F<W>) -> F<W> {
        let p = self.p;
        let t = p.t;
        let a = p.m.albedo;
        // The table at the clamped roughness (PixelTable::eval_value).
        let rr = F::select(
            r.lt(MIN_ROUGHNESS),
            F::splat(MIN_ROUGHNESS),
            F::select(r.gt(1.0), F::splat(1.0), r),
        );
        // The spline's interval and basis per lane (the scalar ones).
        let hs: [(usize, f32, f32, [f32; 4]); W] =
            std::array::from_fn(|l| crate::tables::hermite(rr.0[l]));
        let idx: [usize; W] = std::array::from_fn(|l| hs[l].0);
        let basis = |k: usize| F(std::array::from_fn(|l| hs[l].3[k]));
        let (h00, h10h, h01, h11h) = (basis(0), basis(1), basis(2), basis(3));
        let one_m = 1.0 - mm;
        let mut cons = F::splat(0.0);
        let mut l = F::splat(0.0);
        let mut x = [F::splat(0.0); 3];
        let mut pc = [F::splat(0.0); 3];
        let mut qc = [F::splat(0.0); 3];
        for c in 0..3 {
            let node = |j: usize, e: usize| F(std::array::from_fn(|l| t.spec[idx[l] + j][e][c]));
            let s1 = node(0, 0) * h00 + node(0, 1) * h10h + node(1, 0) * h01 + node(1, 1) * h11h;
            let s2 = node(0, 2) * h00 + node(0, 3) * h10h + node(1, 2) * h01 + node(1, 3) * h11h;
            let d = t.c[0][c] + t.c[1][c] * rr + t.c[2][c] * (rr * rr);
            let f0 = 0.04 * one_m + a[c] * mm;
            let i = t.base[c] + a[c] * d * one_m + f0 * s1 + s2;
            let q = d * one_m + s1 * mm;
            pc[c] = i - a[c] * q;
            qc[c] = q;
            x[c] = F::splat(a[c]);
        }
        if self.parts.albedo {
            for c in 0..3 {
                let (lo, hi) = self.abounds[c];
                let fit = ((p.tl[c] / p.k - pc[c]) / qc[c]).clamp(lo, hi);
                let fallback = F::splat(p.pred.albedo[c].clamp(lo, hi));
                let ok = if p.k > 0.0 {
                    qc[c].gt(0.0)
                } else {
                    M::from_array([false; W])
                };
                x[c] = F::select(ok, fit, fallback);
                cons = cons + (x[c] - p.pred.albedo[c]).abs();
            }
        }
        for c in 0..3 {
            let i = (pc[c] + x[c] * qc[c]) * p.k;
            l = l + channel_loss_lanes(i, p.tg[c], p.sat[c], p.c2, p.toe);
        }
        if self.parts.roughness {
            cons = cons + 3.0 * (r - p.pred.roughness).abs();
        }
        if self.parts.metallic {
            cons = cons + 3.0 * (mm - p.pred.metallic).abs();
        }
        l + self.delta * cons
    }

    /// The objective at every candidate of `cands`, `W` at a time.
    #[inline(always)]
    fn all<const W: usize>(&self, cands: &[(f32, f32)], out: &mut [f32]) {
        let n = cands.len();
        for s in (0..n).step_by(W) {
            let at = |l: usize| cands[(s + l).min(n - 1)];
            let v = self.losses::<W>(
                F(std::array::from_fn(|l| at(l).0)),
                F(std::array::from_fn(|l| at(l).1)),
            );
            let k = W.min(n - s);
            out[s..s + k].copy_from_slice(&v.0[..k]);
        }
    }
}

/// Roughness and metallic of one pixel; with A fixed, or, when the stage
/// also solves albedo, with A at its exact-fit value for each candidate
/// (R, M) (clamped to its bounds), so that the search is over all three.
///
/// Cold: a 10 × 8 grid over the feasible box (denser at low roughness),
/// `W` candidates at a time. Then a compass search from the best point:
/// its four neighbours are evaluated together and the best improving one
/// is taken (the first in order on ties); without one the steps halve.
#[inline(always)]
fn solve_rm<const W: usize>(p: &PixelProblem, o: &SolveOptions) -> (f32, f32) {
    let (pred, m) = (&p.pred, &p.m);
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
    let search = RmSearch {
        p,
        parts: o.parts,
        delta: o.delta,
        abounds: std::array::from_fn(|c| bounds(pred.albedo[c], o.zeta, 0.0)),
    };
    const GR: usize = 10;
    const GM: usize = 8;
    let lerp = |a: f32, b: f32, i: usize, n: usize| a + (b - a) * i as f32 / (n - 1) as f32;
    let start = (m.roughness.clamp(rlo, rhi), m.metallic.clamp(mlo, mhi));
    let mut v = [0f32; GR * GM];
    search.all::<1>(&[start], &mut v[..1]);
    let mut best = (start.0, start.1, v[0]);
    let mut sr = (rhi - rlo) / (GR - 1) as f32;
    let mut sm = (mhi - mlo) / (GM - 1) as f32;
    if o.warm {
        sr *= 0.25;
        sm *= 0.25;
    } else {
        let mut grid = [(0f32, 0f32); GR * GM];
        for i in 0..GR {
            // Denser grid at low roughness, where the lobe changes fastest.
            let u = i as f32 / (GR - 1) as f32;
            let r = rlo + (rhi - rlo) * u * u;
            for j in 0..GM {
                grid[i * GM + j] = (r, lerp(mlo, mhi, j, GM));
            }
        }
        search.all::<W>(&grid, &mut v);
        for (g, &x) in grid.iter().zip(&v) {
            if x < best.2 {
                best = (g.0, g.1, x);
            }
        }
    }
    let mut cands = [(0f32, 0f32); 4];
    let mut vals = [0f32; 4];
    for _ in 0..14 {
        if sr.max(sm) < 2e-4 {
            break;
        }
        let mut n = 0;
        for (dr, dm) in [(sr, 0.0), (-sr, 0.0), (0.0, sm), (0.0, -sm)] {
            if dr == 0.0 && dm == 0.0 {
                continue;
            }
            cands[n] = ((best.0 + dr).clamp(rlo, rhi), (best.1 + dm).clamp(mlo, mhi));
            n += 1;
        }
        // Four candidates: four lanes at any width.
        search.all::<4>(&cands[..n], &mut vals[..n]);
        let mut moved = false;
        for j in 0..n {
            if vals[j] < best.2 {
                best = (cands[j].0, cands[j].1, vals[j]);
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
    let toe = gamma_toe();
    // (L1 + L2 mean, Σ unscaled render, L1 sum, L2 sum)
    let measure = |mats: &[Material], k: f32| -> (f64, f64, f64, f64) {
        let parts: Vec<(f64, f64, f64)> = mats
            .par_chunks(4096)
            .enumerate()
            .map(|(c, ms)| {
                let (mut a, mut b, mut s) = (0f64, 0f64, 0f64);
                for (j, m) in ms.iter().enumerate() {
                    let p = c * 4096 + j;
                    let i = tables[p].eval_value(m).0;
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
                let problem = PixelProblem {
                    t: &tables[p],
                    m: *m,
                    pred: pred[p],
                    tg: target.gamma[p],
                    tl: PixelProblem::linear(target.gamma[p]),
                    sat: target.saturated[p],
                    k,
                    c2,
                    toe,
                };
                let mut out = *m;
                solve_pixel_now(&problem, o, &mut out);
                out
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

    /// Every lane width solves every pixel to the same bits (cold and
    /// warm, all three parts), and the albedo's lane-wide golden sections
    /// are the scalar search's, channel by channel.
    #[test]
    fn lane_widths_give_the_same_bits_and_lanes_the_scalar_search() {
        let TableProblem {
            tables,
            truth,
            target,
            ..
        } = table_problem(13, 16);
        let toe = gamma_toe();
        for warm in [false, true] {
            let o = SolveOptions {
                warm,
                ..one_round(Parts::ARM, 0.1)
            };
            for p in 0..truth.len() {
                let pred = Material {
                    albedo: truth[p].albedo * 0.7 + Vec3::splat(0.1),
                    roughness: (truth[p].roughness + 0.2).min(1.0),
                    metallic: 0.3 * hash01(p as u64),
                };
                let problem = PixelProblem {
                    t: &tables[p],
                    m: pred,
                    pred,
                    tg: target.gamma[p],
                    tl: PixelProblem::linear(target.gamma[p]),
                    sat: target.saturated[p],
                    k: 0.9,
                    c2: 1.5,
                    toe,
                };
                let mut outs = [pred; 4];
                solve_pixel::<1>(&problem, &o, &mut outs[0]);
                solve_pixel::<4>(&problem, &o, &mut outs[1]);
                solve_pixel::<8>(&problem, &o, &mut outs[2]);
                solve_pixel::<16>(&problem, &o, &mut outs[3]);
                let bits = |m: &Material| {
                    (
                        m.albedo.to_array().map(f32::to_bits),
                        m.roughness.to_bits(),
                        m.metallic.to_bits(),
                    )
                };
                for out in &outs[1..] {
                    assert_eq!(bits(out), bits(&outs[0]), "pixel {p}, warm {warm}");
                }
                // The albedo search against the scalar golden section.
                let m = outs[0];
                let lanes = solve_albedo(&problem, &m, &o);
                let (i, q) = tables[p].eval_value(&m);
                let pv = i - m.albedo * q;
                for c in 0..3 {
                    let (lo, hi) = bounds(pred.albedo[c], o.zeta, 0.0);
                    let pa = pred.albedo[c].clamp(lo, hi);
                    let want = if !(q[c] > 0.0) {
                        pa
                    } else {
                        let a0 = ((gamma_inv(problem.tg[c]) / 0.9 - pv[c]) / q[c]).clamp(lo, hi);
                        let (s0, s1) = if a0 <= pa { (a0, pa) } else { (pa, a0) };
                        let f = |a: f32| {
                            channel_loss(
                                0.9 * (pv[c] + a * q[c]),
                                problem.tg[c],
                                problem.sat[c],
                                1.5,
                            ) + o.delta * (a - pa).abs()
                        };
                        if s1 - s0 < 1e-6 {
                            s0
                        } else {
                            golden(s0, s1, 16, f)
                        }
                    };
                    assert_eq!(lanes[c].to_bits(), want.to_bits(), "pixel {p} channel {c}");
                }
            }
        }
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
