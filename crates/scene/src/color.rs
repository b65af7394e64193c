//! Colour transfer functions.
//!
//! The reference implementation linearises photos with a plain power 2.2 and
//! compares images after the inverse power (1/2.2); roughness and metallic
//! PNGs were written through the exact sRGB curve and are decoded with it.

use glam::Vec3;

pub const GAMMA: f32 = 2.2;

/// Exact sRGB decoding (IEC 61966-2-1) of a value in [0, 1].
#[inline]
pub fn srgb_to_linear(c: f32) -> f32 {
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

/// Exact sRGB encoding; input clamped to [0, 1].
#[inline]
pub fn linear_to_srgb(c: f32) -> f32 {
    let c = if c.is_finite() {
        c.clamp(0.0, 1.0)
    } else {
        0.0
    };
    if c <= 0.003_130_8 {
        c * 12.92
    } else {
        1.055 * c.powf(1.0 / 2.4) - 0.055
    }
}

/// Plain gamma decode (power 2.2) of a display value, as the reference does
/// for photos.
#[inline]
pub fn gamma_to_linear(c: f32) -> f32 {
    c.max(0.0).powf(GAMMA)
}

/// Plain gamma encode after clipping to [0, 1] (power 1/2.2): the space in
/// which the reference computes losses and PSNR. Non-finite input maps to 0.
#[inline]
pub fn linear_to_gamma(c: f32) -> f32 {
    let c = if c.is_finite() {
        c.clamp(0.0, 1.0)
    } else {
        0.0
    };
    c.powf(1.0 / GAMMA)
}

#[inline]
pub fn linear_to_gamma3(v: Vec3) -> Vec3 {
    Vec3::new(
        linear_to_gamma(v.x),
        linear_to_gamma(v.y),
        linear_to_gamma(v.z),
    )
}

/// Rec. 709 luminance of linear RGB.
#[inline]
pub fn luminance(v: Vec3) -> f32 {
    0.2126 * v.x + 0.7152 * v.y + 0.0722 * v.z
}

/// 8-bit quantisation of a value in [0, 1] (round half up, clamped).
#[inline]
pub fn to_u8(c: f32) -> u8 {
    (c.clamp(0.0, 1.0) * 255.0 + 0.5) as u8
}

/// The scale that brings an image's log-average luminance to `key` (0.18:
/// a photographer's middle grey), clamped to [1e-4, 1e4]: the automatic
/// exposure of generated photographs.
pub fn exposure_to_key(img: &crate::image::RgbImage, key: f64) -> f64 {
    let mut log_sum = 0.0f64;
    for c in &img.data {
        let l = luminance(*c).max(0.0) as f64;
        log_sum += if l.is_finite() { (l + 1e-4).ln() } else { 0.0 };
    }
    let log_avg = (log_sum / img.data.len().max(1) as f64).exp();
    (key / log_avg.max(1e-6)).clamp(1e-4, 1e4)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn srgb_round_trip() {
        for i in 0..=1000 {
            let x = i as f32 / 1000.0;
            assert!((linear_to_srgb(srgb_to_linear(x)) - x).abs() < 1e-5);
        }
    }

    #[test]
    fn srgb_decodes_known_bytes_like_mitsuba_writer() {
        // METHOD.md: byte ~188 is 0.5 and ~89 is 0.1 in the roughness PNGs.
        assert!((srgb_to_linear(188.0 / 255.0) - 0.5).abs() < 0.01);
        assert!((srgb_to_linear(89.0 / 255.0) - 0.1).abs() < 0.005);
    }

    #[test]
    fn gamma_clips_and_is_monotone() {
        assert_eq!(linear_to_gamma(-1.0), 0.0);
        assert_eq!(linear_to_gamma(7.0), 1.0);
        assert_eq!(linear_to_gamma(f32::NAN), 0.0);
        assert!((gamma_to_linear(linear_to_gamma(0.3)) - 0.3).abs() < 1e-6);
    }
}
