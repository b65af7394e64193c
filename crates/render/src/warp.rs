//! Sample warps and local shading frames.

use glam::Vec3;
use std::f32::consts::PI;

use crate::lanes::{sin_cos, F, V3};

/// Cosine-weighted hemisphere around +z; pdf = cos θ / π. The lane
/// kernel [`cosine_hemisphere_lanes`] at width 1.
#[inline]
pub fn square_to_cosine_hemisphere(u1: f32, u2: f32) -> Vec3 {
    cosine_hemisphere_lanes(F::<1>([u1]), F::<1>([u2])).lane(0)
}

/// [`square_to_cosine_hemisphere`] of `W` lanes: the concentric disk
/// mapping (Shirley–Chiu), lifted to the hemisphere.
#[inline(always)]
pub fn cosine_hemisphere_lanes<const W: usize>(u1: F<W>, u2: F<W>) -> V3<W> {
    let (r, phi) = concentric_polar(u1, u2);
    let (sin, cos) = sin_cos(phi);
    lift_to_hemisphere(r, sin, cos)
}

/// The concentric disk mapping's radius and angle of (u1, u2).
#[inline(always)]
pub fn concentric_polar<const W: usize>(u1: F<W>, u2: F<W>) -> (F<W>, F<W>) {
    let a = 2.0 * u1 - 1.0;
    let b = 2.0 * u2 - 1.0;
    let centre = a.eq(0.0) & b.eq(0.0);
    let wide = (a * a).gt(b * b);
    let zero = F::splat(0.0);
    let r = F::select(centre, zero, F::select(wide, a, b));
    let phi = F::select(
        centre,
        zero,
        F::select(
            wide,
            (PI / 4.0) * (b / a),
            (PI / 2.0) - (PI / 4.0) * (a / b),
        ),
    );
    (r, phi)
}

/// The disk point at radius `r` and angle (sin, cos), lifted to the
/// hemisphere above it.
#[inline(always)]
pub fn lift_to_hemisphere<const W: usize>(r: F<W>, sin: F<W>, cos: F<W>) -> V3<W> {
    let x = r * cos;
    let y = r * sin;
    let z = (1.0 - x * x - y * y).max(0.0).sqrt();
    V3::new(x, y, z)
}

/// [`Frame`]s of `W` lanes.
#[derive(Clone, Copy, Debug)]
pub struct FrameLanes<const W: usize> {
    pub s: V3<W>,
    pub t: V3<W>,
    pub n: V3<W>,
}

impl<const W: usize> FrameLanes<W> {
    /// The frame of each lane's normal (Duff et al. 2017).
    #[inline(always)]
    pub fn from_normal(n: V3<W>) -> FrameLanes<W> {
        let sign = F::splat(1.0).copysign(n.z);
        let a = -1.0 / (sign + n.z);
        let b = n.x * n.y * a;
        FrameLanes {
            s: V3::new(1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x),
            t: V3::new(b, sign + n.y * n.y * a, -n.y),
            n,
        }
    }
    /// [`Frame::to_world`] per lane.
    #[inline(always)]
    pub fn to_world(&self, v: V3<W>) -> V3<W> {
        self.s.scale(v.x) + self.t.scale(v.y) + self.n.scale(v.z)
    }
}

/// Orthonormal basis with `n` as third axis (Duff et al. 2017).
#[derive(Clone, Copy, Debug)]
pub struct Frame {
    pub s: Vec3,
    pub t: Vec3,
    pub n: Vec3,
}

impl Frame {
    /// [`FrameLanes::from_normal`] at width 1.
    #[inline]
    pub fn from_normal(n: Vec3) -> Frame {
        let f = FrameLanes::<1>::from_normal(V3::splat(n));
        Frame {
            s: f.s.lane(0),
            t: f.t.lane(0),
            n,
        }
    }
    #[inline]
    pub fn to_local(&self, v: Vec3) -> Vec3 {
        Vec3::new(v.dot(self.s), v.dot(self.t), v.dot(self.n))
    }
    #[inline]
    pub fn to_world(&self, v: Vec3) -> Vec3 {
        self.s * v.x + self.t * v.y + self.n * v.z
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_is_orthonormal() {
        for n in [
            Vec3::Z,
            -Vec3::Z,
            Vec3::X,
            Vec3::new(0.3, -0.5, 0.8).normalize(),
            Vec3::new(1e-8, 0.0, -1.0).normalize(),
        ] {
            let f = Frame::from_normal(n);
            assert!((f.s.length() - 1.0).abs() < 1e-5 && (f.t.length() - 1.0).abs() < 1e-5);
            assert!(
                f.s.dot(f.t).abs() < 1e-5 && f.s.dot(n).abs() < 1e-5 && f.t.dot(n).abs() < 1e-5
            );
            let v = Vec3::new(0.2, 0.3, 0.9);
            assert!((f.to_local(f.to_world(v)) - v).length() < 1e-5);
        }
    }

    #[test]
    fn cosine_samples_on_hemisphere() {
        for i in 0..32 {
            for j in 0..32 {
                let v =
                    square_to_cosine_hemisphere((i as f32 + 0.5) / 32.0, (j as f32 + 0.5) / 32.0);
                assert!((v.length() - 1.0).abs() < 1e-5 && v.z >= 0.0);
            }
        }
    }
}
