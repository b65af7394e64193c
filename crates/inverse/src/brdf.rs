//! The reference BRDF (see `matflow_render::bsdf`) as a function of four
//! cached angles, with its analytic derivatives with respect to albedo,
//! roughness and metallic.
//!
//! With geometry fixed, a light-path vertex only needs n·l, n·v, sin θ_h and
//! v·h to evaluate f·cos for any material. They are stored quantised to
//! 16 bits each ([`Geo`]); sin θ_h rather than n·h is kept so that the
//! sharp GGX lobe (α = 0.07² at the roughness floor) keeps its relative
//! precision. Every derivative here is of the quantised model, so gradient
//! checks against finite differences are exact up to rounding.
//!
//! f·cos = A(1 − M)·Kd(R) + (F0(1 − s) + s)·Ks(R), with F0 = 0.04(1 − M) + M·A,
//! s = (1 − v·h)⁵, Kd = F_D(n·v) F_D(n·l) (n·l)/π and Ks = D·Vis·(n·l)/4.

use std::f32::consts::PI;

use glam::Vec3;
use matflow_render::bsdf::MIN_ROUGHNESS;
use matflow_render::lanes::F;
use matflow_render::Material;

const QMAX: f32 = 65535.0;

#[inline]
fn quant(x: f32) -> u16 {
    let x = if x.is_finite() {
        x.clamp(0.0, 1.0)
    } else {
        0.0
    };
    (x * QMAX + 0.5) as u16
}

/// The cached angles of one (normal, view, light) triple.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[repr(C)]
pub struct Geo {
    /// n·l, n·v, sin θ_h (1 when h is below the surface), v·h; each in
    /// [0, 1] quantised to 1/65535.
    pub q: [u16; 4],
}

impl Geo {
    pub fn new(n: Vec3, v: Vec3, l: Vec3) -> Geo {
        let nol = n.dot(l).max(0.0);
        let nov = n.dot(v).max(0.0);
        let h = (l + v).normalize_or_zero();
        let voh = v.dot(h).max(0.0);
        let sin_h = if n.dot(h) > 0.0 {
            n.cross(h).length().min(1.0)
        } else {
            1.0
        };
        Geo {
            q: [quant(nol), quant(nov), quant(sin_h), quant(voh)],
        }
    }

    /// Whether light from this direction can be reflected at all.
    #[inline]
    pub fn lit(&self) -> bool {
        self.q[0] > 0
    }

    #[inline]
    pub fn decode(&self) -> GeoF {
        let nol = self.q[0] as f32 / QMAX;
        let nov = self.q[1] as f32 / QMAX;
        let sh = self.q[2] as f32 / QMAX;
        let voh = self.q[3] as f32 / QMAX;
        let p5 = |x: f32| {
            let y = 1.0 - x;
            let y2 = y * y;
            y2 * y2 * y
        };
        GeoF {
            nol,
            nov,
            s2: sh * sh,
            voh,
            p_l: p5(nol),
            p_v: p5(nov),
            s: p5(voh),
        }
    }
}

/// Decoded angles plus the fifth powers every evaluation needs.
#[derive(Clone, Copy, Debug)]
pub struct GeoF {
    pub nol: f32,
    pub nov: f32,
    /// sin²θ_h = 1 − (n·h)².
    pub s2: f32,
    pub voh: f32,
    /// (1 − n·l)⁵, (1 − n·v)⁵, (1 − v·h)⁵.
    pub p_l: f32,
    pub p_v: f32,
    pub s: f32,
}

/// Clamped roughness and d(clamped)/d(raw).
#[inline]
pub fn clamp_roughness(r: f32) -> (f32, f32) {
    if r < MIN_ROUGHNESS {
        (MIN_ROUGHNESS, 0.0)
    } else if r > 1.0 {
        (1.0, 0.0)
    } else {
        (r, 1.0)
    }
}

/// Diffuse factor Kd(R) and dKd/dR (R already clamped).
#[inline]
pub fn kd(g: &GeoF, r: f32) -> (f32, f32) {
    let fd90m1 = -0.5 + 2.0 * r * g.voh * g.voh;
    let fdv = 1.0 + fd90m1 * g.p_v;
    let fdl = 1.0 + fd90m1 * g.p_l;
    let c = g.nol / PI;
    let d = 2.0 * g.voh * g.voh * (g.p_v * fdl + fdv * g.p_l);
    (fdv * fdl * c, d * c)
}

/// Kd(R) = k0 + k1·R + k2·R² exactly; returns (k0, k1, k2).
#[inline]
pub fn kd_poly(g: &GeoF) -> (f32, f32, f32) {
    let av = 1.0 - 0.5 * g.p_v;
    let al = 1.0 - 0.5 * g.p_l;
    let b = 2.0 * g.voh * g.voh;
    let bv = b * g.p_v;
    let bl = b * g.p_l;
    let c = g.nol / PI;
    (av * al * c, (av * bl + bv * al) * c, bv * bl * c)
}

/// Specular factor Ks(R) = D·Vis·(n·l)/4 and dKs/dR (R already clamped):
/// [`ks_lanes`] at width 1.
#[inline]
pub fn ks(g: &GeoF, r: f32) -> (f32, f32) {
    let (k, dk) = ks_lanes(g, F([r]));
    (k.0[0], dk.0[0])
}

/// [`ks`] for `W` roughnesses at once, the same operations in the same
/// order (so the same bits) in every lane.
#[inline(always)]
pub fn ks_lanes<const W: usize>(g: &GeoF, r: F<W>) -> (F<W>, F<W>) {
    let r2 = r * r;
    let a2 = r2 * r2;
    let c = 1.0 - g.s2;
    let t = g.s2 + c * a2 + 1e-6;
    let d = a2 / (PI * t * t);
    let dd_da2 = (t - 2.0 * a2 * c) / (PI * t * t * t);
    let dd = dd_da2 * 4.0 * r2 * r;
    let k = (r + 1.0) * (r + 1.0) / 8.0;
    let av = g.nov * (1.0 - k) + k + 1e-6;
    let al = g.nol * (1.0 - k) + k + 1e-6;
    let vis = 1.0 / (av * al);
    let dvis = -vis * ((1.0 - g.nov) / av + (1.0 - g.nol) / al) * (r + 1.0) / 4.0;
    let q = g.nol / 4.0;
    (d * vis * q, (dd * vis + d * dvis) * q)
}

/// f·cos for material `m`.
#[inline]
pub fn eval(g: &GeoF, m: &Material) -> Vec3 {
    if g.nol <= 0.0 {
        return Vec3::ZERO;
    }
    let (r, _) = clamp_roughness(m.roughness);
    let (kd, _) = kd(g, r);
    let (ks, _) = ks(g, r);
    let f0 = Vec3::splat(0.04 * (1.0 - m.metallic)) + m.albedo * m.metallic;
    m.albedo * ((1.0 - m.metallic) * kd) + (f0 * (1.0 - g.s) + Vec3::splat(g.s)) * ks
}

/// f·cos and its derivatives. The Jacobian with respect to albedo is
/// diagonal (channel c depends only on A_c), so `da` holds ∂f_c/∂A_c.
#[derive(Clone, Copy, Debug, Default)]
pub struct BrdfGrad {
    pub f: Vec3,
    pub da: Vec3,
    pub dr: Vec3,
    pub dm: Vec3,
}

#[inline]
pub fn eval_grad(g: &GeoF, m: &Material) -> BrdfGrad {
    if g.nol <= 0.0 {
        return BrdfGrad::default();
    }
    let (r, dr_raw) = clamp_roughness(m.roughness);
    let (kd, dkd) = kd(g, r);
    let (ks, dks) = ks(g, r);
    let mm = m.metallic;
    let a = m.albedo;
    let f0 = Vec3::splat(0.04 * (1.0 - mm)) + a * mm;
    let fr = f0 * (1.0 - g.s) + Vec3::splat(g.s);
    let f = a * ((1.0 - mm) * kd) + fr * ks;
    let da = Vec3::splat((1.0 - mm) * kd + mm * (1.0 - g.s) * ks);
    let dm = -a * kd + (a - Vec3::splat(0.04)) * ((1.0 - g.s) * ks);
    let dr = (a * ((1.0 - mm) * dkd) + fr * dks) * dr_raw;
    BrdfGrad { f, da, dr, dm }
}

#[cfg(test)]
mod tests {
    use super::*;
    use matflow_render::bsdf;

    fn dirs() -> Vec<(Vec3, Vec3)> {
        let mut out = Vec::new();
        let vs = [
            Vec3::Z,
            Vec3::new(0.5, 0.0, 0.866),
            Vec3::new(-0.3, 0.6, 0.3),
            Vec3::new(0.9, 0.1, 0.2),
        ];
        let ls = [
            Vec3::new(0.1, 0.2, 0.97),
            Vec3::new(-0.5, 0.0, 0.866),
            Vec3::new(0.7, -0.2, 0.4),
            Vec3::new(0.2, 0.9, 0.05),
            Vec3::new(0.3, 0.3, -0.5),
        ];
        for v in vs {
            for l in ls {
                out.push((v.normalize(), l.normalize()));
            }
        }
        out
    }

    fn mats() -> Vec<Material> {
        let mut v = Vec::new();
        for &r in &[0.07, 0.15, 0.4, 0.8, 1.0] {
            for &m in &[0.0, 0.3, 1.0] {
                v.push(Material {
                    albedo: Vec3::new(0.8, 0.45, 0.1),
                    roughness: r,
                    metallic: m,
                });
            }
        }
        v
    }

    #[test]
    fn matches_the_forward_bsdf() {
        let n = Vec3::Z;
        for (v, l) in dirs() {
            let g = Geo::new(n, v, l).decode();
            for m in mats() {
                let a = eval(&g, &m);
                let b = bsdf::eval(&m, n, v, l);
                let tol = 2e-3 * b.max_element().max(1e-3) + 1e-5;
                assert!(
                    (a - b).abs().max_element() <= tol,
                    "v {v} l {l} m {m:?}: cached {a} forward {b}"
                );
            }
        }
    }

    #[test]
    fn diffuse_polynomial_is_exact() {
        for (v, l) in dirs() {
            let g = Geo::new(Vec3::Z, v, l).decode();
            let (k0, k1, k2) = kd_poly(&g);
            for &r in &[0.07f32, 0.3, 0.77, 1.0] {
                let (k, _) = kd(&g, r);
                assert!((k - (k0 + k1 * r + k2 * r * r)).abs() <= 1e-6 * (1.0 + k.abs()));
            }
        }
    }

    /// Analytic derivatives against central differences in f64 arithmetic
    /// terms (step relative to the parameter, tolerance 1e-3 relative).
    #[test]
    fn gradients_match_central_differences() {
        for (v, l) in dirs() {
            let g = Geo::new(Vec3::Z, v, l).decode();
            if g.nol <= 0.0 {
                continue;
            }
            for m0 in mats() {
                // Keep roughness off the clamp corners for the derivative.
                let m0 = Material {
                    roughness: m0.roughness.clamp(0.1, 0.97),
                    metallic: m0.metallic.clamp(0.05, 0.95),
                    ..m0
                };
                let gr = eval_grad(&g, &m0);
                let fd = |pert: &dyn Fn(&mut Material, f32), h: f32| -> Vec3 {
                    let mut p = m0;
                    pert(&mut p, h);
                    let mut q = m0;
                    pert(&mut q, -h);
                    (eval(&g, &p) - eval(&g, &q)) / (2.0 * h)
                };
                let check = |name: &str, an: Vec3, num: Vec3| {
                    let scale = an.abs().max_element().max(num.abs().max_element());
                    let err = (an - num).abs().max_element();
                    assert!(
                        err <= 1e-3 * scale + 2e-4,
                        "{name}: analytic {an} numeric {num} (m {m0:?}, v {v}, l {l})"
                    );
                };
                let h = 1e-3;
                check("dr", gr.dr, fd(&|m, h| m.roughness += h, h));
                check("dm", gr.dm, fd(&|m, h| m.metallic += h, h));
                let num_a = Vec3::new(
                    fd(&|m, h| m.albedo.x += h, h).x,
                    fd(&|m, h| m.albedo.y += h, h).y,
                    fd(&|m, h| m.albedo.z += h, h).z,
                );
                check("da", gr.da, num_a);
            }
        }
    }
}
