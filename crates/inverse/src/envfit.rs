//! Environment-map recovery on the frozen paths.
//!
//! With materials held fixed the frozen estimator is exactly linear in the
//! envmap: every sky record contributes (path throughput × f·w) times a
//! bilinear blend of four texels. [`EnvTransport`] sums those terms per
//! pixel and texel for a subset of pixels (the envmap has only W·H·3
//! unknowns), so a loss evaluation and its gradient are one sparse
//! product each way.

use glam::Vec3;
use matflow_render::Material;
use rayon::prelude::*;

use crate::brdf::eval;
use crate::paths::{taps, PathCache, Record, MAX_DEPTH, NO_MATERIAL};
use crate::transport::for_each_path;

/// One sky record's term while the transport is built: its texel cell,
/// bilinear position and weight.
#[derive(Clone, Copy, Debug)]
struct EnvTerm {
    cell: u16,
    fx: u16,
    fy: u16,
    w: Vec3,
}

/// A pixel's weight on one texel (or lamp): the sum over its terms of
/// term weight × bilinear tap weight.
#[derive(Clone, Copy, Debug)]
#[repr(C)]
pub struct EnvEntry {
    pub texel: u32,
    pub w: Vec3,
}

/// The linear map envmap → image for the selected pixels.
pub struct EnvTransport {
    pub env_width: usize,
    pub env_height: usize,
    /// Lamps after the envmap's texels ([`crate::paths::light_len`]).
    pub lamps: usize,
    /// Per lamp, whether it is distant (the sun, which the lamps'
    /// sparsity prior leaves alone: it is only there when the scout found
    /// it).
    pub distant: Vec<bool>,
    /// Selected pixel indices (row-major image index).
    pub pixels: Vec<u32>,
    /// Per selected pixel, start of its row (len = pixels + 1).
    pub start: Vec<u32>,
    /// Each pixel's row: one entry per texel it sees, in the order its
    /// terms first reach them. Merged, a jinjya pixel's ~35 terms (~140
    /// bilinear taps) are ~75 entries, and a step decodes no taps: a step
    /// took 17 ms instead of 30.
    pub entries: Vec<EnvEntry>,
}

/// Pixels on a regular grid with the given stride (offset to its centre).
pub fn strided_pixels(width: usize, height: usize, stride: usize) -> Vec<u32> {
    let s = stride.max(1);
    let o = s / 2;
    let mut v = Vec::new();
    for y in (o.min(height.saturating_sub(1))..height).step_by(s) {
        for x in (o.min(width.saturating_sub(1))..width).step_by(s) {
            v.push((y * width + x) as u32);
        }
    }
    v
}

impl EnvTransport {
    pub fn build(cache: &PathCache, mats: &[Material], pixels: Vec<u32>) -> EnvTransport {
        let inv = 1.0 / cache.spp as f32;
        let w = cache.width;
        let chunk = 1024;
        let ew = cache.env_width;
        let ntex = crate::paths::light_len(cache.env_width, cache.env_height, cache.lamps);
        let parts: Vec<(Vec<u32>, Vec<EnvEntry>)> = pixels
            .par_chunks(chunk)
            .map(|px| {
                let mut counts = Vec::with_capacity(px.len());
                let mut entries = Vec::new();
                let mut terms = Vec::new();
                // Per texel, its entry in the current pixel's row.
                let mut slot = vec![u32::MAX; ntex];
                for &p in px {
                    let (x, y) = (p as usize % w, p as usize / w);
                    let (verts, recs) = cache.pixel(x, y);
                    terms.clear();
                    for_each_path(verts, |first, end, r0| {
                        let mut beta = Vec3::splat(inv);
                        let mut r = r0;
                        for k in first..end.min(first + MAX_DEPTH as usize) {
                            let v = verts[k];
                            let rs: &[Record] = &recs[r..r + v.n_records()];
                            r += v.n_records();
                            if v.q == NO_MATERIAL {
                                for rec in &rs[..v.n_env as usize] {
                                    terms.push(term(rec, beta * rec.w));
                                }
                                break;
                            }
                            let m = mats[v.q as usize];
                            for rec in &rs[..v.n_env as usize] {
                                let f = eval(&rec.geo.decode(), &m) * rec.w;
                                if f != Vec3::ZERO {
                                    terms.push(term(rec, beta * f));
                                }
                            }
                            if !v.has_cont() {
                                break;
                            }
                            let rec = &rs[v.n_env as usize];
                            beta *= eval(&rec.geo.decode(), &m) * rec.w;
                            if beta == Vec3::ZERO || !beta.is_finite() {
                                break;
                            }
                        }
                    });
                    let before = entries.len();
                    for t in &terms {
                        let (idx, wt) = tap_of(t, ew);
                        for k in 0..4 {
                            if wt[k] == 0.0 {
                                continue;
                            }
                            let s = &mut slot[idx[k]];
                            if *s == u32::MAX {
                                *s = (entries.len() - before) as u32;
                                entries.push(EnvEntry {
                                    texel: idx[k] as u32,
                                    w: Vec3::ZERO,
                                });
                            }
                            entries[before + *s as usize].w += t.w * wt[k];
                        }
                    }
                    for e in &entries[before..] {
                        slot[e.texel as usize] = u32::MAX;
                    }
                    counts.push((entries.len() - before) as u32);
                }
                (counts, entries)
            })
            .collect();
        let total: usize = parts.iter().map(|p| p.1.len()).sum();
        let mut start = Vec::with_capacity(pixels.len() + 1);
        let mut entries = Vec::with_capacity(total);
        start.push(0u32);
        for (counts, t) in parts {
            let mut s = entries.len() as u32;
            for c in counts {
                s += c;
                start.push(s);
            }
            entries.extend(t);
        }
        EnvTransport {
            env_width: cache.env_width,
            env_height: cache.env_height,
            lamps: cache.lamps,
            distant: cache.distant.clone(),
            pixels,
            start,
            entries,
        }
    }

    /// A selected pixel's row.
    #[inline]
    fn row(&self, i: usize) -> &[EnvEntry] {
        &self.entries[self.start[i] as usize..self.start[i + 1] as usize]
    }

    /// Image values at the selected pixels for envmap `env`.
    pub fn apply(&self, env: &[Vec3]) -> Vec<Vec3> {
        (0..self.pixels.len())
            .into_par_iter()
            .with_min_len(256)
            .map(|i| {
                let mut acc = Vec3::ZERO;
                for e in self.row(i) {
                    acc += e.w * env[e.texel as usize];
                }
                acc
            })
            .collect()
    }

    /// Transpose: ∂loss/∂env from ∂loss/∂I at the selected pixels.
    pub fn apply_t(&self, adj: &[Vec3]) -> Vec<Vec3> {
        let ntex = crate::paths::light_len(self.env_width, self.env_height, self.lamps);
        let chunk = 2048;
        let parts: Vec<Vec<[f64; 3]>> = (0..self.pixels.len().div_ceil(chunk))
            .into_par_iter()
            .map(|c| {
                let mut acc = vec![[0f32; 3]; ntex];
                for i in c * chunk..((c + 1) * chunk).min(self.pixels.len()) {
                    let a = adj[i];
                    if a == Vec3::ZERO {
                        continue;
                    }
                    for e in self.row(i) {
                        let g = a * e.w;
                        let t = &mut acc[e.texel as usize];
                        t[0] += g.x;
                        t[1] += g.y;
                        t[2] += g.z;
                    }
                }
                acc.into_iter()
                    .map(|e| [e[0] as f64, e[1] as f64, e[2] as f64])
                    .collect()
            })
            .collect();
        let mut tot = vec![[0f64; 3]; ntex];
        for p in parts {
            for (t, e) in tot.iter_mut().zip(p) {
                t[0] += e[0];
                t[1] += e[1];
                t[2] += e[2];
            }
        }
        tot.iter()
            .map(|t| Vec3::new(t[0] as f32, t[1] as f32, t[2] as f32))
            .collect()
    }
}

#[inline]
fn term(rec: &Record, w: Vec3) -> EnvTerm {
    EnvTerm {
        cell: rec.cell,
        fx: rec.fx,
        fy: rec.fy,
        w,
    }
}

#[inline]
fn tap_of(t: &EnvTerm, ew: usize) -> ([usize; 4], [f32; 4]) {
    let rec = Record {
        geo: Default::default(),
        w: 0.0,
        cell: t.cell,
        fx: t.fx,
        fy: t.fy,
        _pad: 0,
    };
    taps(&rec, ew)
}

/// What an optimisation stage did.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct FitTrace {
    pub steps: usize,
    /// Re-rendering loss (L1 + L2 on γ-encoded images) after each step's
    /// forward pass, i.e. `losses[k]` is the loss of the parameters before
    /// update k.
    pub losses: Vec<f64>,
    pub stopped_early: bool,
}

#[derive(Clone, Copy, Debug)]
pub struct EnvFitOptions {
    pub steps: usize,
    pub lr: f32,
    pub early_stop: bool,
    /// Texel route: weight of a smoothness prior, the mean over
    /// neighbouring texel pairs (longitude wraps) and channels of the
    /// squared difference of log radiance. Texels few paths see follow
    /// their neighbours instead of fitting noise; a sun costs only its
    /// few edge pairs. 0 turns it off.
    pub smooth: f32,
    /// Texel route with lamps: weight of a sparsity prior, the sum of the
    /// lamps' entries over the envmap's mean texel at the start (per
    /// channel, over 3): a lamp shines only where the envmap cannot
    /// explain the light (lamps and sky openings both explain a lit room;
    /// a lamp must earn its light).
    pub lamp_sparsity: f32,
}

/// The sparsity prior on the lamps' entries `e[lamps]` (log
/// parametrised, θ = ln e) and its gradient with respect to θ, added into
/// `grad`; `reference` is the scale an entry is measured against.
fn lamp_prior(
    theta: &[f32],
    lamps: &[usize],
    reference: f32,
    weight: f32,
    grad: &mut [f32],
) -> f64 {
    if weight <= 0.0 || lamps.is_empty() || !(reference > 0.0) {
        return 0.0;
    }
    let norm = weight / (3.0 * reference);
    let mut sum = 0f64;
    for &t in lamps {
        for c in 0..3 {
            let e = theta[3 * t + c].exp();
            sum += (norm * e) as f64;
            grad[3 * t + c] += norm * e;
        }
    }
    sum
}

/// Neighbouring texel pairs of a `w`×`h` envmap: right neighbours (the
/// longitude wraps) and lower neighbours.
fn texel_pairs(w: usize, h: usize) -> Vec<(usize, usize)> {
    let mut v = Vec::with_capacity(2 * w * h);
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            if w > 1 {
                v.push((i, y * w + (x + 1) % w));
            }
            if y + 1 < h {
                v.push((i, i + w));
            }
        }
    }
    v
}

/// The smoothness prior on log texels θ (3 per texel) and its gradient,
/// added into `grad`.
fn smooth_prior(theta: &[f32], pairs: &[(usize, usize)], weight: f32, grad: &mut [f32]) -> f64 {
    if weight <= 0.0 || pairs.is_empty() {
        return 0.0;
    }
    let norm = weight as f64 / (3 * pairs.len()) as f64;
    let mut sum = 0f64;
    for &(i, j) in pairs {
        for c in 0..3 {
            let d = (theta[3 * i + c] - theta[3 * j + c]) as f64;
            sum += d * d;
            let g = (2.0 * norm * d) as f32;
            grad[3 * i + c] += g;
            grad[3 * j + c] -= g;
        }
    }
    sum * norm
}

/// Log-space texel parametrisation: E = exp(θ), clamped to [1e-6, 1e6].
pub const LOG_E_MIN: f32 = -13.815_511; // ln 1e-6
pub const LOG_E_MAX: f32 = 13.815_511;

/// The fast route: every texel (and channel) is a free parameter, E =
/// exp(θ) so steps are relative (HDR suns and dim sky alike), fitted by
/// Adam on the frozen linear transport. Texels no selected pixel sees
/// keep their initial value.
pub fn fit_texels(
    tr: &EnvTransport,
    target: &crate::loss::Target,
    init: &[Vec3],
    opts: &EnvFitOptions,
    progress: &(dyn Fn(usize, f64) + Sync),
) -> (Vec<Vec3>, FitTrace) {
    use crate::loss::loss_and_grad;
    use crate::optim::{Adam, EarlyStop};
    let n = init.len();
    let mut theta: Vec<f32> = init
        .iter()
        .flat_map(|e| [e.x, e.y, e.z])
        .map(|x| x.max(1e-6).ln().clamp(LOG_E_MIN, LOG_E_MAX))
        .collect();
    let to_env = |th: &[f32]| -> Vec<Vec3> {
        (0..n)
            .map(|t| Vec3::new(th[3 * t].exp(), th[3 * t + 1].exp(), th[3 * t + 2].exp()))
            .collect()
    };
    let pairs = texel_pairs(tr.env_width, tr.env_height);
    let ntex = tr.env_width * tr.env_height;
    // Point lamps' entries (the sun has no sparsity prior).
    let lamps: Vec<usize> = (0..tr.lamps)
        .filter(|&k| !tr.distant.get(k).copied().unwrap_or(false))
        .map(|k| ntex + k)
        .filter(|&t| t < n)
        .collect();
    let reference = (init[..ntex.min(n)]
        .iter()
        .map(|e| e.element_sum() as f64)
        .sum::<f64>()
        / (3 * ntex.max(1)) as f64) as f32;
    let priors = |theta: &[f32], grad: &mut [f32]| {
        smooth_prior(theta, &pairs, opts.smooth, grad)
            + lamp_prior(theta, &lamps, reference, opts.lamp_sparsity, grad)
    };
    let mut adam = Adam::new(3 * n, opts.lr);
    let mut stop = EarlyStop::paper();
    let mut trace = FitTrace::default();
    let mut best = (f64::INFINITY, theta.clone());
    for step in 0..opts.steps {
        let env = to_env(&theta);
        let img = tr.apply(&env);
        let (lv, adj) = loss_and_grad(&img, target, Some(&tr.pixels));
        let g_env = tr.apply_t(&adj);
        let mut grad: Vec<f32> = (0..n)
            .flat_map(|t| {
                let e = env[t];
                let g = g_env[t];
                [g.x * e.x, g.y * e.y, g.z * e.z]
            })
            .collect();
        let loss = lv.total() + priors(&theta, &mut grad);
        trace.losses.push(loss);
        progress(step, loss);
        if loss < best.0 {
            best = (loss, theta.clone());
        }
        if opts.early_stop && stop.update(loss) {
            trace.stopped_early = true;
            break;
        }
        adam.step(&mut theta, &grad);
        for x in theta.iter_mut() {
            *x = x.clamp(LOG_E_MIN, LOG_E_MAX);
        }
        trace.steps = step + 1;
    }
    // Evaluate the final parameters too, then keep the best seen.
    let env = to_env(&theta);
    let img = tr.apply(&env);
    let (lv, _) = loss_and_grad(&img, target, Some(&tr.pixels));
    let mut scratch = vec![0f32; theta.len()];
    let last = lv.total() + priors(&theta, &mut scratch);
    if last < best.0 {
        best = (last, theta);
    }
    (to_env(&best.1), trace)
}

/// A global scale s such that the mean of T·(s·init) equals the target's
/// mean over the selected pixels (a good starting exposure).
pub fn exposure_scale(tr: &EnvTransport, target_linear: &[Vec3], init: &[Vec3]) -> f32 {
    let img = tr.apply(init);
    let a: f64 = img.iter().map(|v| v.element_sum() as f64).sum();
    let b: f64 = tr
        .pixels
        .iter()
        .map(|&p| {
            let v = target_linear[p as usize];
            if v.is_finite() {
                v.max(Vec3::ZERO).element_sum() as f64
            } else {
                0.0
            }
        })
        .sum();
    if a > 1e-30 && b > 0.0 {
        ((b / a) as f32).clamp(1e-6, 1e6)
    } else {
        1.0
    }
}

/// The paper's envmap parametrisation: a positional-encoding MLP over the
/// texel grid with a Softplus head, kept across stages (the reference
/// trains one network through all its loops).
///
/// E(i, j) = scale · softplus(net(PE(i, j), 1, 1, 1)) / ln 2. The output
/// layer starts at zero, so a fresh network gives E = scale everywhere
/// (the reference starts at softplus(0) and lets Adam find the exposure;
/// the scale is that exposure found in closed form, and material stages
/// fold their exposure ratio into it).
#[derive(Clone, Debug)]
pub struct EnvMlp {
    pub net: crate::mlp::PosMlp,
    /// Per channel.
    pub scale: Vec3,
    feats: Vec<f32>,
    width: usize,
    height: usize,
}

/// Settings of the envmap MLP (the reference: width 256, depth 4, skips
/// [1, 3], 2 octaves).
#[derive(Clone, Copy, Debug)]
pub struct EnvMlpOptions {
    /// Adam learning rate (the reference: 1e-3, ×0.8 every 100 steps).
    pub lr: f32,
    pub width: usize,
    pub depth: usize,
    pub multires: usize,
    pub seed: u64,
}

impl Default for EnvMlpOptions {
    fn default() -> Self {
        EnvMlpOptions {
            lr: 1e-3,
            width: 64,
            depth: 4,
            multires: 2,
            seed: 0,
        }
    }
}

const LN2: f32 = std::f32::consts::LN_2;

/// Softplus and its derivative (the logistic function), overflow-safe.
#[inline]
fn softplus(y: f32) -> (f32, f32) {
    if y > 20.0 {
        (y, 1.0)
    } else if y < -20.0 {
        (y.exp(), y.exp())
    } else {
        let e = y.exp();
        ((1.0 + e).ln(), e / (1.0 + e))
    }
}

impl EnvMlp {
    pub fn new(width: usize, height: usize, scale: f32, o: &EnvMlpOptions) -> EnvMlp {
        let mut feats = Vec::new();
        for i in 0..height {
            for j in 0..width {
                crate::mlp::position_features(i as f32, j as f32, o.multires, &mut feats);
                feats.extend_from_slice(&[1.0, 1.0, 1.0]);
            }
        }
        let nf = crate::mlp::position_feature_count(o.multires) + 3;
        EnvMlp {
            net: crate::mlp::PosMlp::new(nf, o.width, o.depth, 3, &[1, 3], o.seed),
            scale: Vec3::splat(if scale.is_finite() && scale > 0.0 {
                scale
            } else {
                1.0
            }),
            feats,
            width,
            height,
        }
    }

    fn decode(&self, y: &[f32]) -> Vec<Vec3> {
        let k = self.scale / LN2;
        y.chunks(3)
            .map(|c| Vec3::new(softplus(c[0]).0, softplus(c[1]).0, softplus(c[2]).0) * k)
            .map(|e| e.clamp(Vec3::splat(1e-6), Vec3::splat(1e6)))
            .collect()
    }

    /// The current envmap (row-major texels).
    pub fn envmap(&self) -> Vec<Vec3> {
        self.decode(&self.net.forward(&self.feats))
    }

    /// Trains the network on the frozen transport; keeps the best
    /// parameters seen and returns the envmap they give.
    pub fn fit(
        &mut self,
        tr: &EnvTransport,
        target: &crate::loss::Target,
        opts: &EnvFitOptions,
        progress: &(dyn Fn(usize, f64) + Sync),
    ) -> (Vec<Vec3>, FitTrace) {
        use crate::loss::loss_and_grad;
        use crate::optim::{Adam, Patience};
        assert_eq!(tr.env_width * tr.env_height, self.width * self.height);
        let mut adam = Adam::new(self.net.param_count(), opts.lr);
        // The reference's envmap rule: 100 steps without a 1 % gain.
        let mut stop = Patience::new(100, 0.01);
        let mut trace = FitTrace::default();
        let mut best = (f64::INFINITY, self.net.params.clone());
        let k = self.scale / LN2;
        for step in 0..=opts.steps {
            let (y, tape) = self.net.forward_taped(&self.feats);
            let env = self.decode(&y);
            let img = tr.apply(&env);
            let (lv, adj) = loss_and_grad(&img, target, Some(&tr.pixels));
            let loss = lv.total();
            if loss < best.0 {
                best = (loss, self.net.params.clone());
            }
            if step == opts.steps {
                break;
            }
            trace.losses.push(loss);
            progress(step, loss);
            if opts.early_stop && stop.update(loss) {
                trace.stopped_early = true;
                break;
            }
            let g_env = tr.apply_t(&adj);
            let dout: Vec<f32> = y
                .chunks(3)
                .zip(&g_env)
                .flat_map(|(c, g)| {
                    [
                        g.x * softplus(c[0]).1 * k.x,
                        g.y * softplus(c[1]).1 * k.y,
                        g.z * softplus(c[2]).1 * k.z,
                    ]
                })
                .collect();
            let grad = self.net.backward(&tape, &dout);
            adam.lr = crate::optim::step_lr(opts.lr, step, 100, 0.8);
            adam.step(&mut self.net.params, &grad);
            trace.steps = step + 1;
        }
        self.net.params = best.1;
        (self.envmap(), trace)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::loss::Target;
    use crate::testutil::{cache_of, materials_of, room, texels};

    /// The prior is zero on a constant envmap, its gradient matches
    /// central differences, and every texel has 4 neighbours on a 32×16
    /// map except the poles' rows (3).
    #[test]
    fn smoothness_prior_is_a_checked_quadratic() {
        let (w, h) = (32, 16);
        let pairs = texel_pairs(w, h);
        assert_eq!(pairs.len(), w * h + w * (h - 1));
        let mut g = vec![0f32; 3 * w * h];
        assert_eq!(
            smooth_prior(&vec![1.7; 3 * w * h], &pairs, 0.01, &mut g),
            0.0
        );
        assert!(g.iter().all(|x| *x == 0.0));
        let theta: Vec<f32> = (0..3 * w * h)
            .map(|i| ((i * 7919) % 101) as f32 / 25.0 - 2.0)
            .collect();
        let mut g = vec![0f32; theta.len()];
        let f0 = smooth_prior(&theta, &pairs, 0.01, &mut g);
        assert!(f0 > 0.0);
        let eps = 1e-2f32;
        for i in [0usize, 5, 97, 3 * w * h - 1] {
            let mut t = theta.clone();
            let mut s = vec![0f32; t.len()];
            t[i] += eps;
            let fp = smooth_prior(&t, &pairs, 0.01, &mut s);
            t[i] -= 2.0 * eps;
            let fm = smooth_prior(&t, &pairs, 0.01, &mut s);
            let fd = (fp - fm) / (2.0 * eps as f64);
            let rel = (fd - g[i] as f64).abs() / fd.abs().max(1e-9);
            assert!(rel < 1e-3, "texel {i}: {fd} vs {}", g[i]);
        }
    }

    /// Target: the frozen estimator's own image under the true envmap, so
    /// both routes can reach (nearly) zero loss from a flat start.
    fn setup() -> (EnvTransport, Target, Vec<Vec3>) {
        let t = room(3, 24);
        let cache = cache_of(&t.scene, 8);
        let mats = materials_of(&t.maps);
        let truth = texels(&t.env);
        let img = crate::transport::render(&cache, &mats, &truth);
        let target = Target::new(cache.width, cache.height, &img);
        let pixels: Vec<u32> = (0..img.len() as u32).collect();
        let tr = EnvTransport::build(&cache, &mats, pixels);
        let flat = vec![Vec3::ONE; truth.len()];
        let s = exposure_scale(&tr, &img, &flat);
        (tr, target, flat.iter().map(|e| *e * s).collect())
    }

    /// The merged rows are the frozen estimator: for a random envmap the
    /// transport's image is the frozen paths' render, its transpose is
    /// its adjoint (⟨T·e, a⟩ = ⟨e, Tᵀ·a⟩), and every row names each
    /// texel once.
    #[test]
    fn merged_rows_are_the_frozen_render_and_its_adjoint() {
        let t = room(4, 20);
        let cache = cache_of(&t.scene, 6);
        let mats = materials_of(&t.maps);
        let n = crate::paths::light_len(cache.env_width, cache.env_height, cache.lamps);
        let env: Vec<Vec3> = (0..n)
            .map(|i| Vec3::new(0.2, 0.5, 1.0) + Vec3::splat(crate::testutil::hash01(i as u64)))
            .collect();
        let img = crate::transport::render(&cache, &mats, &env);
        let pixels: Vec<u32> = (0..img.len() as u32).step_by(3).collect();
        let tr = EnvTransport::build(&cache, &mats, pixels.clone());
        let got = tr.apply(&env);
        let mut lit = 0;
        for (g, &p) in got.iter().zip(&pixels) {
            let want = img[p as usize];
            assert!(
                (*g - want).abs().max_element() <= 1e-4 * (1.0 + want.max_element()),
                "pixel {p}: {g} vs {want}"
            );
            lit += (want.max_element() > 0.0) as usize;
        }
        assert!(lit > pixels.len() / 2, "too few lit pixels to test");
        for i in 0..pixels.len() {
            let mut seen = std::collections::HashSet::new();
            assert!(tr.row(i).iter().all(|e| seen.insert(e.texel)));
        }
        let adj: Vec<Vec3> = (0..pixels.len())
            .map(|i| Vec3::splat(crate::testutil::hash01(7 + i as u64) - 0.5))
            .collect();
        let g = tr.apply_t(&adj);
        let dot =
            |a: &[Vec3], b: &[Vec3]| a.iter().zip(b).map(|(x, y)| x.dot(*y) as f64).sum::<f64>();
        let (lhs, rhs) = (dot(&got, &adj), dot(&env, &g));
        assert!(
            (lhs - rhs).abs() <= 1e-4 * lhs.abs().max(1.0),
            "{lhs} vs {rhs}"
        );
    }

    fn opts(steps: usize, lr: f32) -> EnvFitOptions {
        EnvFitOptions {
            steps,
            lr,
            early_stop: false,
            smooth: 0.0,
            lamp_sparsity: 0.0,
        }
    }

    #[test]
    fn texel_route_fits_the_image() {
        let (tr, target, init) = setup();
        let (env, trace) = fit_texels(&tr, &target, &init, &opts(300, 0.05), &|_, _| {});
        let first = trace.losses[0];
        let (lv, _) = crate::loss::loss_and_grad(&tr.apply(&env), &target, Some(&tr.pixels));
        assert!(lv.total() < 0.2 * first, "{first} -> {}", lv.total());
        assert!(env.iter().all(|e| e.is_finite() && e.min_element() > 0.0));
    }

    #[test]
    fn mlp_route_starts_at_its_scale_fits_and_is_deterministic() {
        let (tr, target, init) = setup();
        let o = EnvMlpOptions {
            width: 32,
            ..Default::default()
        };
        let mut net = EnvMlp::new(32, 16, init[0].x, &o);
        // The zero output layer gives exactly the starting exposure.
        for e in net.envmap() {
            assert!((e - init[0]).abs().max_element() < 1e-4 * init[0].x);
        }
        let mut net2 = net.clone();
        let (env, trace) = net.fit(&tr, &target, &opts(300, 3e-3), &|_, _| {});
        let first = trace.losses[0];
        let (lv, _) = crate::loss::loss_and_grad(&tr.apply(&env), &target, Some(&tr.pixels));
        assert!(lv.total() < 0.5 * first, "{first} -> {}", lv.total());
        assert!(env.iter().all(|e| e.is_finite() && e.min_element() > 0.0));
        let (env2, _) = net2.fit(&tr, &target, &opts(300, 3e-3), &|_, _| {});
        assert_eq!(env, env2);
    }
}
