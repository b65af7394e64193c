//! Material optimisation on the per-pixel tables.
//!
//! Parametrisation (paper eq. 15): x = clamp(m + ζ·tanh(z), lo, hi) for
//! each of A (3 channels), R, M, where m is the prediction; the clamp
//! passes gradients straight through (as the reference does) so a
//! parameter that hits a bound can come back. Loss (eqs. 19–21):
//! L_re + δ·L_cons with L_re = mean L1 + L2 on γ-encoded images and
//! L_cons = mean |x − m| over the parts being optimised.

use glam::Vec3;
use matflow_render::bsdf::MIN_ROUGHNESS;
use matflow_render::Material;
use rayon::prelude::*;

use crate::envfit::FitTrace;
use crate::loss::{exposure_ratio, pixel_loss, sign, Target};
use crate::optim::{Adam, EarlyStop};
use crate::tables::PixelTable;

/// Which material channels a stage optimises.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub struct Parts {
    pub albedo: bool,
    pub roughness: bool,
    pub metallic: bool,
}

impl Parts {
    pub const RM: Parts = Parts {
        albedo: false,
        roughness: true,
        metallic: true,
    };
    pub const A: Parts = Parts {
        albedo: true,
        roughness: false,
        metallic: false,
    };
    pub const ARM: Parts = Parts {
        albedo: true,
        roughness: true,
        metallic: true,
    };
    pub fn name(&self) -> String {
        let mut s = String::new();
        if self.albedo {
            s.push('a');
        }
        if self.roughness {
            s.push('r');
        }
        if self.metallic {
            s.push('m');
        }
        s
    }
}

#[derive(Clone, Copy, Debug)]
pub struct MatFitOptions {
    pub steps: usize,
    pub lr: f32,
    /// Weight of the consistency term.
    pub delta: f32,
    /// Range of the tanh offset (paper ζ; the reference uses 1.3).
    pub zeta: f32,
    pub parts: Parts,
    pub early_stop: bool,
    /// Compare the render scaled by k = mean(target) / mean(render) (the
    /// reference's `ratio`, held constant for the gradient), so that the
    /// global light level is not pushed into the albedo. All light comes
    /// from the envmap, so k is folded into it exactly afterwards.
    pub rescale: bool,
}

/// What a material stage returns.
pub struct MatFit {
    pub materials: Vec<Material>,
    /// Exposure factor for the envmap (1 without `rescale`).
    pub scale: f32,
    pub trace: FitTrace,
}

/// A material as the 5 optimised values (A rgb, R, M).
#[inline]
fn arm(m: &Material) -> [f32; 5] {
    [m.albedo.x, m.albedo.y, m.albedo.z, m.roughness, m.metallic]
}

/// The 5 parameters of a pixel from z, with d(x)/d(z) (straight-through).
#[inline]
pub fn decode(pred: &Material, z: &[f32], zeta: f32) -> (Material, [f32; 5]) {
    let mut x = [0f32; 5];
    let mut d = [0f32; 5];
    let base = arm(pred);
    for k in 0..5 {
        let t = z[k].tanh();
        let lo = if k == 3 { MIN_ROUGHNESS } else { 0.0 };
        x[k] = (base[k] + zeta * t).clamp(lo, 1.0);
        d[k] = zeta * (1.0 - t * t);
    }
    (
        Material {
            albedo: Vec3::new(x[0], x[1], x[2]),
            roughness: x[3],
            metallic: x[4],
        },
        d,
    )
}

/// z that reproduces `start` given `pred` (as closely as tanh allows).
#[inline]
pub fn encode(pred: &Material, start: &Material, zeta: f32) -> [f32; 5] {
    let p = arm(pred);
    let s = arm(start);
    let mut z = [0f32; 5];
    for k in 0..5 {
        let t = ((s[k] - p[k]) / zeta).clamp(-0.999, 0.999);
        z[k] = t.atanh();
    }
    z
}

/// The material for offsets `zp`: the decoded channels in `parts`, the
/// others from `start`.
#[inline]
fn merge(pred: &Material, start: &Material, zp: &[f32], parts: Parts, zeta: f32) -> Material {
    let (m, _) = decode(pred, zp, zeta);
    Material {
        albedo: if parts.albedo { m.albedo } else { start.albedo },
        roughness: if parts.roughness {
            m.roughness
        } else {
            start.roughness
        },
        metallic: if parts.metallic {
            m.metallic
        } else {
            start.metallic
        },
    }
}

/// Sums of the loss terms over a set of pixels.
#[derive(Clone, Copy, Debug, Default)]
struct Sums {
    l1: f64,
    l2: f64,
    cons: f64,
    /// Sum of the unscaled linear render over pixels and channels.
    render: f64,
    /// Sum of the target (linear) over the same pixels.
    target: f64,
}

impl Sums {
    fn add(&mut self, o: &Sums) {
        self.l1 += o.l1;
        self.l2 += o.l2;
        self.cons += o.cons;
        self.render += o.render;
        self.target += o.target;
    }
}

/// What the per-pixel loss needs besides the pixel: active channels,
/// normalisations (means over `n` pixels) and δ.
struct Terms {
    active: [bool; 5],
    parts: Parts,
    zeta: f32,
    delta: f32,
    norm_re: f64,
    norm_a: f64,
    norm_1: f64,
}

impl Terms {
    fn new(opts: &MatFitOptions, n: usize) -> Terms {
        let parts = opts.parts;
        Terms {
            active: [
                parts.albedo,
                parts.albedo,
                parts.albedo,
                parts.roughness,
                parts.metallic,
            ],
            parts,
            zeta: opts.zeta.max(1e-3),
            delta: opts.delta,
            norm_re: 1.0 / (3.0 * n.max(1) as f64),
            norm_a: 1.0 / (3.0 * n.max(1) as f64),
            norm_1: 1.0 / n.max(1) as f64,
        }
    }
}

/// One pixel's share of L_re + δ·L_cons for offsets `zp` (the render
/// scaled by `k`), and its gradient with respect to `zp`.
#[allow(clippy::too_many_arguments)]
#[inline]
fn pixel_terms(
    table: &PixelTable,
    target: &Target,
    p: usize,
    pred: &Material,
    start: &Material,
    zp: &[f32],
    t: &Terms,
    k: f32,
) -> (Sums, [f32; 5]) {
    let mut s = Sums::default();
    let parts = t.parts;
    let (mut m, dx) = decode(pred, zp, t.zeta);
    if !parts.albedo {
        m.albedo = start.albedo;
    }
    if !parts.roughness {
        m.roughness = start.roughness;
    }
    if !parts.metallic {
        m.metallic = start.metallic;
    }
    let e = table.eval(&m);
    s.render = target.exposure_part(p, e.i);
    s.target = target.exposure_part(p, target.linear[p]);
    let (l1, l2, di) = pixel_loss(e.i * k, target.gamma[p], target.saturated[p]);
    s.l1 = l1 as f64;
    s.l2 = l2 as f64;
    let di = di * (t.norm_re as f32 * k);
    let mut gx = [
        di.x * e.da.x,
        di.y * e.da.y,
        di.z * e.da.z,
        (di * e.dr).element_sum(),
        (di * e.dm).element_sum(),
    ];
    let (xs, ps) = (arm(&m), arm(pred));
    let mut gz = [0f32; 5];
    for c in 0..5 {
        if !t.active[c] {
            continue;
        }
        let r = xs[c] - ps[c];
        let norm = if c < 3 { t.norm_a } else { t.norm_1 };
        s.cons += r.abs() as f64 * norm;
        let v = (gx[c] + t.delta * sign(r) * norm as f32) * dx[c];
        gx[c] = v;
        gz[c] = if v.is_finite() { v } else { 0.0 };
    }
    (s, gz)
}

/// Loss sums and ∂loss/∂z over the pixels `idx` (every pixel in order
/// when `None`): the b-th pixel's offsets are z[5b..5b + 5] and its
/// gradient goes to grad[5b..5b + 5]. Chunks are summed in order.
#[allow(clippy::too_many_arguments)]
fn batch_terms(
    tables: &[PixelTable],
    target: &Target,
    pred: &[Material],
    start: &[Material],
    idx: Option<&[u32]>,
    z: &[f32],
    terms: &Terms,
    k: f32,
    grad: &mut [f32],
) -> Sums {
    let chunk = 4096;
    let sums: Vec<Sums> = grad
        .par_chunks_mut(5 * chunk)
        .enumerate()
        .map(|(c, g)| {
            let mut s = Sums::default();
            for (j, gp) in g.chunks_mut(5).enumerate() {
                let b = c * chunk + j;
                let p = idx.map_or(b, |v| v[b] as usize);
                let (l, gz) = pixel_terms(
                    &tables[p],
                    target,
                    p,
                    &pred[p],
                    &start[p],
                    &z[5 * b..5 * b + 5],
                    terms,
                    k,
                );
                s.add(&l);
                gp.copy_from_slice(&gz);
            }
            s
        })
        .collect();
    let mut tot = Sums::default();
    for s in sums {
        tot.add(&s);
    }
    tot
}

/// Per-pixel route: z is a free 5-vector per pixel, fitted by Adam.
/// `start` gives the current materials (channels not in `parts` stay at
/// `start`); returns the fitted materials and the trace.
pub fn fit_pixels(
    tables: &[PixelTable],
    target: &Target,
    pred: &[Material],
    start: &[Material],
    opts: &MatFitOptions,
    progress: &(dyn Fn(usize, f64) + Sync),
) -> MatFit {
    let n = tables.len();
    let target_sum: f64 = target.exposure_sum();
    // k lags one step behind the render it normalises (one pass per step).
    let mut k = 1f32;
    let zeta = opts.zeta.max(1e-3);
    let mut z: Vec<f32> = (0..n)
        .flat_map(|p| encode(&pred[p], &start[p], zeta))
        .collect();
    let mut grad = vec![0f32; 5 * n];
    let mut adam = Adam::new(5 * n, opts.lr);
    let mut stop = EarlyStop::paper();
    let mut trace = FitTrace::default();
    let parts = opts.parts;
    let terms = Terms::new(opts, n);
    let norm_re = terms.norm_re;
    let delta = opts.delta;
    let materialise = |z: &[f32]| -> Vec<Material> {
        (0..n)
            .into_par_iter()
            .with_min_len(1024)
            .map(|p| merge(&pred[p], &start[p], &z[5 * p..5 * p + 5], parts, zeta))
            .collect()
    };
    let mut best = (f64::INFINITY, z.clone(), 1f32);
    for step in 0..=opts.steps {
        let tot = batch_terms(tables, target, pred, start, None, &z, &terms, k, &mut grad);
        let l_re = (tot.l1 + tot.l2) * norm_re;
        let total = l_re + delta as f64 * tot.cons;
        trace.losses.push(l_re);
        progress(step, l_re);
        if total < best.0 {
            best = (total, z.clone(), k);
        }
        if let Some(r) = exposure_ratio(target_sum, tot.render).filter(|_| opts.rescale) {
            k = r;
        }
        if step == opts.steps {
            break;
        }
        if opts.early_stop && stop.update(l_re) {
            trace.stopped_early = true;
            break;
        }
        adam.step(&mut z, &grad);
        trace.steps = step + 1;
    }
    MatFit {
        materials: materialise(&best.1),
        scale: best.2,
        trace,
    }
}

/// The paper's material parametrisation: one positional-encoding MLP over
/// the pixel grid gives the offsets z of every pixel, [A, R, M] =
/// clamp(m + ζ·tanh(z)) (the reference's `PosMLP` with `output_type =
/// arm`; its input is the pixel's (row, column) encoding followed by the
/// starting A, R, M). The network is kept across stages.
///
/// On the CPU a full-image pass per step is the cost of the whole budget,
/// so each step trains on a stratified minibatch: one pixel per `block`
/// (4×4) cell, chosen by hashing (seed, step, cell), so every region is
/// seen every step and results stay deterministic.
#[derive(Clone, Debug)]
pub struct MatMlp {
    pub net: crate::mlp::PosMlp,
    feats: Vec<f32>,
    width: usize,
    height: usize,
    seed: u64,
}

/// Settings of the material MLP (the reference: width 256, depth 4,
/// skips [1, 3], 2 octaves, AdamW 3e-4 with StepLR 100 × 0.8).
#[derive(Clone, Copy, Debug)]
pub struct MatMlpOptions {
    /// AdamW learning rate (×0.8 every 100 steps).
    pub lr: f32,
    pub width: usize,
    pub depth: usize,
    pub multires: usize,
    /// Minibatch cell edge in pixels (1: full image every step).
    pub block: usize,
    /// Pixel coordinates enter as (row, col)·coord_scale / max(W, H).
    /// The reference feeds unscaled integers; at 512² their sines act as
    /// a per-pixel hash and the network barely trains in a CPU step
    /// budget (indoor, 60 s plan: 19.0 dB unscaled vs 22.3 dB at 8).
    pub coord_scale: f32,
    pub seed: u64,
}

impl Default for MatMlpOptions {
    fn default() -> Self {
        MatMlpOptions {
            lr: 1e-3,
            width: 32,
            depth: 4,
            multires: 2,
            block: 4,
            coord_scale: 8.0,
            seed: 0,
        }
    }
}

fn hash3(a: u64, b: u64, c: u64) -> u64 {
    let mut z = a ^ b.wrapping_mul(0x9e37_79b9_7f4a_7c15) ^ c.wrapping_mul(0xc2b2_ae3d_27d4_eb4f);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

impl MatMlp {
    /// `start` is the network's conditioning input (the reference's
    /// `start_arm`: predictions with R, M replaced when not trusted).
    pub fn new(width: usize, height: usize, start: &[Material], o: &MatMlpOptions) -> MatMlp {
        let nf = crate::mlp::position_feature_count(o.multires) + 5;
        let mut feats = Vec::with_capacity(nf * width * height);
        for (p, m) in start.iter().enumerate() {
            let row = (p / width) as f32 * o.coord_scale / width.max(height) as f32;
            let col = (p % width) as f32 * o.coord_scale / width.max(height) as f32;
            crate::mlp::position_features(row, col, o.multires, &mut feats);
            feats.extend_from_slice(&[
                m.albedo.x.clamp(0.0, 1.0),
                m.albedo.y.clamp(0.0, 1.0),
                m.albedo.z.clamp(0.0, 1.0),
                m.roughness.clamp(0.0, 1.0),
                m.metallic.clamp(0.0, 1.0),
            ]);
        }
        MatMlp {
            net: crate::mlp::PosMlp::new(nf, o.width, o.depth, 5, &[1, 3], o.seed),
            feats,
            width,
            height,
            seed: o.seed,
        }
    }

    fn batch(&self, step: usize, block: usize) -> Vec<u32> {
        let b = block.max(1);
        let (w, h) = (self.width, self.height);
        let mut idx = Vec::with_capacity(w.div_ceil(b) * h.div_ceil(b));
        for by in (0..h).step_by(b) {
            for bx in (0..w).step_by(b) {
                let (cw, ch) = (b.min(w - bx), b.min(h - by));
                let r = hash3(self.seed, step as u64, (by * w + bx) as u64);
                let k = (r % (cw * ch) as u64) as usize;
                idx.push(((by + k / cw) * w + bx + k % cw) as u32);
            }
        }
        idx
    }

    fn gather(&self, idx: &[u32]) -> Vec<f32> {
        let nf = self.net.n_features;
        let mut f = Vec::with_capacity(idx.len() * nf);
        for &p in idx {
            let p = p as usize;
            f.extend_from_slice(&self.feats[p * nf..(p + 1) * nf]);
        }
        f
    }

    /// Trains on the tables; returns the materials of the whole image.
    #[allow(clippy::too_many_arguments)]
    pub fn fit(
        &mut self,
        tables: &[PixelTable],
        target: &Target,
        pred: &[Material],
        start: &[Material],
        opts: &MatFitOptions,
        mlp: &MatMlpOptions,
        progress: &(dyn Fn(usize, f64) + Sync),
    ) -> MatFit {
        let n = tables.len();
        assert_eq!(n, self.width * self.height);
        let zeta = opts.zeta.max(1e-3);
        let mut adam = Adam::new(self.net.param_count(), mlp.lr);
        adam.weight_decay = 0.01; // AdamW's default, as the reference
                                  // The reference's material rule (patience 200 // loop, 0.5 %); the
                                  // paper's 5 %-in-20-steps rule stops a network this slow to start
                                  // before it has moved.
        let mut stop = crate::optim::Patience::new(100, 0.005);
        let mut trace = FitTrace::default();
        let mut k = 1f32;
        let chunk = 1024;
        for step in 0..opts.steps {
            let idx = self.batch(step, mlp.block);
            let terms = Terms::new(opts, idx.len());
            let feats = self.gather(&idx);
            let (z, tape) = self.net.forward_taped(&feats);
            let mut dout = vec![0f32; z.len()];
            let tot = batch_terms(
                tables,
                target,
                pred,
                start,
                Some(&idx),
                &z,
                &terms,
                k,
                &mut dout,
            );
            let l_re = (tot.l1 + tot.l2) * terms.norm_re;
            trace.losses.push(l_re);
            progress(step, l_re);
            if let Some(r) = exposure_ratio(tot.target, tot.render).filter(|_| opts.rescale) {
                k = r;
            }
            if opts.early_stop && stop.update(l_re) {
                trace.stopped_early = true;
                break;
            }
            let grad = self.net.backward(&tape, &dout);
            adam.lr = crate::optim::step_lr(mlp.lr, step, 100, 0.8);
            adam.step(&mut self.net.params, &grad);
            trace.steps = step + 1;
        }
        // The whole image, and the exposure ratio over it.
        let z = self.net.forward(&self.feats);
        let materials: Vec<Material> = (0..n)
            .into_par_iter()
            .with_min_len(1024)
            .map(|p| merge(&pred[p], &start[p], &z[5 * p..5 * p + 5], opts.parts, zeta))
            .collect();
        let scale = if opts.rescale {
            let render: f64 = materials
                .par_chunks(chunk)
                .enumerate()
                .map(|(c, ms)| {
                    ms.iter()
                        .enumerate()
                        .map(|(j, m)| {
                            let p = c * chunk + j;
                            target.exposure_part(p, tables[p].eval(m).i)
                        })
                        .sum::<f64>()
                })
                .collect::<Vec<f64>>()
                .iter()
                .sum();
            exposure_ratio(target.exposure_sum(), render).unwrap_or(1.0)
        } else {
            1.0
        };
        MatFit {
            materials,
            scale,
            trace,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testutil::{hash01, table_problem, TableProblem};

    #[test]
    fn mlp_route_lowers_the_loss_from_perturbed_predictions() {
        let TableProblem {
            tables: tabs,
            truth,
            target,
            ..
        } = table_problem(5, 24);
        let pred: Vec<Material> = truth
            .iter()
            .enumerate()
            .map(|(p, m)| Material {
                albedo: (m.albedo * (0.7 + 0.2 * hash01(p as u64))).clamp(Vec3::ZERO, Vec3::ONE),
                ..*m
            })
            .collect();
        let o = MatMlpOptions {
            block: 2,
            ..Default::default()
        };
        let fit_opts = MatFitOptions {
            steps: 300,
            lr: 0.0,
            delta: 0.01,
            zeta: 1.3,
            parts: Parts::A,
            early_stop: false,
            rescale: false,
        };
        let run = || {
            let mut net = MatMlp::new(24, 24, &pred, &o);
            net.fit(&tabs, &target, &pred, &pred, &fit_opts, &o, &|_, _| {})
        };
        let fit = run();
        let loss = |ms: &[Material]| -> f64 {
            let im: Vec<Vec3> = tabs.iter().zip(ms).map(|(t, m)| t.eval(m).i).collect();
            crate::loss::loss_and_grad(&im, &target, None).0.total()
        };
        let (before, after) = (loss(&pred), loss(&fit.materials));
        assert!(after < 0.5 * before, "{before} -> {after}");
        // An albedo stage keeps R and M; A stays in [0, 1].
        for (m, p) in fit.materials.iter().zip(&pred) {
            assert!(m.albedo.min_element() >= 0.0 && m.albedo.max_element() <= 1.0);
            assert_eq!((m.roughness, m.metallic), (p.roughness, p.metallic));
        }
        assert_eq!(fit.materials, run().materials);
    }
}
