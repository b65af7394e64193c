//! Per-pixel material model with cached incident light.
//!
//! Hold the envmap and the light arriving at every primary vertex from
//! deeper bounces fixed; then a pixel's value depends only on its own
//! albedo A, roughness R and metallic M, and the sum over its frozen
//! directions collapses to a handful of numbers per pixel:
//!
//! I = B + (1 − M)·A ⊙ (C0 + C1·R + C2·R²) + F0 ⊙ S1(R) + S2(R)
//!
//! B is what does not depend on the pixel's material (sky seen directly,
//! the rare primary vertex that projects into a neighbour). The diffuse
//! part is exactly quadratic in R (Disney's F_D90 is linear in R);
//! S1 = Σ Ks(R)(1 − s)·L and S2 = Σ Ks(R)·s·L are tabulated on a roughness
//! grid with their exact R-derivatives and interpolated by cubic Hermite
//! splines. An optimisation step then costs O(1) per pixel instead of
//! O(paths × bounces); the incident light is refreshed between stages.

use glam::Vec3;
use matflow_render::bsdf::MIN_ROUGHNESS;
use matflow_render::Material;
use rayon::prelude::*;

use crate::brdf::{clamp_roughness, kd_poly, ks_lanes, GeoF};
use crate::paths::{sky, PathCache, MAX_DEPTH, NO_MATERIAL};
use crate::transport::{for_each_path, path_radiance};
use matflow_render::lanes::F;

/// Roughness nodes: R_i = 0.07 + 0.93·(i/(N−1))², denser where the GGX
/// lobe changes fastest.
pub const NODES: usize = 16;

#[inline]
pub fn node(i: usize) -> f32 {
    let t = i as f32 / (NODES - 1) as f32;
    MIN_ROUGHNESS + (1.0 - MIN_ROUGHNESS) * t * t
}

#[inline]
fn interval(r: f32) -> usize {
    let t = ((r - MIN_ROUGHNESS) / (1.0 - MIN_ROUGHNESS))
        .max(0.0)
        .sqrt();
    ((t * (NODES - 1) as f32) as usize).min(NODES - 2)
}

/// The roughness interval of `r` (clamped to the nodes' range), its width
/// h, the position t in it, and the cubic Hermite basis at t with the
/// tangent terms scaled by h: (h00, h10·h, h01, h11·h).
#[inline]
pub(crate) fn hermite(r: f32) -> (usize, f32, f32, [f32; 4]) {
    let i = interval(r);
    let (r0, r1) = (node(i), node(i + 1));
    let h = r1 - r0;
    let t = ((r - r0) / h).clamp(0.0, 1.0);
    let (t2, t3) = (t * t, t * t * t);
    let basis = [
        2.0 * t3 - 3.0 * t2 + 1.0,
        (t3 - 2.0 * t2 + t) * h,
        -2.0 * t3 + 3.0 * t2,
        (t3 - t2) * h,
    ];
    (i, h, t, basis)
}

/// One pixel's model: 4 + 4·NODES RGB values.
#[derive(Clone, Copy, Debug)]
pub struct PixelTable {
    pub base: Vec3,
    pub c: [Vec3; 3],
    /// Per node: S1, dS1/dR, S2, dS2/dR.
    pub spec: [[Vec3; 4]; NODES],
}

impl Default for PixelTable {
    fn default() -> Self {
        PixelTable {
            base: Vec3::ZERO,
            c: [Vec3::ZERO; 3],
            spec: [[Vec3::ZERO; 4]; NODES],
        }
    }
}

/// The value of a pixel and its derivatives.
#[derive(Clone, Copy, Debug, Default)]
pub struct PixelEval {
    pub i: Vec3,
    /// ∂I_c/∂A_c (diagonal).
    pub da: Vec3,
    pub dr: Vec3,
    pub dm: Vec3,
}

impl PixelTable {
    #[inline]
    fn spec_at(&self, r: f32) -> (Vec3, Vec3, Vec3, Vec3) {
        let (i, h, t, basis) = hermite(r);
        let t2 = t * t;
        let d00 = (6.0 * t2 - 6.0 * t) / h;
        let d10 = 3.0 * t2 - 4.0 * t + 1.0;
        let d01 = (-6.0 * t2 + 6.0 * t) / h;
        let d11 = 3.0 * t2 - 2.0 * t;
        let (a, b) = (&self.spec[i], &self.spec[i + 1]);
        let (s1, s2) = self.spec_values(i, basis);
        let ds1 = a[0] * d00 + a[1] * d10 + b[0] * d01 + b[1] * d11;
        let ds2 = a[2] * d00 + a[3] * d10 + b[2] * d01 + b[3] * d11;
        (s1, ds1, s2, ds2)
    }

    /// S1 and S2 on interval `i` with [`hermite`]'s basis.
    #[inline]
    fn spec_values(&self, i: usize, [h00, h10h, h01, h11h]: [f32; 4]) -> (Vec3, Vec3) {
        let (a, b) = (&self.spec[i], &self.spec[i + 1]);
        let s1 = a[0] * h00 + a[1] * h10h + b[0] * h01 + b[1] * h11h;
        let s2 = a[2] * h00 + a[3] * h10h + b[2] * h01 + b[3] * h11h;
        (s1, s2)
    }

    /// The pixel's value I and ∂I/∂A alone, bit for bit those of
    /// [`Self::eval`]: what the per-pixel searches need, at about half
    /// the cost.
    #[inline]
    pub fn eval_value(&self, m: &Material) -> (Vec3, Vec3) {
        let (r, _) = clamp_roughness(m.roughness);
        let mm = m.metallic;
        let a = m.albedo;
        let d = self.c[0] + self.c[1] * r + self.c[2] * (r * r);
        let (i, _, _, basis) = hermite(r);
        let (s1, s2) = self.spec_values(i, basis);
        let f0 = Vec3::splat(0.04 * (1.0 - mm)) + a * mm;
        let i = self.base + a * d * (1.0 - mm) + f0 * s1 + s2;
        (i, d * (1.0 - mm) + s1 * mm)
    }

    #[inline]
    pub fn eval(&self, m: &Material) -> PixelEval {
        let (r, dr_raw) = clamp_roughness(m.roughness);
        let mm = m.metallic;
        let a = m.albedo;
        let d = self.c[0] + self.c[1] * r + self.c[2] * (r * r);
        let dd = self.c[1] + self.c[2] * (2.0 * r);
        let (s1, ds1, s2, ds2) = self.spec_at(r);
        let f0 = Vec3::splat(0.04 * (1.0 - mm)) + a * mm;
        let i = self.base + a * d * (1.0 - mm) + f0 * s1 + s2;
        PixelEval {
            i,
            da: d * (1.0 - mm) + s1 * mm,
            dm: -a * d + (a - Vec3::splat(0.04)) * s1,
            dr: (a * dd * (1.0 - mm) + f0 * ds1 + ds2) * dr_raw,
        }
    }
}

/// A pixel's specular sums while its table is built: per channel, per
/// entry (S1, dS1/dR, S2, dS2/dR), per node, so that `W` nodes are one
/// vector.
type SpecSums = [[[f32; NODES]; 4]; 3];

const _: () = assert!(
    NODES.is_multiple_of(16),
    "nodes must split into lanes of 1, 4, 8 or 16"
);

matflow_render::lane_kernel!(fn add_spec_now = add_spec(
    spec: &mut SpecSums,
    g: &GeoF,
    lin: Vec3,
    nodes: &[f32; NODES],
));

/// Adds one record's light `lin` through geometry `g` to the specular
/// sums at every node: Ks and dKs/dR of `W` nodes at once
/// ([`ks_lanes`]), the same operations per entry as one node at a time.
#[inline(always)]
fn add_spec<const W: usize>(spec: &mut SpecSums, g: &GeoF, lin: Vec3, nodes: &[f32; NODES]) {
    let one_s = 1.0 - g.s;
    for i in (0..NODES).step_by(W) {
        let (k, dk) = ks_lanes(g, F::<W>(std::array::from_fn(|l| nodes[i + l])));
        let f = [k * one_s, dk * one_s, k * g.s, dk * g.s];
        for (c, sc) in spec.iter_mut().enumerate() {
            let lc = lin[c];
            for (fj, sj) in f.iter().zip(sc.iter_mut()) {
                let a = &mut sj[i..i + W];
                let v = F::<W>(std::array::from_fn(|l| a[l])) + lc * *fj;
                a.copy_from_slice(&v.0);
            }
        }
    }
}

/// Builds every pixel's table for materials `mats` and envmap `env`.
pub fn build_tables(cache: &PathCache, mats: &[Material], env: &[Vec3]) -> Vec<PixelTable> {
    build_tables_with_variance(cache, mats, env).0
}

/// [`build_tables`], plus per pixel the variance of the estimate of
/// [`crate::denoise::table_luminance`] (from the spread of its paths) and
/// whether the pixel's table models its own primary vertex (false for
/// sky pixels and for pixels none of whose paths start on themselves).
pub fn build_tables_with_variance(
    cache: &PathCache,
    mats: &[Material],
    env: &[Vec3],
) -> (Vec<PixelTable>, Vec<f32>, Vec<bool>) {
    let w = cache.width;
    let ew = cache.env_width;
    let spp = cache.spp.max(1) as f32;
    let inv = 1.0 / spp;
    let lum = |v: Vec3| 0.2126 * v.x + 0.7152 * v.y + 0.0722 * v.z;
    // Filled in place, row by row in parallel: no second copy of the
    // tables (214 MB at 512²) while they are assembled.
    let n = w * cache.height;
    let mut tables = vec![PixelTable::default(); n];
    let mut var = vec![0f32; n];
    let mut valid = vec![false; n];
    tables
        .par_chunks_mut(w.max(1))
        .zip(var.par_chunks_mut(w.max(1)))
        .zip(valid.par_chunks_mut(w.max(1)))
        .enumerate()
        .for_each(|(y, ((t_row, v_row), o_row))| {
            let mut l = [Vec3::ZERO; MAX_DEPTH as usize];
            let mut rst = [0usize; MAX_DEPTH as usize];
            let nodes: [f32; NODES] = std::array::from_fn(node);
            let mut pixel = |x: usize| {
                let p = (y * w + x) as u32;
                let (verts, recs) = cache.pixel(x, y);
                let mut t = PixelTable::default();
                let mut spec: SpecSums = [[[0.0; NODES]; 4]; 3];
                let mut own = false;
                // Per-path contributions to lum(c0): first and second
                // moments (paths on other pixels contribute 0).
                let (mut m1, mut m2) = (0f64, 0f64);
                for_each_path(verts, |first, end, r0| {
                    let n =
                        path_radiance(verts, recs, first, end, r0, mats, env, ew, &mut l, &mut rst);
                    let v = verts[first];
                    if v.q != p || v.q == NO_MATERIAL {
                        t.base += l[0];
                        return;
                    }
                    own = true;
                    let before = lum(t.c[0]);
                    let rs = &recs[rst[0]..rst[0] + v.n_records()];
                    let mut add = |geo: &crate::brdf::Geo, lin: Vec3| {
                        let g = geo.decode();
                        if g.nol <= 0.0 || lin == Vec3::ZERO {
                            return;
                        }
                        let (k0, k1, k2) = kd_poly(&g);
                        t.c[0] += lin * k0;
                        t.c[1] += lin * k1;
                        t.c[2] += lin * k2;
                        add_spec_now(&mut spec, &g, lin, &nodes);
                    };
                    for rec in &rs[..v.n_env as usize] {
                        add(&rec.geo, sky(rec, env, ew) * rec.w);
                    }
                    if v.has_cont() && n > 1 {
                        let rec = &rs[v.n_env as usize];
                        add(&rec.geo, l[1] * rec.w);
                    }
                    let d = (lum(t.c[0]) - before) as f64;
                    m1 += d;
                    m2 += d * d;
                });
                t.base *= inv;
                for c in &mut t.c {
                    *c *= inv;
                }
                for (i, e) in t.spec.iter_mut().enumerate() {
                    for (j, v) in e.iter_mut().enumerate() {
                        *v = Vec3::new(spec[0][j][i], spec[1][j][i], spec[2][j][i]) * inv;
                    }
                }
                let n = spp as f64;
                let mean = m1 / n;
                let var = ((m2 / n - mean * mean).max(0.0) / n) as f32;
                (t, var, own)
            };
            for x in 0..w {
                (t_row[x], v_row[x], o_row[x]) = pixel(x);
            }
        });
    (tables, var, valid)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The specular sums of a record are the same bits at lane widths 1,
    /// 4, 8 and 16 as [`ks`] one node at a time.
    #[test]
    fn spec_sums_are_the_same_at_every_width() {
        use crate::brdf::{ks, Geo};
        use crate::testutil::hash01;
        let nodes: [f32; NODES] = std::array::from_fn(node);
        let mut want: SpecSums = [[[0.0; NODES]; 4]; 3];
        let mut got = [want; 4];
        for r in 0..50u64 {
            let d = |k: u64| {
                Vec3::new(
                    hash01(r * 9 + k),
                    hash01(r * 9 + k + 1),
                    hash01(r * 9 + k + 2),
                ) * 2.0
                    - Vec3::ONE
            };
            let n = Vec3::Z;
            let g = Geo::new(
                n,
                (d(0) + n * 1.2).normalize(),
                (d(3) + n * 1.1).normalize(),
            );
            let g = g.decode();
            let lin = d(6).abs() * 4.0;
            for (i, &r) in nodes.iter().enumerate() {
                let (k, dk) = ks(&g, r);
                for c in 0..3 {
                    let e = &mut want[c];
                    e[0][i] += lin[c] * (k * (1.0 - g.s));
                    e[1][i] += lin[c] * (dk * (1.0 - g.s));
                    e[2][i] += lin[c] * (k * g.s);
                    e[3][i] += lin[c] * (dk * g.s);
                }
            }
            add_spec::<1>(&mut got[0], &g, lin, &nodes);
            add_spec::<4>(&mut got[1], &g, lin, &nodes);
            add_spec::<8>(&mut got[2], &g, lin, &nodes);
            add_spec::<16>(&mut got[3], &g, lin, &nodes);
        }
        let bits = |s: &SpecSums| {
            s.as_flattened()
                .as_flattened()
                .iter()
                .map(|x| x.to_bits())
                .collect::<Vec<_>>()
        };
        for g in &got {
            assert_eq!(bits(g), bits(&want));
        }
    }

    #[test]
    fn nodes_cover_the_roughness_range() {
        assert!((node(0) - MIN_ROUGHNESS).abs() < 1e-7);
        assert!((node(NODES - 1) - 1.0).abs() < 1e-6);
        for i in 0..NODES - 1 {
            let mid = 0.5 * (node(i) + node(i + 1));
            assert_eq!(interval(mid), i);
        }
        assert_eq!(interval(0.0), 0);
        assert_eq!(interval(1.0), NODES - 2);
    }
}

#[cfg(test)]
mod model_tests {
    use super::*;
    use crate::paths::PathCache;
    use crate::testutil::{cache_of, hash01, materials_of, room, texels};
    use crate::transport::render;

    /// The exact frozen estimator for pixel p with its primary vertices
    /// using `m` and deeper vertices the original materials (what the
    /// table models: the light arriving from deeper bounces held fixed).
    fn primary_override(
        cache: &PathCache,
        p: usize,
        m: &Material,
        mats: &[Material],
        env: &[Vec3],
    ) -> Vec3 {
        use crate::brdf::eval;
        let (x, y) = (p % cache.width, p / cache.width);
        let (verts, recs) = cache.pixel(x, y);
        let mut l = [Vec3::ZERO; MAX_DEPTH as usize];
        let mut rst = [0usize; MAX_DEPTH as usize];
        let mut sum = Vec3::ZERO;
        for_each_path(verts, |a, b, r0| {
            let n = path_radiance(
                verts,
                recs,
                a,
                b,
                r0,
                mats,
                env,
                cache.env_width,
                &mut l,
                &mut rst,
            );
            let v = verts[a];
            if v.q as usize != p {
                sum += l[0];
                return;
            }
            let rs = &recs[rst[0]..rst[0] + v.n_records()];
            for rec in &rs[..v.n_env as usize] {
                sum += eval(&rec.geo.decode(), m) * rec.w * sky(rec, env, cache.env_width);
            }
            if v.has_cont() && n > 1 {
                let rec = &rs[v.n_env as usize];
                sum += eval(&rec.geo.decode(), m) * rec.w * l[1];
            }
        });
        sum / cache.spp as f32
    }

    /// With the materials it was built for, the table reproduces the
    /// frozen estimator; for another roughness/metallic/albedo at one pixel
    /// it reproduces the exact re-evaluation to interpolation accuracy, and
    /// its derivatives match central differences of itself.
    #[test]
    fn tables_reproduce_the_exact_estimator() {
        let t = room(11, 16);
        let cache = cache_of(&t.scene, 8);
        let mats = materials_of(&t.maps);
        let env = texels(&t.env);
        let tabs = build_tables(&cache, &mats, &env);
        let img = render(&cache, &mats, &env);
        for p in 0..img.len() {
            let e = tabs[p].eval(&mats[p]).i;
            let tol = 2e-3 * img[p].max_element() + 1e-6;
            assert!(
                (e - img[p]).abs().max_element() <= tol,
                "pixel {p}: {e} vs {}",
                img[p]
            );
        }
        let mut worst = 0.0f32;
        for p in (0..img.len()).step_by(7) {
            for k in 0..6 {
                let m = Material {
                    albedo: Vec3::new(
                        hash01((p * 31 + k) as u64),
                        hash01((p * 37 + k) as u64),
                        hash01((p * 41 + k) as u64),
                    ),
                    roughness: 0.07 + 0.93 * hash01((p * 43 + k) as u64),
                    metallic: hash01((p * 47 + k) as u64),
                };
                let exact = primary_override(&cache, p, &m, &mats, &env);
                let e = tabs[p].eval(&m);
                // The searches' value-only evaluation is the same bits.
                let (vi, vda) = tabs[p].eval_value(&m);
                assert_eq!(
                    vi.to_array().map(f32::to_bits),
                    e.i.to_array().map(f32::to_bits)
                );
                assert_eq!(
                    vda.to_array().map(f32::to_bits),
                    e.da.to_array().map(f32::to_bits)
                );
                let rel = (e.i - exact).abs().max_element() / exact.max_element().max(1e-3);
                worst = worst.max(rel);
                // Derivatives against central differences of the model.
                let h = 1e-3;
                let num_r = (tabs[p]
                    .eval(&Material {
                        roughness: m.roughness + h,
                        ..m
                    })
                    .i
                    - tabs[p]
                        .eval(&Material {
                            roughness: m.roughness - h,
                            ..m
                        })
                        .i)
                    / (2.0 * h);
                if m.roughness > 0.07 + h && m.roughness < 1.0 - h {
                    let s = num_r.abs().max_element().max(e.dr.abs().max_element());
                    assert!(
                        (num_r - e.dr).abs().max_element() <= 2e-2 * s + 1e-4,
                        "{num_r} vs {}",
                        e.dr
                    );
                }
                let num_m = (tabs[p]
                    .eval(&Material {
                        metallic: m.metallic + h,
                        ..m
                    })
                    .i
                    - tabs[p]
                        .eval(&Material {
                            metallic: m.metallic - h,
                            ..m
                        })
                        .i)
                    / (2.0 * h);
                let s = num_m.abs().max_element().max(e.dm.abs().max_element());
                assert!((num_m - e.dm).abs().max_element() <= 1e-2 * s + 1e-4);
            }
        }
        // Interpolation in roughness is the only approximation (measured
        // worst case ≈ 2.4e-3 relative, at the sharpest lobes).
        assert!(worst < 5e-3, "worst relative error {worst}");
    }
}
