//! Deterministic random numbers: a PCG32 stream seeded by hashing the render
//! seed, the pixel and the sample index, so every pixel's samples are the
//! same whatever the thread count or tile order.

/// SplitMix64 finaliser: a strong 64-bit mixing function.
#[inline]
pub fn mix64(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// PCG32 (XSH-RR), O'Neill 2014.
#[derive(Clone, Debug)]
pub struct Pcg32 {
    state: u64,
    inc: u64,
}

impl Pcg32 {
    const MULT: u64 = 6_364_136_223_846_793_005;

    pub fn new(seed: u64, stream: u64) -> Self {
        let mut r = Pcg32 {
            state: 0,
            inc: (stream << 1) | 1,
        };
        r.next_u32();
        r.state = r.state.wrapping_add(seed);
        r.next_u32();
        r
    }

    /// A generator for one (pixel, sample) pair of a render with `seed`.
    pub fn for_sample(seed: u64, pixel: u64, sample: u64) -> Self {
        let a = mix64(seed ^ mix64(pixel.wrapping_mul(0x2545_f491_4f6c_dd1d)));
        let b = mix64(a ^ sample);
        Pcg32::new(b, mix64(b ^ 0xda94_2042_e4dd_58b5))
    }

    #[inline]
    pub fn next_u32(&mut self) -> u32 {
        let old = self.state;
        self.state = old.wrapping_mul(Self::MULT).wrapping_add(self.inc);
        let xorshifted = (((old >> 18) ^ old) >> 27) as u32;
        let rot = (old >> 59) as u32;
        xorshifted.rotate_right(rot)
    }

    /// Uniform in [0, 1), 24 bits of precision (never returns 1.0).
    #[inline]
    pub fn next_f32(&mut self) -> f32 {
        (self.next_u32() >> 8) as f32 * (1.0 / 16_777_216.0)
    }

    #[inline]
    pub fn next_2d(&mut self) -> (f32, f32) {
        let a = self.next_f32();
        (a, self.next_f32())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uniform_in_unit_interval_with_plausible_mean() {
        let mut r = Pcg32::for_sample(1, 2, 3);
        let mut sum = 0.0f64;
        for _ in 0..100_000 {
            let x = r.next_f32();
            assert!((0.0..1.0).contains(&x));
            sum += x as f64;
        }
        assert!((sum / 100_000.0 - 0.5).abs() < 0.005);
    }

    #[test]
    fn streams_differ_and_repeat() {
        let a: Vec<u32> = (0..4)
            .map(|_| 0)
            .scan(Pcg32::for_sample(7, 1, 0), |r, _| Some(r.next_u32()))
            .collect();
        let b: Vec<u32> = (0..4)
            .map(|_| 0)
            .scan(Pcg32::for_sample(7, 1, 0), |r, _| Some(r.next_u32()))
            .collect();
        let c: Vec<u32> = (0..4)
            .map(|_| 0)
            .scan(Pcg32::for_sample(7, 2, 0), |r, _| Some(r.next_u32()))
            .collect();
        assert_eq!(a, b);
        assert_ne!(a, c);
    }
}
