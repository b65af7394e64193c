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
}

impl PixelProblem<'_> {
    /// γ⁻¹ of a target in γ space, per channel.
    fn linear(tg: Vec3) -> Vec3 {
        Vec3::new(gamma_inv(tg.x), gamma_inv(tg.y), gamma_inv(tg.z))
    }
}

/// What every pixel of a round shares.
#[derive(Clone, Copy, Debug)]
struct Round {
    /// The exposure factor.
    k: f32,
    /// The squared term's weight.
    c2: f32,
    /// [`gamma_toe`], hoisted.
    toe: f32,
}

/// Pixels solved side by side. Each search is a chain of dependent steps
/// (a compass move waits for the losses before it, a golden-section step
/// for the one before), which leaves the vector units idle while one
/// pixel's step finishes; `BATCH` pixels' searches share a vector of
/// 4·`BATCH` lanes instead, each lane the one-pixel search's operations,
/// bit for bit (a pixel's answer does not depend on its neighbour). Two
/// pixels took a cold round 0.80× and a warm one 0.89× (jinjya and indoor
/// at 20 s); four, in two AVX2 registers, were slower than two.
const BATCH: usize = 2;
/// Four lanes per pixel: a compass search's four neighbours, or the
/// albedo's three channels (the fourth repeating the third).
const LANES: usize = 4 * BATCH;

matflow_render::lane_kernel!(fn solve_batch_now = solve_batch(ps: &[PixelProblem], round: &Round, o: &SolveOptions, out: &mut [Material]));

/// The solves of 1 to [`BATCH`] pixels (`out` as long as `ps`): R and M
/// (with A at its exact fit per candidate when the stage solves A too),
/// then A. `W` is the width of the cold search's grid.
#[inline(always)]
fn solve_batch<const W: usize>(
    ps: &[PixelProblem],
    round: &Round,
    o: &SolveOptions,
    out: &mut [Material],
) {
    let n = ps.len().min(out.len()).min(BATCH);
    if n == 0 {
        return;
    }
    // Empty slots repeat the last pixel; their answers are dropped.
    let slot: [&PixelProblem; BATCH] = std::array::from_fn(|i| &ps[i.min(n - 1)]);
    let mut ms: [Material; BATCH] = slot.map(|p| p.m);
    if o.parts.roughness || o.parts.metallic {
        for (m, (r, mm)) in ms.iter_mut().zip(solve_rm::<W>(&slot, round, o)) {
            m.roughness = r;
            m.metallic = mm;
        }
    }
    if o.parts.albedo {
        let albedo = solve_albedo(&slot, &ms, round, o);
        for (m, a) in ms.iter_mut().zip(albedo) {
            m.albedo = a;
        }
    }
    for (o, m) in out.iter_mut().zip(&ms[..n]) {
        *o = m.sanitized();
    }
}

/// [`channel_loss`] in lanes, bit for bit; each lane its own target.
#[inline(always)]
fn channel_loss_lanes<const W: usize>(i: F<W>, t: F<W>, sat: M<W>, c2: f32, toe: f32) -> F<W> {
    let e = gamma_value(i, toe) - t;
    let e = F::select(sat & e.gt(0.0), F::splat(0.0), e);
    e.abs() + c2 * e * e
}

/// A pixel's albedo bounds in channel `c` (within ζ of the prediction)
/// and the prediction clamped to them.
#[inline]
fn albedo_bounds(p: &PixelProblem, c: usize, o: &SolveOptions) -> (f32, f32, f32) {
    let (lo, hi) = bounds(p.pred.albedo[c], o.zeta, 0.0);
    (lo, hi, p.pred.albedo[c].clamp(lo, hi))
}

/// `f32::clamp` per lane with per-lane bounds ([`F::clamp`]'s steps).
#[inline(always)]
fn clamp_lanes<const W: usize>(x: F<W>, lo: F<W>, hi: F<W>) -> F<W> {
    let x = F::select(x.lt(lo), lo, x);
    F::select(x.gt(hi), hi, x)
}

/// One pixel's albedo search with R, M fixed: per channel, the interval
/// between the exact fit and the prediction, and whether it is a point.
struct AlbedoStart {
    /// The render without the albedo's term, and that term's factor.
    p: Vec3,
    q: Vec3,
    /// The prediction clamped to its bounds.
    pa: [f32; 3],
    ends: [(f32, f32); 3],
    fixed: [bool; 3],
}

impl AlbedoStart {
    fn new(p: &PixelProblem, m: &Material, round: &Round, o: &SolveOptions) -> AlbedoStart {
        let (i, q) = p.t.eval_value(m);
        let pv = i - m.albedo * q;
        let k = round.k;
        let mut st = AlbedoStart {
            p: pv,
            q,
            pa: [0.0; 3],
            ends: [(0.0, 0.0); 3],
            fixed: [true; 3],
        };
        for c in 0..3 {
            let (lo, hi, pa) = albedo_bounds(p, c, o);
            st.pa[c] = pa;
            if !(q[c] > 0.0) || !(k > 0.0) {
                st.ends[c] = (pa, pa);
                continue;
            }
            // Exact fit: k(P + aQ) = γ⁻¹(T).
            let a0 = ((p.tl[c] / k - pv[c]) / q[c]).clamp(lo, hi);
            st.ends[c] = if a0 <= pa { (a0, pa) } else { (pa, a0) };
            st.fixed[c] = st.ends[c].1 - st.ends[c].0 < 1e-6;
        }
        st
    }
}

/// Albedo of each pixel with its R, M fixed: per channel, a
/// golden-section search between the exact fit and the prediction, all
/// pixels' channels side by side in lanes (each lane the scalar search's
/// steps, bit for bit).
#[inline(always)]
fn solve_albedo(
    ps: &[&PixelProblem; BATCH],
    ms: &[Material; BATCH],
    round: &Round,
    o: &SolveOptions,
) -> [Vec3; BATCH] {
    let st: [AlbedoStart; BATCH] =
        std::array::from_fn(|i| AlbedoStart::new(ps[i], &ms[i], round, o));
    let ends = |i: usize| Vec3::new(st[i].ends[0].0, st[i].ends[1].0, st[i].ends[2].0);
    if st.iter().all(|s| s.fixed.iter().all(|&f| f)) {
        return std::array::from_fn(ends);
    }
    // Lane 4i + c is pixel i's channel c; lane 4i + 3 repeats channel 2.
    let at = |l: usize| (l / 4, (l % 4).min(2));
    let lane = |f: &dyn Fn(usize, usize) -> f32| {
        F::<LANES>(std::array::from_fn(|l| {
            let (i, c) = at(l);
            f(i, c)
        }))
    };
    let ch = AlbedoChannels {
        p: lane(&|i, c| st[i].p[c]),
        q: lane(&|i, c| st[i].q[c]),
        pa: lane(&|i, c| st[i].pa[c]),
        tg: lane(&|i, c| ps[i].tg[c]),
        sat: M::from_array(std::array::from_fn(|l| {
            let (i, c) = at(l);
            ps[i].sat[c]
        })),
        k: round.k,
        toe: round.toe,
        c2: round.c2,
        delta: o.delta,
    };
    let best = golden_lanes(
        lane(&|i, c| st[i].ends[c].0),
        lane(&|i, c| st[i].ends[c].1),
        16,
        &ch,
    );
    std::array::from_fn(|i| {
        let pick = |c: usize| {
            if st[i].fixed[c] {
                st[i].ends[c].0
            } else {
                best.0[4 * i + c]
            }
        };
        Vec3::new(pick(0), pick(1), pick(2))
    })
}

/// The albedo objective of pixels' channels, one per lane.
struct AlbedoChannels<const L: usize> {
    p: F<L>,
    q: F<L>,
    pa: F<L>,
    tg: F<L>,
    sat: M<L>,
    k: f32,
    toe: f32,
    c2: f32,
    delta: f32,
}

impl<const L: usize> AlbedoChannels<L> {
    /// h(γ(k(P + aQ)) − γ(T)) + δ·|a − â| per lane: [`channel_loss`] plus
    /// consistency, bit for bit.
    #[inline(always)]
    fn loss(&self, a: F<L>) -> F<L> {
        let e = gamma_value(self.k * (self.p + a * self.q), self.toe) - self.tg;
        let e = F::select(self.sat & e.gt(0.0), F::splat(0.0), e);
        (e.abs() + self.c2 * e * e) + self.delta * (a - self.pa).abs()
    }
}

/// [`golden`] in lanes: each lane its own interval and search, the steps
/// of the scalar one, bit for bit.
#[inline(always)]
fn golden_lanes<const L: usize>(
    mut a: F<L>,
    mut b: F<L>,
    iters: usize,
    f: &AlbedoChannels<L>,
) -> F<L> {
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

/// What a pixel's table gives at one roughness, per channel: S1, S2 and
/// the diffuse factor. It depends on R alone, so candidates that share
/// R share it.
#[derive(Clone, Copy, Debug, Default)]
struct AtR {
    s1: [f32; 3],
    s2: [f32; 3],
    d: [f32; 3],
}

/// Each lane's table at its roughness ([`PixelTable::eval_value`]'s
/// operations, per lane the same bits as one at a time).
#[inline(always)]
fn at_r<const L: usize>(t: &[&PixelTable; L], r: F<L>) -> [AtR; L] {
    let rr = F::select(
        r.lt(MIN_ROUGHNESS),
        F::splat(MIN_ROUGHNESS),
        F::select(r.gt(1.0), F::splat(1.0), r),
    );
    // The spline's interval and basis per lane (the scalar ones).
    let hs: [(usize, f32, f32, [f32; 4]); L] =
        std::array::from_fn(|l| crate::tables::hermite(rr.0[l]));
    let idx: [usize; L] = std::array::from_fn(|l| hs[l].0);
    let basis = |k: usize| F::<L>(std::array::from_fn(|l| hs[l].3[k]));
    let (h00, h10h, h01, h11h) = (basis(0), basis(1), basis(2), basis(3));
    let mut out = [AtR::default(); L];
    for c in 0..3 {
        let node =
            |j: usize, e: usize| F::<L>(std::array::from_fn(|l| t[l].spec[idx[l] + j][e][c]));
        let coef = |k: usize| F::<L>(std::array::from_fn(|l| t[l].c[k][c]));
        let s1 = node(0, 0) * h00 + node(0, 1) * h10h + node(1, 0) * h01 + node(1, 1) * h11h;
        let s2 = node(0, 2) * h00 + node(0, 3) * h10h + node(1, 2) * h01 + node(1, 3) * h11h;
        let d = coef(0) + coef(1) * rr + coef(2) * (rr * rr);
        for (l, o) in out.iter_mut().enumerate() {
            o.s1[c] = s1.0[l];
            o.s2[c] = s2.0[l];
            o.d[c] = d.0[l];
        }
    }
    out
}

/// The search of R and M of the pixel in each lane: what its objective
/// needs of the pixel.
struct RmLanes<'a, const L: usize> {
    t: [&'a PixelTable; L],
    base: [F<L>; 3],
    /// The current albedo.
    a: [F<L>; 3],
    /// γ⁻¹(T)/k, the exact fit's.
    tl_k: [F<L>; 3],
    pred_a: [F<L>; 3],
    /// The albedo's bounds, and the prediction clamped to them.
    alo: [F<L>; 3],
    ahi: [F<L>; 3],
    pa: [F<L>; 3],
    pred_r: F<L>,
    pred_m: F<L>,
    tg: [F<L>; 3],
    sat: [M<L>; 3],
    round: Round,
    parts: Parts,
    delta: f32,
}

impl<'a, const L: usize> RmLanes<'a, L> {
    /// Lane `l` is pixel `ps[at(l)]`.
    fn new(
        ps: &[&'a PixelProblem<'a>; BATCH],
        at: impl Fn(usize) -> usize,
        round: &Round,
        o: &SolveOptions,
    ) -> RmLanes<'a, L> {
        let p: [&PixelProblem; L] = std::array::from_fn(|l| ps[at(l)]);
        let per = |f: &dyn Fn(&PixelProblem) -> f32| F::<L>(std::array::from_fn(|l| f(p[l])));
        RmLanes {
            t: p.map(|p| p.t),
            base: std::array::from_fn(|c| per(&|p| p.t.base[c])),
            a: std::array::from_fn(|c| per(&|p| p.m.albedo[c])),
            tl_k: std::array::from_fn(|c| per(&|p| p.tl[c] / round.k)),
            pred_a: std::array::from_fn(|c| per(&|p| p.pred.albedo[c])),
            alo: std::array::from_fn(|c| per(&|p| albedo_bounds(p, c, o).0)),
            ahi: std::array::from_fn(|c| per(&|p| albedo_bounds(p, c, o).1)),
            pa: std::array::from_fn(|c| per(&|p| albedo_bounds(p, c, o).2)),
            pred_r: per(&|p| p.pred.roughness),
            pred_m: per(&|p| p.pred.metallic),
            tg: std::array::from_fn(|c| per(&|p| p.tg[c])),
            sat: std::array::from_fn(|c| M::from_array(std::array::from_fn(|l| p[l].sat[c]))),
            round: *round,
            parts: o.parts,
            delta: o.delta,
        }
    }

    /// The objective (re-rendering loss plus δ·consistency) at each
    /// lane's candidate (R, M), with its roughness's [`AtR`]; per lane the
    /// same bits as one at a time.
    #[inline(always)]
    fn losses_at(&self, at: &[AtR; L], r: F<L>, mm: F<L>) -> F<L> {
        let k = self.round.k;
        let one_m = 1.0 - mm;
        let mut cons = F::splat(0.0);
        let mut l = F::splat(0.0);
        let mut x = [F::splat(0.0); 3];
        let mut pc = [F::splat(0.0); 3];
        let mut qc = [F::splat(0.0); 3];
        for c in 0..3 {
            let s1 = F::<L>(std::array::from_fn(|l| at[l].s1[c]));
            let s2 = F::<L>(std::array::from_fn(|l| at[l].s2[c]));
            let d = F::<L>(std::array::from_fn(|l| at[l].d[c]));
            let a = self.a[c];
            let f0 = 0.04 * one_m + a * mm;
            let i = self.base[c] + a * d * one_m + f0 * s1 + s2;
            let q = d * one_m + s1 * mm;
            pc[c] = i - a * q;
            qc[c] = q;
            x[c] = a;
        }
        if self.parts.albedo {
            for c in 0..3 {
                let fit = clamp_lanes((self.tl_k[c] - pc[c]) / qc[c], self.alo[c], self.ahi[c]);
                let ok = if k > 0.0 {
                    qc[c].gt(0.0)
                } else {
                    M::from_array([false; L])
                };
                x[c] = F::select(ok, fit, self.pa[c]);
                cons = cons + (x[c] - self.pred_a[c]).abs();
            }
        }
        for c in 0..3 {
            let i = (pc[c] + x[c] * qc[c]) * k;
            l = l + channel_loss_lanes(i, self.tg[c], self.sat[c], self.round.c2, self.round.toe);
        }
        if self.parts.roughness {
            cons = cons + 3.0 * (r - self.pred_r).abs();
        }
        if self.parts.metallic {
            cons = cons + 3.0 * (mm - self.pred_m).abs();
        }
        l + self.delta * cons
    }

    /// The objective at every candidate of a grid of `GR` roughnesses by
    /// `ms.len()` metallics (row-major), `L` at a time, the table
    /// evaluated once per roughness (every lane lane 0's pixel).
    #[inline(always)]
    fn grid<const GR: usize>(&self, rs: &[f32; GR], ms: &[f32], out: &mut [f32]) {
        let at = at_r(&[self.t[0]; GR], F(*rs));
        let n = GR * ms.len();
        for s in (0..n).step_by(L) {
            let c = |l: usize| (s + l).min(n - 1);
            let v = self.losses_at(
                &std::array::from_fn(|l| at[c(l) / ms.len()]),
                F(std::array::from_fn(|l| rs[c(l) / ms.len()])),
                F(std::array::from_fn(|l| ms[c(l) % ms.len()])),
            );
            let k = L.min(n - s);
            out[s..s + k].copy_from_slice(&v.0[..k]);
        }
    }
}

/// One pixel's compass search: its box, its best point and the table at
/// that point's roughness (kept while the best moves in M), its steps.
#[derive(Clone, Copy)]
struct Compass {
    rb: (f32, f32),
    mb: (f32, f32),
    best: (f32, f32, f32),
    at_best: (f32, AtR),
    sr: f32,
    sm: f32,
    active: bool,
}

impl Compass {
    /// The four moves, in the order ties are broken: ±R, then ±M.
    fn steps(&self) -> [(f32, f32); 4] {
        [
            (self.sr, 0.0),
            (-self.sr, 0.0),
            (0.0, self.sm),
            (0.0, -self.sm),
        ]
    }
}

/// Roughness and metallic of each pixel; with A fixed, or, when the stage
/// also solves albedo, with A at its exact-fit value for each candidate
/// (R, M) (clamped to its bounds), so that the search is over all three.
///
/// Cold: a 10 × 8 grid over the feasible box (denser at low roughness),
/// `W` candidates at a time. Then a compass search from the best point:
/// its four neighbours are evaluated together and the best improving one
/// is taken (the first in order on ties); without one the steps halve.
/// The pixels' compass searches run in lockstep, four lanes each.
#[inline(always)]
fn solve_rm<const W: usize>(
    ps: &[&PixelProblem; BATCH],
    round: &Round,
    o: &SolveOptions,
) -> [(f32, f32); BATCH] {
    const GR: usize = 10;
    const GM: usize = 8;
    let lerp = |a: f32, b: f32, i: usize, n: usize| a + (b - a) * i as f32 / (n - 1) as f32;
    let tables: [&PixelTable; BATCH] = ps.map(|p| p.t);
    let boxes: [((f32, f32), (f32, f32)); BATCH] = ps.map(|p| {
        let (pred, m) = (&p.pred, &p.m);
        let rb = if o.parts.roughness {
            bounds(
                pred.roughness,
                o.zeta,
                o.min_roughness.min(pred.roughness).max(MIN_ROUGHNESS),
            )
        } else {
            (m.roughness, m.roughness)
        };
        let mb = if o.parts.metallic {
            bounds(pred.metallic, o.zeta, 0.0)
        } else {
            (m.metallic, m.metallic)
        };
        (rb, mb)
    });
    // The start points, evaluated together.
    let starts: [(f32, f32); BATCH] = std::array::from_fn(|i| {
        let ((rlo, rhi), (mlo, mhi)) = boxes[i];
        (
            ps[i].m.roughness.clamp(rlo, rhi),
            ps[i].m.metallic.clamp(mlo, mhi),
        )
    });
    let one = RmLanes::<BATCH>::new(ps, |l| l, round, o);
    let r0 = F(starts.map(|s| s.0));
    let at0 = at_r(&tables, r0);
    let v0 = one.losses_at(&at0, r0, F(starts.map(|s| s.1)));
    let mut walks: [Compass; BATCH] = std::array::from_fn(|i| {
        let ((rlo, rhi), (mlo, mhi)) = boxes[i];
        Compass {
            rb: (rlo, rhi),
            mb: (mlo, mhi),
            best: (starts[i].0, starts[i].1, v0.0[i]),
            at_best: (starts[i].0, at0[i]),
            sr: (rhi - rlo) / (GR - 1) as f32,
            sm: (mhi - mlo) / (GM - 1) as f32,
            active: true,
        }
    });
    for (i, w) in walks.iter_mut().enumerate() {
        if o.warm {
            w.sr *= 0.25;
            w.sm *= 0.25;
            continue;
        }
        let ((rlo, rhi), (mlo, mhi)) = (w.rb, w.mb);
        // Denser grid at low roughness, where the lobe changes fastest.
        let rs: [f32; GR] = std::array::from_fn(|i| {
            let u = i as f32 / (GR - 1) as f32;
            rlo + (rhi - rlo) * u * u
        });
        let ms: [f32; GM] = std::array::from_fn(|j| lerp(mlo, mhi, j, GM));
        let mut v = [0f32; GR * GM];
        RmLanes::<W>::new(ps, |_| i, round, o).grid(&rs, &ms, &mut v);
        for (g, &x) in v.iter().enumerate() {
            if x < w.best.2 {
                w.best = (rs[g / GM], ms[g % GM], x);
            }
        }
        if w.best.0.to_bits() != w.at_best.0.to_bits() {
            w.at_best = (w.best.0, at_r::<1>(&[tables[i]], F([w.best.0]))[0]);
        }
    }
    let lanes = RmLanes::<LANES>::new(ps, |l| l / 4, round, o);
    let lane_tables: [&PixelTable; 2 * BATCH] = std::array::from_fn(|l| tables[l / 2]);
    let mut cands = [(0f32, 0f32); LANES];
    let mut at = [AtR::default(); LANES];
    for _ in 0..14 {
        for w in walks.iter_mut() {
            w.active &= w.sr.max(w.sm) >= 2e-4;
        }
        if !walks.iter().any(|w| w.active) {
            break;
        }
        // Each pixel's four neighbours, as (best + step) clamped: two new
        // roughnesses, whose tables are evaluated together, and two new
        // metallics at the best's roughness, whose table is kept.
        let next: [[(f32, f32); 4]; BATCH] = walks.map(|w| {
            w.steps().map(|(dr, dm)| {
                (
                    (w.best.0 + dr).clamp(w.rb.0, w.rb.1),
                    (w.best.1 + dm).clamp(w.mb.0, w.mb.1),
                )
            })
        });
        let at_rn = at_r(
            &lane_tables,
            F(std::array::from_fn(|l| next[l / 2][l % 2].0)),
        );
        let mut n = [0usize; BATCH];
        for (i, w) in walks.iter().enumerate() {
            let (cs, ats) = (&mut cands[4 * i..4 * i + 4], &mut at[4 * i..4 * i + 4]);
            if !w.active {
                // Idle lanes: the pixel's best, whose losses are dropped.
                cs.fill((w.best.0, w.best.1));
                ats.fill(w.at_best.1);
                continue;
            }
            for (j, (dr, dm)) in w.steps().into_iter().enumerate() {
                if dr == 0.0 && dm == 0.0 {
                    continue;
                }
                cs[n[i]] = next[i][j];
                ats[n[i]] = if j < 2 {
                    at_rn[2 * i + j]
                } else if next[i][j].0.to_bits() == w.at_best.0.to_bits() {
                    w.at_best.1
                } else {
                    at_r::<1>(&[tables[i]], F([next[i][j].0]))[0]
                };
                n[i] += 1;
            }
            // Unused lanes repeat the last candidate.
            for j in n[i]..4 {
                (cs[j], ats[j]) = (cs[n[i] - 1], ats[n[i] - 1]);
            }
        }
        let vals = lanes.losses_at(
            &at,
            F(std::array::from_fn(|l| cands[l].0)),
            F(std::array::from_fn(|l| cands[l].1)),
        );
        for (i, w) in walks.iter_mut().enumerate() {
            if !w.active {
                continue;
            }
            let mut moved = false;
            for j in 4 * i..4 * i + n[i] {
                if vals.0[j] < w.best.2 {
                    w.best = (cands[j].0, cands[j].1, vals.0[j]);
                    w.at_best = (cands[j].0, at[j]);
                    moved = true;
                }
            }
            if !moved {
                w.sr *= 0.5;
                w.sm *= 0.5;
            }
        }
    }
    walks.map(|w| (w.best.0, w.best.1))
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
        let shared = Round { k, c2, toe };
        let problem = |p: usize| PixelProblem {
            t: &tables[p],
            m: mats[p],
            pred: pred[p],
            tg: target.gamma[p],
            tl: PixelProblem::linear(target.gamma[p]),
            sat: target.saturated[p],
        };
        let mut next = mats.clone();
        next.par_chunks_mut(BATCH)
            .enumerate()
            .with_min_len(256)
            .for_each(|(b, out)| {
                let ps: [PixelProblem; BATCH] =
                    std::array::from_fn(|i| problem(b * BATCH + i.min(out.len() - 1)));
                solve_batch_now(&ps[..out.len()], &shared, o, out);
            });
        mats = next;
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
    /// warm, all three parts), alone or beside another pixel in either
    /// slot of a batch, and the albedo's lane-wide golden sections are
    /// the scalar search's, channel by channel.
    #[test]
    fn lane_widths_and_batches_give_the_same_bits_and_lanes_the_scalar_search() {
        let TableProblem {
            tables,
            truth,
            target,
            ..
        } = table_problem(13, 16);
        let round = Round {
            k: 0.9,
            c2: 1.5,
            toe: gamma_toe(),
        };
        let bits = |m: &Material| {
            (
                m.albedo.to_array().map(f32::to_bits),
                m.roughness.to_bits(),
                m.metallic.to_bits(),
            )
        };
        let n = truth.len();
        for warm in [false, true] {
            let o = SolveOptions {
                warm,
                ..one_round(Parts::ARM, 0.1)
            };
            let problem = |p: usize| {
                let pred = Material {
                    albedo: truth[p].albedo * 0.7 + Vec3::splat(0.1),
                    roughness: (truth[p].roughness + 0.2).min(1.0),
                    metallic: 0.3 * hash01(p as u64),
                };
                PixelProblem {
                    t: &tables[p],
                    m: pred,
                    pred,
                    tg: target.gamma[p],
                    tl: PixelProblem::linear(target.gamma[p]),
                    sat: target.saturated[p],
                }
            };
            for p in 0..n {
                let one = [problem(p)];
                let mut outs = [one[0].m; 4];
                solve_batch::<1>(&one, &round, &o, &mut outs[0..1]);
                solve_batch::<4>(&one, &round, &o, &mut outs[1..2]);
                solve_batch::<8>(&one, &round, &o, &mut outs[2..3]);
                solve_batch::<16>(&one, &round, &o, &mut outs[3..4]);
                for out in &outs[1..] {
                    assert_eq!(bits(out), bits(&outs[0]), "pixel {p}, warm {warm}");
                }
                // Beside another pixel (one that stops at another step),
                // first and last in the batch.
                let q = (p * 7 + 3) % n;
                let mut pair = [one[0].m; BATCH];
                let ps: [PixelProblem; BATCH] =
                    std::array::from_fn(|i| problem(if i == 0 { p } else { q }));
                solve_batch::<8>(&ps, &round, &o, &mut pair);
                assert_eq!(
                    bits(&pair[0]),
                    bits(&outs[0]),
                    "pixel {p} first, warm {warm}"
                );
                let ps: [PixelProblem; BATCH] =
                    std::array::from_fn(|i| problem(if i + 1 == BATCH { p } else { q }));
                solve_batch::<4>(&ps, &round, &o, &mut pair);
                assert_eq!(
                    bits(&pair[BATCH - 1]),
                    bits(&outs[0]),
                    "pixel {p} last, warm {warm}"
                );
                // The albedo search against the scalar golden section.
                let m = outs[0];
                let slot = [&one[0]; BATCH];
                let lanes = solve_albedo(&slot, &[m; BATCH], &round, &o)[0];
                let (i, q) = tables[p].eval_value(&m);
                let pv = i - m.albedo * q;
                let pred = one[0].pred;
                for c in 0..3 {
                    let (lo, hi) = bounds(pred.albedo[c], o.zeta, 0.0);
                    let pa = pred.albedo[c].clamp(lo, hi);
                    let want = if !(q[c] > 0.0) {
                        pa
                    } else {
                        let a0 = ((gamma_inv(one[0].tg[c]) / 0.9 - pv[c]) / q[c]).clamp(lo, hi);
                        let (s0, s1) = if a0 <= pa { (a0, pa) } else { (pa, a0) };
                        let f = |a: f32| {
                            channel_loss(0.9 * (pv[c] + a * q[c]), one[0].tg[c], one[0].sat[c], 1.5)
                                + o.delta * (a - pa).abs()
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
