//! The one random stream of matflow's procedural content and searches:
//! SplitMix64 (Steele, Lea and Flood 2014), seeded explicitly, so that a
//! generated scene, envmap, room or dataset draw is a pure function of its
//! seed. (The renderer's samples come from `matflow_render::rng`'s
//! scrambled sequences, keyed by [`mix64`].)

/// SplitMix64's step and finaliser as a hash: the next output of a stream
/// whose state is `z`.
#[inline]
pub fn mix64(z: u64) -> u64 {
    Rng(z).next_u64()
}

/// SplitMix64: the procedural generators' random stream (scene layout,
/// envmaps, rooms, dataset draws).
pub struct Rng(pub u64);
impl Rng {
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }
    /// Uniform in [0, 1), 24 bits.
    pub fn f(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32
    }
    pub fn range(&mut self, a: f32, b: f32) -> f32 {
        a + (b - a) * self.f()
    }
    pub fn chance(&mut self, p: f32) -> bool {
        self.f() < p
    }
    /// Uniform in 0..n (n > 0), by multiply-shift.
    pub fn below(&mut self, n: u64) -> u64 {
        ((self.next_u64() as u128 * n as u128) >> 64) as u64
    }
    /// Uniform in 0..n (n > 0; 0 for n = 0) by the remainder: the plane
    /// search's draw (`matflow_geom::planes`), whose fits were measured
    /// with it; new code takes [`Rng::below`].
    pub fn below_mod(&mut self, n: usize) -> usize {
        (self.next_u64() % n.max(1) as u64) as usize
    }
    /// Uniform in [−1, 1), 24 bits.
    pub fn signed(&mut self) -> f32 {
        self.f() * 2.0 - 1.0
    }
}
