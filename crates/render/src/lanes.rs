//! Lanes: the renderer's shading arithmetic on `W` values at once
//! (structure of arrays), with the vector width chosen at run time.
//!
//! A kernel is written once, generic over the lane count `W`, from the
//! element-wise operations of [`F`] and [`V3`]. Every lane performs the
//! same IEEE operations in the same order whatever `W` is (no horizontal
//! sums, no fused multiply-adds: Rust never contracts `a * b + c`, and
//! `sqrt` and division are correctly rounded), and the transcendental
//! functions are this module's own polynomials rather than libm's, which
//! vectorised code cannot call. So a kernel gives the same bits for a lane
//! at width 1, 4, 8 or 16, and a render is byte-identical on machines with
//! different vector units. The scalar entry points of the BSDF are the
//! kernels at width 1: there is one implementation.
//!
//! The width is picked once per process ([`width`]): 16 where the CPU has
//! AVX-512F, 8 with AVX2, else 4 (SSE2, the x86-64 baseline; 4 elsewhere
//! too). `MATFLOW_LANES=1|4|8|16` forces one, which the tests use to check
//! that every width gives the same image. [`dispatch!`] runs a kernel
//! compiled for the instruction set of the chosen width: the lane loops
//! are plain arrays, which LLVM turns into vector instructions of the
//! enabled target features (`wide` picks its instruction set at compile
//! time, so in a baseline build it would stay SSE2 inside an AVX2
//! function; arrays under `#[target_feature]` do not).

use std::ops::{Add, BitAnd, BitOr, Div, Mul, Neg, Not, Sub};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::OnceLock;

/// `W` f32 lanes.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct F<const W: usize>(pub [f32; W]);

/// `W` lane conditions, each all ones (true) or all zeros (false), as a
/// vector compare leaves them: a select is then bitwise, which LLVM keeps
/// in vector registers (a `bool` per lane made it extract and re-insert
/// lanes one at a time).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct M<const W: usize>([i32; W]);

/// `W` 3-vectors, one component per array.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct V3<const W: usize> {
    pub x: F<W>,
    pub y: F<W>,
    pub z: F<W>,
}

macro_rules! binop {
    ($tr:ident, $f:ident, $op:tt) => {
        impl<const W: usize> $tr for F<W> {
            type Output = F<W>;
            #[inline(always)]
            fn $f(self, o: F<W>) -> F<W> {
                F(std::array::from_fn(|i| self.0[i] $op o.0[i]))
            }
        }
        impl<const W: usize> $tr<f32> for F<W> {
            type Output = F<W>;
            #[inline(always)]
            fn $f(self, o: f32) -> F<W> {
                F(std::array::from_fn(|i| self.0[i] $op o))
            }
        }
        impl<const W: usize> $tr<F<W>> for f32 {
            type Output = F<W>;
            #[inline(always)]
            fn $f(self, o: F<W>) -> F<W> {
                F(std::array::from_fn(|i| self $op o.0[i]))
            }
        }
    };
}
binop!(Add, add, +);
binop!(Sub, sub, -);
binop!(Mul, mul, *);
binop!(Div, div, /);

impl<const W: usize> Neg for F<W> {
    type Output = F<W>;
    #[inline(always)]
    fn neg(self) -> F<W> {
        F(std::array::from_fn(|i| -self.0[i]))
    }
}

macro_rules! v3op {
    ($tr:ident, $f:ident, $op:tt) => {
        impl<const W: usize> $tr for V3<W> {
            type Output = V3<W>;
            /// Component by component.
            #[inline(always)]
            fn $f(self, o: V3<W>) -> V3<W> {
                V3::new(self.x $op o.x, self.y $op o.y, self.z $op o.z)
            }
        }
    };
}
v3op!(Add, add, +);
v3op!(Sub, sub, -);
v3op!(Mul, mul, *);

impl<const W: usize> BitAnd for M<W> {
    type Output = M<W>;
    #[inline(always)]
    fn bitand(self, o: M<W>) -> M<W> {
        M(std::array::from_fn(|i| self.0[i] & o.0[i]))
    }
}

impl<const W: usize> BitOr for M<W> {
    type Output = M<W>;
    #[inline(always)]
    fn bitor(self, o: M<W>) -> M<W> {
        M(std::array::from_fn(|i| self.0[i] | o.0[i]))
    }
}

impl<const W: usize> Not for M<W> {
    type Output = M<W>;
    #[inline(always)]
    fn not(self) -> M<W> {
        M(std::array::from_fn(|i| !self.0[i]))
    }
}

impl<const W: usize> M<W> {
    /// Lane `i`'s condition.
    #[inline(always)]
    pub fn lane(&self, i: usize) -> bool {
        self.0[i] != 0
    }
    /// The mask of one condition per lane.
    #[inline(always)]
    pub fn from_array(b: [bool; W]) -> M<W> {
        M::from_fn(|i| b[i])
    }
    /// The mask of `f(i)` for lanes `0..W`.
    #[inline(always)]
    fn from_fn(f: impl Fn(usize) -> bool) -> M<W> {
        M(std::array::from_fn(|i| mask(f(i))))
    }
}

/// All ones for true, zeros for false.
#[inline(always)]
fn mask(b: bool) -> i32 {
    -(b as i32)
}

impl<const W: usize> F<W> {
    #[inline(always)]
    pub fn splat(x: f32) -> F<W> {
        F([x; W])
    }
    #[inline(always)]
    pub fn map(self, f: impl Fn(f32) -> f32) -> F<W> {
        F(std::array::from_fn(|i| f(self.0[i])))
    }
    /// The larger of the two, the other where one is NaN (as `f32::max`),
    /// and `self` for equal values (so ±0 has one answer at every width).
    #[inline(always)]
    pub fn max(self, o: impl Into<F<W>>) -> F<W> {
        let o = o.into();
        F::select(self.lt(o) | self.is_nan(), o, self)
    }
    /// The smaller of the two, as [`F::max`].
    #[inline(always)]
    pub fn min(self, o: impl Into<F<W>>) -> F<W> {
        let o = o.into();
        F::select(o.lt(self) | self.is_nan(), o, self)
    }
    /// `f32::clamp` per lane (NaN stays NaN); `lo` ≤ `hi`.
    #[inline(always)]
    pub fn clamp(self, lo: f32, hi: f32) -> F<W> {
        let x = F::select(self.lt(lo), F::splat(lo), self);
        F::select(x.gt(hi), F::splat(hi), x)
    }
    /// Whether each lane is NaN.
    #[inline(always)]
    pub fn is_nan(self) -> M<W> {
        #[allow(clippy::eq_op)]
        M::from_fn(|i| self.0[i] != self.0[i])
    }
    #[inline(always)]
    pub fn sqrt(self) -> F<W> {
        self.map(f32::sqrt)
    }
    #[inline(always)]
    pub fn abs(self) -> F<W> {
        self.map(f32::abs)
    }
    /// `copysign(self, sign)` per lane.
    #[inline(always)]
    pub fn copysign(self, sign: F<W>) -> F<W> {
        F(std::array::from_fn(|i| self.0[i].copysign(sign.0[i])))
    }
    #[inline(always)]
    pub fn lt(self, o: impl Into<F<W>>) -> M<W> {
        let o = o.into();
        M::from_fn(|i| self.0[i] < o.0[i])
    }
    #[inline(always)]
    pub fn gt(self, o: impl Into<F<W>>) -> M<W> {
        let o = o.into();
        M::from_fn(|i| self.0[i] > o.0[i])
    }
    #[inline(always)]
    pub fn le(self, o: impl Into<F<W>>) -> M<W> {
        let o = o.into();
        M::from_fn(|i| self.0[i] <= o.0[i])
    }
    #[inline(always)]
    pub fn eq(self, o: impl Into<F<W>>) -> M<W> {
        let o = o.into();
        M::from_fn(|i| self.0[i] == o.0[i])
    }
    #[inline(always)]
    pub fn is_finite(self) -> M<W> {
        // x − x is 0 for finite x and NaN for ±∞ and NaN: a float
        // subtraction and compare per lane, where `f32::is_finite` becomes
        // an integer class test that LLVM does not vectorize.
        #[allow(clippy::eq_op)]
        let z = self - self;
        M::from_fn(|i| z.0[i] == 0.0)
    }
    /// `a` where `m`, else `b`.
    #[inline(always)]
    pub fn select(m: M<W>, a: F<W>, b: F<W>) -> F<W> {
        F(std::array::from_fn(|i| {
            let m = m.0[i] as u32;
            f32::from_bits((a.0[i].to_bits() & m) | (b.0[i].to_bits() & !m))
        }))
    }
    /// The nearest integer (ties to even) for |x| < 2²², as the f32
    /// `x + 1.5·2²³`, whose low mantissa bits hold it in two's complement
    /// (see [`F::rounded_int`]); an addition, no conversion.
    #[inline(always)]
    fn round_shifted(self) -> F<W> {
        self + ROUND_SHIFT
    }
    /// The integer of [`F::round_shifted`]'s result.
    #[inline(always)]
    fn rounded_int(shifted: F<W>) -> [i32; W] {
        std::array::from_fn(|i| {
            (shifted.0[i].to_bits() as i32).wrapping_sub(ROUND_SHIFT.to_bits() as i32)
        })
    }
}

/// 1.5·2²³: added to |x| < 2²², it leaves round(x) in the low mantissa
/// bits.
const ROUND_SHIFT: f32 = 12_582_912.0;

impl<const W: usize> From<f32> for F<W> {
    #[inline(always)]
    fn from(x: f32) -> F<W> {
        F([x; W])
    }
}

impl<const W: usize> V3<W> {
    #[inline(always)]
    pub fn new(x: F<W>, y: F<W>, z: F<W>) -> V3<W> {
        V3 { x, y, z }
    }
    #[inline(always)]
    pub fn splat(v: glam::Vec3) -> V3<W> {
        V3::new(F::splat(v.x), F::splat(v.y), F::splat(v.z))
    }
    /// Lanes `0..W` from `f(i)`.
    #[inline(always)]
    pub fn gather(f: impl Fn(usize) -> glam::Vec3) -> V3<W> {
        let mut v = V3::splat(glam::Vec3::ZERO);
        for i in 0..W {
            let a = f(i);
            v.x.0[i] = a.x;
            v.y.0[i] = a.y;
            v.z.0[i] = a.z;
        }
        v
    }
    #[inline(always)]
    pub fn lane(&self, i: usize) -> glam::Vec3 {
        glam::Vec3::new(self.x.0[i], self.y.0[i], self.z.0[i])
    }
    /// x·x' + y·y' + z·z', summed in that order (as `glam::Vec3::dot`).
    #[inline(always)]
    pub fn dot(self, o: V3<W>) -> F<W> {
        self.x * o.x + self.y * o.y + self.z * o.z
    }
    #[inline(always)]
    pub fn scale(self, s: F<W>) -> V3<W> {
        V3::new(self.x * s, self.y * s, self.z * s)
    }
    #[inline(always)]
    pub fn max_element(self) -> F<W> {
        self.x.max(self.y).max(self.z)
    }
    #[inline(always)]
    pub fn is_finite(self) -> M<W> {
        self.x.is_finite() & self.y.is_finite() & self.z.is_finite()
    }
    #[inline(always)]
    pub fn select(m: M<W>, a: V3<W>, b: V3<W>) -> V3<W> {
        V3::new(
            F::select(m, a.x, b.x),
            F::select(m, a.y, b.y),
            F::select(m, a.z, b.z),
        )
    }
    /// `glam::Vec3::normalize_or_zero`, with its operations: the vector
    /// times 1/√(v·v), or zero where that is not finite and positive.
    #[inline(always)]
    pub fn normalize_or_zero(self) -> V3<W> {
        let r = 1.0 / self.dot(self).sqrt();
        let ok = r.is_finite() & r.gt(0.0);
        let n = self.scale(r);
        let z = F::splat(0.0);
        V3::new(
            F::select(ok, n.x, z),
            F::select(ok, n.y, z),
            F::select(ok, n.z, z),
        )
    }
}

/// sin x and cos x for |x| ≤ 2¹⁸ (the renderer's angles lie within
/// [−2π, 2π]): reduced to [−π/4, π/4] by multiples of π/2 in two parts
/// (Cody–Waite), then odd and even polynomials (within 2 ulp of
/// libm's on [−2π, 2π]; the tests pin that).
#[inline(always)]
pub fn sin_cos<const W: usize>(x: F<W>) -> (F<W>, F<W>) {
    const PIO2_HI: f32 = 1.570_312_5; // π/2 with 9 significant bits
    const PIO2_LO: f32 = 4.838_268e-4; // π/2 − PIO2_HI
    let shifted = (x * std::f32::consts::FRAC_2_PI).round_shifted();
    let q = shifted - ROUND_SHIFT;
    let r = (x - q * PIO2_HI) - q * PIO2_LO;
    let r2 = r * r;
    // Taylor series to r⁹ and r¹⁰: below 2·10⁻⁹ on [−π/4, π/4].
    let s = r + r
        * r2
        * (-1.0 / 6.0 + r2 * (1.0 / 120.0 + r2 * (-1.0 / 5040.0 + r2 * (1.0 / 362_880.0))));
    let c = 1.0 - r2 * 0.5
        + r2 * r2
            * (1.0 / 24.0
                + r2 * (-1.0 / 720.0 + r2 * (1.0 / 40_320.0 + r2 * (-1.0 / 3_628_800.0))));
    let qi = F::rounded_int(shifted);
    let swap = M::from_fn(|i| qi[i] & 1 == 1);
    let sin_neg = M::from_fn(|i| qi[i] & 2 == 2);
    let cos_neg = M::from_fn(|i| (qi[i] + 1) & 2 == 2);
    let sn = F::select(swap, c, s);
    let cs = F::select(swap, s, c);
    (F::select(sin_neg, -sn, sn), F::select(cos_neg, -cs, cs))
}

/// eˣ for every f32 x: 2^k · e^r with r = x − k·ln 2 in [−ln2/2, ln2/2]
/// (two-part ln 2) and a degree-7 polynomial; 0 below −104, +∞ above 89
/// (within 2 ulp of libm's where the result is normal; the tests pin it).
#[inline(always)]
pub fn exp<const W: usize>(x: F<W>) -> F<W> {
    const LN2_HI: f32 = 0.693_145_75;
    const LN2_LO: f32 = 1.428_606_8e-6;
    let xc = x.clamp(-104.0, 89.0);
    let shifted = (xc * std::f32::consts::LOG2_E).round_shifted();
    let k = shifted - ROUND_SHIFT;
    let ki = F::rounded_int(shifted);
    let r = (xc - k * LN2_HI) - k * LN2_LO;
    // Taylor series to r⁷: below 10⁻⁹ on [−ln2/2, ln2/2].
    let p = 1.0
        + r * (1.0
            + r * (0.5
                + r * (1.0 / 6.0
                    + r * (1.0 / 24.0
                        + r * (1.0 / 120.0 + r * (1.0 / 720.0 + r * (1.0 / 5040.0)))))));
    // 2^k in two halves, so k down to −150 still lands on subnormals.
    let scaled = F(std::array::from_fn(|i| {
        let k1 = ki[i] >> 1;
        let k2 = ki[i] - k1;
        // k ∈ [−150, 129] (x clamped; NaN lanes are replaced below), so
        // both halves are normal exponents.
        let e1 = f32::from_bits(((k1 + 127) as u32) << 23);
        let e2 = f32::from_bits(((k2 + 127) as u32) << 23);
        p.0[i] * e1 * e2
    }));
    let big = x.gt(88.722_84);
    let nan = x.is_nan();
    F::select(nan, x, F::select(big, F::splat(f32::INFINITY), scaled))
}

/// ln x for every f32 x: x = 2ᵉ·m with m in [√½, √2), ln m = 2·atanh t
/// with t = (m − 1)/(m + 1) by its odd series to t¹¹ (|t| ≤ 0.172: the
/// rest is below 10⁻⁹), e·ln 2 in two parts; −∞ at ±0, NaN below 0 and
/// at NaN, +∞ at +∞; subnormals scaled first (within 2 ulp of libm's;
/// the tests pin it).
#[inline(always)]
pub fn ln<const W: usize>(x: F<W>) -> F<W> {
    const LN2_HI: f32 = 0.693_145_75;
    const LN2_LO: f32 = 1.428_606_8e-6;
    let sub = x.lt(f32::MIN_POSITIVE);
    let xs = F::select(sub, x * 16_777_216.0, x);
    // Mantissa in [1, 2) and exponent, then centred on 1: [√½, √2).
    let m1 = F(std::array::from_fn(|i| {
        f32::from_bits((xs.0[i].to_bits() & 0x007f_ffff) | 0x3f80_0000)
    }));
    let high = m1.gt(std::f32::consts::SQRT_2);
    let m = F::select(high, m1 * 0.5, m1);
    let e = F(std::array::from_fn(|i| {
        let ex = ((xs.0[i].to_bits() >> 23) & 0xff) as i32 - 127;
        (ex - if sub.lane(i) { 24 } else { 0 } + high.lane(i) as i32) as f32
    }));
    let t = (m - 1.0) / (m + 1.0);
    let t2 = t * t;
    let s = t2
        * (1.0 / 3.0 + t2 * (1.0 / 5.0 + t2 * (1.0 / 7.0 + t2 * (1.0 / 9.0 + t2 * (1.0 / 11.0)))));
    let t2x = t + t;
    let lnm = t2x + t2x * s;
    let r = e * LN2_HI + (lnm + e * LN2_LO);
    let r = F::select(x.eq(f32::INFINITY), x, r);
    let r = F::select(x.eq(0.0), F::splat(f32::NEG_INFINITY), r);
    F::select(x.lt(0.0) | x.is_nan(), F::splat(f32::NAN), r)
}

/// acos x for x in [−1, 1] (NaN outside): through asin, as Cephes'
/// `asinf` does — |x| ≤ ½ by an odd polynomial, above by
/// 2·asin(√((1 − |x|)/2)) — within 2.5·10⁻⁷ of libm's (the tests pin it).
#[inline(always)]
pub fn acos<const W: usize>(x: F<W>) -> F<W> {
    let a = x.abs();
    let big = a.gt(0.5);
    let z = F::select(big, 0.5 * (1.0 - a), a * a);
    let s = F::select(big, z.sqrt(), a);
    let p = (((4.216_32e-2 * z + 2.418_131e-2) * z + 4.547_002_6e-2) * z + 7.495_300_3e-2) * z
        + 1.666_675_2e-1;
    // asin of the reduced argument.
    let r = s + s * z * p;
    // Above ½: acos |x| = 2·asin √((1 − |x|)/2) (no cancellation near 1);
    // below: π/2 − asin |x|; acos(−x) = π − acos x.
    use std::f32::consts::{FRAC_PI_2, PI};
    let neg = x.lt(0.0);
    F::select(
        big,
        F::select(neg, PI - 2.0 * r, 2.0 * r),
        F::select(neg, FRAC_PI_2 + r, FRAC_PI_2 - r),
    )
}

/// atan2(y, x) for finite arguments, as `f32::atan2` (its quadrants and
/// its answers for zeros): atan of the smaller over the larger magnitude
/// by Cephes' `atanf` reduction and polynomial, within 2 ulp (at least
/// 1.5·10⁻⁷) of libm's (the tests pin it).
#[inline(always)]
pub fn atan2<const W: usize>(y: F<W>, x: F<W>) -> F<W> {
    use std::f32::consts::{FRAC_PI_2, FRAC_PI_4, PI};
    let (ax, ay) = (x.abs(), y.abs());
    let swap = ay.gt(ax);
    let num = F::select(swap, ax, ay);
    let den = F::select(swap, ay, ax);
    // t = min/max in [0, 1] (0/0 → 0).
    let t = F::select(den.gt(0.0), num / den, F::splat(0.0));
    // atan t on [0, 1]: above tan(π/8), π/4 + atan((t − 1)/(t + 1)).
    let mid = t.gt(0.414_213_57);
    let tr = F::select(mid, (t - 1.0) / (t + 1.0), t);
    let z = tr * tr;
    let p =
        (((8.053_744_5e-2 * z - 1.387_768_6e-1) * z + 1.997_771_1e-1) * z - 3.333_295e-1) * z * tr
            + tr;
    let at = F::select(mid, FRAC_PI_4 + p, p);
    // Back to the octant, then the quadrant of (x, y).
    let at = F::select(swap, FRAC_PI_2 - at, at);
    let at = F::select(x.lt(0.0), PI - at, at);
    // x = −0 counts as negative (atan2(±0, −0) = ±π).
    let negx0 = M::from_fn(|i| (x.0[i] == 0.0) & ((x.0[i].to_bits() as i32) < 0));
    let at = F::select(negx0 & y.eq(0.0), F::splat(PI), at);
    at.copysign(y)
}

/// The vector width this process renders with: the one [`force_width`]
/// set, else `MATFLOW_LANES` (1, 4, 8 or 16) when set, else the widest
/// the CPU runs natively (16 with AVX-512F, 8 with AVX2, else 4). Every
/// width gives the same bits.
pub fn width() -> usize {
    match FORCED.load(Ordering::Relaxed) {
        0 => {}
        w => return w,
    }
    static WIDTH: OnceLock<usize> = OnceLock::new();
    *WIDTH.get_or_init(|| {
        if let Ok(s) = std::env::var("MATFLOW_LANES") {
            match parse_width(&s) {
                Some(w) => return w,
                None => {
                    eprintln!("MATFLOW_LANES={s:?} is not 1, 4, 8 or 16; using the CPU's width")
                }
            }
        }
        native_width()
    })
}

static FORCED: AtomicUsize = AtomicUsize::new(0);

/// Makes every kernel of the process run `w` lanes wide (1, 4, 8 or 16;
/// `None`: back to [`width`]'s choice), for tests and benchmarks that
/// compare widths. Any other `w` is refused.
pub fn force_width(w: Option<usize>) -> Result<(), String> {
    match w {
        None => FORCED.store(0, Ordering::Relaxed),
        Some(w) if parse_width(&w.to_string()).is_some() => FORCED.store(w, Ordering::Relaxed),
        Some(w) => return Err(format!("a lane width is 1, 4, 8 or 16, not {w}")),
    }
    Ok(())
}

fn parse_width(s: &str) -> Option<usize> {
    match s.trim() {
        "1" => Some(1),
        "4" => Some(4),
        "8" => Some(8),
        "16" => Some(16),
        _ => None,
    }
}

/// The widest lane count the CPU runs natively.
pub fn native_width() -> usize {
    #[cfg(target_arch = "x86_64")]
    {
        if std::is_x86_feature_detected!("avx512f") {
            return 16;
        }
        if std::is_x86_feature_detected!("avx2") {
            return 8;
        }
    }
    4
}

/// Whether this CPU has the instruction set the kernels of width `w` are
/// compiled for (16: AVX-512F; 8: AVX2; 1 and 4: the baseline).
pub fn has_features_for(w: usize) -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        match w {
            16 => std::is_x86_feature_detected!("avx512f"),
            8 => std::is_x86_feature_detected!("avx2"),
            _ => true,
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = w;
        true
    }
}

/// Defines `fn $name(args)`, which runs the kernel `$kernel::<W>(args)`
/// (an `#[inline(always)]` function generic over the lane count) at
/// [`width()`] lanes, compiled for the instruction set of that width
/// where the CPU has it: AVX-512F for 16, AVX2 for 8 (a forced width the
/// CPU lacks runs on the baseline instructions, with the same bits).
#[macro_export]
macro_rules! lane_kernel {
    ($(#[$attr:meta])* $vis:vis fn $name:ident = $kernel:ident($($a:ident: $t:ty),* $(,)?)) => {
        $(#[$attr])*
        $vis fn $name($($a: $t),*) {
            #[cfg(target_arch = "x86_64")]
            #[target_feature(enable = "avx2")]
            unsafe fn avx2($($a: $t),*) {
                $kernel::<8>($($a),*)
            }
            #[cfg(target_arch = "x86_64")]
            #[target_feature(enable = "avx512f,avx2")]
            unsafe fn avx512($($a: $t),*) {
                $kernel::<16>($($a),*)
            }
            match $crate::lanes::width() {
                // SAFETY: the CPU has AVX-512F (checked).
                #[cfg(target_arch = "x86_64")]
                16 if $crate::lanes::has_features_for(16) => unsafe { avx512($($a),*) },
                16 => $kernel::<16>($($a),*),
                // SAFETY: the CPU has AVX2 (checked).
                #[cfg(target_arch = "x86_64")]
                8 if $crate::lanes::has_features_for(8) => unsafe { avx2($($a),*) },
                8 => $kernel::<8>($($a),*),
                1 => $kernel::<1>($($a),*),
                _ => $kernel::<4>($($a),*),
            }
        }
    };
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ulps(a: f32, b: f32) -> u32 {
        if a == b {
            return 0;
        }
        let (ia, ib) = (a.to_bits() as i32, b.to_bits() as i32);
        (ia.wrapping_sub(ib)).unsigned_abs()
    }

    #[test]
    fn sin_cos_are_within_two_ulp_of_libm_s_or_1e_7() {
        let mut worst = 0.0f32;
        for i in -200_000..=200_000 {
            let x = i as f32 * (2.0 * std::f32::consts::PI / 200_000.0);
            let (s, c) = sin_cos(F::<1>([x]));
            for (got, want) in [(s.0[0], x.sin()), (c.0[0], x.cos())] {
                let err = (got - want).abs();
                worst = worst.max(err);
                assert!(
                    ulps(got, want) <= 2 || err <= 1.2e-7,
                    "x {x}: {got} vs {want} ({} ulp)",
                    ulps(got, want)
                );
            }
        }
        assert!(worst < 1.2e-7, "worst {worst:e}");
    }

    #[test]
    fn ln_is_within_two_ulp_of_libm_s() {
        // Every 97th f32 from the smallest subnormal to the largest
        // finite one, and the neighbourhood of 1 densely.
        let mut worst = 0;
        let mut check = |x: f32| {
            let got = ln(F::<1>([x])).0[0];
            let want = x.ln();
            let u = ulps(got, want);
            worst = worst.max(u);
            assert!(u <= 2, "x {x:e}: {got} vs {want} ({u} ulp)");
        };
        let mut b = 1u32;
        while b < 0x7f80_0000 {
            check(f32::from_bits(b));
            b += 97;
        }
        for i in -100_000..100_000 {
            check(1.0 + i as f32 * 1e-6);
        }
        assert!(worst <= 2, "worst {worst} ulp");
        assert_eq!(ln(F::<1>([0.0])).0[0], f32::NEG_INFINITY);
        assert_eq!(ln(F::<1>([-0.0])).0[0], f32::NEG_INFINITY);
        assert_eq!(ln(F::<1>([1.0])).0[0], 0.0);
        assert_eq!(ln(F::<1>([f32::INFINITY])).0[0], f32::INFINITY);
        assert!(ln(F::<1>([-1.0])).0[0].is_nan());
        assert!(ln(F::<1>([f32::NAN])).0[0].is_nan());
        // Every width gives the same bits.
        let xs: [f32; 16] = std::array::from_fn(|i| 1e-3 * (i as f32 + 0.5).powi(3));
        let wide = ln(F::<16>(xs)).0;
        for (i, &x) in xs.iter().enumerate() {
            assert_eq!(ln(F::<1>([x])).0[0].to_bits(), wide[i].to_bits());
        }
    }

    #[test]
    fn exp_is_within_two_ulp_of_libm_s() {
        let mut x = -103.0f32;
        while x < 88.7 {
            let got = exp(F::<1>([x])).0[0];
            let want = x.exp();
            if want >= f32::MIN_POSITIVE {
                assert!(ulps(got, want) <= 2, "x {x}: {got} vs {want}");
            } else {
                assert!((got - want).abs() <= 2.0 * f32::from_bits(1), "x {x}");
            }
            x += 0.000_731;
        }
        assert_eq!(exp(F::<1>([-200.0])).0[0], 0.0);
        assert_eq!(exp(F::<1>([100.0])).0[0], f32::INFINITY);
        assert!(exp(F::<1>([f32::NAN])).0[0].is_nan());
        assert_eq!(exp(F::<1>([0.0])).0[0], 1.0);
    }

    #[test]
    fn acos_and_atan2_are_within_a_few_1e_7_of_libm_s() {
        let mut worst = (0.0f32, 0.0f32);
        for i in -100_000..=100_000 {
            let x = i as f32 / 100_000.0;
            let got = acos(F::<1>([x])).0[0];
            worst.0 = worst.0.max((got - x.acos()).abs());
        }
        for i in 0..200_000 {
            let a = i as f32 * (2.0 * std::f32::consts::PI / 200_000.0) - std::f32::consts::PI;
            for r in [1e-3f32, 0.7, 3.0] {
                let (y, x) = (r * a.sin(), r * a.cos());
                let got = atan2(F::<1>([y]), F::<1>([x])).0[0];
                let want = y.atan2(x);
                // In units of 2 ulp of the answer, at least 1.5·10⁻⁷.
                let unit = (2.0 * f32::EPSILON * want.abs()).max(1.5e-7);
                worst.1 = worst.1.max((got - want).abs() / unit);
            }
        }
        assert!(worst.0 < 2.5e-7 && worst.1 <= 1.0, "{worst:?}");
        assert!(acos(F::<1>([1.5])).0[0].is_nan());
        // The axes and the zeros, as libm.
        for (y, x) in [
            (0.0f32, 1.0f32),
            (1.0, 0.0),
            (0.0, -1.0),
            (-0.0, -1.0),
            (-1.0, 0.0),
            (0.0, 0.0),
            (-0.0, 0.0),
            (0.0, -0.0),
            (-0.0, -0.0),
            (2.0, 2.0),
            (-2.0, -2.0),
        ] {
            let got = atan2(F::<1>([y]), F::<1>([x])).0[0];
            let want = y.atan2(x);
            assert!(
                (got - want).abs() < 3e-7 && got.is_sign_negative() == want.is_sign_negative(),
                "atan2({y}, {x}) = {got}, libm {want}"
            );
        }
    }

    /// max, min and clamp follow the scalar rules lane by lane: the other
    /// operand where one is NaN (max/min), NaN kept (clamp), and `self`
    /// for equal values, so ±0 has one answer at every width; selects
    /// and masks combine as booleans.
    #[test]
    fn blends_follow_the_scalar_rules() {
        let xs = [0.0f32, -0.0, 1.0, -1.0, 0.5, f32::NAN, f32::INFINITY, -3.0];
        let ys = [-0.0f32, 0.0, f32::NAN, -1.0, 2.0, 1.0, 0.25, -f32::INFINITY];
        let (x, y) = (F::<8>(xs), F::<8>(ys));
        let (mx, mn, cl) = (x.max(y), x.min(y), x.clamp(-0.75, 0.75));
        let same = |a: f32, b: f32| a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan());
        for i in 0..8 {
            let (a, b) = (xs[i], ys[i]);
            let want_max = if a < b || a.is_nan() { b } else { a };
            let want_min = if b < a || a.is_nan() { b } else { a };
            assert!(same(mx.0[i], want_max), "max lane {i}: {}", mx.0[i]);
            assert!(same(mn.0[i], want_min), "min lane {i}: {}", mn.0[i]);
            assert!(same(cl.0[i], a.clamp(-0.75, 0.75)), "clamp lane {i}");
            let m = x.lt(y) | y.is_nan();
            assert_eq!(m.lane(i), a < b || b.is_nan());
            assert_eq!((!m).lane(i), !(a < b || b.is_nan()));
            assert_eq!((x.le(y) & x.is_finite()).lane(i), a <= b && a.is_finite());
            let s = F::select(m, x, y).0[i];
            assert!(same(s, if m.lane(i) { a } else { b }));
        }
    }

    /// The same inputs give the same bits at every width.
    #[test]
    fn every_width_gives_the_same_bits() {
        let xs: Vec<f32> = (0..1024)
            .map(|i| ((i as f32 * 0.618_034).fract() - 0.5) * 40.0)
            .collect();
        let one: Vec<(u32, u32, u32)> = xs
            .iter()
            .map(|&x| {
                let (s, c) = sin_cos(F::<1>([x]));
                (
                    s.0[0].to_bits(),
                    c.0[0].to_bits(),
                    exp(F::<1>([x])).0[0].to_bits(),
                )
            })
            .collect();
        #[inline(always)]
        fn wide<const W: usize>(xs: &[f32], out: &mut Vec<(u32, u32, u32)>) {
            out.clear();
            for c in xs.chunks(W) {
                let x = F::<W>(std::array::from_fn(|i| c[i]));
                let (s, co) = sin_cos(x);
                let e = exp(x);
                out.extend(
                    (0..W).map(move |i| (s.0[i].to_bits(), co.0[i].to_bits(), e.0[i].to_bits())),
                );
            }
        }
        crate::lane_kernel!(fn wide_now = wide(xs: &[f32], out: &mut Vec<(u32, u32, u32)>));
        let mut got = Vec::new();
        wide::<4>(&xs, &mut got);
        assert_eq!(one, got);
        for w in [8, 16] {
            force_width(Some(w)).unwrap();
            wide_now(&xs, &mut got);
            force_width(None).unwrap();
            assert_eq!(one, got, "width {w}");
        }
    }
}
