//! Portal sampling: next-event estimation through the openings a scene's
//! light is known to come in through ([`matflow_geom::Portal`]: the
//! windows a completed room leaves in its assumed walls).
//!
//! Inside a closed room nearly every envmap sample's shadow ray meets a
//! wall, and the light guide ([`crate::guide`]) only knows the openings
//! to the resolution of its voxels and direction cells. A portal is known
//! exactly, so a vertex can aim at it: a portal is chosen in proportion
//! to an estimate of the solid angle it subtends, and a direction is drawn
//! uniformly in the exact solid angle of that rectangle (Ureña, Fajardo
//! and King 2013, "An area-preserving parametrization for spherical
//! rectangles"). The renderer mixes this with the envmap's own density
//! (the *portal share* of the light samples), so the combined density is
//! positive wherever the envmap's is and the estimate stays unbiased
//! whatever the portals are: a portal only has to be where light may
//! come in, not exactly the opening.
//!
//! A point sees a portal only from its inward side (`u × v`): points
//! outside the room do not aim at it.

use std::f32::consts::PI;

use glam::Vec3;
use matflow_geom::Portal;

use crate::fmath::ONE_BELOW;

/// Most portals a scene samples ([`crate::RenderScene`] refuses more): a
/// completed room has at most one window per assumed wall.
pub const MAX_PORTALS: usize = 8;

/// Where a vertex sees a portal, the share of its light samples aimed at
/// the portals by default ([`crate::RenderScene::portal_share`]).
pub const PORTAL_SHARE: f32 = 0.75;

/// Smallest approximate solid angle (sr) for a portal to be sampled from
/// a point: farther portals pass too little light to be worth aiming at
/// (their light still arrives through the envmap's and the BSDF's
/// samples).
const MIN_SOLID_ANGLE: f32 = 1e-4;

/// A portal prepared for sampling: its corner, unit edge directions and
/// lengths, inward unit normal, area and centre.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PortalRect {
    corner: Vec3,
    x: Vec3,
    y: Vec3,
    lx: f32,
    ly: f32,
    n: Vec3,
    area: f32,
    centre: Vec3,
}

impl PortalRect {
    /// `None` for a portal that is not [`Portal::is_valid`].
    pub fn new(p: &Portal) -> Option<PortalRect> {
        if !p.is_valid() {
            return None;
        }
        let (lx, ly) = (p.u.length(), p.v.length());
        let (x, y) = (p.u / lx, p.v / ly);
        // Exactly perpendicular in the sampling frame.
        let n = x.cross(y).normalize_or_zero();
        let y = n.cross(x);
        (n != Vec3::ZERO).then_some(PortalRect {
            corner: p.corner,
            x,
            y,
            lx,
            ly,
            n,
            area: lx * ly,
            centre: p.corner + p.u * 0.5 + p.v * 0.5,
        })
    }

    /// An estimate of the solid angle the portal subtends from `o`
    /// (area × cosine / distance², at most 2π), 0 from its outer side or
    /// below [`MIN_SOLID_ANGLE`]: what a portal is chosen by.
    #[inline]
    pub fn weight(&self, o: Vec3) -> f32 {
        let d = o - self.centre;
        let h = self.n.dot(d);
        let r2 = d.length_squared();
        if !(h > 0.0) || !(r2 > 0.0) {
            return 0.0;
        }
        let w = (self.area * h / (r2 * r2.sqrt())).min(2.0 * PI);
        if w >= MIN_SOLID_ANGLE && w.is_finite() {
            w
        } else {
            0.0
        }
    }

    /// Whether the ray from `o` in direction `d` passes through the
    /// portal (from its inward side).
    #[inline]
    pub fn hit(&self, o: Vec3, d: Vec3) -> bool {
        let denom = self.n.dot(d);
        if !(denom < 0.0) {
            return false;
        }
        let t = self.n.dot(self.corner - o) / denom;
        if !(t > 0.0) || !t.is_finite() {
            return false;
        }
        let q = o + d * t - self.corner;
        let (a, b) = (q.dot(self.x), q.dot(self.y));
        (0.0..=self.lx).contains(&a) && (0.0..=self.ly).contains(&b)
    }

    /// The spherical rectangle the portal subtends from `o`; `None` if
    /// `o` lies (nearly) in its plane or the solid angle is not positive.
    #[inline]
    pub fn seen_from(&self, o: Vec3) -> Option<SphericalRect> {
        let d = self.corner - o;
        let (x0, y0) = (d.dot(self.x), d.dot(self.y));
        let mut z0 = d.dot(self.n);
        let mut z = self.n;
        if z0 > 0.0 {
            z0 = -z0;
            z = -z;
        }
        if !(z0 < -1e-7 * (x0.abs() + y0.abs() + 1e-7)) {
            return None;
        }
        let (x1, y1) = (x0 + self.lx, y0 + self.ly);
        // The z components of the unit normals of the planes through o
        // and each edge: n0 ∝ (0, z0, −y0), n1 ∝ (−z0, 0, x1),
        // n2 ∝ (0, −z0, y1), n3 ∝ (z0, 0, −x0). Neighbours share no
        // other component, so their dot products are products of these.
        let nz = |a: f32, b: f32| {
            let l = (a * a + b * b).sqrt();
            if l > 0.0 {
                b / l
            } else {
                0.0
            }
        };
        let (n0z, n1z, n2z, n3z) = (nz(z0, -y0), nz(-z0, x1), nz(-z0, y1), nz(z0, -x0));
        let angle = |c: f32| c.clamp(-1.0, 1.0).acos();
        // The internal angles between neighbouring edge planes.
        let g0 = angle(-(n0z * n1z));
        let g1 = angle(-(n1z * n2z));
        let g2 = angle(-(n2z * n3z));
        let g3 = angle(-(n3z * n0z));
        let k = 2.0 * PI - g2 - g3;
        let s = g0 + g1 - k;
        (s > 0.0 && s.is_finite()).then_some(SphericalRect {
            o_x: self.x,
            o_y: self.y,
            o_z: z,
            x0,
            x1,
            y0,
            y1,
            z0,
            b0: n0z,
            b1: n2z,
            k,
            solid_angle: s,
        })
    }
}

/// A rectangle as seen from a point: its local frame and bounds, and the
/// constants of the area-preserving map.
#[derive(Clone, Copy, Debug)]
pub struct SphericalRect {
    o_x: Vec3,
    o_y: Vec3,
    o_z: Vec3,
    x0: f32,
    x1: f32,
    y0: f32,
    y1: f32,
    z0: f32,
    b0: f32,
    b1: f32,
    k: f32,
    /// Solid angle, sr.
    pub solid_angle: f32,
}

impl SphericalRect {
    /// A direction uniform in the rectangle's solid angle, from (u, v) in
    /// [0, 1)²; `None` where rounding leaves no direction.
    #[inline]
    pub fn sample(&self, u: f32, v: f32) -> Option<Vec3> {
        let au = u * self.solid_angle + self.k;
        let (sa, ca) = au.sin_cos();
        if sa.abs() < 1e-12 {
            return None;
        }
        let fu = (ca * self.b0 - self.b1) / sa;
        let r = (fu * fu + self.b0 * self.b0).sqrt();
        if !(r > 0.0) {
            return None;
        }
        let cu = (if fu > 0.0 { 1.0 } else { -1.0 } / r).clamp(-1.0, 1.0);
        let su = (1.0 - cu * cu).max(1e-12).sqrt();
        let xu = (-(cu * self.z0) / su).clamp(self.x0, self.x1);
        let dd = (xu * xu + self.z0 * self.z0).sqrt();
        let h0 = self.y0 / (dd * dd + self.y0 * self.y0).sqrt();
        let h1 = self.y1 / (dd * dd + self.y1 * self.y1).sqrt();
        let hv = h0 + v * (h1 - h0);
        let hv2 = hv * hv;
        let yv = if hv2 < 1.0 - 1e-6 {
            (hv * dd / (1.0 - hv2).sqrt()).clamp(self.y0, self.y1)
        } else {
            self.y1
        };
        let d = (self.o_x * xu + self.o_y * yv + self.o_z * self.z0).normalize_or_zero();
        (d != Vec3::ZERO && d.is_finite()).then_some(d)
    }
}

/// The portals of a scene, as [`PortalRect`]s.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Portals {
    rects: Vec<PortalRect>,
}

impl Portals {
    /// The valid ones of `portals` (at most [`MAX_PORTALS`], which the
    /// caller checks).
    pub fn new(portals: &[Portal]) -> Portals {
        Portals {
            rects: portals
                .iter()
                .filter_map(PortalRect::new)
                .take(MAX_PORTALS)
                .collect(),
        }
    }

    #[inline]
    pub fn is_empty(&self) -> bool {
        self.rects.is_empty()
    }

    pub fn len(&self) -> usize {
        self.rects.len()
    }

    /// Every portal's [`PortalRect::weight`] from `o`.
    #[inline]
    pub fn weights(&self, o: Vec3) -> PortalWeights {
        let mut w = PortalWeights {
            each: [0.0; MAX_PORTALS],
            total: 0.0,
        };
        for (wk, r) in w.each.iter_mut().zip(&self.rects) {
            *wk = r.weight(o);
            w.total += *wk;
        }
        w
    }

    /// Draws a direction from `o`: a portal chosen by weight with `u1`
    /// (`w` from [`Portals::weights`] at `o`), then uniform in its solid
    /// angle. Returns the direction and [`Portals::pdf`]'s density of it;
    /// `None` when no portal is seen or rounding leaves none.
    #[inline]
    pub fn sample(&self, o: Vec3, w: &PortalWeights, u1: f32, u2: f32) -> Option<(Vec3, f32)> {
        if !(w.total > 0.0) {
            return None;
        }
        let target = u1 * w.total;
        let mut acc = 0.0;
        let mut pick = None;
        for (k, &wk) in w.each.iter().enumerate().take(self.rects.len()) {
            if wk <= 0.0 {
                continue;
            }
            let next = acc + wk;
            pick = Some((k, ((target - acc) / wk).clamp(0.0, ONE_BELOW)));
            if target < next {
                break;
            }
            acc = next;
        }
        let (k, u) = pick?;
        let rect = self.rects[k].seen_from(o)?;
        let d = rect.sample(u, u2)?;
        Some((d, self.density(o, w, d, Some((k, rect.solid_angle)))))
    }

    /// The density (per solid angle) that [`Portals::sample`] draws
    /// direction `d` from `o` with (`w` from [`Portals::weights`] at `o`):
    /// the sum over the portals `d` passes through.
    #[inline]
    pub fn pdf(&self, o: Vec3, w: &PortalWeights, d: Vec3) -> f32 {
        self.density(o, w, d, None)
    }

    /// [`Portals::pdf`], with the solid angle of portal `known.0` already
    /// known to be `known.1` and `d` drawn through it.
    #[inline]
    fn density(&self, o: Vec3, w: &PortalWeights, d: Vec3, known: Option<(usize, f32)>) -> f32 {
        if !(w.total > 0.0) {
            return 0.0;
        }
        let mut pdf = 0.0;
        for (k, (r, &wk)) in self.rects.iter().zip(&w.each).enumerate() {
            if wk <= 0.0 {
                continue;
            }
            let solid_angle = match known {
                Some((kk, s)) if kk == k => s,
                _ if !r.hit(o, d) => continue,
                _ => match r.seen_from(o) {
                    Some(s) => s.solid_angle,
                    None => continue,
                },
            };
            pdf += wk / w.total / solid_angle;
        }
        pdf
    }
}

/// What each portal weighs from a point ([`PortalRect::weight`]; the
/// entries past the scene's portals are 0) and their sum.
#[derive(Clone, Copy, Debug)]
pub struct PortalWeights {
    pub each: [f32; MAX_PORTALS],
    pub total: f32,
}

#[cfg(test)]
mod tests {
    use super::*;

    fn window() -> Portal {
        // A 2 × 1 window in the plane z = −3, facing +z (towards the
        // origin).
        Portal {
            corner: Vec3::new(-1.0, 0.5, -3.0),
            u: Vec3::new(2.0, 0.0, 0.0),
            v: Vec3::new(0.0, 1.0, 0.0),
        }
    }

    /// Solid angle by a fine midpoint rule over the rectangle's area
    /// (dω = cos θ / r² dA).
    fn solid_angle_by_area(p: &Portal, o: Vec3, m: usize) -> f64 {
        let n = p.u.cross(p.v).normalize();
        let da = (p.u.length() * p.v.length()) as f64 / (m * m) as f64;
        let mut s = 0.0;
        for i in 0..m {
            for j in 0..m {
                let q = p.corner
                    + p.u * ((i as f32 + 0.5) / m as f32)
                    + p.v * ((j as f32 + 0.5) / m as f32);
                let d = (q - o).as_dvec3();
                let r2 = d.length_squared();
                s += (n.as_dvec3().dot(-d) / r2.sqrt()).abs() / r2 * da;
            }
        }
        s
    }

    #[test]
    fn the_solid_angle_matches_the_area_integral() {
        let p = window();
        let r = PortalRect::new(&p).unwrap();
        for o in [
            Vec3::ZERO,
            Vec3::new(3.0, -1.0, 1.0),
            Vec3::new(0.1, 0.9, -2.9),
            Vec3::new(-5.0, 4.0, 10.0),
        ] {
            let s = r.seen_from(o).unwrap().solid_angle as f64;
            let q = solid_angle_by_area(&p, o, 600);
            assert!((s - q).abs() < 2e-4 * q.max(1e-3), "{o}: {s} vs {q}");
        }
        // In its plane: nothing to see.
        assert!(r.seen_from(Vec3::new(5.0, 0.0, -3.0)).is_none());
    }

    /// Directions drawn land in the rectangle, and uniformly in solid
    /// angle: each quarter of the rectangle gets its share of samples.
    #[test]
    fn samples_are_uniform_in_solid_angle_and_hit_the_portal() {
        let p = window();
        let ports = Portals::new(&[p]);
        for o in [
            Vec3::ZERO,
            Vec3::new(2.5, -0.5, -1.0),
            Vec3::new(0.0, 1.0, -2.5),
        ] {
            let w = ports.weights(o);
            let r = PortalRect::new(&p).unwrap();
            let total_s = r.seen_from(o).unwrap().solid_angle as f64;
            // Solid angle of each quarter (as its own portal).
            let half = |a: f32, b: f32| Portal {
                corner: p.corner + p.u * a + p.v * b,
                u: p.u * 0.5,
                v: p.v * 0.5,
            };
            let quarters = [
                half(0.0, 0.0),
                half(0.5, 0.0),
                half(0.0, 0.5),
                half(0.5, 0.5),
            ];
            let rects: Vec<PortalRect> = quarters
                .iter()
                .map(|q| PortalRect::new(q).unwrap())
                .collect();
            let n = 40_000;
            let mut counts = [0usize; 4];
            for i in 0..n {
                let u1 = ((i as f64 + 0.5) / n as f64) as f32;
                let u2 = (((i as u64 * 7919) % n as u64) as f64 / n as f64 + 0.5 / n as f64) as f32;
                let (d, drawn) = ports.sample(o, &w, u1, u2).expect("a direction");
                assert!(r.hit(o, d), "{o}: {d} misses");
                let k = rects.iter().position(|q| q.hit(o, d)).expect("a quarter");
                counts[k] += 1;
                let pdf = ports.pdf(o, &w, d);
                assert_eq!(drawn, pdf, "{o}: the density sampling reports");
                let pdf = pdf as f64;
                assert!(
                    (pdf * total_s - 1.0).abs() < 1e-3,
                    "{o}: pdf {pdf} vs 1/{total_s}"
                );
            }
            for (k, q) in rects.iter().enumerate() {
                let share = q.seen_from(o).unwrap().solid_angle as f64 / total_s;
                let got = counts[k] as f64 / n as f64;
                assert!(
                    (got - share).abs() < 0.01,
                    "{o}: quarter {k}: {got} vs {share}"
                );
            }
        }
    }

    /// From outside (behind the portal's facing side) or far away, no
    /// portal is sampled and the density is 0.
    #[test]
    fn points_outside_or_far_away_do_not_aim_at_the_portal() {
        let ports = Portals::new(&[window()]);
        for o in [Vec3::new(0.0, 1.0, -5.0), Vec3::new(0.0, 1.0, 1e4)] {
            let w = ports.weights(o);
            assert_eq!(w.total, 0.0, "{o}");
            assert!(ports.sample(o, &w, 0.5, 0.5).is_none());
            assert_eq!(ports.pdf(o, &w, Vec3::new(0.0, 0.0, -1.0)), 0.0);
        }
    }

    /// With two portals, each is drawn in proportion to its weight, and
    /// the density integrates to 1 over the sphere.
    #[test]
    fn two_portals_share_by_weight_and_the_density_is_normalised() {
        let a = window();
        let b = Portal {
            corner: Vec3::new(3.0, 0.0, 1.0),
            u: Vec3::new(0.0, 1.5, 0.0),
            v: Vec3::new(0.0, 0.0, -1.5),
        };
        assert!(b.u.cross(b.v).x < 0.0, "b faces −x, towards the origin");
        let ports = Portals::new(&[a, b]);
        let o = Vec3::new(0.3, 0.2, 0.1);
        let w = ports.weights(o);
        assert!(w.each[0] > 0.0 && w.each[1] > 0.0);
        // ∫ pdf dω on a fine lat-long grid.
        let (nu, nv) = (1600, 800);
        let mut integral = 0.0f64;
        for j in 0..nv {
            let theta = (j as f64 + 0.5) / nv as f64 * std::f64::consts::PI;
            for i in 0..nu {
                let phi = (i as f64 + 0.5) / nu as f64 * 2.0 * std::f64::consts::PI;
                let d = Vec3::new(
                    (theta.sin() * phi.cos()) as f32,
                    theta.cos() as f32,
                    (theta.sin() * phi.sin()) as f32,
                );
                let dw = theta.sin()
                    * (std::f64::consts::PI / nv as f64)
                    * (2.0 * std::f64::consts::PI / nu as f64);
                integral += ports.pdf(o, &w, d) as f64 * dw;
            }
        }
        assert!((integral - 1.0).abs() < 0.01, "∫ pdf = {integral}");
        let ra = PortalRect::new(&a).unwrap();
        let n = 20_000;
        let through_a = (0..n)
            .filter(|&i| {
                let u1 = (i as f32 + 0.5) / n as f32;
                ra.hit(o, ports.sample(o, &w, u1, 0.37).unwrap().0)
            })
            .count();
        let share = w.each[0] / w.total;
        assert!((through_a as f32 / n as f32 - share).abs() < 1e-3);
    }

    /// The opening of [`crate::guide::tests::box_with_window`] (x in
    /// [−0.5, 0.5], z in [−2.5, −1.5] in the ceiling y = 2), facing down
    /// into the room, grown by `grow` on every side.
    fn ceiling_window(grow: f32) -> Portal {
        Portal {
            corner: Vec3::new(-0.5 - grow, 2.0, -2.5 - grow),
            u: Vec3::new(1.0 + 2.0 * grow, 0.0, 0.0),
            v: Vec3::new(0.0, 0.0, 1.0 + 2.0 * grow),
        }
    }

    /// Inside a closed room lit through one opening, aiming light samples
    /// at it converges to the same image as the envmap's density alone
    /// (also with a portal larger than the opening, whose extra samples
    /// meet the ceiling), with far less noise at equal samples, and
    /// bit-identically on any number of threads. Both scenes are guided
    /// by visibility, as the renderer builds closed rooms.
    #[test]
    fn a_render_through_a_portal_is_unbiased_and_less_noisy() {
        use crate::guide::tests::{box_with_window, mean, opts, render, rmse, room_scene, sky};
        let n = 24;
        let plain = room_scene(n, sky(64, 32), box_with_window());
        assert!(plain.portals.is_empty());
        let through = |grow: f32| {
            let mut s = room_scene(n, sky(64, 32), box_with_window());
            s.set_portals(&[ceiling_window(grow)]).unwrap();
            assert_eq!(s.portals.len(), 1);
            s
        };
        let (exact, loose) = (through(0.0), through(0.5));
        // Direct light is where portals act (measured: 8× less error);
        // with all bounces the sunlit floor's light dominates the noise,
        // which portals leave as it is (measured: 0.9×).
        for (depth, gain) in [(2, 0.3), (4, 1.0)] {
            let reference = render(&plain, opts(4096, 99, depth));
            let mp = mean(&reference);
            let ep = rmse(&render(&plain, opts(16, 1, depth)), &reference);
            for (name, s) in [("exact", &exact), ("loose", &loose)] {
                let m = mean(&render(s, opts(4096, 99, depth)));
                assert!(
                    (m - mp).abs() < 0.02 * mp,
                    "depth {depth}, {name} portal: converged mean {m} vs {mp} without"
                );
            }
            let e = rmse(&render(&exact, opts(16, 1, depth)), &reference);
            assert!(
                e < gain * ep,
                "depth {depth}: 16 spp error {e} through the portal vs {ep} without"
            );
        }
        let one = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        let a = one.install(|| render(&exact, opts(8, 1, 4)));
        assert_eq!(a.data, render(&exact, opts(8, 1, 4)).data);
    }

    /// A scene refuses portals that are not rectangles, or too many.
    #[test]
    fn bad_portals_are_refused() {
        use crate::guide::tests::{box_with_window, room_scene, sky};
        let mut s = room_scene(8, sky(16, 8), box_with_window());
        let good = ceiling_window(0.0);
        let skew = Portal {
            v: good.v + good.u * 0.5,
            ..good
        };
        let nan = Portal {
            corner: Vec3::new(f32::NAN, 0.0, 0.0),
            ..good
        };
        let flat = Portal {
            u: Vec3::ZERO,
            ..good
        };
        for (k, bad) in [skew, nan, flat].into_iter().enumerate() {
            let e = s.set_portals(&[good, bad]).unwrap_err();
            assert!(
                matches!(e, crate::RenderError::Portal { index: 1 }),
                "{k}: {e}"
            );
        }
        let many = vec![good; MAX_PORTALS + 1];
        let e = s.set_portals(&many).unwrap_err().to_string();
        assert!(e.contains("at most 8"), "{e}");
        s.set_portals(&[good]).unwrap();
        assert_eq!(s.portals.len(), 1);
        s.set_portals(&[]).unwrap();
        assert!(s.portals.is_empty());
    }
}
