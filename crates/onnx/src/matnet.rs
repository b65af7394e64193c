//! MatNet's contract (`../shared/paper/MATNET.md`, and the reference's
//! `inverse_img_w_mi.py`, `myutils/misc.py`, `Material_net/dpt.py`):
//!
//! - input: centre-crop the photo to a square (offsets rounded down),
//!   keep RGB (drop alpha), resize it to 512² bilinearly with
//!   `align_corners = true`; an 8-bit photo is divided by 255 and raised
//!   to the power 2.2 (a pure power, not the piecewise sRGB curve; an EXR
//!   is already linear and is not), with no mean or std and no clamp; then
//!   resize to the model's input bicubically (A = −0.75, half-pixel
//!   centres, indices clamped at the borders, no antialiasing); 512 → 518
//!   = 37·14. The reference does this with OpenCV's `INTER_CUBIC`, which
//!   is the same kernel as PyTorch's: on the reference photos the two
//!   differ by at most 1.7e-5 (0.004 of an 8-bit step; see
//!   `docs/official-matnet.md`), and the tests hold this resize to both.
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
    network_input(&linearise(&sq), input)
}

/// The square side the photo is resized to first, and every output
/// resized back to.
pub const SQUARE: usize = 512;
/// The input side for a model whose spatial input axes are dynamic:
/// MatNet's (37 patches of 14).
pub const DYNAMIC_INPUT: usize = 518;
/// The smallest input side matflow accepts from a model.
pub const MIN_INPUT: usize = 16;

/// How a photo's values become the network's.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Encoding {
    /// Display-encoded, 0–255 (8-bit; 16-bit values are divided by 257):
    /// /255, then ^2.2 after the square resize.
    Display,
    /// Linear radiance (EXR): used as it is.
    Linear,
}

/// The centred square of an `h`×`w` photo, resized to `side`² bilinearly
/// with aligned corners — [`centre_square`] then [`resize_bilinear`],
/// reading the photo through `at(channel, y, x)` so that a large photo is
/// never copied whole.
pub fn square_of(
    h: usize,
    w: usize,
    at: impl Fn(usize, usize, usize) -> f32,
    side: usize,
) -> Planar {
    let s = h.min(w);
    let (y0, x0) = ((h - s) / 2, (w - s) / 2);
    let mut out = Planar::new(3, side, side);
    let axis = |i: usize| -> (usize, usize, f32) {
        let src = source(i, s, side, true).max(0.0);
        let i0 = (src.floor() as usize).min(s - 1);
        let i1 = (i0 + 1).min(s - 1);
        (i0, i1, (src - i0 as f64) as f32)
    };
    let cols: Vec<_> = (0..side).map(axis).collect();
    for y in 0..side {
        let (ya, yb, fy) = axis(y);
        for (x, &(xa, xb, fx)) in cols.iter().enumerate() {
            for ch in 0..3 {
                let a = at(ch, y0 + ya, x0 + xa) * (1.0 - fx) + at(ch, y0 + ya, x0 + xb) * fx;
                let b = at(ch, y0 + yb, x0 + xa) * (1.0 - fx) + at(ch, y0 + yb, x0 + xb) * fx;
                out.set(ch, y, x, a * (1.0 - fy) + b * fy);
            }
        }
    }
    out
}

/// The square in linear values: linearised when display-encoded.
pub fn linear(square: Planar, enc: Encoding) -> Planar {
    match enc {
        Encoding::Display => linearise(&square),
        Encoding::Linear => square,
    }
}

/// The network's input from the linear square: resized bicubically to
/// `input`² (as it is when already that size).
pub fn network_input(lin: &Planar, input: usize) -> Planar {
    if input == lin.h && input == lin.w {
        lin.clone()
    } else {
        resize_bicubic(lin, input, input, false)
    }
}

/// What a model's depth output means.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DepthKind {
    /// MatNet's: disparity-like, larger is nearer (z = 2·max − d).
    Disparity,
    /// Camera-space z (metadata `matflow.depth = z`).
    Z,
}

/// Where the five maps are among a model's outputs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Layout {
    /// Outputs named `depth` (1), `albedo` (3), `roughness` (1),
    /// `metallic` (1), `normal` (3): the official network's dict.
    Named {
        depth: usize,
        albedo: usize,
        roughness: usize,
        metallic: usize,
        normal: usize,
    },
    /// The two heads: `depth` (1) and `material` (8: albedo 0–2,
    /// roughness 3, metallic 4, normal 5–7).
    Heads { depth: usize, material: usize },
}

/// A model's reading of the contract: input side, output layout, depth
/// meaning.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Contract {
    pub input: usize,
    pub layout: Layout,
    pub depth: DepthKind,
}

const EXPECTED_OUTPUTS: &str = "outputs named depth [N, 1, h, w], albedo [N, 3, h, w], \
    roughness [N, 1, h, w], metallic [N, 1, h, w] and normal [N, 3, h, w] (or depth and an \
    8-channel material)";

fn describe_ports(ports: &[crate::Port]) -> String {
    if ports.is_empty() {
        return "none".into();
    }
    ports
        .iter()
        .map(|p| p.describe())
        .collect::<Vec<_>>()
        .join(", ")
}

impl Contract {
    /// Reads the contract off a model's ports and metadata; a model that
    /// does not honour it is an error saying what was expected and what
    /// the model has.
    pub fn of(
        inputs: &[crate::Port],
        outputs: &[crate::Port],
        meta: &std::collections::BTreeMap<String, String>,
    ) -> Result<Contract, String> {
        let bad_input = |why: &str| {
            format!(
                "expected one input f32 [1 or N, 3, S, S] ({why}); the model has {}",
                describe_ports(inputs)
            )
        };
        if inputs.len() != 1 {
            return Err(bad_input(&format!("{} inputs", inputs.len())));
        }
        let i = &inputs[0];
        if !i.f32 || i.shape.len() != 4 {
            return Err(bad_input("element type or rank"));
        }
        if i.shape[0] > 1 {
            return Err(bad_input("a batch of one"));
        }
        if i.shape[1] != 3 && i.shape[1] >= 0 {
            return Err(bad_input("3 channels"));
        }
        let input = match (i.shape[2], i.shape[3]) {
            (a, b) if a < 0 && b < 0 => match meta.get("matflow.input_size") {
                Some(v) => v
                    .trim()
                    .parse::<usize>()
                    .map_err(|_| format!("metadata matflow.input_size = {v:?} is not a size"))?,
                None => DYNAMIC_INPUT,
            },
            (a, b) if a == b && a > 0 => a as usize,
            _ => return Err(bad_input("a square, fixed or fully dynamic")),
        };
        if !(MIN_INPUT..=4096).contains(&input) {
            return Err(bad_input(&format!(
                "a side of {MIN_INPUT} to 4096, not {input}"
            )));
        }
        let find = |name: &str| outputs.iter().position(|p| p.name == name);
        let check = |idx: usize, ch: i64| -> Result<usize, String> {
            let p = &outputs[idx];
            let ok = p.f32
                && p.shape.len() == 4
                && p.shape[0] <= 1
                && (p.shape[1] == ch || p.shape[1] < 0);
            if ok {
                Ok(idx)
            } else {
                Err(format!(
                    "expected {EXPECTED_OUTPUTS}; output {} is {}",
                    p.name,
                    p.describe()
                ))
            }
        };
        let layout = match (
            find("depth"),
            find("albedo"),
            find("roughness"),
            find("metallic"),
            find("normal"),
            find("material"),
        ) {
            (Some(d), Some(a), Some(r), Some(m), Some(n), None) if outputs.len() == 5 => {
                Layout::Named {
                    depth: check(d, 1)?,
                    albedo: check(a, 3)?,
                    roughness: check(r, 1)?,
                    metallic: check(m, 1)?,
                    normal: check(n, 3)?,
                }
            }
            (Some(d), None, None, None, None, Some(m)) if outputs.len() == 2 => Layout::Heads {
                depth: check(d, 1)?,
                material: check(m, 8)?,
            },
            _ => {
                return Err(format!(
                    "expected {EXPECTED_OUTPUTS}; the model has {}",
                    describe_ports(outputs)
                ))
            }
        };
        let depth = match meta.get("matflow.depth").map(|s| s.trim()) {
            None | Some("disparity") => DepthKind::Disparity,
            Some("z") => DepthKind::Z,
            Some(v) => {
                return Err(format!(
                    "metadata matflow.depth = {v:?}: expected \"z\" or \"disparity\""
                ))
            }
        };
        Ok(Contract {
            input,
            layout,
            depth,
        })
    }

    pub fn describe(&self) -> String {
        format!(
            "input {0}x{0}, outputs {1}, depth {2}",
            self.input,
            match self.layout {
                Layout::Named { .. } => "depth/albedo/roughness/metallic/normal",
                Layout::Heads { .. } => "depth/material",
            },
            match self.depth {
                DepthKind::Disparity => "disparity",
                DepthKind::Z => "z",
            }
        )
    }
}

/// The five maps at [`SQUARE`]², as the network gave them (resized, not
/// clamped; normals renormalised after the resize).
#[derive(Clone, Debug, PartialEq)]
pub struct Maps {
    pub depth: Planar,
    pub albedo: Planar,
    pub roughness: Planar,
    pub metallic: Planar,
    pub normal: Planar,
}

/// Channels `c0..c0+n` of one output, resized to `side`² (bilinear,
/// aligned corners).
fn pick(o: &crate::Output, c0: usize, n: usize, side: usize) -> Result<Planar, String> {
    let [b, c, h, w] = o.shape[..] else {
        return Err(format!("output {} has shape {:?}", o.name, o.shape));
    };
    if b != 1 || c < c0 + n || h == 0 || w == 0 {
        return Err(format!(
            "output {} has shape {:?}: expected [1, {}, h, w]",
            o.name,
            o.shape,
            c0 + n
        ));
    }
    let p = Planar {
        c: n,
        h,
        w,
        data: o.data[c0 * h * w..(c0 + n) * h * w].to_vec(),
    };
    Ok(if h == side && w == side {
        p
    } else {
        resize_bilinear(&p, side, side, true)
    })
}

impl Maps {
    /// The maps from one run's outputs (in the model's order).
    pub fn from_outputs(outs: &[crate::Output], c: &Contract) -> Result<Maps, String> {
        let (depth, albedo, roughness, metallic, mut normal) = match c.layout {
            Layout::Named {
                depth,
                albedo,
                roughness,
                metallic,
                normal,
            } => (
                pick(&outs[depth], 0, 1, SQUARE)?,
                pick(&outs[albedo], 0, 3, SQUARE)?,
                pick(&outs[roughness], 0, 1, SQUARE)?,
                pick(&outs[metallic], 0, 1, SQUARE)?,
                pick(&outs[normal], 0, 3, SQUARE)?,
            ),
            Layout::Heads { depth, material } => (
                pick(&outs[depth], 0, 1, SQUARE)?,
                pick(&outs[material], 0, 3, SQUARE)?,
                pick(&outs[material], 3, 1, SQUARE)?,
                pick(&outs[material], 4, 1, SQUARE)?,
                pick(&outs[material], 5, 3, SQUARE)?,
            ),
        };
        let n = SQUARE * SQUARE;
        for i in 0..n {
            let v = [normal.data[i], normal.data[n + i], normal.data[2 * n + i]];
            let len = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            let u = if len > 1e-6 && len.is_finite() {
                [v[0] / len, v[1] / len, v[2] / len]
            } else {
                [0.0, 0.0, 1.0]
            };
            for (k, x) in u.into_iter().enumerate() {
                normal.data[k * n + i] = x;
            }
        }
        if c.depth == DepthKind::Z {
            if let Some(i) = depth.data.iter().position(|&v| v < 0.0) {
                return Err(format!(
                    "the model's depth (camera-space z) is negative ({}) at x={}, y={}",
                    depth.data[i],
                    i % SQUARE,
                    i / SQUARE
                ));
            }
        }
        Ok(Maps {
            depth,
            albedo,
            roughness,
            metallic,
            normal,
        })
    }
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

    /// The official code's 512 → 518 step is OpenCV's `INTER_CUBIC`, not
    /// PyTorch's bicubic: the same kernel (A = −0.75, half-pixel centres,
    /// replicated borders), so matflow's resize meets OpenCV's answers
    /// (written by `train/matnet/preprocess_fixture.py`) to float
    /// rounding, up and down.
    #[test]
    fn bicubic_matches_opencv_inter_cubic() {
        let lin = fixture("linear");
        let lin = Planar {
            c: 3,
            h: 12,
            w: 12,
            data: lin.values.clone(),
        };
        close(
            &resize_bicubic(&lin, 7, 7, false),
            &fixture("cv2_down"),
            1e-5,
        );
        close(
            &resize_bicubic(&lin, 17, 17, false),
            &fixture("cv2_up"),
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

    /// Reading through the sampler equals cropping then resizing.
    #[test]
    fn square_of_equals_crop_then_resize() {
        let photo = fixture("photo");
        let px: Vec<u8> = photo.values.iter().map(|&v| v as u8).collect();
        let p = Planar::from_interleaved_u8(9, 13, 3, &px);
        let want = resize_bilinear(&centre_square(&p), 12, 12, true);
        let got = square_of(9, 13, |c, y, x| p.at(c, y, x), 12);
        assert_eq!(got, want);
    }

    fn port(name: &str, shape: &[i64]) -> crate::Port {
        crate::Port {
            name: name.into(),
            f32: true,
            elem: "Float32".into(),
            shape: shape.to_vec(),
        }
    }

    fn named(albedo_ch: i64) -> Vec<crate::Port> {
        vec![
            port("depth", &[1, 1, 37, 37]),
            port("albedo", &[1, albedo_ch, 37, 37]),
            port("roughness", &[1, 1, 37, 37]),
            port("metallic", &[1, 1, 37, 37]),
            port("normal", &[1, 3, 37, 37]),
        ]
    }

    #[test]
    fn the_contract_is_read_from_the_model() {
        use std::collections::BTreeMap;
        let none = BTreeMap::new();
        let input = [port("image", &[1, 3, 518, 518])];
        let c = Contract::of(&input, &named(3), &none).unwrap();
        assert_eq!(c.input, 518);
        assert_eq!(c.depth, DepthKind::Disparity);
        assert!(matches!(c.layout, Layout::Named { albedo: 1, .. }));
        // Dynamic spatial axes take MatNet's 518, or the metadata's size.
        let dynamic = [port("x", &[-1, 3, -1, -1])];
        let heads = [
            port("material", &[-1, 8, -1, -1]),
            port("depth", &[-1, 1, -1, -1]),
        ];
        let c = Contract::of(&dynamic, &heads, &none).unwrap();
        assert_eq!(c.input, DYNAMIC_INPUT);
        assert_eq!(
            c.layout,
            Layout::Heads {
                depth: 1,
                material: 0
            }
        );
        let meta: BTreeMap<String, String> = [
            ("matflow.input_size".to_string(), "256".to_string()),
            ("matflow.depth".to_string(), "z".to_string()),
        ]
        .into();
        let c = Contract::of(&dynamic, &heads, &meta).unwrap();
        assert_eq!((c.input, c.depth), (256, DepthKind::Z));
        // What does not honour it is refused, saying what and why.
        let e = Contract::of(&input, &named(2), &none).unwrap_err();
        assert!(
            e.contains("output albedo is albedo f32 [1, 2, 37, 37]"),
            "{e}"
        );
        let e = Contract::of(&input, &named(3)[..4], &none).unwrap_err();
        assert!(e.contains("expected outputs named depth"), "{e}");
        assert!(e.contains("the model has depth f32 [1, 1, 37, 37]"), "{e}");
        let e = Contract::of(&[port("x", &[1, 3, 512, 256])], &named(3), &none).unwrap_err();
        assert!(e.contains("a square"), "{e}");
        let e = Contract::of(&[port("x", &[1, 1, 64, 64])], &named(3), &none).unwrap_err();
        assert!(e.contains("3 channels"), "{e}");
        let bad: BTreeMap<String, String> =
            [("matflow.depth".to_string(), "metres".to_string())].into();
        assert!(Contract::of(&input, &named(3), &bad)
            .unwrap_err()
            .contains("metres"));
    }

    #[test]
    fn maps_are_resized_and_normals_renormalised() {
        let c = Contract {
            input: 4,
            layout: Layout::Heads {
                depth: 0,
                material: 1,
            },
            depth: DepthKind::Z,
        };
        let (h, w) = (2, 2);
        let depth = crate::Output {
            name: "depth".into(),
            shape: vec![1, 1, h, w],
            data: vec![1.0, 2.0, 3.0, 4.0],
        };
        let mut m = vec![0.5f32; 8 * h * w];
        // Normals (channels 5-7) of length 2 along z, and one zero vector.
        for i in 0..4 {
            m[5 * 4 + i] = 0.0;
            m[6 * 4 + i] = 0.0;
            m[7 * 4 + i] = if i == 3 { 0.0 } else { 2.0 };
        }
        let material = crate::Output {
            name: "material".into(),
            shape: vec![1, 8, h, w],
            data: m,
        };
        let maps = Maps::from_outputs(&[depth.clone(), material.clone()], &c).unwrap();
        assert_eq!((maps.depth.h, maps.albedo.c, maps.normal.c), (SQUARE, 3, 3));
        // Corners keep their values (aligned corners).
        assert_eq!(maps.depth.at(0, 0, 0), 1.0);
        assert_eq!(maps.depth.at(0, SQUARE - 1, SQUARE - 1), 4.0);
        for i in 0..SQUARE * SQUARE {
            let n = [
                maps.normal.data[i],
                maps.normal.data[SQUARE * SQUARE + i],
                maps.normal.data[2 * SQUARE * SQUARE + i],
            ];
            let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
            assert!((len - 1.0).abs() < 1e-5);
        }
        // Negative z is refused.
        let mut neg = depth;
        neg.data[2] = -1.0;
        let e = Maps::from_outputs(&[neg, material], &c).unwrap_err();
        assert!(e.contains("negative"), "{e}");
    }
}
