//! The re-rendering loss of the paper (eqs. 13, 19): L1 + L2 between the
//! render and the input after the inverse gamma x^(1/2.2), averaged over
//! pixels and channels; and the consistency term (eq. 20).
//!
//! Guards: x^(1/2.2) has an infinite slope at 0, so below [`GAMMA_EPS`] it
//! is continued linearly (slope bounded by ≈ 150); saturated input pixels
//! (≥ [`SATURATED`] in any channel after clipping) only penalise renders
//! that are too dark there, since the true radiance may be anything above.

use glam::Vec3;
use matflow_render::lanes::{self, F};
use rayon::prelude::*;

pub const GAMMA: f32 = 2.2;
pub const GAMMA_EPS: f32 = 1e-4;
pub const SATURATED: f32 = 0.999;

/// x^(1/2.2) for positive x, as exp(ln x / 2.2) in lanes: within 5·10⁻⁷
/// of the exact power from 10⁻⁴ up, and the same bits at every lane width and on every
/// machine (libm picks its `powf` by CPU feature and promises no bits).
#[inline(always)]
pub fn gamma_pow<const W: usize>(x: F<W>) -> F<W> {
    lanes::exp(lanes::ln(x) * (1.0 / GAMMA))
}

/// The slope of [`gamma`]'s linear continuation below [`GAMMA_EPS`].
#[inline]
pub fn gamma_toe() -> f32 {
    gamma_pow(F::<1>([GAMMA_EPS])).0[0] / GAMMA_EPS
}

/// [`gamma`]'s value in lanes, bit for bit; `toe` is [`gamma_toe`].
#[inline(always)]
pub fn gamma_value<const W: usize>(x: F<W>, toe: f32) -> F<W> {
    // NaN takes the continuation, as in the scalar branch.
    let on_curve = F::splat(GAMMA_EPS).le(x);
    let y = gamma_pow(F::select(on_curve, x, F::splat(1.0)));
    F::select(on_curve, y, toe * x.max(0.0))
}

/// x^(1/2.2) with a linear continuation below GAMMA_EPS; returns (value,
/// derivative).
#[inline]
pub fn gamma(x: f32) -> (f32, f32) {
    let e = 1.0 / GAMMA;
    if x >= GAMMA_EPS {
        let y = gamma_pow(F::<1>([x])).0[0];
        (y, e * y / x)
    } else {
        let s = gamma_toe();
        // The slope is kept below 0 too, so a black render can brighten.
        (s * F::<1>([x]).max(0.0).0[0], s)
    }
}

/// Inverse of [`gamma`], linear toe included.
#[inline]
pub fn gamma_inv(y: f32) -> f32 {
    let (y0, _) = gamma(GAMMA_EPS);
    if y >= y0 {
        y.powf(GAMMA)
    } else {
        y.max(0.0) * (GAMMA_EPS / y0)
    }
}

/// The reference's exposure `ratio`: the factor k that makes the mean of
/// k·render equal the target's, from their sums; `None` when either is not
/// positive. Clamped to [1e-3, 1e3] so a black render cannot blow it up.
#[inline]
pub fn exposure_ratio(target_sum: f64, render_sum: f64) -> Option<f32> {
    (target_sum > 0.0 && render_sum > 0.0)
        .then(|| ((target_sum / render_sum) as f32).clamp(1e-3, 1e3))
}

/// Subgradient of |x|: the sign, 0 at 0.
#[inline]
pub fn sign(x: f32) -> f32 {
    if x > 0.0 {
        1.0
    } else if x < 0.0 {
        -1.0
    } else {
        0.0
    }
}

/// A target image prepared for the loss.
pub struct Target {
    pub width: usize,
    pub height: usize,
    /// γ(target), per pixel.
    pub gamma: Vec<Vec3>,
    /// Per pixel, per channel: target saturated (one-sided residual).
    pub saturated: Vec<[bool; 3]>,
    /// The linear target (non-finite values as 0, negatives clipped).
    pub linear: Vec<Vec3>,
}

impl Target {
    pub fn new(width: usize, height: usize, linear: &[Vec3]) -> Target {
        let gamma = linear
            .iter()
            .map(|v| {
                let f = |x: f32| gamma(if x.is_finite() { x.max(0.0) } else { 0.0 }).0;
                Vec3::new(f(v.x), f(v.y), f(v.z))
            })
            .collect();
        let saturated = linear
            .iter()
            .map(|v| [v.x >= SATURATED, v.y >= SATURATED, v.z >= SATURATED])
            .collect();
        let linear = linear
            .iter()
            .map(|v| {
                let f = |x: f32| if x.is_finite() { x.max(0.0) } else { 0.0 };
                Vec3::new(f(v.x), f(v.y), f(v.z))
            })
            .collect();
        Target {
            width,
            height,
            gamma,
            saturated,
            linear,
        }
    }

    /// Pixel `p`'s part of an exposure sum for the linear values `i`: the
    /// channels where the target is not saturated. The exposure ratio is
    /// taken only where the loss measures anything: a linear (HDR) input
    /// showing sky far above 1 through a window would otherwise dominate
    /// the target's sum while the loss, one-sided there, leaves the render
    /// near 1, and the ratio would brighten everything else.
    #[inline]
    pub fn exposure_part(&self, p: usize, i: Vec3) -> f64 {
        let s = self.saturated[p];
        (0..3).filter(|&c| !s[c]).map(|c| i[c] as f64).sum()
    }

    /// The target's own exposure sum ([`Target::exposure_part`] of its
    /// linear values, pixels in order).
    pub fn exposure_sum(&self) -> f64 {
        (0..self.linear.len())
            .map(|p| self.exposure_part(p, self.linear[p]))
            .sum()
    }
}

/// Loss terms: L1 and L2 means.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct LossValue {
    pub l1: f64,
    pub l2: f64,
}

impl LossValue {
    pub fn total(&self) -> f64 {
        self.l1 + self.l2
    }
}

/// Residual, its contribution to L1 and L2, and d(|r| + r²)/dI.
#[inline]
pub fn pixel_loss(i: Vec3, tg: Vec3, sat: [bool; 3]) -> (f32, f32, Vec3) {
    let mut l1 = 0.0;
    let mut l2 = 0.0;
    let mut d = Vec3::ZERO;
    for c in 0..3 {
        let (g, dg) = gamma(i[c]);
        let mut r = g - tg[c];
        if sat[c] && r > 0.0 {
            r = 0.0;
        }
        l1 += r.abs();
        l2 += r * r;
        d[c] = (sign(r) + 2.0 * r) * dg;
    }
    (l1, l2, d)
}

/// Loss over the pixels `idx` (all when `None`) and ∂loss/∂I for them (the
/// mean runs over the selected pixels × 3 channels).
pub fn loss_and_grad(
    image: &[Vec3],
    target: &Target,
    idx: Option<&[u32]>,
) -> (LossValue, Vec<Vec3>) {
    let n = idx.map(|v| v.len()).unwrap_or(image.len());
    let norm = 1.0 / (3.0 * n.max(1) as f64);
    let chunk = 4096;
    let parts: Vec<(f64, f64, Vec<Vec3>)> = (0..n.div_ceil(chunk))
        .into_par_iter()
        .map(|c| {
            let mut l1 = 0.0f64;
            let mut l2 = 0.0f64;
            let mut g = Vec::with_capacity(chunk);
            for k in c * chunk..((c + 1) * chunk).min(n) {
                let p = idx.map(|v| v[k] as usize).unwrap_or(k);
                let (a, b, d) = pixel_loss(image[k], target.gamma[p], target.saturated[p]);
                l1 += a as f64;
                l2 += b as f64;
                g.push(d * norm as f32);
            }
            (l1, l2, g)
        })
        .collect();
    let mut v = LossValue::default();
    let mut grad = Vec::with_capacity(n);
    for (a, b, g) in parts {
        v.l1 += a;
        v.l2 += b;
        grad.extend(g);
    }
    v.l1 *= norm;
    v.l2 *= norm;
    (v, grad)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gamma_is_continuous_and_finite() {
        let (a, _) = gamma(GAMMA_EPS * (1.0 - 1e-6));
        let (b, _) = gamma(GAMMA_EPS);
        assert!((a - b).abs() < 1e-5);
        for x in [0.0, -1.0, 1e-30, 1e-8, 0.5, 1.0, 1e10] {
            let (y, d) = gamma(x);
            assert!(y.is_finite() && d.is_finite() && d >= 0.0, "{x}: {y} {d}");
        }
    }

    /// The lane power is within 5·10⁻⁷ (relative) of libm's on the range
    /// a render spans — ln x's last bit, times 1/2.2, is the exponent's
    /// error: up to 8 ulp at 10⁻⁴ — and the lane value is the scalar one,
    /// bit for bit, at every width (NaN and negatives included).
    #[test]
    fn gamma_in_lanes_matches_powf_and_the_scalar_branch() {
        let mut x = GAMMA_EPS;
        let mut worst = 0f64;
        while x < 1e4 {
            let got = gamma(x).0 as f64;
            let want = (x as f64).powf(1.0 / GAMMA as f64);
            worst = worst.max((got - want).abs() / want);
            x *= 1.000_37;
        }
        assert!(worst < 5e-7, "worst relative error {worst:e}");
        let toe = gamma_toe();
        let xs: [f32; 16] = [
            0.0,
            -0.0,
            -1.0,
            1e-6,
            5e-5,
            9.99e-5,
            1e-4,
            0.01,
            0.18,
            0.5,
            1.0,
            3.0,
            1e3,
            f32::NAN,
            f32::INFINITY,
            f32::NEG_INFINITY,
        ];
        let wide = gamma_value(F::<16>(xs), toe).0;
        let eight = gamma_value(F::<8>(std::array::from_fn(|i| xs[i + 8])), toe).0;
        for (i, &x) in xs.iter().enumerate() {
            let want = gamma(x).0;
            assert_eq!(wide[i].to_bits(), want.to_bits(), "{x}");
            if i >= 8 {
                assert_eq!(eight[i - 8].to_bits(), want.to_bits(), "{x}");
            }
        }
    }

    #[test]
    fn gamma_inverse_round_trips() {
        for x in [0.0f32, 1e-6, 5e-5, 1e-4, 0.01, 0.5, 1.0, 3.0] {
            let y = gamma(x).0;
            assert!((gamma_inv(y) - x).abs() <= 1e-4 * x.max(1e-3), "{x}");
        }
    }

    #[test]
    fn exposure_sums_skip_the_targets_saturated_channels() {
        // A dim room pixel and a window's sky far above 1 (linear HDR
        // input), green channel of the first one saturated too.
        let t = Target::new(
            2,
            1,
            &[Vec3::new(0.2, 1.5, 0.3), Vec3::new(40.0, 50.0, 60.0)],
        );
        assert!((t.exposure_sum() - 0.5).abs() < 1e-6);
        let render = Vec3::new(0.1, 0.9, 0.15);
        assert!((t.exposure_part(0, render) - 0.25).abs() < 1e-6);
        assert_eq!(t.exposure_part(1, Vec3::splat(1.0)), 0.0);
        // So the ratio is the room's, not the sky's.
        let k = exposure_ratio(t.exposure_sum(), t.exposure_part(0, render)).unwrap();
        assert!((k - 2.0).abs() < 1e-5, "{k}");
    }

    #[test]
    fn exposure_ratio_matches_means_and_guards_zero() {
        assert_eq!(exposure_ratio(6.0, 3.0), Some(2.0));
        assert_eq!(exposure_ratio(1.0, 0.0), None);
        assert_eq!(exposure_ratio(0.0, 1.0), None);
        assert_eq!(exposure_ratio(1e9, 1.0), Some(1e3));
    }

    #[test]
    fn loss_gradient_matches_central_differences() {
        let target_lin = vec![Vec3::new(0.2, 0.5, 1.0), Vec3::new(0.01, 0.3, 0.7)];
        let t = Target::new(2, 1, &target_lin);
        let img = vec![Vec3::new(0.25, 0.4, 0.8), Vec3::new(0.02, 0.31, 0.65)];
        let (_, g) = loss_and_grad(&img, &t, None);
        for p in 0..2 {
            for c in 0..3 {
                let h = 1e-4;
                let mut a = img.clone();
                a[p][c] += h;
                let mut b = img.clone();
                b[p][c] -= h;
                let num = (loss_and_grad(&a, &t, None).0.total()
                    - loss_and_grad(&b, &t, None).0.total())
                    / (2.0 * h as f64);
                let an = g[p][c] as f64;
                assert!(
                    (an - num).abs() <= 2e-3 * an.abs().max(1e-3),
                    "p{p} c{c}: {an} vs {num}"
                );
            }
        }
    }

    #[test]
    fn saturated_pixels_only_penalise_dark_renders() {
        let t = Target::new(1, 1, &[Vec3::ONE]);
        let (v, g) = loss_and_grad(&[Vec3::splat(3.0)], &t, None);
        assert_eq!(v.total(), 0.0);
        assert_eq!(g[0], Vec3::ZERO);
        let (v, _) = loss_and_grad(&[Vec3::splat(0.5)], &t, None);
        assert!(v.total() > 0.0);
    }
}
