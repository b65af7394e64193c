//! Material edits on screen-space maps: masks (a region grown from a seed
//! pixel over the albedo) and operations on the masked pixels (set or
//! scale roughness and metallic, set the albedo, shift its hue, scale
//! saturation and value).

use std::collections::VecDeque;

use glam::Vec3;

use crate::color::{gamma_to_linear, linear_to_gamma};
use crate::{Image, MaterialMaps, RgbImage};

/// The operations of one edit. Colours and the HSV shift work on
/// γ-encoded albedo (power 1/2.2, the reference's display encoding), the
/// space a colour picker shows; results are stored linear.
#[derive(Clone, Debug, Default)]
pub struct EditOps {
    pub roughness: Option<f32>,
    pub roughness_scale: f32,
    pub metallic: Option<f32>,
    pub metallic_scale: f32,
    /// γ-encoded RGB in [0, 1].
    pub albedo: Option<Vec3>,
    pub hue_shift_deg: f32,
    pub saturation_scale: f32,
    pub value_scale: f32,
}

/// Shifts hue (degrees), scales saturation and value of a γ-encoded colour.
pub fn hsv_shift(c: Vec3, hue_deg: f32, sat: f32, val: f32) -> Vec3 {
    let c = c.clamp(Vec3::ZERO, Vec3::ONE);
    let max = c.max_element();
    let min = c.min_element();
    let d = max - min;
    let mut h = if d <= 0.0 {
        0.0
    } else if max == c.x {
        60.0 * ((c.y - c.z) / d).rem_euclid(6.0)
    } else if max == c.y {
        60.0 * ((c.z - c.x) / d + 2.0)
    } else {
        60.0 * ((c.x - c.y) / d + 4.0)
    };
    let s = if max > 0.0 { d / max } else { 0.0 };
    h = (h + hue_deg).rem_euclid(360.0);
    let s = (s * sat).clamp(0.0, 1.0);
    let v = (max * val).clamp(0.0, 1.0);
    let cc = v * s;
    let x = cc * (1.0 - ((h / 60.0).rem_euclid(2.0) - 1.0).abs());
    let m = v - cc;
    let (r, g, b) = match (h / 60.0) as u32 {
        0 => (cc, x, 0.0),
        1 => (x, cc, 0.0),
        2 => (0.0, cc, x),
        3 => (0.0, x, cc),
        4 => (x, 0.0, cc),
        _ => (cc, 0.0, x),
    };
    Vec3::new(r + m, g + m, b + m)
}

/// Applies `ops` where `mask` is set.
pub fn apply_ops(maps: &MaterialMaps, mask: &Image<bool>, ops: &EditOps) -> MaterialMaps {
    let mut out = maps.clone();
    for i in 0..mask.data.len() {
        if !mask.data[i] {
            continue;
        }
        let r = ops.roughness.unwrap_or(out.roughness.data[i]) * ops.roughness_scale;
        out.roughness.data[i] = r.clamp(0.0, 1.0);
        let m = ops.metallic.unwrap_or(out.metallic.data[i]) * ops.metallic_scale;
        out.metallic.data[i] = m.clamp(0.0, 1.0);
        let a = out.albedo.data[i];
        let enc = ops.albedo.unwrap_or(Vec3::new(
            linear_to_gamma(a.x),
            linear_to_gamma(a.y),
            linear_to_gamma(a.z),
        ));
        let enc = hsv_shift(
            enc,
            ops.hue_shift_deg,
            ops.saturation_scale,
            ops.value_scale,
        );
        out.albedo.data[i] = Vec3::new(
            gamma_to_linear(enc.x),
            gamma_to_linear(enc.y),
            gamma_to_linear(enc.z),
        );
    }
    out
}

/// Pixels 4-connected to `seed` whose γ-encoded albedo differs from the
/// seed's by at most `tol` in every channel.
pub fn flood_mask(albedo: &RgbImage, seed: (usize, usize), tol: f32) -> Image<bool> {
    let (w, h) = (albedo.width, albedo.height);
    let mut m = Image::new(w, h, false);
    if seed.0 >= w || seed.1 >= h {
        return m;
    }
    let enc = |v: Vec3| {
        Vec3::new(
            linear_to_gamma(v.x),
            linear_to_gamma(v.y),
            linear_to_gamma(v.z),
        )
    };
    let c0 = enc(albedo.get(seed.0, seed.1));
    let mut q = VecDeque::from([seed]);
    m.set(seed.0, seed.1, true);
    while let Some((x, y)) = q.pop_front() {
        let nb = [
            (x.wrapping_sub(1), y),
            (x + 1, y),
            (x, y.wrapping_sub(1)),
            (x, y + 1),
        ];
        for (nx, ny) in nb {
            if nx < w
                && ny < h
                && !m.get(nx, ny)
                && (enc(albedo.get(nx, ny)) - c0).abs().max_element() <= tol
            {
                m.set(nx, ny, true);
                q.push_back((nx, ny));
            }
        }
    }
    m
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hsv_shift_known_answers() {
        let red = Vec3::new(1.0, 0.0, 0.0);
        let g = hsv_shift(red, 120.0, 1.0, 1.0);
        assert!(
            (g - Vec3::new(0.0, 1.0, 0.0)).abs().max_element() < 1e-5,
            "{g}"
        );
        let grey = hsv_shift(Vec3::new(0.8, 0.4, 0.2), 0.0, 0.0, 1.0);
        assert!(
            (grey - Vec3::splat(0.8)).abs().max_element() < 1e-5,
            "{grey}"
        );
        let c = Vec3::new(0.3, 0.6, 0.9);
        assert!((hsv_shift(c, 0.0, 1.0, 1.0) - c).abs().max_element() < 1e-5);
        assert!(
            (hsv_shift(c, 360.0, 1.0, 0.5) - c * 0.5)
                .abs()
                .max_element()
                < 1e-5
        );
    }

    #[test]
    fn flood_fill_stops_at_colour_edges() {
        let img = Image::from_fn(6, 4, |x, _| {
            if x < 3 {
                Vec3::splat(0.2)
            } else {
                Vec3::splat(0.8)
            }
        });
        let m = flood_mask(&img, (0, 0), 0.05);
        assert_eq!(m.data.iter().filter(|&&b| b).count(), 12);
        assert!(m.get(2, 3) && !m.get(3, 0));
    }

    #[test]
    fn ops_touch_only_the_mask_and_apply_in_order() {
        let maps = MaterialMaps::uniform(4, 4, Vec3::splat(0.5), 0.5, 0.2);
        let mask = Image::from_fn(4, 4, |x, y| x == 1 && y == 2);
        let ops = EditOps {
            roughness: Some(0.3),
            roughness_scale: 2.0,
            metallic: None,
            metallic_scale: 10.0,
            albedo: None,
            hue_shift_deg: 0.0,
            saturation_scale: 1.0,
            value_scale: 1.0,
        };
        let out = apply_ops(&maps, &mask, &ops);
        assert!((out.roughness.get(1, 2) - 0.6).abs() < 1e-6);
        assert_eq!(out.metallic.get(1, 2), 1.0);
        assert_eq!(out.roughness.get(0, 0), 0.5);
        assert!(
            (out.albedo.get(1, 2) - Vec3::splat(0.5))
                .abs()
                .max_element()
                < 1e-5
        );
    }
}
