//! Scalar helpers the hot loops use in place of libm calls, with exactly
//! libm's results. On the x86-64 baseline (SSE2) `f32::floor` and
//! `f32::ceil` are calls into libm; these are a conversion and a compare.

/// The largest f32 below 1: where a number in [0, 1] remapped from part
/// of another must stay below 1.
pub const ONE_BELOW: f32 = 1.0 - f32::EPSILON / 2.0;

/// ⌊x⌋, exactly as `f32::floor` (a value of magnitude ≥ 2²³ is already
/// an integer and comes back unchanged, as do NaN and ±∞; the sign of a
/// zero result may differ).
#[inline(always)]
pub fn floor(x: f32) -> f32 {
    if !(x.abs() < 8_388_608.0) {
        return x;
    }
    let t = x as i32 as f32;
    if t > x {
        t - 1.0
    } else {
        t
    }
}

/// ⌈x⌉, exactly as `f32::ceil` (as [`floor`]).
#[inline(always)]
pub fn ceil(x: f32) -> f32 {
    if !(x.abs() < 8_388_608.0) {
        return x;
    }
    let t = x as i32 as f32;
    if t < x {
        t + 1.0
    } else {
        t
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn floor_and_ceil_are_libm_s() {
        let mut xs = vec![
            0.0,
            -0.0,
            0.5,
            -0.5,
            1.0,
            -1.0,
            2.5,
            -2.5,
            8_388_607.5,
            -8_388_607.5,
            8_388_608.0,
            1e20,
            -1e20,
            f32::MIN_POSITIVE,
            -f32::MIN_POSITIVE,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::MAX,
        ];
        let mut bits = 0x1234_5678u32;
        for _ in 0..100_000 {
            bits ^= bits << 13;
            bits ^= bits >> 17;
            bits ^= bits << 5;
            xs.push(f32::from_bits(bits));
            xs.push((bits as f32 / u32::MAX as f32 - 0.5) * 2048.0);
        }
        for x in xs {
            if x.is_nan() {
                assert!(floor(x).is_nan() && ceil(x).is_nan());
                continue;
            }
            // Equal as numbers (a zero's sign aside).
            assert_eq!(floor(x), x.floor(), "floor {x:e}");
            assert_eq!(ceil(x), x.ceil(), "ceil {x:e}");
        }
        assert!(floor(f32::NAN).is_nan() && ceil(f32::NAN).is_nan());
    }
}
