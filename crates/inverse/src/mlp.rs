//! The reference's positional-encoding MLP (`PosMLP`), forward and
//! reverse mode on the CPU.
//!
//! Architecture, as in the reference (`mymodels/mlps.py`):
//!
//! - input features: the integer grid position (row, column) — unscaled —
//!   with its NeRF positional encoding (`multires` octaves of sin and cos,
//!   frequencies 1, 2, …), followed by per-sample conditioning values (the
//!   starting envmap texel, or the predicted A, R, M of the pixel);
//! - `depth` hidden sine layers (SIREN with ω = 1) of `width` units; the
//!   layers listed in `skips` see the input features again (concatenated),
//!   and the layer before a skip is narrowed so the skip layer's input is
//!   still `width` wide;
//! - a linear output layer initialised to zero, so the network starts at
//!   exactly its head's value for zero (the starting point);
//! - the head (Softplus for envmaps, ζ·tanh + prediction for materials) is
//!   applied by the caller.
//!
//! Hidden layers are initialised like PyTorch's `nn.Linear` default,
//! U(±1/√fan_in) for weights and biases, from a seeded generator.
//! Gradients with respect to the weights are accumulated over fixed chunks
//! of samples and summed in chunk order, so results do not depend on the
//! thread count.

use rayon::prelude::*;

/// Samples per gradient chunk (fixed: the summation order depends on it).
const CHUNK: usize = 64;

#[derive(Clone, Copy, Debug)]
struct Layer {
    n_in: usize,
    n_out: usize,
    /// Offset of the weights (row-major, n_out × n_in) in `params`.
    w: usize,
    /// Offset of the biases.
    b: usize,
    sine: bool,
    /// Whether this layer's input is the previous output followed by the
    /// input features.
    skip: bool,
}

/// A positional-encoding MLP with its parameters.
#[derive(Clone, Debug)]
pub struct PosMlp {
    pub n_features: usize,
    pub n_out: usize,
    layers: Vec<Layer>,
    /// Floats of activation record per sample.
    tape_len: usize,
    /// Offset of each layer's record (its input, then cos a) in a tape.
    tape_offsets: Vec<usize>,
    pub params: Vec<f32>,
}

/// Input features of a grid position: (row, col), then for each octave
/// k < `multires`: sin(2ᵏ·row), sin(2ᵏ·col), cos(2ᵏ·row), cos(2ᵏ·col) —
/// the reference's `get_embedder` with `include_input` and log sampling.
pub fn position_features(row: f32, col: f32, multires: usize, out: &mut Vec<f32>) {
    out.push(row);
    out.push(col);
    for k in 0..multires {
        let f = (1u32 << k) as f32;
        out.push((row * f).sin());
        out.push((col * f).sin());
        out.push((row * f).cos());
        out.push((col * f).cos());
    }
}

/// Number of features [`position_features`] produces.
pub fn position_feature_count(multires: usize) -> usize {
    2 + 4 * multires
}

impl PosMlp {
    /// `depth` hidden layers of `width` units; `skips` are hidden-layer
    /// indices (1-based like the reference's `skip_connection = [1, 3]`,
    /// i.e. layer k's input gets the features appended).
    pub fn new(
        n_features: usize,
        width: usize,
        depth: usize,
        n_out: usize,
        skips: &[usize],
        seed: u64,
    ) -> PosMlp {
        let width = width.max(n_features + 1);
        let mut layers = Vec::new();
        let mut n_in = n_features;
        let mut off = 0;
        let mut tape_len = 0;
        let mut tape_offsets = Vec::new();
        for l in 0..=depth {
            let last = l == depth;
            let n_out_l = if last {
                n_out
            } else if skips.contains(&(l + 1)) {
                width - n_features
            } else {
                width
            };
            let skip = skips.contains(&l) && l > 0;
            let n_in_l = if skip { n_in + n_features } else { n_in };
            layers.push(Layer {
                n_in: n_in_l,
                n_out: n_out_l,
                w: off,
                b: off + n_in_l * n_out_l,
                sine: !last,
                skip,
            });
            off += n_in_l * n_out_l + n_out_l;
            tape_offsets.push(tape_len);
            tape_len += n_in_l + if last { 0 } else { n_out_l };
            n_in = n_out_l;
        }
        let mut params = vec![0f32; off];
        let mut rng = matflow_scene::rng::Rng(seed ^ 0x6d6c_705f_696e_6974);
        for ly in &layers {
            if !ly.sine {
                continue; // the output layer starts at zero
            }
            let bound = 1.0 / (ly.n_in as f32).sqrt();
            for p in &mut params[ly.w..ly.b + ly.n_out] {
                *p = bound * rng.signed();
            }
        }
        PosMlp {
            n_features,
            n_out,
            layers,
            tape_len,
            tape_offsets,
            params,
        }
    }

    pub fn param_count(&self) -> usize {
        self.params.len()
    }

    /// One sample forward; `tape` (len `tape_len`) records what the
    /// backward pass needs: each layer's input and, for sine layers,
    /// cos of the pre-activation. `h` is scratch for a layer's output.
    fn forward_one(&self, feat: &[f32], out: &mut [f32], tape: &mut [f32], h: &mut Vec<f32>) {
        let p = &self.params;
        let mut t = 0;
        for (li, ly) in self.layers.iter().enumerate() {
            let x_off = t;
            if li == 0 {
                tape[t..t + feat.len()].copy_from_slice(feat);
            } else {
                tape[t..t + h.len()].copy_from_slice(h);
                if ly.skip {
                    tape[t + h.len()..t + h.len() + feat.len()].copy_from_slice(feat);
                }
            }
            t += ly.n_in;
            let (xs, rest) = tape.split_at_mut(t);
            let x = &xs[x_off..];
            if ly.sine {
                h.clear();
                for o in 0..ly.n_out {
                    let w = &p[ly.w + o * ly.n_in..ly.w + (o + 1) * ly.n_in];
                    let (s, c) = (dot(w, x) + p[ly.b + o]).sin_cos();
                    rest[o] = c;
                    h.push(s);
                }
                t += ly.n_out;
            } else {
                for o in 0..ly.n_out {
                    let w = &p[ly.w + o * ly.n_in..ly.w + (o + 1) * ly.n_in];
                    out[o] = dot(w, x) + p[ly.b + o];
                }
            }
        }
    }

    /// Outputs for `n` samples (`feats` is n × n_features), without
    /// recording anything.
    pub fn forward(&self, feats: &[f32]) -> Vec<f32> {
        let nf = self.n_features;
        let n = feats.len() / nf;
        let mut out = vec![0f32; n * self.n_out];
        out.par_chunks_mut(self.n_out * CHUNK)
            .enumerate()
            .for_each(|(c, o)| {
                let mut tape = vec![0f32; self.tape_len];
                let mut h = Vec::new();
                for (j, oj) in o.chunks_mut(self.n_out).enumerate() {
                    let s = c * CHUNK + j;
                    self.forward_one(&feats[s * nf..(s + 1) * nf], oj, &mut tape, &mut h);
                }
            });
        out
    }

    /// Outputs and the activation record for `n` samples.
    pub fn forward_taped(&self, feats: &[f32]) -> (Vec<f32>, Vec<f32>) {
        let nf = self.n_features;
        let n = feats.len() / nf;
        let mut out = vec![0f32; n * self.n_out];
        let mut tape = vec![0f32; n * self.tape_len];
        out.par_chunks_mut(self.n_out * CHUNK)
            .zip(tape.par_chunks_mut(self.tape_len * CHUNK))
            .enumerate()
            .for_each(|(c, (o, tp))| {
                let mut h = Vec::new();
                for (j, (oj, tj)) in o
                    .chunks_mut(self.n_out)
                    .zip(tp.chunks_mut(self.tape_len))
                    .enumerate()
                {
                    let s = c * CHUNK + j;
                    self.forward_one(&feats[s * nf..(s + 1) * nf], oj, tj, &mut h);
                }
            });
        (out, tape)
    }

    /// Gradient of Σ_s dout_s · out_s with respect to the parameters.
    pub fn backward(&self, tape: &[f32], dout: &[f32]) -> Vec<f32> {
        let n = dout.len() / self.n_out;
        let np = self.params.len();
        let partials: Vec<Vec<f32>> = (0..n.div_ceil(CHUNK))
            .into_par_iter()
            .map(|c| {
                let mut g = vec![0f32; np];
                let mut dy = Vec::new();
                let mut dx = Vec::new();
                for s in c * CHUNK..((c + 1) * CHUNK).min(n) {
                    let tp = &tape[s * self.tape_len..(s + 1) * self.tape_len];
                    dy.clear();
                    dy.extend_from_slice(&dout[s * self.n_out..(s + 1) * self.n_out]);
                    self.backward_one(tp, &mut dy, &mut dx, &mut g);
                }
                g
            })
            .collect();
        let mut g = vec![0f32; np];
        for part in partials {
            for (a, b) in g.iter_mut().zip(part) {
                *a += b;
            }
        }
        g
    }

    fn backward_one(&self, tape: &[f32], dy: &mut Vec<f32>, dx: &mut Vec<f32>, g: &mut [f32]) {
        let p = &self.params;
        let offs = &self.tape_offsets;
        for li in (0..self.layers.len()).rev() {
            let ly = self.layers[li];
            let x = &tape[offs[li]..offs[li] + ly.n_in];
            if ly.sine {
                let cos_a = &tape[offs[li] + ly.n_in..offs[li] + ly.n_in + ly.n_out];
                for (d, c) in dy.iter_mut().zip(cos_a) {
                    *d *= c;
                }
            }
            dx.clear();
            dx.resize(ly.n_in, 0.0);
            for o in 0..ly.n_out {
                let d = dy[o];
                if d == 0.0 {
                    continue;
                }
                g[ly.b + o] += d;
                let gw = &mut g[ly.w + o * ly.n_in..ly.w + (o + 1) * ly.n_in];
                let w = &p[ly.w + o * ly.n_in..ly.w + (o + 1) * ly.n_in];
                for k in 0..ly.n_in {
                    gw[k] += d * x[k];
                    dx[k] += d * w[k];
                }
            }
            if li == 0 {
                break;
            }
            // The previous layer's output is the first part of this input.
            let prev = self.layers[li - 1].n_out;
            dy.clear();
            dy.extend_from_slice(&dx[..prev]);
        }
    }
}

#[inline]
fn dot(a: &[f32], b: &[f32]) -> f32 {
    let mut s = [0f32; 8];
    let n8 = a.len() / 8 * 8;
    for i in (0..n8).step_by(8) {
        for k in 0..8 {
            s[k] += a[i + k] * b[i + k];
        }
    }
    let mut t = (s[0] + s[4]) + (s[1] + s[5]) + ((s[2] + s[6]) + (s[3] + s[7]));
    for i in n8..a.len() {
        t += a[i] * b[i];
    }
    t
}

#[cfg(test)]
mod tests {
    use super::*;

    fn features(n: usize) -> Vec<f32> {
        let mut f = Vec::new();
        for s in 0..n {
            position_features((s / 4) as f32, (s % 4) as f32, 2, &mut f);
            f.push(0.3 + 0.1 * s as f32);
        }
        f
    }

    fn net() -> PosMlp {
        let nf = position_feature_count(2) + 1;
        let mut m = PosMlp::new(nf, 16, 4, 3, &[1, 3], 7);
        // Give the zero-initialised output layer values so every weight
        // has a gradient.
        let last = *m.layers.last().unwrap();
        let mut rng = matflow_scene::rng::Rng(99);
        for p in &mut m.params[last.w..last.b + last.n_out] {
            *p = 0.3 * rng.signed();
        }
        m
    }

    #[test]
    fn output_layer_starts_at_zero_and_shapes_follow_the_reference() {
        let nf = position_feature_count(2) + 3;
        assert_eq!(nf, 13);
        let m = PosMlp::new(nf, 32, 4, 3, &[1, 3], 1);
        // Layer 0 is narrowed before the skip at layer 1, which is `width`
        // wide again; likewise around layer 3.
        let widths: Vec<(usize, usize)> = m.layers.iter().map(|l| (l.n_in, l.n_out)).collect();
        assert_eq!(
            widths,
            vec![(13, 19), (32, 32), (32, 19), (32, 32), (32, 3)]
        );
        assert!(m.forward(&[]).is_empty());
        let f: Vec<f32> = (0..13 * 3).map(|k| k as f32 * 0.1).collect();
        assert!(m.forward(&f).iter().all(|&v| v == 0.0));
    }

    #[test]
    fn gradients_match_central_differences() {
        let m = net();
        let n = 70; // more than one chunk
        let f = features(n);
        let nf = m.n_features;
        assert_eq!(f.len(), n * nf);
        // Loss: Σ c_s · out_s with fixed coefficients.
        let c: Vec<f32> = (0..n * 3)
            .map(|k| ((k * 37 % 11) as f32 - 5.0) * 0.1)
            .collect();
        let (out, tape) = m.forward_taped(&f);
        assert_eq!(out, m.forward(&f));
        let g = m.backward(&tape, &c);
        let loss = |m: &PosMlp| -> f64 {
            m.forward(&f)
                .iter()
                .zip(&c)
                .map(|(a, b)| *a as f64 * *b as f64)
                .sum()
        };
        let mut checked = 0;
        for k in (0..m.param_count()).step_by(m.param_count() / 60) {
            let h = 1e-2f32;
            let mut mp = m.clone();
            mp.params[k] += h;
            let mut mm = m.clone();
            mm.params[k] -= h;
            let fd = (loss(&mp) - loss(&mm)) / (2.0 * h as f64);
            let err = (fd - g[k] as f64).abs();
            assert!(
                err < 2e-3 * (1.0 + fd.abs()),
                "param {k}: analytic {} vs finite difference {fd}",
                g[k]
            );
            checked += 1;
        }
        assert!(checked > 20);
    }

    #[test]
    fn learns_a_smooth_function_deterministically() {
        use crate::optim::Adam;
        let train = || {
            let mut m = PosMlp::new(position_feature_count(2), 24, 3, 1, &[2], 3);
            let mut f = Vec::new();
            let mut y = Vec::new();
            for r in 0..8 {
                for c in 0..16 {
                    position_features(r as f32, c as f32, 2, &mut f);
                    y.push((r as f32 * 0.3).sin() * 0.5 + c as f32 * 0.05);
                }
            }
            let mut adam = Adam::new(m.param_count(), 3e-3);
            let mse = |o: &[f32]| -> f32 {
                o.iter()
                    .zip(&y)
                    .map(|(a, b)| (a - b) * (a - b))
                    .sum::<f32>()
                    / y.len() as f32
            };
            let first = mse(&m.forward(&f));
            for _ in 0..400 {
                let (o, tape) = m.forward_taped(&f);
                let d: Vec<f32> = o
                    .iter()
                    .zip(&y)
                    .map(|(a, b)| 2.0 * (a - b) / y.len() as f32)
                    .collect();
                let g = m.backward(&tape, &d);
                adam.step(&mut m.params, &g);
            }
            (first, mse(&m.forward(&f)), m.params)
        };
        let (first, last, p1) = train();
        assert!(last < 0.05 * first, "MSE {first} -> {last}");
        let (_, _, p2) = train();
        assert_eq!(p1, p2);
    }
}
