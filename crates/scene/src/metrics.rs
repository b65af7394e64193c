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
}
