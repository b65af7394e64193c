//! Regions of the photo made transparent (the paper's §3.3, eqs. 22–23),
//! as a layer of the screen-space materials, and the classical image
//! operations that build it: harmonic inpainting of the background behind
//! a region, the distance to a region's boundary and the thickness rule.
//!
//! A pixel is glass when its `ior` is positive. Its glass has index of
//! refraction `ior`, specular transmission `transmission`, roughness and
//! tint, and the refraction distances `d1` (front surface to the back,
//! inside the object) and `d2` (back surface to the background), in scene
//! units. The background behind a region — what shows through it — has its
//! own materials (`bg_*`): inpainted inside the regions, the ordinary ones
//! outside (see `render`'s integrator for how a path uses them).

use glam::Vec3;

use crate::image::{GrayImage, Image, RgbImage};

#[derive(Clone, Debug, PartialEq)]
pub struct Transparency {
    /// Index of refraction inside the regions, 0 elsewhere (opaque).
    pub ior: GrayImage,
    pub transmission: GrayImage,
    pub roughness: GrayImage,
    pub tint: RgbImage,
    /// Refraction distances (scene units).
    pub d1: GrayImage,
    pub d2: GrayImage,
    /// The background's materials.
    pub bg_albedo: RgbImage,
    pub bg_roughness: GrayImage,
    pub bg_metallic: GrayImage,
}

impl Transparency {
    /// No transparent region; the background is `albedo`, `roughness`,
    /// `metallic` as they are.
    pub fn none(albedo: &RgbImage, roughness: &GrayImage, metallic: &GrayImage) -> Transparency {
        let (w, h) = (albedo.width, albedo.height);
        Transparency {
            ior: GrayImage::new(w, h, 0.0),
            transmission: GrayImage::new(w, h, 0.0),
            roughness: GrayImage::new(w, h, 0.0),
            tint: RgbImage::new(w, h, Vec3::ONE),
            d1: GrayImage::new(w, h, 0.0),
            d2: GrayImage::new(w, h, 0.0),
            bg_albedo: albedo.clone(),
            bg_roughness: roughness.clone(),
            bg_metallic: metallic.clone(),
        }
    }

    /// Whether pixel `k` (row-major) is glass.
    #[inline]
    pub fn is_glass(&self, k: usize) -> bool {
        self.ior.data[k] > 0.0
    }

    /// Whether the glass parameters of pixel `k` differ from `other`'s.
    pub fn glass_differs(&self, other: &Transparency, k: usize) -> bool {
        self.ior.data[k] != other.ior.data[k]
            || self.transmission.data[k] != other.transmission.data[k]
            || self.roughness.data[k] != other.roughness.data[k]
            || self.tint.data[k] != other.tint.data[k]
            || self.d1.data[k] != other.d1.data[k]
            || self.d2.data[k] != other.d2.data[k]
    }

    /// Whether the background's material at pixel `k` differs.
    pub fn background_differs(&self, other: &Transparency, k: usize) -> bool {
        self.bg_albedo.data[k] != other.bg_albedo.data[k]
            || self.bg_roughness.data[k] != other.bg_roughness.data[k]
            || self.bg_metallic.data[k] != other.bg_metallic.data[k]
    }

    /// All maps have the size `w`×`h`.
    pub fn has_size(&self, w: usize, h: usize) -> bool {
        let g = |i: &GrayImage| i.width == w && i.height == h;
        let c = |i: &RgbImage| i.width == w && i.height == h;
        g(&self.ior)
            && g(&self.transmission)
            && g(&self.roughness)
            && c(&self.tint)
            && g(&self.d1)
            && g(&self.d2)
            && c(&self.bg_albedo)
            && g(&self.bg_roughness)
            && g(&self.bg_metallic)
    }
}

/// Harmonic (membrane) inpainting: the values inside `mask` replaced by the
/// solution of Laplace's equation Δu = 0 there, with the values outside as
/// boundary conditions (4-neighbour stencil; the image border is a mirror,
/// i.e. zero normal derivative). Smooth, and exact for anything linear
/// across the hole. Solved per channel by red-black successive
/// over-relaxation, started from the solution on a grid half the size
/// (recursively; the coarsest from the mean of the boundary), to a change
/// below 10⁻⁵ or 10 000 sweeps, in a fixed order (deterministic). With nothing known
/// (the mask covers the image) the image is returned as it is.
pub fn inpaint_harmonic_gray(img: &GrayImage, mask: &Image<bool>) -> GrayImage {
    let mut out = img.clone();
    inpaint_channel(&mut out.data, img.width, img.height, &mask.data);
    out
}

/// [`inpaint_harmonic_gray`] for colour, channel by channel.
pub fn inpaint_harmonic_rgb(img: &RgbImage, mask: &Image<bool>) -> RgbImage {
    let (w, h) = (img.width, img.height);
    let mut ch: Vec<Vec<f32>> = (0..3)
        .map(|c| img.data.iter().map(|v| v[c]).collect())
        .collect();
    {
        use rayon::prelude::*;
        ch.par_iter_mut()
            .for_each(|c| inpaint_channel(c, w, h, &mask.data));
    }
    Image::from_vec(
        w,
        h,
        (0..w * h)
            .map(|k| Vec3::new(ch[0][k], ch[1][k], ch[2][k]))
            .collect(),
    )
}

fn inpaint_channel(u: &mut [f32], w: usize, h: usize, unknown: &[bool]) {
    let n_unknown = unknown.iter().filter(|&&m| m).count();
    if n_unknown == 0 || n_unknown == w * h {
        return;
    }
    // Start from the solution on a grid half the size (recursively), so
    // relaxation only has to remove fine-scale error.
    if w >= 16 && h >= 16 && n_unknown >= 64 {
        let (w2, h2) = (w.div_ceil(2), h.div_ceil(2));
        let mut cu = vec![0.0f32; w2 * h2];
        let mut ck = vec![true; w2 * h2];
        for y2 in 0..h2 {
            for x2 in 0..w2 {
                let (mut sum, mut cnt) = (0.0f64, 0u32);
                for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                    let (x, y) = (2 * x2 + dx, 2 * y2 + dy);
                    if x < w && y < h && !unknown[y * w + x] {
                        sum += u[y * w + x] as f64;
                        cnt += 1;
                    }
                }
                if cnt > 0 {
                    cu[y2 * w2 + x2] = (sum / cnt as f64) as f32;
                    ck[y2 * w2 + x2] = false;
                }
            }
        }
        inpaint_channel(&mut cu, w2, h2, &ck);
        for y in 0..h {
            for x in 0..w {
                if unknown[y * w + x] {
                    u[y * w + x] = cu[(y / 2) * w2 + x / 2];
                }
            }
        }
    } else {
        // The mean of the known pixels bordering the hole.
        let (mut sum, mut cnt) = (0.0f64, 0usize);
        for y in 0..h {
            for x in 0..w {
                let k = y * w + x;
                if unknown[k] {
                    continue;
                }
                let touches = (x > 0 && unknown[k - 1])
                    || (x + 1 < w && unknown[k + 1])
                    || (y > 0 && unknown[k - w])
                    || (y + 1 < h && unknown[k + w]);
                if touches {
                    sum += u[k] as f64;
                    cnt += 1;
                }
            }
        }
        let start = if cnt > 0 {
            (sum / cnt as f64) as f32
        } else {
            0.0
        };
        for k in 0..w * h {
            if unknown[k] {
                u[k] = start;
            }
        }
    }
    relax(u, w, h, unknown);
}

/// Red-black over-relaxation of Laplace's equation on the unknown pixels.
fn relax(u: &mut [f32], w: usize, h: usize, unknown: &[bool]) {
    let cells: Vec<usize> = (0..w * h).filter(|&k| unknown[k]).collect();
    // Over-relaxation factor for the hole's extent.
    let (mut x0, mut x1, mut y0, mut y1) = (w, 0, h, 0);
    for &k in &cells {
        let (x, y) = (k % w, k / w);
        x0 = x0.min(x);
        x1 = x1.max(x);
        y0 = y0.min(y);
        y1 = y1.max(y);
    }
    let extent = ((x1 - x0).max(y1 - y0) + 2) as f64;
    let omega = (2.0 / (1.0 + (std::f64::consts::PI / extent).sin())) as f32;
    let (red, black): (Vec<usize>, Vec<usize>) = cells
        .iter()
        .partition(|&&k| (k % w + k / w).is_multiple_of(2));
    let at = |u: &[f32], x: usize, y: usize, dx: isize, dy: isize| -> f32 {
        // Mirror at the border: the missing neighbour is the pixel itself.
        let nx = x as isize + dx;
        let ny = y as isize + dy;
        if nx < 0 || ny < 0 || nx >= w as isize || ny >= h as isize {
            u[y * w + x]
        } else {
            u[ny as usize * w + nx as usize]
        }
    };
    for _sweep in 0..10_000 {
        let mut change = 0.0f32;
        for set in [&red, &black] {
            for &k in set.iter() {
                let (x, y) = (k % w, k / w);
                let avg = 0.25
                    * (at(u, x, y, -1, 0)
                        + at(u, x, y, 1, 0)
                        + at(u, x, y, 0, -1)
                        + at(u, x, y, 0, 1));
                let d = omega * (avg - u[k]);
                u[k] += d;
                change = change.max(d.abs());
            }
        }
        if change < 1e-5 {
            break;
        }
    }
}

/// Per pixel of `mask`, the Euclidean distance (pixels, between centres)
/// to the nearest pixel outside it, or to the image border where the mask
/// reaches it (the region is taken to end half a pixel beyond); 0 outside.
/// Exact (Felzenszwalb–Huttenlocher's separable transform).
pub fn distance_to_boundary(mask: &Image<bool>) -> Vec<f32> {
    let (w, h) = (mask.width, mask.height);
    const INF: f64 = 1e20;
    // Squared distances to the nearest outside pixel, with a frame of
    // outside pixels around the image.
    let (fw, fh) = (w + 2, h + 2);
    let mut f = vec![INF; fw * fh];
    for y in 0..fh {
        for x in 0..fw {
            let inside = x > 0 && y > 0 && x <= w && y <= h && mask.data[(y - 1) * w + (x - 1)];
            if !inside {
                f[y * fw + x] = 0.0;
            }
        }
    }
    let mut buf = vec![0.0f64; fw.max(fh)];
    let mut out = vec![0.0f64; fw.max(fh)];
    for x in 0..fw {
        for y in 0..fh {
            buf[y] = f[y * fw + x];
        }
        dt1(&buf[..fh], &mut out[..fh]);
        for y in 0..fh {
            f[y * fw + x] = out[y];
        }
    }
    for y in 0..fh {
        buf[..fw].copy_from_slice(&f[y * fw..(y + 1) * fw]);
        dt1(&buf[..fw], &mut out[..fw]);
        f[y * fw..(y + 1) * fw].copy_from_slice(&out[..fw]);
    }
    (0..w * h)
        .map(|k| {
            let (x, y) = (k % w + 1, k / w + 1);
            if mask.data[k] {
                // Distance to the region's edge: half a pixel short of the
                // nearest outside pixel's centre.
                (f[y * fw + x].sqrt() - 0.5).max(0.5) as f32
            } else {
                0.0
            }
        })
        .collect()
}

/// One-dimensional squared-distance transform (lower envelope of
/// parabolas).
fn dt1(f: &[f64], d: &mut [f64]) {
    let n = f.len();
    let mut v = vec![0usize; n];
    let mut z = vec![0.0f64; n + 1];
    let mut k = 0usize;
    z[0] = f64::NEG_INFINITY;
    z[1] = f64::INFINITY;
    let sect = |q: usize, p: usize| {
        ((f[q] + (q * q) as f64) - (f[p] + (p * p) as f64)) / (2.0 * (q as f64 - p as f64))
    };
    for q in 1..n {
        let mut s = sect(q, v[k]);
        // z[0] is −∞, so this stops at k = 0 at the latest.
        while s <= z[k] {
            k -= 1;
            s = sect(q, v[k]);
        }
        k += 1;
        v[k] = q;
        z[k] = s;
        z[k + 1] = f64::INFINITY;
    }
    let mut k = 0usize;
    for q in 0..n {
        while z[k + 1] < q as f64 {
            k += 1;
        }
        let p = v[k];
        d[q] = (q as f64 - p as f64).powi(2) + f[p];
    }
}

/// The thickness rule for a region seen at camera depth `z` (per pixel)
/// with focal length `focal` (pixels): the region is taken to be a round
/// object whose silhouette is the mask, so at a pixel b pixels inside its
/// edge, with the region's inradius R, the chord through it is
/// 2·√(R² − (R − b)²) pixels, converted to scene units at the pixel's depth
/// (z / focal per pixel) and multiplied by `scale`. Exact for a sphere
/// seen head-on; thin at the rim, thickest in the middle.
pub fn thickness_rule(mask: &Image<bool>, z: &GrayImage, focal: f32, scale: f32) -> GrayImage {
    let b = distance_to_boundary(mask);
    let r = b.iter().copied().fold(0.0f32, f32::max);
    Image::from_vec(
        mask.width,
        mask.height,
        b.iter()
            .zip(&z.data)
            .map(|(&b, &z)| {
                if b <= 0.0 || !(focal > 0.0) {
                    return 0.0;
                }
                let chord = 2.0 * (r * r - (r - b) * (r - b)).max(0.0).sqrt();
                let t = chord * z.max(0.0) / focal * scale;
                if t.is_finite() {
                    t
                } else {
                    0.0
                }
            })
            .collect(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn disk(n: usize, c: (f32, f32), r: f32) -> Image<bool> {
        Image::from_fn(n, n, |x, y| {
            let (dx, dy) = (x as f32 - c.0, y as f32 - c.1);
            dx * dx + dy * dy <= r * r
        })
    }

    #[test]
    fn harmonic_inpainting_reproduces_linear_fields_and_keeps_the_known_pixels() {
        let n = 40;
        let f = |x: usize, y: usize| 0.3 + 0.01 * x as f32 - 0.02 * y as f32;
        let img = GrayImage::from_fn(n, n, f);
        let mask = disk(n, (20.0, 18.0), 9.0);
        let mut holed = img.clone();
        for (k, &m) in mask.data.iter().enumerate() {
            if m {
                holed.data[k] = 5.0; // garbage in the hole
            }
        }
        let out = inpaint_harmonic_gray(&holed, &mask);
        for k in 0..n * n {
            if mask.data[k] {
                assert!((out.data[k] - img.data[k]).abs() < 1e-4, "pixel {k}");
            } else {
                assert_eq!(out.data[k], img.data[k]);
            }
        }
        // A hole touching the border (mirror there) and colour.
        let mask = Image::from_fn(n, n, |x, y| x < 10 && (10..30).contains(&y));
        let rgb = RgbImage::from_fn(n, n, |x, _| Vec3::new(0.5, 0.1 * (x % 2) as f32, 1.0));
        let out = inpaint_harmonic_rgb(&rgb, &mask);
        for (k, v) in out.data.iter().enumerate() {
            assert!(v.is_finite());
            if mask.data[k] {
                assert!((v.x - 0.5).abs() < 1e-5 && (v.z - 1.0).abs() < 1e-5);
                assert!((0.0..=0.1).contains(&v.y));
            }
        }
        // Everything unknown: nothing to go on, unchanged.
        let all = Image::from_fn(4, 4, |_, _| true);
        let g = GrayImage::from_fn(4, 4, |x, _| x as f32);
        assert_eq!(inpaint_harmonic_gray(&g, &all), g);
    }

    #[test]
    fn distances_to_the_boundary_are_euclidean() {
        let n = 41;
        let mask = disk(n, (20.0, 20.0), 12.0);
        let d = distance_to_boundary(&mask);
        // Brute force.
        for y in 0..n {
            for x in 0..n {
                let k = y * n + x;
                if !mask.data[k] {
                    assert_eq!(d[k], 0.0);
                    continue;
                }
                let mut best = f32::INFINITY;
                for yy in -1..=n as i64 {
                    for xx in -1..=n as i64 {
                        let outside = xx < 0
                            || yy < 0
                            || xx >= n as i64
                            || yy >= n as i64
                            || !mask.data[yy as usize * n + xx as usize];
                        if outside {
                            let dd = ((xx - x as i64).pow(2) + (yy - y as i64).pow(2)) as f32;
                            best = best.min(dd.sqrt());
                        }
                    }
                }
                assert!(
                    (d[k] - (best - 0.5).max(0.5)).abs() < 1e-4,
                    "({x},{y}) {} {best}",
                    d[k]
                );
            }
        }
    }

    #[test]
    fn the_thickness_rule_is_a_spheres_chord() {
        let n = 61;
        let r = 20.0;
        let mask = disk(n, (30.0, 30.0), r);
        let z = GrayImage::new(n, n, 4.0);
        let focal = 100.0;
        let t = thickness_rule(&mask, &z, focal, 1.0);
        // Centre: the diameter, in scene units at depth 4.
        let centre = t.get(30, 30);
        let want = 2.0 * (r - 0.5 + 0.5) * 4.0 / focal;
        assert!((centre - want).abs() < 0.1 * want, "{centre} {want}");
        // Thinner towards the rim, zero outside, finite everywhere.
        assert!(t.get(30, 12) < t.get(30, 20) && t.get(30, 20) < centre);
        assert_eq!(t.get(0, 0), 0.0);
        assert!(t.data.iter().all(|v| v.is_finite() && *v >= 0.0));
    }
}
