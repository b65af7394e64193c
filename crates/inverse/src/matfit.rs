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

/// The 5 parameters of a pixel from z, with d(x)/d(z) (straight-through).
#[inline]
pub fn decode(pred: &Material, z: &[f32], zeta: f32) -> (Material, [f32; 5]) {
    let mut x = [0f32; 5];
    let mut d = [0f32; 5];
    let base = [
        pred.albedo.x,
        pred.albedo.y,
        pred.albedo.z,
        pred.roughness,
        pred.metallic,
    ];
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
    let p = [
        pred.albedo.x,
        pred.albedo.y,
        pred.albedo.z,
        pred.roughness,
        pred.metallic,
    ];
    let s = [
        start.albedo.x,
        start.albedo.y,
        start.albedo.z,
        start.roughness,
        start.metallic,
    ];
    let mut z = [0f32; 5];
    for k in 0..5 {
        let t = ((s[k] - p[k]) / zeta).clamp(-0.999, 0.999);
        z[k] = t.atanh();
    }
    z
}

/// Sums of the loss terms over a set of pixels.
#[derive(Clone, Copy, Debug, Default)]
struct Sums {
    l1: f64,
    l2: f64,
    cons: f64,
    /// Sum of the unscaled linear render over pixels and channels.
    render: f64,
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
    let target_sum: f64 = target.linear_sum();
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
    let active = [
        parts.albedo,
        parts.albedo,
        parts.albedo,
        parts.roughness,
        parts.metallic,
    ];
    let norm_re = 1.0 / (3.0 * n as f64);
    let norm_a = 1.0 / (3.0 * n as f64);
    let norm_1 = 1.0 / n as f64;
    let delta = opts.delta;
    let materialise = |z: &[f32]| -> Vec<Material> {
        (0..n)
            .into_par_iter()
            .with_min_len(1024)
            .map(|p| {
                let (m, _) = decode(&pred[p], &z[5 * p..5 * p + 5], zeta);
                Material {
                    albedo: if parts.albedo {
                        m.albedo
                    } else {
                        start[p].albedo
                    },
                    roughness: if parts.roughness {
                        m.roughness
                    } else {
                        start[p].roughness
                    },
                    metallic: if parts.metallic {
                        m.metallic
                    } else {
                        start[p].metallic
                    },
                }
            })
            .collect()
    };
    let mut best = (f64::INFINITY, z.clone(), 1f32);
    let chunk = 4096;
    for step in 0..=opts.steps {
        let sums: Vec<Sums> = grad
            .par_chunks_mut(5 * chunk)
            .enumerate()
            .map(|(c, g)| {
                let mut s = Sums::default();
                for (j, gp) in g.chunks_mut(5).enumerate() {
                    let p = c * chunk + j;
                    let zp = &z[5 * p..5 * p + 5];
                    let (mut m, dx) = decode(&pred[p], zp, zeta);
                    if !parts.albedo {
                        m.albedo = start[p].albedo;
                    }
                    if !parts.roughness {
                        m.roughness = start[p].roughness;
                    }
                    if !parts.metallic {
                        m.metallic = start[p].metallic;
                    }
                    let e = tables[p].eval(&m);
                    s.render += e.i.element_sum() as f64;
                    let (l1, l2, di) = pixel_loss(e.i * k, target.gamma[p], target.saturated[p]);
                    s.l1 += l1 as f64;
                    s.l2 += l2 as f64;
                    let di = di * (norm_re as f32 * k);
                    let mut gx = [
                        di.x * e.da.x,
                        di.y * e.da.y,
                        di.z * e.da.z,
                        (di * e.dr).element_sum(),
                        (di * e.dm).element_sum(),
                    ];
                    let xs = [m.albedo.x, m.albedo.y, m.albedo.z, m.roughness, m.metallic];
                    let ps = [
                        pred[p].albedo.x,
                        pred[p].albedo.y,
                        pred[p].albedo.z,
                        pred[p].roughness,
                        pred[p].metallic,
                    ];
                    for k in 0..5 {
                        if !active[k] {
                            gx[k] = 0.0;
                            continue;
                        }
                        let r = xs[k] - ps[k];
                        s.cons += r.abs() as f64 * if k < 3 { norm_a } else { norm_1 };
                        gx[k] +=
                            delta * sign(r) * if k < 3 { norm_a as f32 } else { norm_1 as f32 };
                    }
                    for k in 0..5 {
                        let v = gx[k] * dx[k];
                        gp[k] = if v.is_finite() { v } else { 0.0 };
                    }
                }
                s
            })
            .collect();
        let mut tot = Sums::default();
        for s in sums {
            tot.l1 += s.l1;
            tot.l2 += s.l2;
            tot.cons += s.cons;
            tot.render += s.render;
        }
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
