//! Image comparison in the reference's display space: clip to [0, 1], then
//! power 1/2.2 ("sRGB, γ 2.2" in the issues and METHOD.md).

use crate::color::linear_to_gamma;
use crate::image::RgbImage;

/// Mean squared error over all channels after gamma encoding (f64 sum).
pub fn mse_gamma(a: &RgbImage, b: &RgbImage) -> f64 {
    assert!(a.same_size(b), "mse_gamma: image sizes differ");
    let mut sum = 0.0f64;
    for (p, q) in a.data.iter().zip(b.data.iter()) {
        for c in 0..3 {
            let d = linear_to_gamma(p[c]) as f64 - linear_to_gamma(q[c]) as f64;
            sum += d * d;
        }
    }
    sum / (3 * a.data.len()).max(1) as f64
}

/// PSNR in dB with peak 1 after gamma encoding; capped at 100 dB for
/// identical images.
pub fn psnr_gamma(a: &RgbImage, b: &RgbImage) -> f64 {
    psnr_from_mse(mse_gamma(a, b))
}

pub fn psnr_from_mse(mse: f64) -> f64 {
    if mse <= 1e-10 {
        100.0
    } else {
        -10.0 * mse.log10()
    }
}

/// Mean squared error of linear values (f64 sum).
pub fn mse_linear(a: &RgbImage, b: &RgbImage) -> f64 {
    assert!(a.same_size(b), "mse_linear: image sizes differ");
    let mut sum = 0.0f64;
    for (p, q) in a.data.iter().zip(b.data.iter()) {
        let d = (*p - *q).as_dvec3();
        sum += d.length_squared();
    }
    sum / (3 * a.data.len()).max(1) as f64
}

/// SSIM (Wang et al. 2004: 11×11 Gaussian window, σ = 1.5, K1 = 0.01,
/// K2 = 0.03, peak 1) of two single-channel images, windows clipped at the
/// border; the mean over pixels.
pub fn ssim_channel(a: &[f32], b: &[f32], w: usize, h: usize) -> f64 {
    use rayon::prelude::*;
    assert_eq!(a.len(), w * h);
    assert_eq!(b.len(), w * h);
    if w == 0 || h == 0 {
        return 0.0;
    }
    let r = 5i64;
    let g: Vec<f64> = (-r..=r)
        .map(|i| (-(i * i) as f64 / (2.0 * 1.5 * 1.5)).exp())
        .collect();
    // The five blurred signals x, y, x², y², xy (separable, renormalised
    // at the border), rows in parallel; each value's sum runs in tap
    // order, so the result does not depend on the thread count.
    let signals = |i: usize| {
        let (x, y) = (a[i] as f64, b[i] as f64);
        [x, y, x * x, y * y, x * y]
    };
    let mut tmp = vec![[0f64; 5]; w * h];
    tmp.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        for (x, out) in row.iter_mut().enumerate() {
            *out = window(&g, x, w, |xx| signals(y * w + xx));
        }
    });
    let (c1, c2) = (0.01f64 * 0.01, 0.03f64 * 0.03);
    let mut terms = vec![0f64; w * h];
    terms.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        for (x, term) in row.iter_mut().enumerate() {
            let [ma, mb, saa, sbb, sab] = window(&g, y, h, |yy| tmp[yy * w + x]);
            let va = (saa - ma * ma).max(0.0);
            let vb = (sbb - mb * mb).max(0.0);
            let cov = sab - ma * mb;
            *term = ((2.0 * ma * mb + c1) * (2.0 * cov + c2))
                / ((ma * ma + mb * mb + c1) * (va + vb + c2));
        }
    });
    // Summed in pixel order, as one thread would.
    let mut sum = 0.0;
    for t in terms {
        sum += t;
    }
    sum / (w * h) as f64
}

/// The Gaussian window `g` (taps −r..=r) at `p` along a line of `len`
/// values `v`: the weighted mean of the five signals over the taps inside
/// the line (renormalised at its ends), summed in tap order.
#[inline]
fn window(g: &[f64], p: usize, len: usize, v: impl Fn(usize) -> [f64; 5]) -> [f64; 5] {
    let r = (g.len() / 2) as i64;
    let (mut s, mut n) = ([0f64; 5], 0.0);
    for k in -r..=r {
        let q = p as i64 + k;
        if q >= 0 && (q as usize) < len {
            let gk = g[(k + r) as usize];
            let x = v(q as usize);
            for j in 0..5 {
                s[j] += gk * x[j];
            }
            n += gk;
        }
    }
    s.map(|x| x / n)
}

/// SSIM after clipping to [0, 1] and gamma encoding, mean over channels.
pub fn ssim_gamma(a: &RgbImage, b: &RgbImage) -> f64 {
    assert!(a.same_size(b), "ssim_gamma: image sizes differ");
    let mut tot = 0.0;
    for c in 0..3 {
        let ca: Vec<f32> = a.data.iter().map(|v| linear_to_gamma(v[c])).collect();
        let cb: Vec<f32> = b.data.iter().map(|v| linear_to_gamma(v[c])).collect();
        tot += ssim_channel(&ca, &cb, a.width, a.height);
    }
    tot / 3.0
}

/// SSIM of linear (HDR) values without clipping, mean over channels.
pub fn ssim_linear(a: &RgbImage, b: &RgbImage) -> f64 {
    assert!(a.same_size(b), "ssim_linear: image sizes differ");
    let mut tot = 0.0;
    for c in 0..3 {
        let ca: Vec<f32> = a.data.iter().map(|v| v[c]).collect();
        let cb: Vec<f32> = b.data.iter().map(|v| v[c]).collect();
        tot += ssim_channel(&ca, &cb, a.width, a.height);
    }
    tot / 3.0
}

/// Number of real spherical-harmonic coefficients up to band 4.
pub const SH_COEFFS: usize = 25;

/// Real orthonormal spherical harmonics Y_lm(θ, φ) for l ≤ 4, in the
/// order (0,0), (1,−1), (1,0), (1,1), (2,−2), … (m from −l to l).
pub fn sh_basis(theta: f64, phi: f64) -> [f64; SH_COEFFS] {
    let x = theta.cos();
    let sx = theta.sin().abs();
    // Associated Legendre P_l^m(x) without the Condon–Shortley phase.
    let mut p = [[0f64; 5]; 5];
    p[0][0] = 1.0;
    for m in 0..5 {
        if m > 0 {
            p[m][m] = p[m - 1][m - 1] * (2 * m - 1) as f64 * sx;
        }
        if m < 4 {
            p[m + 1][m] = x * (2 * m + 1) as f64 * p[m][m];
        }
        for l in m + 2..5 {
            p[l][m] = ((2 * l - 1) as f64 * x * p[l - 1][m] - (l + m - 1) as f64 * p[l - 2][m])
                / (l - m) as f64;
        }
    }
    let fact = |n: usize| (1..=n).map(|k| k as f64).product::<f64>();
    let mut out = [0f64; SH_COEFFS];
    let mut k = 0;
    for l in 0..5usize {
        for m in -(l as i64)..=(l as i64) {
            let am = m.unsigned_abs() as usize;
            let norm = ((2 * l + 1) as f64 / (4.0 * std::f64::consts::PI) * fact(l - am)
                / fact(l + am))
            .sqrt();
            out[k] = match m.cmp(&0) {
                std::cmp::Ordering::Equal => norm * p[l][0],
                std::cmp::Ordering::Greater => {
                    std::f64::consts::SQRT_2 * norm * (m as f64 * phi).cos() * p[l][am]
                }
                std::cmp::Ordering::Less => {
                    std::f64::consts::SQRT_2 * norm * (am as f64 * phi).sin() * p[l][am]
                }
            };
            k += 1;
        }
    }
    out
}

/// Projection of a lat-long envmap (Mitsuba layout: column j at
/// φ = 2π(j + ½)/W, row i at θ = πi/(H − 1)) onto SH bands 0–4, RGB;
/// texels weighted by their solid angle sin θ·Δθ·Δφ.
pub fn sh_project(env: &RgbImage) -> [[f64; 3]; SH_COEFFS] {
    let (w, h) = (env.width, env.height);
    let mut c = [[0f64; 3]; SH_COEFFS];
    if w == 0 || h < 2 {
        return c;
    }
    let dphi = 2.0 * std::f64::consts::PI / w as f64;
    let dtheta = std::f64::consts::PI / (h - 1) as f64;
    for i in 0..h {
        let theta = dtheta * i as f64;
        // Trapezoid in θ: the pole rows carry half a row.
        let edge = if i == 0 || i == h - 1 { 0.5 } else { 1.0 };
        let wgt = theta.sin() * dtheta * dphi * edge;
        for j in 0..w {
            let phi = dphi * (j as f64 + 0.5);
            let y = sh_basis(theta, phi);
            let v = env.get(j, i);
            for k in 0..SH_COEFFS {
                for ch in 0..3 {
                    c[k][ch] += y[k] * wgt * v[ch] as f64;
                }
            }
        }
    }
    c
}

/// The paper's SH error (Table 3): the Frobenius norm of the difference
/// of the two envmaps' SH coefficient matrices (bands 0–4, RGB).
pub fn sh_error(a: &RgbImage, b: &RgbImage) -> f64 {
    let (ca, cb) = (sh_project(a), sh_project(b));
    let mut s = 0.0;
    for k in 0..SH_COEFFS {
        for ch in 0..3 {
            let d = ca[k][ch] - cb[k][ch];
            s += d * d;
        }
    }
    s.sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::image::Image;
    use glam::Vec3;

    #[test]
    fn psnr_of_known_offset() {
        let a = Image::new(8, 8, Vec3::splat(0.0));
        // gamma(x) = 0.1 everywhere → mse 0.01 → 20 dB.
        let b = Image::new(8, 8, Vec3::splat(0.1f32.powf(2.2)));
        assert!((psnr_gamma(&a, &b) - 20.0).abs() < 1e-3);
        assert_eq!(psnr_gamma(&a, &a), 100.0);
    }

    #[test]
    fn sh_basis_is_orthonormal_under_quadrature() {
        // Midpoint rule on a fine grid: ∫ Y_a Y_b dω = δ_ab.
        let (nt, np) = (200, 400);
        let mut g = [[0f64; SH_COEFFS]; SH_COEFFS];
        for i in 0..nt {
            let t = std::f64::consts::PI * (i as f64 + 0.5) / nt as f64;
            for j in 0..np {
                let ph = 2.0 * std::f64::consts::PI * (j as f64 + 0.5) / np as f64;
                let y = sh_basis(t, ph);
                let w = t.sin()
                    * (std::f64::consts::PI / nt as f64)
                    * (2.0 * std::f64::consts::PI / np as f64);
                for a in 0..SH_COEFFS {
                    for b in 0..SH_COEFFS {
                        g[a][b] += y[a] * y[b] * w;
                    }
                }
            }
        }
        for a in 0..SH_COEFFS {
            for b in 0..SH_COEFFS {
                let want = if a == b { 1.0 } else { 0.0 };
                assert!((g[a][b] - want).abs() < 1e-3, "<Y{a}, Y{b}> = {}", g[a][b]);
            }
        }
        // Known values: Y00 = 1/(2√π); Y10 = √(3/4π)·cos θ.
        let y = sh_basis(0.3, 1.1);
        assert!((y[0] - 0.5 / std::f64::consts::PI.sqrt()).abs() < 1e-12);
        assert!((y[2] - (3.0 / (4.0 * std::f64::consts::PI)).sqrt() * 0.3f64.cos()).abs() < 1e-12);
    }

    #[test]
    fn sh_projection_of_a_constant_envmap() {
        // A constant c projects to c·√(4π) on Y00 and ~0 elsewhere.
        let env = Image::new(64, 32, Vec3::splat(2.0));
        let c = sh_project(&env);
        let want = 2.0 * (4.0 * std::f64::consts::PI).sqrt();
        assert!((c[0][0] - want).abs() < 0.01 * want, "{}", c[0][0]);
        for k in 1..SH_COEFFS {
            assert!(c[k][1].abs() < 0.02, "coefficient {k}: {}", c[k][1]);
        }
        assert_eq!(sh_error(&env, &env), 0.0);
        let brighter = env.map(|v| v * 1.5);
        assert!((sh_error(&env, &brighter) - 3f64.sqrt() * 0.5 * c[0][0]).abs() < 0.05);
    }

    #[test]
    fn ssim_is_one_for_identical_and_drops_with_noise() {
        let a = Image::from_fn(32, 24, |x, y| {
            Vec3::splat(((x * 7 + y * 3) % 11) as f32 / 11.0)
        });
        assert!((ssim_gamma(&a, &a) - 1.0).abs() < 1e-9);
        let b = a.map(|v| v * 0.5);
        let s = ssim_gamma(&a, &b);
        assert!(s < 0.99 && s > 0.0, "{s}");
        // Symmetric.
        assert!((ssim_gamma(&b, &a) - s).abs() < 1e-12);
    }
}
