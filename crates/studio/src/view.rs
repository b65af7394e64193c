//! What the page shows: the scene's maps, the renders and the selection,
//! as PNGs (EXR for the result's download).

use std::path::Path;

use matflow_nodes::SceneData;
use matflow_scene::{GrayImage, Image, RgbImage};

/// A session's images: the photo and the scene's maps, each as a PNG.
#[derive(Default)]
pub struct Maps {
    pub images: Vec<(&'static str, Vec<u8>)>,
    pub width: usize,
    pub height: usize,
}

/// The names of the images a session shows, in the page's order.
pub const MAP_NAMES: [&str; 6] = [
    "photo",
    "albedo",
    "roughness",
    "metallic",
    "normal",
    "depth",
];

/// A linear render as the page shows it: a PNG, γ 2.2, 8 bits, as
/// `render` writes beside its `output`.
pub fn png(img: &RgbImage) -> Vec<u8> {
    matflow_scene::io::encode_png_gamma(Path::new("result.png"), img).unwrap_or_default()
}

/// A linear render as `render` writes its `output` EXR, so that a
/// download is the file `matflow run` writes.
pub fn exr(img: &RgbImage) -> Vec<u8> {
    matflow_scene::io::encode_exr_rgb(Path::new("result.exr"), img).unwrap_or_default()
}

/// The selection as an RGBA PNG: a translucent tint where it is set,
/// clear elsewhere (drawn over the image).
pub fn overlay(mask: &Image<bool>) -> Vec<u8> {
    let mut out = image::RgbaImage::new(mask.width as u32, mask.height as u32);
    for (o, &m) in out.pixels_mut().zip(mask.data.iter()) {
        *o = if m {
            image::Rgba([40, 160, 255, 110])
        } else {
            image::Rgba([0, 0, 0, 0])
        };
    }
    let mut buf = std::io::Cursor::new(Vec::new());
    let _ = out.write_to(&mut buf, image::ImageFormat::Png);
    buf.into_inner()
}

/// The scene's images for display: the photo and albedo γ-encoded,
/// roughness and metallic as their values, normals as (n + 1) / 2, depth
/// as nearness (the nearest surface white, the sky black).
pub fn maps(s: &SceneData) -> Maps {
    let (w, h) = (s.depth.width, s.depth.height);
    let gamma = |img: &RgbImage| {
        matflow_scene::io::encode_png_gamma(Path::new("image"), img).unwrap_or_default()
    };
    let mut images = Vec::new();
    if let Some(photo) = &s.target {
        images.push(("photo", gamma(photo)));
    }
    images.push(("albedo", gamma(&s.pred.albedo)));
    images.push(("roughness", values(&s.pred.roughness.to_rgb())));
    images.push(("metallic", values(&s.pred.metallic.to_rgb())));
    if let Some(n) = &s.pred.normal {
        let shown = RgbImage::from_vec(
            n.width,
            n.height,
            n.data.iter().map(|v| (*v + 1.0) * 0.5).collect(),
        );
        images.push(("normal", values(&shown)));
    }
    images.push(("depth", values(&nearness(&s.depth).to_rgb())));
    Maps {
        images,
        width: w,
        height: h,
    }
}

/// Depth as nearness in [0, 1]: the nearest surface 1, the farthest a
/// tenth, the sky (z ≤ 0 or not finite) 0.
fn nearness(depth: &GrayImage) -> GrayImage {
    let seen = |z: f32| z.is_finite() && z > 0.0;
    let (lo, hi) = depth
        .data
        .iter()
        .copied()
        .filter(|&z| seen(z))
        .fold((f32::INFINITY, 0.0f32), |(lo, hi), z| {
            (lo.min(z), hi.max(z))
        });
    let data = depth
        .data
        .iter()
        .map(|&z| {
            if !seen(z) || hi <= 0.0 {
                0.0
            } else if hi - lo <= f32::EPSILON {
                1.0
            } else {
                1.0 - 0.9 * (z - lo) / (hi - lo)
            }
        })
        .collect();
    GrayImage::from_vec(depth.width, depth.height, data)
}

/// Values in [0, 1] (clipped; NaN as 0) as an 8-bit PNG, no curve.
fn values(img: &RgbImage) -> Vec<u8> {
    let to8 = |c: f32| {
        if c.is_finite() {
            (c.clamp(0.0, 1.0) * 255.0).round() as u8
        } else {
            0
        }
    };
    let mut out = image::RgbImage::new(img.width as u32, img.height as u32);
    for (o, v) in out.pixels_mut().zip(img.data.iter()) {
        *o = image::Rgb([to8(v.x), to8(v.y), to8(v.z)]);
    }
    let mut buf = std::io::Cursor::new(Vec::new());
    let _ = out.write_to(&mut buf, image::ImageFormat::Png);
    buf.into_inner()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn depth_shows_near_as_bright_and_sky_as_black() {
        let d = GrayImage::from_vec(4, 1, vec![1.0, 3.0, 0.0, f32::NAN]);
        let n = nearness(&d);
        assert_eq!(n.data[0], 1.0);
        assert!((n.data[1] - 0.1).abs() < 1e-6);
        assert_eq!(n.data[2], 0.0);
        assert_eq!(n.data[3], 0.0);
    }

    #[test]
    fn the_selection_shows_as_a_tint_where_set_and_clear_elsewhere() {
        let m = Image::from_fn(3, 2, |x, _| x == 1);
        let png = overlay(&m);
        let img = image::load_from_memory(&png).unwrap().to_rgba8();
        assert_eq!(img.dimensions(), (3, 2));
        assert_eq!(img.get_pixel(0, 0)[3], 0);
        assert!(img.get_pixel(1, 1)[3] > 0);
    }
}
