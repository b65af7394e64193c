//! Pixel reconstruction filters.
//!
//! The reference renders with Mitsuba 3's default film: samples are placed
//! uniformly inside their pixel and splatted to every pixel within the
//! filter radius with separable Gaussian weights
//! g(x) = max(0, exp(−x²/2σ²) − exp(−r²/2σ²)), σ = 0.5, r = 2; a pixel is
//! Σ w·L / Σ w. The box filter keeps each sample in its own pixel.

use crate::lanes::{exp, F};

#[derive(Clone, Copy, Debug, PartialEq)]
pub enum PixelFilter {
    Gaussian { stddev: f32, radius: f32 },
    Box,
}

impl Default for PixelFilter {
    fn default() -> Self {
        PixelFilter::Gaussian {
            stddev: 0.5,
            radius: 2.0,
        }
    }
}

impl PixelFilter {
    /// The name `FromStr` reads back (`gaussian` for any Gaussian).
    pub fn name(&self) -> &'static str {
        match self {
            PixelFilter::Gaussian { .. } => "gaussian",
            PixelFilter::Box => "box",
        }
    }

    /// Splat radius in pixels (0 for the box filter).
    pub fn radius(&self) -> f32 {
        match *self {
            PixelFilter::Gaussian { radius, .. } => radius,
            PixelFilter::Box => 0.0,
        }
    }

    /// The filter with its constants evaluated once, for weighting many
    /// samples.
    pub fn weights(&self) -> FilterWeights {
        match *self {
            PixelFilter::Gaussian { stddev, radius } => {
                let a = -1.0 / (2.0 * stddev * stddev);
                FilterWeights {
                    filter: *self,
                    a,
                    floor: exp(F::<1>([a * radius * radius])).0[0],
                }
            }
            PixelFilter::Box => FilterWeights {
                filter: *self,
                a: 0.0,
                floor: 0.0,
            },
        }
    }

    /// 1-D weight at offset `x` (pixels) from a pixel centre.
    #[inline]
    pub fn weight_1d(&self, x: f32) -> f32 {
        self.weights().weight_1d(x)
    }
}

/// [`PixelFilter`] with its constant terms precomputed.
#[derive(Clone, Copy, Debug)]
pub struct FilterWeights {
    filter: PixelFilter,
    a: f32,
    floor: f32,
}

impl FilterWeights {
    /// The filter these weights are of.
    pub fn filter(&self) -> PixelFilter {
        self.filter
    }

    /// 1-D weight at offset `x` (pixels) from a pixel centre:
    /// [`FilterWeights::weight_lanes`] at width 1.
    #[inline]
    pub fn weight_1d(&self, x: f32) -> f32 {
        self.weight_lanes(F::<1>([x])).0[0]
    }

    /// 1-D weights at `W` offsets (pixels) from pixel centres.
    #[inline(always)]
    pub fn weight_lanes<const W: usize>(&self, x: F<W>) -> F<W> {
        let zero = F::splat(0.0);
        match self.filter {
            PixelFilter::Gaussian { radius, .. } => {
                let g = (exp(self.a * x * x) - self.floor).max(0.0);
                F::select(x.abs().lt(radius), g, zero)
            }
            PixelFilter::Box => F::select(x.abs().le(0.5), F::splat(1.0), zero),
        }
    }

    /// The separable weights of a sample at film position `at` for the
    /// columns `first.0, first.0 + 1, …` and rows `first.1, …` (as many
    /// as `wx` and `wy` hold). A footprint of up to 4×4 (the default
    /// Gaussian's) takes one 8-lane evaluation: columns in lanes 0–3,
    /// rows in 4–7.
    #[inline(always)]
    pub fn footprint(&self, at: glam::Vec2, first: (i64, i64), wx: &mut [f32], wy: &mut [f32]) {
        if wx.len() > 4 || wy.len() > 4 {
            self.weights_from(first.0, at.x, wx);
            self.weights_from(first.1, at.y, wy);
            return;
        }
        let w = self.weight_lanes(F::<8>(std::array::from_fn(|k| {
            if k < 4 {
                (first.0 + k as i64) as f32 + 0.5 - at.x
            } else {
                (first.1 + k as i64 - 4) as f32 + 0.5 - at.y
            }
        })));
        wx.copy_from_slice(&w.0[..wx.len()]);
        wy.copy_from_slice(&w.0[4..4 + wy.len()]);
    }

    /// The 1-D weights of the pixels `first`, `first + 1`, … (as many as
    /// `out` holds) for a sample at film coordinate `at`.
    #[inline]
    fn weights_from(&self, first: i64, at: f32, out: &mut [f32]) {
        for (c, chunk) in out.chunks_mut(8).enumerate() {
            let x = F::<8>(std::array::from_fn(|k| {
                (first + (c * 8 + k) as i64) as f32 + 0.5 - at
            }));
            let w = self.weight_lanes(x);
            chunk.copy_from_slice(&w.0[..chunk.len()]);
        }
    }
}

impl std::str::FromStr for PixelFilter {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "gaussian" => Ok(PixelFilter::default()),
            "box" => Ok(PixelFilter::Box),
            _ => Err(format!("unknown filter '{s}' (expected gaussian or box)")),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gaussian_is_zero_at_radius_and_peaks_at_centre() {
        let f = PixelFilter::default();
        assert_eq!(f.weight_1d(2.0), 0.0);
        assert_eq!(f.weight_1d(-2.5), 0.0);
        assert!(f.weight_1d(0.0) > f.weight_1d(0.3));
        assert!((f.weight_1d(0.0) - (1.0 - (-8.0f32).exp())).abs() < 1e-6);
    }
}
