//! A minimal row-major image container. Row 0 is the top of the picture,
//! column 0 its left edge, as in every file format matflow reads.

use glam::Vec3;

#[derive(Clone, Debug, PartialEq)]
pub struct Image<T> {
    pub width: usize,
    pub height: usize,
    pub data: Vec<T>,
}

pub type RgbImage = Image<Vec3>;
pub type GrayImage = Image<f32>;

impl<T: Copy> Image<T> {
    pub fn new(width: usize, height: usize, fill: T) -> Self {
        Image {
            width,
            height,
            data: vec![fill; width * height],
        }
    }

    /// Wraps `data` (row-major, `width * height` entries).
    ///
    /// # Panics
    /// If the length does not match; callers construct `data` themselves.
    pub fn from_vec(width: usize, height: usize, data: Vec<T>) -> Self {
        assert_eq!(data.len(), width * height, "image data length");
        Image {
            width,
            height,
            data,
        }
    }

    pub fn from_fn(width: usize, height: usize, f: impl Fn(usize, usize) -> T) -> Self {
        let mut data = Vec::with_capacity(width * height);
        for y in 0..height {
            for x in 0..width {
                data.push(f(x, y));
            }
        }
        Image {
            width,
            height,
            data,
        }
    }

    #[inline]
    pub fn get(&self, x: usize, y: usize) -> T {
        self.data[y * self.width + x]
    }

    #[inline]
    pub fn set(&mut self, x: usize, y: usize, v: T) {
        self.data[y * self.width + x] = v;
    }

    pub fn map<U: Copy>(&self, f: impl Fn(T) -> U) -> Image<U> {
        Image {
            width: self.width,
            height: self.height,
            data: self.data.iter().map(|&v| f(v)).collect(),
        }
    }

    pub fn same_size<U>(&self, other: &Image<U>) -> bool {
        self.width == other.width && self.height == other.height
    }
}

impl GrayImage {
    /// Replicates a single channel into RGB.
    pub fn to_rgb(&self) -> RgbImage {
        self.map(Vec3::splat)
    }

    pub fn max_value(&self) -> f32 {
        self.data.iter().copied().fold(f32::NEG_INFINITY, f32::max)
    }
}

impl RgbImage {
    /// The first channel (maps stored as RGB with equal channels, such as
    /// roughness and metallic, are read this way).
    pub fn channel(&self, c: usize) -> GrayImage {
        self.map(|v| v[c])
    }

    /// Mean of the three channels.
    pub fn mean_channel(&self) -> GrayImage {
        self.map(|v| (v.x + v.y + v.z) / 3.0)
    }
}

/// Counts non-finite samples; returns (count, first (x, y)).
pub fn count_non_finite<T: Copy>(
    img: &Image<T>,
    finite: impl Fn(T) -> bool,
) -> (usize, (usize, usize)) {
    let mut count = 0;
    let mut first = (0, 0);
    for (i, &v) in img.data.iter().enumerate() {
        if !finite(v) {
            if count == 0 {
                first = (i % img.width, i / img.width);
            }
            count += 1;
        }
    }
    (count, first)
}
