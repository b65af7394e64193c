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
    assert_eq!(a.len(), w * h);
    assert_eq!(b.len(), w * h);
    let r = 5i64;
    let g: Vec<f64> = (-r..=r)
        .map(|i| (-(i * i) as f64 / (2.0 * 1.5 * 1.5)).exp())
        .collect();
    // Separable blur of x, y, x², y², xy with border renormalisation.
    let blur = |f: &dyn Fn(usize) -> f64| -> Vec<f64> {
        let mut tmp = vec![0f64; w * h];
        for y in 0..h {
            for x in 0..w {
                let (mut s, mut n) = (0.0, 0.0);
                for k in -r..=r {
                    let xx = x as i64 + k;
                    if xx >= 0 && (xx as usize) < w {
                        let gk = g[(k + r) as usize];
                        s += gk * f(y * w + xx as usize);
                        n += gk;
                    }
                }
                tmp[y * w + x] = s / n;
            }
        }
        let mut out = vec![0f64; w * h];
        for y in 0..h {
            for x in 0..w {
                let (mut s, mut n) = (0.0, 0.0);
                for k in -r..=r {
                    let yy = y as i64 + k;
                    if yy >= 0 && (yy as usize) < h {
                        let gk = g[(k + r) as usize];
                        s += gk * tmp[yy as usize * w + x];
                        n += gk;
                    }
                }
                out[y * w + x] = s / n;
            }
        }
        out
    };
    let ma = blur(&|i| a[i] as f64);
    let mb = blur(&|i| b[i] as f64);
    let saa = blur(&|i| (a[i] as f64) * (a[i] as f64));
    let sbb = blur(&|i| (b[i] as f64) * (b[i] as f64));
    let sab = blur(&|i| (a[i] as f64) * (b[i] as f64));
    let (c1, c2) = (0.01f64 * 0.01, 0.03f64 * 0.03);
    let mut sum = 0.0;
    for i in 0..w * h {
        let va = (saa[i] - ma[i] * ma[i]).max(0.0);
        let vb = (sbb[i] - mb[i] * mb[i]).max(0.0);
        let cov = sab[i] - ma[i] * mb[i];
        sum += ((2.0 * ma[i] * mb[i] + c1) * (2.0 * cov + c2))
            / ((ma[i] * ma[i] + mb[i] * mb[i] + c1) * (va + vb + c2));
    }
    sum / (w * h).max(1) as f64
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
