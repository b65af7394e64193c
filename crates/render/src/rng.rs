//! Deterministic random numbers. The renderer draws from [`Sampler`]: an
//! Owen-scrambled (0,2)-sequence per dimension pair, keyed by hashing the
//! render seed, the pixel and the sample index, so every pixel's samples
//! are the same whatever the thread count or tile order. [`Pcg32`] is a
//! plain stream for tests and benchmarks.

/// SplitMix64 finaliser: a strong 64-bit mixing function (the one
/// stream's, [`matflow_scene::rng`]).
pub use matflow_scene::rng::mix64;

/// PCG32 (XSH-RR), O'Neill 2014: for tests and the benchmark's random
/// rays (rendering samples with [`Sampler`]).
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

/// Kensler's hashed permutation (Correlated Multi-Jittered Sampling,
/// 2013): element `i` of a pseudo-random permutation of 0..`n` chosen by
/// `key`. [`permutation_lanes`] at width 1.
#[inline]
pub fn permutation_element(i: u32, n: u32, key: u32) -> u32 {
    permutation_lanes([i], [n], [key])[0]
}

/// [`permutation_element`] of `W` lanes: every lane hashes until its
/// value falls below its `n` (cycle walking), the lanes together until
/// the last one has.
#[inline(always)]
pub fn permutation_lanes<const W: usize>(i: [u32; W], n: [u32; W], key: [u32; W]) -> [u32; W] {
    let w: [u32; W] = std::array::from_fn(|l| {
        let mut w = n[l].wrapping_sub(1);
        w |= w >> 1;
        w |= w >> 2;
        w |= w >> 4;
        w |= w >> 8;
        w |= w >> 16;
        w
    });
    let mut cur = i;
    let mut out = [0u32; W];
    // Lanes with n ≤ 1 have the one element 0.
    let mut done: [bool; W] = std::array::from_fn(|l| n[l] <= 1);
    loop {
        for l in 0..W {
            let (p, w) = (key[l], w[l]);
            let mut i = cur[l];
            i ^= p;
            i = i.wrapping_mul(0xe170_893d);
            i ^= p >> 16;
            i ^= (i & w) >> 4;
            i ^= p >> 8;
            i = i.wrapping_mul(0x0929_eb3f);
            i ^= p >> 23;
            i ^= (i & w) >> 1;
            i = i.wrapping_mul(1 | p >> 27);
            i = i.wrapping_mul(0x6935_fa69);
            i ^= (i & w) >> 11;
            i = i.wrapping_mul(0x74dc_b303);
            i ^= (i & w) >> 2;
            i = i.wrapping_mul(0x9e50_1cc3);
            i ^= (i & w) >> 2;
            i = i.wrapping_mul(0xc860_a3df);
            i &= w;
            i ^= i >> 5;
            cur[l] = i;
        }
        let mut all = true;
        for l in 0..W {
            let hit = !done[l] && cur[l] < n[l];
            if hit {
                out[l] = cur[l];
            }
            done[l] |= hit;
            all &= done[l];
        }
        if all {
            break;
        }
    }
    std::array::from_fn(|l| out[l].wrapping_add(key[l]) % n[l].max(1))
}

/// Owen scrambling with a hash (Burley, "Practical Hash-based Owen
/// Scrambling", 2020) of the 32-bit binary fraction whose bits, reversed,
/// are `v`: flipping bit j depends on the bits above it, as a nested
/// uniform scramble does. The hash works on the reversed bits, so the
/// caller passes them (a Sobol index is already its first coordinate
/// reversed); the result is the scrambled fraction.
#[inline(always)]
pub fn owen_scramble_reversed(mut v: u32, seed: u32) -> u32 {
    v ^= v.wrapping_mul(0x3d20_adea);
    v = v.wrapping_add(seed);
    v = v.wrapping_mul((seed >> 16) | 1);
    v ^= v.wrapping_mul(0x0552_6c56);
    v ^= v.wrapping_mul(0x53a2_2864);
    v.reverse_bits()
}

/// Point `i` of the first two dimensions of the Sobol sequence (van der
/// Corput, Sobol's second dimension; a (0, 2)-sequence) as 32-bit
/// fractions with their bits reversed, as [`owen_scramble_reversed`]
/// takes them: (i, the second dimension's generator columns applied in
/// reversed bit order). [`sobol_2d_reversed_lanes`] at width 1.
#[inline]
pub fn sobol_2d_reversed(i: u32) -> (u32, u32) {
    let (x, y) = sobol_2d_reversed_lanes([i]);
    (x[0], y[0])
}

/// [`sobol_2d_reversed`] of `W` lanes: as many rounds as the largest
/// index has bits.
#[inline(always)]
pub fn sobol_2d_reversed_lanes<const W: usize>(i: [u32; W]) -> ([u32; W], [u32; W]) {
    let mut y = [0u32; W];
    let mut v = [1u32; W];
    let mut rest = i;
    while rest.iter().any(|&r| r != 0) {
        for l in 0..W {
            // Branch-free: the bit is unpredictable.
            y[l] ^= v[l] & (rest[l] & 1).wrapping_neg();
            rest[l] >>= 1;
            v[l] ^= v[l] << 1;
        }
    }
    (i, y)
}

#[inline(always)]
fn to_unit(x: u32) -> f32 {
    // 24 bits: never 1.0 (and exact through i32, which vectorises).
    ((x >> 8) as i32) as f32 * (1.0 / 16_777_216.0)
}

/// [`Sampler::next_2d_with`] of `W` samplers (sample index and count of
/// each, and its keys), without advancing them.
#[inline(always)]
pub(crate) fn draws_2d<const W: usize>(
    sample: [u32; W],
    spp: [u32; W],
    k: [Keys2d; W],
) -> ([f32; W], [f32; W]) {
    let i = permutation_lanes(sample, spp, std::array::from_fn(|l| k[l].permutation));
    // The Sobol point's coordinates bit-reversed: what the scramble works
    // on (it reverses its input and output).
    let (x, y) = sobol_2d_reversed_lanes(i);
    (
        std::array::from_fn(|l| to_unit(owen_scramble_reversed(x[l], k[l].scramble_x))),
        std::array::from_fn(|l| to_unit(owen_scramble_reversed(y[l], k[l].scramble_y))),
    )
}

/// [`Sampler::next_f32_with`] of `W` samplers, without advancing them.
#[inline(always)]
pub(crate) fn draws_1d<const W: usize>(
    sample: [u32; W],
    spp: [u32; W],
    k: [Keys1d; W],
) -> [f32; W] {
    let i = permutation_lanes(sample, spp, std::array::from_fn(|l| k[l].permutation));
    std::array::from_fn(|l| to_unit(owen_scramble_reversed(i[l], k[l].scramble)))
}

/// Per-pixel stratified sample generator ("padded" scrambled Sobol, as in
/// pbrt-v4's PaddedSobolSampler): each successive 1-D or 2-D request of a
/// path is its own dimension; within a pixel, the `spp` samples of one
/// dimension are the first `spp` points of an Owen-scrambled Sobol
/// sequence, visited in a per-dimension random order so that dimensions
/// are not correlated with each other. Much lower variance than
/// independent numbers for the same sample count, and a pure function of
/// (seed, pixel, sample, dimension).
#[derive(Clone, Debug)]
pub struct Sampler {
    key: u64,
    sample: u32,
    spp: u32,
    dim: u32,
}

impl Sampler {
    pub fn for_sample(seed: u64, pixel: u64, sample: u32, spp: u32) -> Sampler {
        Sampler {
            key: mix64(seed ^ mix64(pixel.wrapping_mul(0x2545_f491_4f6c_dd1d) ^ 0x5a3b)),
            sample,
            spp: spp.max(1),
            dim: 0,
        }
    }

    /// The sampler of sample `sample` of the same pixel (what
    /// [`Sampler::for_sample`] gives for it, without hashing the pixel
    /// again).
    #[inline]
    pub fn for_sample_index(&self, sample: u32) -> Sampler {
        Sampler {
            key: self.key,
            sample,
            spp: self.spp,
            dim: 0,
        }
    }

    #[inline]
    fn hash(&self, salt: u64) -> u64 {
        mix64(self.key ^ ((self.dim as u64) << 8 | salt).wrapping_mul(0x9e37_79b9_7f4a_7c15))
    }

    /// The keys of the next 2-D draw: a function of the pixel and the
    /// dimension only, so every sample of a pixel standing at the same
    /// dimension shares them (see [`Sampler::same_dimension`]).
    #[inline]
    pub fn keys_2d(&self) -> Keys2d {
        let h = self.hash(2);
        Keys2d {
            permutation: h as u32,
            scramble_x: (h >> 32) as u32,
            scramble_y: mix64(h) as u32,
        }
    }

    /// The keys of the next 1-D draw (as [`Sampler::keys_2d`]).
    #[inline]
    pub fn keys_1d(&self) -> Keys1d {
        let h = self.hash(1);
        Keys1d {
            permutation: h as u32,
            scramble: (h >> 32) as u32,
        }
    }

    /// True when `other`'s next draws have the same keys as this one's:
    /// another sample of the same pixel at the same dimension.
    #[inline]
    pub fn same_dimension(&self, other: &Sampler) -> bool {
        self.key == other.key && self.dim == other.dim
    }

    /// Skips `n` draws (1-D or 2-D, each is one dimension).
    #[inline]
    pub fn skip(&mut self, n: u32) {
        self.dim += n;
    }

    #[inline]
    pub fn next_2d(&mut self) -> (f32, f32) {
        let k = self.keys_2d();
        self.next_2d_with(k)
    }

    /// [`Sampler::next_2d`] with its keys already computed (they must be
    /// this sampler's [`Sampler::keys_2d`]).
    #[inline]
    pub fn next_2d_with(&mut self, k: Keys2d) -> (f32, f32) {
        debug_assert!(k == self.keys_2d());
        let (x, y) = draws_2d([self.sample], [self.spp], [k]);
        self.dim += 1;
        (x[0], y[0])
    }

    /// The sample index and count: where this sampler stands among its
    /// pixel's samples.
    #[inline(always)]
    pub(crate) fn index(&self) -> (u32, u32) {
        (self.sample, self.spp)
    }

    #[inline]
    pub fn next_f32(&mut self) -> f32 {
        let k = self.keys_1d();
        self.next_f32_with(k)
    }

    /// [`Sampler::next_f32`] with its keys already computed.
    #[inline]
    pub fn next_f32_with(&mut self, k: Keys1d) -> f32 {
        debug_assert!(k == self.keys_1d());
        let x = draws_1d([self.sample], [self.spp], [k]);
        self.dim += 1;
        x[0]
    }
}

/// The keys of one 2-D draw of a pixel's samples: which permutation of
/// the samples, and the two coordinates' scrambles.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Keys2d {
    permutation: u32,
    scramble_x: u32,
    scramble_y: u32,
}

/// The keys of one 1-D draw of a pixel's samples.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Keys1d {
    permutation: u32,
    scramble: u32,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sobol_points_are_the_first_two_sobol_dimensions() {
        // Known answers, in eighths, for i = 0..8: van der Corput, and
        // Sobol's second dimension (direction numbers 1/2, 3/4, 5/8, taken
        // by the bits of i, not in Gray-code order).
        let x = [0, 4, 2, 6, 1, 5, 3, 7];
        let y = [0, 4, 6, 2, 5, 1, 3, 7];
        for i in 0..8u32 {
            let (xr, yr) = sobol_2d_reversed(i);
            assert_eq!(xr.reverse_bits() >> 29, x[i as usize], "x of {i}");
            assert_eq!(yr.reverse_bits() >> 29, y[i as usize], "y of {i}");
            assert_eq!(xr.reverse_bits() << 3, 0);
            assert_eq!(yr.reverse_bits() << 3, 0);
        }
    }

    /// A nested uniform scramble permutes the 2^k aligned intervals of
    /// [0, 1): the 16 points j/16 land one in each sixteenth.
    #[test]
    fn owen_scrambling_keeps_points_stratified() {
        let mut r = Pcg32::new(5, 9);
        for _ in 0..1000 {
            let seed = r.next_u32();
            let mut seen = [false; 16];
            for j in 0..16u32 {
                let cell = (owen_scramble_reversed((j << 28).reverse_bits(), seed) >> 28) as usize;
                assert!(!seen[cell], "seed {seed:#x}: sixteenth {cell} twice");
                seen[cell] = true;
            }
        }
    }

    /// The draws are pinned (the bits the renderer has always drawn:
    /// hashing, permutation, Sobol points and scrambling), and drawing
    /// with keys computed once gives the same numbers.
    #[test]
    fn draws_are_pinned_and_keyed_draws_equal_them() {
        let golden: [(u64, u64, u32, u32, [u32; 9]); 2] = [
            (
                3,
                77,
                5,
                64,
                [
                    0x3f44_2c08,
                    0x3e97_3272,
                    0x3f4b_73d2,
                    0x3f22_c000,
                    0x3e0a_6c4c,
                    0x3f67_f316,
                    0x3d27_64c0,
                    0x3f23_3c1a,
                    0x3dd0_3c38,
                ],
            ),
            (
                1,
                12345,
                17,
                41,
                [
                    0x3db4_f280,
                    0x3f57_87bf,
                    0x3e81_0a26,
                    0x3ecb_ebbc,
                    0x3e38_3ce4,
                    0x3e06_12e0,
                    0x3f31_8939,
                    0x3e56_286c,
                    0x3f6e_d78d,
                ],
            ),
        ];
        for (seed, pixel, sample, spp, want) in golden {
            let s = Sampler::for_sample(seed, pixel, sample, spp);
            let (mut a, mut b) = (s.clone(), s.clone());
            let mut got = Vec::new();
            for _ in 0..3 {
                assert!(a.same_dimension(&b));
                let k1 = b.keys_1d();
                let x = a.next_f32();
                assert_eq!(x, b.next_f32_with(k1));
                let k2 = b.keys_2d();
                let (u, v) = a.next_2d();
                assert_eq!((u, v), b.next_2d_with(k2));
                got.extend([x.to_bits(), u.to_bits(), v.to_bits()]);
            }
            assert_eq!(got, want, "sampler ({seed}, {pixel}, {sample}, {spp})");
            assert!(!a.same_dimension(&s));
        }
    }

    #[test]
    fn permutation_is_a_bijection() {
        for n in [1u32, 2, 3, 7, 16, 41, 100, 257] {
            for key in [0u32, 1, 0xdead_beef] {
                let mut seen = vec![false; n as usize];
                for i in 0..n {
                    let j = permutation_element(i, n, key) as usize;
                    assert!(!seen[j], "n {n} key {key}: {j} twice");
                    seen[j] = true;
                }
            }
        }
    }

    /// 16 samples of any 2-D dimension form a (0,4,2)-net: one point in
    /// every 4×4 cell, every 16×1 and every 1×16 strip.
    #[test]
    fn sampler_dimensions_are_stratified() {
        for pixel in 0..20u64 {
            for dim in 0..5 {
                let pts: Vec<(f32, f32)> = (0..16)
                    .map(|s| {
                        let mut sm = Sampler::for_sample(3, pixel, s, 16);
                        for _ in 0..dim {
                            sm.next_2d();
                        }
                        sm.next_2d()
                    })
                    .collect();
                for (bx, by) in [(4usize, 4usize), (16, 1), (1, 16), (2, 8), (8, 2)] {
                    let mut cells = vec![0; 16];
                    for &(x, y) in &pts {
                        assert!((0.0..1.0).contains(&x) && (0.0..1.0).contains(&y));
                        let cx = (x * bx as f32) as usize;
                        let cy = (y * by as f32) as usize;
                        cells[cy * bx + cx] += 1;
                    }
                    assert!(cells.iter().all(|&c| c == 1), "{bx}x{by}: {cells:?}");
                }
            }
        }
    }

    /// Stratification pays: the mean of a smooth integrand over 32 samples
    /// is far closer to the truth than with independent numbers.
    #[test]
    fn sampler_beats_independent_numbers_on_a_smooth_integrand() {
        let f = |x: f32, y: f32| (3.0 * x).sin() * y * y + x;
        let truth = (1.0 - 3f64.cos()) / 9.0 + 0.5; // ∫∫ f
        let (mut e_strat, mut e_ind) = (0.0f64, 0.0f64);
        for pixel in 0..200u64 {
            let (mut a, mut b) = (0.0f64, 0.0f64);
            for s in 0..32u32 {
                let mut sm = Sampler::for_sample(1, pixel, s, 32);
                sm.next_f32();
                let (x, y) = sm.next_2d();
                a += f(x, y) as f64;
                let mut r = Pcg32::for_sample(1, pixel, s as u64);
                let (x, y) = r.next_2d();
                b += f(x, y) as f64;
            }
            e_strat += (a / 32.0 - truth).powi(2);
            e_ind += (b / 32.0 - truth).powi(2);
        }
        assert!(e_strat < 0.1 * e_ind, "{e_strat} vs {e_ind}");
    }

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
