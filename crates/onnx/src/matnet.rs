//! MatNet's contract (`../shared/paper/MATNET.md`, and the reference's
//! `inverse_img_w_mi.py`, `myutils/misc.py`, `Material_net/dpt.py`):
//!
//! - input: centre-crop the photo to a square (offsets rounded down),
//!   keep RGB (drop alpha), resize it to 512² bilinearly with
//!   `align_corners = true`; an 8-bit photo is divided by 255 and raised
//!   to the power 2.2 (a pure power, not the piecewise sRGB curve; an EXR
//!   is already linear and is not), with no mean or std and no clamp; then
//!   resize to the model's input bicubically (the reference uses OpenCV's
//!   `INTER_CUBIC`, PyTorch's kernel here: A = −0.75, half-pixel centres,
//!   indices clamped at the borders, no antialiasing); 512 → 518 = 37·14.
//! - output (the official network): depth [1, 1] (ReLU; raw, larger is
//!   nearer as the reference meshes it: z = 2·max − d), albedo [1, 3],
//!   roughness [1, 1], metallic [1, 1] (ReLU, unbounded), normal [1, 3]
//!   (tanh then L2-normalised), each resized back to 512² bilinearly with
//!   `align_corners = true`; the reference then clamps albedo to [0, 1],
//!   roughness to [0.07, 1], metallic to [0, 1] in memory but writes the
//!   unclamped values (albedo and normals as linear EXR, roughness and
//!   metallic as sRGB-encoded 8-bit PNG, depth as EXR).
//!
//! Images here are planar f32, channel-major ([C, H, W]), as the networks
//! take them.

/// A planar image: `c` channels of `h`×`w`, channel-major.
#[derive(Clone, Debug, PartialEq)]
pub struct Planar {
    pub c: usize,
    pub h: usize,
    pub w: usize,
    pub data: Vec<f32>,
}

impl Planar {
    pub fn new(c: usize, h: usize, w: usize) -> Planar {
        Planar {
            c,
            h,
            w,
            data: vec![0.0; c * h * w],
        }
    }
    #[inline]
    pub fn at(&self, ch: usize, y: usize, x: usize) -> f32 {
        self.data[(ch * self.h + y) * self.w + x]
    }
    #[inline]
    fn set(&mut self, ch: usize, y: usize, x: usize, v: f32) {
        self.data[(ch * self.h + y) * self.w + x] = v;
    }
    /// The interleaved 8-bit photo (`h`×`w`×`c`, row-major) as planar
    /// values 0–255.
    pub fn from_interleaved_u8(h: usize, w: usize, c: usize, px: &[u8]) -> Planar {
        let mut p = Planar::new(c, h, w);
        for y in 0..h {
            for x in 0..w {
                for ch in 0..c {
                    p.set(ch, y, x, px[(y * w + x) * c + ch] as f32);
                }
            }
        }
        p
    }
}

/// The centred square of side min(h, w) (offsets rounded down).
pub fn centre_square(p: &Planar) -> Planar {
    let s = p.h.min(p.w);
    let (y0, x0) = ((p.h - s) / 2, (p.w - s) / 2);
    let mut out = Planar::new(p.c, s, s);
    for ch in 0..p.c {
        for y in 0..s {
            for x in 0..s {
                out.set(ch, y, x, p.at(ch, y0 + y, x0 + x));
            }
        }
    }
    out
}

/// Source coordinate of output index `i` (PyTorch's
/// `area_pixel_compute_source_index` for the cubic and linear modes).
fn source(i: usize, in_len: usize, out_len: usize, align_corners: bool) -> f64 {
    if align_corners {
        if out_len > 1 {
            i as f64 * (in_len - 1) as f64 / (out_len - 1) as f64
        } else {
            0.0
        }
    } else {
        (i as f64 + 0.5) * in_len as f64 / out_len as f64 - 0.5
    }
}

/// Bilinear resize (PyTorch's `interpolate(mode="bilinear")`).
pub fn resize_bilinear(p: &Planar, h: usize, w: usize, align_corners: bool) -> Planar {
    let mut out = Planar::new(p.c, h, w);
    let axis = |i: usize, n_in: usize, n_out: usize| -> (usize, usize, f32) {
        // Non-aligned sources below 0 clamp to 0, as PyTorch does.
        let s = source(i, n_in, n_out, align_corners).max(0.0);
        let i0 = (s.floor() as usize).min(n_in - 1);
        let i1 = (i0 + 1).min(n_in - 1);
        (i0, i1, (s - i0 as f64) as f32)
    };
    for y in 0..h {
        let (y0, y1, fy) = axis(y, p.h, h);
        for x in 0..w {
            let (x0, x1, fx) = axis(x, p.w, w);
            for ch in 0..p.c {
                let a = p.at(ch, y0, x0) * (1.0 - fx) + p.at(ch, y0, x1) * fx;
                let b = p.at(ch, y1, x0) * (1.0 - fx) + p.at(ch, y1, x1) * fx;
                out.set(ch, y, x, a * (1.0 - fy) + b * fy);
            }
        }
    }
    out
}

/// The cubic convolution weights of offset `t` ∈ [0, 1) (A = −0.75).
fn cubic_weights(t: f32) -> [f32; 4] {
    const A: f32 = -0.75;
    let near = |x: f32| ((A + 2.0) * x - (A + 3.0)) * x * x + 1.0;
    let far = |x: f32| ((A * x - 5.0 * A) * x + 8.0 * A) * x - 4.0 * A;
    [far(t + 1.0), near(t), near(1.0 - t), far(2.0 - t)]
}

/// Bicubic resize (PyTorch's `interpolate(mode="bicubic")`, no
/// antialiasing): taps at indices clamped to the image.
pub fn resize_bicubic(p: &Planar, h: usize, w: usize, align_corners: bool) -> Planar {
    let mut out = Planar::new(p.c, h, w);
    let taps = |i: usize, n_in: usize, n_out: usize| -> ([usize; 4], [f32; 4]) {
        let s = source(i, n_in, n_out, align_corners);
        let f = s.floor();
        let t = (s - f) as f32;
        let base = f as i64;
        let idx = std::array::from_fn(|k| (base - 1 + k as i64).clamp(0, n_in as i64 - 1) as usize);
        (idx, cubic_weights(t))
    };
    let cols: Vec<_> = (0..w).map(|x| taps(x, p.w, w)).collect();
    for y in 0..h {
        let (ys, wy) = taps(y, p.h, h);
        for (x, (xs, wx)) in cols.iter().enumerate() {
            for ch in 0..p.c {
                let mut v = 0.0f32;
                for (a, &yy) in ys.iter().enumerate() {
                    let mut row = 0.0f32;
                    for (b, &xx) in xs.iter().enumerate() {
                        row += p.at(ch, yy, xx) * wx[b];
                    }
                    v += row * wy[a];
                }
                out.set(ch, y, x, v);
            }
        }
    }
    out
}

/// Values 0–255 to linear: /255, then ^2.2 (negative overshoot clamped
/// to 0 first).
pub fn linearise(p: &Planar) -> Planar {
    Planar {
        data: p
            .data
            .iter()
            .map(|&v| (v / 255.0).max(0.0).powf(2.2))
            .collect(),
        ..p.clone()
    }
}

/// The whole chain for an 8-bit photo: square, 512² bilinear
/// (align_corners), linear, then `input`² bicubic.
pub fn preprocess(photo: &Planar, square: usize, input: usize) -> Planar {
    let sq = resize_bilinear(&centre_square(photo), square, square, true);
    resize_bicubic(&linearise(&sq), input, input, false)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    fn fixture(name: &str) -> matflow_scene::npy::Array {
        let p = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../tests/data")
            .join(format!("matnet_pre_{name}.npy"));
        matflow_scene::npy::decode(&std::fs::read(p).unwrap()).unwrap()
    }

    fn close(got: &Planar, want: &matflow_scene::npy::Array, tol: f32) {
        assert_eq!(want.shape, vec![got.c, got.h, got.w]);
        let worst = got
            .data
            .iter()
            .zip(&want.values)
            .map(|(a, b)| (a - b).abs() / b.abs().max(1.0))
            .fold(0.0f32, f32::max);
        assert!(worst <= tol, "off by {worst} (relative)");
    }

    /// Against PyTorch's `interpolate` on the same photo
    /// (`train/matnet/preprocess_fixture.py` wrote the answers).
    #[test]
    fn each_step_matches_pytorch() {
        let photo = fixture("photo");
        assert_eq!(photo.shape, vec![9, 13, 3]);
        let px: Vec<u8> = photo.values.iter().map(|&v| v as u8).collect();
        let p = Planar::from_interleaved_u8(9, 13, 3, &px);
        let sq = centre_square(&p);
        assert_eq!((sq.h, sq.w), (9, 9));
        let bil = resize_bilinear(&sq, 12, 12, true);
        close(&bil, &fixture("bilinear"), 1e-5);
        let lin = linearise(&bil);
        close(&lin, &fixture("linear"), 1e-5);
        close(
            &resize_bicubic(&lin, 7, 7, false),
            &fixture("bicubic_down"),
            1e-5,
        );
        close(
            &resize_bicubic(&lin, 17, 17, false),
            &fixture("bicubic_up"),
            1e-5,
        );
    }

    #[test]
    fn hand_computed_cases() {
        // Aligned corners keep the corner values; the middle of 2 → 3 is
        // the mean.
        let p = Planar {
            c: 1,
            h: 1,
            w: 2,
            data: vec![0.0, 10.0],
        };
        let r = resize_bilinear(&p, 1, 3, true);
        assert_eq!(r.data, vec![0.0, 5.0, 10.0]);
        // Cubic weights sum to one and interpolate at t = 0.
        for t in [0.0f32, 0.25, 0.5, 0.9] {
            let w = cubic_weights(t);
            assert!((w.iter().sum::<f32>() - 1.0).abs() < 1e-6);
        }
        assert_eq!(cubic_weights(0.0), [0.0, 1.0, 0.0, 0.0]);
        // A constant image stays constant through every step.
        let c = Planar {
            c: 3,
            h: 5,
            w: 8,
            data: vec![128.0; 120],
        };
        let out = preprocess(&c, 16, 11);
        let want = (128.0f32 / 255.0).powf(2.2);
        assert!(out.data.iter().all(|v| (v - want).abs() < 1e-6));
        assert_eq!((out.c, out.h, out.w), (3, 11, 11));
    }
}
