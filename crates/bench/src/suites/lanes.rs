//! `matflow-bench lanes`: the renderer's BRDF kernel written with three
//! SIMD routes, timed on the same shading points.
//!
//! The kernel is [`bsdf::eval_pdf_lanes`] (GGX + Disney diffuse: f·cos and
//! the sampling pdf of both lobes), the one the renderer runs over each
//! wavefront step's depth-mesh vertices. It is written three ways with the
//! same operations in the same order (no fused multiply-add):
//!
//! 1. matflow's lane arrays (`matflow_render::lanes`), compiled under
//!    `#[target_feature]` and picked at run time by [`lane_kernel!`]
//!    (AVX2: 8 lanes here);
//! 2. `wide::f32x8`, whose instruction set is fixed when the crate is
//!    compiled (`cfg(target_feature)`): in a portable build that is two
//!    SSE halves, whatever the CPU;
//! 3. `pulp`'s `Simd` trait, dispatched at run time (`Arch::dispatch`:
//!    AVX2+FMA here, 8 lanes), written with macros: closures are functions
//!    of their own and do not inherit the dispatched instruction set (with
//!    closures for its operations it ran 9× slower).
//!
//! Every route must give the same bits as the renderer's kernel (checked
//! before timing), so the comparison is of speed alone.

use std::f32::consts::PI;
use std::time::Instant;

use anyhow::{ensure, Result};
use clap::Args;
use matflow_render::bsdf::{eval_pdf_lanes, MaterialLanes, MIN_ROUGHNESS};
use matflow_render::lanes::{F, V3};
use pulp::{Arch, Simd, WithSimd};
use wide::{f32x8, CmpGt, CmpLe, CmpLt};

use crate::harness::median;

#[derive(Args)]
pub struct BenchLanesArgs {
    /// Shading points per pass (a multiple of 16; the default's arrays,
    /// 300 KB, stay in the L2 cache, so the kernel's arithmetic is timed).
    #[arg(long, default_value_t = 4096)]
    pub points: usize,
    /// Passes over the points per timing.
    #[arg(long, default_value_t = 2000)]
    pub passes: usize,
    /// Timings per route (interleaved); medians are reported.
    #[arg(long, default_value_t = 5)]
    pub runs: usize,
}

/// Shading points as arrays: normal, view, light, albedo, roughness,
/// metallic.
struct Points {
    n: [Vec<f32>; 3],
    v: [Vec<f32>; 3],
    l: [Vec<f32>; 3],
    albedo: [Vec<f32>; 3],
    roughness: Vec<f32>,
    metallic: Vec<f32>,
}

/// f·cos (three arrays) and pdf per point.
#[derive(Clone, PartialEq)]
struct Values {
    f: [Vec<f32>; 3],
    pdf: Vec<f32>,
}

impl Values {
    fn new(n: usize) -> Values {
        Values {
            f: std::array::from_fn(|_| vec![0.0; n]),
            pdf: vec![0.0; n],
        }
    }
}

/// Unit vectors, a fifth of the lights below the surface.
fn points(count: usize) -> Points {
    let mut s = 0x9e37_79b9_7f4a_7c15u64;
    let mut u = move || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        (s >> 40) as f32 / (1u64 << 24) as f32
    };
    let mut unit = |up: bool| {
        let (a, b) = (u() * 2.0 * PI, u());
        let z = if up { b } else { 2.0 * b - 1.0 };
        let r = (1.0 - z * z).max(0.0).sqrt();
        [r * a.cos(), r * a.sin(), z]
    };
    let mut p = Points {
        n: Default::default(),
        v: Default::default(),
        l: Default::default(),
        albedo: Default::default(),
        roughness: Vec::new(),
        metallic: Vec::new(),
    };
    for _ in 0..count {
        // Normal along +z, view above it, light anywhere.
        let (n, v, l) = ([0.0, 0.0, 1.0], unit(true), unit(false));
        for k in 0..3 {
            p.n[k].push(n[k]);
            p.v[k].push(v[k]);
            p.l[k].push(l[k]);
        }
    }
    let mut rest = |n: usize| (0..n).map(|_| u()).collect::<Vec<f32>>();
    p.albedo = [rest(count), rest(count), rest(count)];
    p.roughness = rest(count);
    p.metallic = rest(count);
    p
}

// --- 1. matflow's lanes ----------------------------------------------------

#[inline(always)]
fn eval_matflow<const W: usize>(p: &Points, out: &mut Values) {
    let count = p.roughness.len();
    for i in (0..count).step_by(W) {
        let f = |a: &[f32]| F::<W>(a[i..i + W].try_into().unwrap());
        let v3 = |a: &[Vec<f32>; 3]| V3::new(f(&a[0]), f(&a[1]), f(&a[2]));
        let m = MaterialLanes {
            albedo: v3(&p.albedo),
            roughness: f(&p.roughness),
            metallic: f(&p.metallic),
        };
        let (fc, pdf) = eval_pdf_lanes(&m, v3(&p.n), v3(&p.v), v3(&p.l));
        out.f[0][i..i + W].copy_from_slice(&fc.x.0);
        out.f[1][i..i + W].copy_from_slice(&fc.y.0);
        out.f[2][i..i + W].copy_from_slice(&fc.z.0);
        out.pdf[i..i + W].copy_from_slice(&pdf.0);
    }
}

matflow_render::lane_kernel!(fn matflow_now = eval_matflow(p: &Points, out: &mut Values));

// --- 2. wide ---------------------------------------------------------------

fn eval_wide(p: &Points, out: &mut Values) {
    type X = f32x8;
    let s = X::splat;
    let count = p.roughness.len();
    for i in (0..count).step_by(8) {
        let ld = |a: &[f32]| X::from(<[f32; 8]>::try_from(&a[i..i + 8]).unwrap());
        let v3 = |a: &[Vec<f32>; 3]| [ld(&a[0]), ld(&a[1]), ld(&a[2])];
        let dot = |a: [X; 3], b: [X; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
        let (n, v, l) = (v3(&p.n), v3(&p.v), v3(&p.l));
        let (albedo, rough, metal) = (v3(&p.albedo), ld(&p.roughness), ld(&p.metallic));
        let pow5 = |x: X| {
            let x2 = x * x;
            x2 * x2 * x
        };
        let nol = dot(n, l).max(s(0.0));
        let hs = [l[0] + v[0], l[1] + v[1], l[2] + v[2]];
        let r = s(1.0) / dot(hs, hs).sqrt();
        let ok = r.cmp_lt(s(f32::INFINITY)) & r.cmp_gt(s(0.0));
        let h = hs.map(|c| ok.blend(c * r, s(0.0)));
        let voh = dot(v, h).max(s(0.0));
        let noh = dot(n, h).max(s(0.0));
        let r = rough.max(s(MIN_ROUGHNESS)).min(s(1.0));
        let alpha = r * r;
        let alpha2 = alpha * alpha;
        let t = noh * noh * (alpha2 - s(1.0)) + s(1.0) + s(1e-6);
        let d = alpha2 / (s(PI) * t * t);
        let pdf = s(0.5) * d * noh / (s(4.0) * voh.max(s(1e-6))) + s(0.5) * nol / s(PI);
        let nov = dot(n, v).max(s(0.0));
        let k = (r + s(1.0)) * (r + s(1.0)) / s(8.0);
        let vis =
            s(1.0) / ((nov * (s(1.0) - k) + k + s(1e-6)) * (nol * (s(1.0) - k) + k + s(1e-6)));
        let f0_base = s(0.04) * (s(1.0) - metal);
        let schlick = pow5(s(1.0) - voh);
        let fd90 = s(0.5) + s(2.0) * r * voh * voh;
        let fd = |x: X| s(1.0) + (fd90 - s(1.0)) * pow5(s(1.0) - x);
        let diffuse = (s(1.0) - metal) / s(PI) * fd(nov) * fd(nol) * nol;
        let spec = d * vis / s(4.0) * nol;
        let below = nol.cmp_le(s(0.0));
        for (a, o) in albedo.iter().zip(&mut out.f) {
            let f0 = f0_base + *a * metal;
            let fr = f0 + (s(1.0) - f0) * schlick;
            let fc = below.blend(s(0.0), *a * diffuse + fr * spec);
            o[i..i + 8].copy_from_slice(&fc.to_array());
        }
        out.pdf[i..i + 8].copy_from_slice(&pdf.to_array());
    }
}

// --- 3. pulp ---------------------------------------------------------------

struct PulpEval<'a> {
    p: &'a Points,
    out: &'a mut Values,
}

impl WithSimd for PulpEval<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: Simd>(self, simd: S) -> Self::Output {
        let (p, out) = (self.p, self.out);
        fn sp<S: Simd>(a: &[f32]) -> &[S::f32s] {
            S::as_simd_f32s(a).0
        }
        let (n, v, l) = (
            p.n.each_ref().map(|a| sp::<S>(a)),
            p.v.each_ref().map(|a| sp::<S>(a)),
            p.l.each_ref().map(|a| sp::<S>(a)),
        );
        let albedo = p.albedo.each_ref().map(|a| sp::<S>(a));
        let (rough, metal) = (sp::<S>(&p.roughness), sp::<S>(&p.metallic));
        let [f0s, f1s, f2s] = &mut out.f;
        let fout = [
            S::as_mut_simd_f32s(f0s).0,
            S::as_mut_simd_f32s(f1s).0,
            S::as_mut_simd_f32s(f2s).0,
        ];
        let [fo0, fo1, fo2] = fout;
        let pout = S::as_mut_simd_f32s(&mut out.pdf).0;
        // Macros, not closures: a closure is a function of its own, which
        // does not inherit the dispatched instruction set.
        macro_rules! s {
            ($x:expr) => {
                simd.splat_f32s($x)
            };
        }
        macro_rules! op {
            ($f:ident, $a:expr, $b:expr) => {
                simd.$f($a, $b)
            };
        }
        macro_rules! dot {
            ($a:expr, $b:expr) => {
                op!(
                    add_f32s,
                    op!(
                        add_f32s,
                        op!(mul_f32s, $a[0], $b[0]),
                        op!(mul_f32s, $a[1], $b[1])
                    ),
                    op!(mul_f32s, $a[2], $b[2])
                )
            };
        }
        macro_rules! pow5 {
            ($x:expr) => {{
                let x = $x;
                let x2 = op!(mul_f32s, x, x);
                op!(mul_f32s, op!(mul_f32s, x2, x2), x)
            }};
        }
        let one = s!(1.0);
        for i in 0..pout.len() {
            let (n, v, l) = (n.map(|a| a[i]), v.map(|a| a[i]), l.map(|a| a[i]));
            let nol = op!(max_f32s, dot!(n, l), s!(0.0));
            let hs = [
                op!(add_f32s, l[0], v[0]),
                op!(add_f32s, l[1], v[1]),
                op!(add_f32s, l[2], v[2]),
            ];
            let r = op!(div_f32s, one, simd.sqrt_f32s(dot!(hs, hs)));
            let ok = simd.and_m32s(
                simd.less_than_f32s(r, s!(f32::INFINITY)),
                simd.greater_than_f32s(r, s!(0.0)),
            );
            let h = [
                simd.select_f32s(ok, op!(mul_f32s, hs[0], r), s!(0.0)),
                simd.select_f32s(ok, op!(mul_f32s, hs[1], r), s!(0.0)),
                simd.select_f32s(ok, op!(mul_f32s, hs[2], r), s!(0.0)),
            ];
            let voh = op!(max_f32s, dot!(v, h), s!(0.0));
            let noh = op!(max_f32s, dot!(n, h), s!(0.0));
            let r = op!(min_f32s, op!(max_f32s, rough[i], s!(MIN_ROUGHNESS)), one);
            let alpha = op!(mul_f32s, r, r);
            let alpha2 = op!(mul_f32s, alpha, alpha);
            let t = op!(
                add_f32s,
                op!(
                    add_f32s,
                    op!(
                        mul_f32s,
                        op!(mul_f32s, noh, noh),
                        op!(sub_f32s, alpha2, one)
                    ),
                    one
                ),
                s!(1e-6)
            );
            let d = op!(div_f32s, alpha2, op!(mul_f32s, op!(mul_f32s, s!(PI), t), t));
            let pdf = op!(
                add_f32s,
                op!(
                    div_f32s,
                    op!(mul_f32s, op!(mul_f32s, s!(0.5), d), noh),
                    op!(mul_f32s, s!(4.0), op!(max_f32s, voh, s!(1e-6)))
                ),
                op!(div_f32s, op!(mul_f32s, s!(0.5), nol), s!(PI))
            );
            let nov = op!(max_f32s, dot!(n, v), s!(0.0));
            let r1 = op!(add_f32s, r, one);
            let k = op!(div_f32s, op!(mul_f32s, r1, r1), s!(8.0));
            let av = op!(
                add_f32s,
                op!(add_f32s, op!(mul_f32s, nov, op!(sub_f32s, one, k)), k),
                s!(1e-6)
            );
            let al = op!(
                add_f32s,
                op!(add_f32s, op!(mul_f32s, nol, op!(sub_f32s, one, k)), k),
                s!(1e-6)
            );
            let vis = op!(div_f32s, one, op!(mul_f32s, av, al));
            let m = metal[i];
            let f0_base = op!(mul_f32s, s!(0.04), op!(sub_f32s, one, m));
            let schlick = pow5!(op!(sub_f32s, one, voh));
            let fd90 = op!(
                add_f32s,
                s!(0.5),
                op!(mul_f32s, op!(mul_f32s, op!(mul_f32s, s!(2.0), r), voh), voh)
            );
            let fd90m1 = op!(sub_f32s, fd90, one);
            let fdv = op!(
                add_f32s,
                one,
                op!(mul_f32s, fd90m1, pow5!(op!(sub_f32s, one, nov)))
            );
            let fdl = op!(
                add_f32s,
                one,
                op!(mul_f32s, fd90m1, pow5!(op!(sub_f32s, one, nol)))
            );
            let diffuse = op!(
                mul_f32s,
                op!(
                    mul_f32s,
                    op!(mul_f32s, op!(div_f32s, op!(sub_f32s, one, m), s!(PI)), fdv),
                    fdl
                ),
                nol
            );
            let spec = op!(mul_f32s, op!(div_f32s, op!(mul_f32s, d, vis), s!(4.0)), nol);
            let below = simd.less_than_or_equal_f32s(nol, s!(0.0));
            let mut fc = [s!(0.0); 3];
            for (c, o) in fc.iter_mut().enumerate() {
                let a = albedo[c][i];
                let f0 = op!(add_f32s, f0_base, op!(mul_f32s, a, m));
                let fr = op!(add_f32s, f0, op!(mul_f32s, op!(sub_f32s, one, f0), schlick));
                let f = op!(add_f32s, op!(mul_f32s, a, diffuse), op!(mul_f32s, fr, spec));
                *o = simd.select_f32s(below, s!(0.0), f);
            }
            fo0[i] = fc[0];
            fo1[i] = fc[1];
            fo2[i] = fc[2];
            pout[i] = pdf;
        }
    }
}

fn eval_pulp(p: &Points, out: &mut Values) {
    Arch::new().dispatch(PulpEval { p, out });
}

// ---------------------------------------------------------------------------

pub fn bench_lanes(a: BenchLanesArgs) -> Result<()> {
    ensure!(
        a.points > 0 && a.points.is_multiple_of(16),
        "--points must be a positive multiple of 16"
    );
    let p = points(a.points);
    type Route = fn(&Points, &mut Values);
    let routes: [(&str, Route); 3] = [
        ("matflow lanes (lane_kernel!, run-time width)", matflow_now),
        ("wide::f32x8 (compile-time instruction set)", eval_wide),
        ("pulp (Arch::dispatch, run-time)", eval_pulp),
    ];
    let mut want = Values::new(a.points);
    matflow_now(&p, &mut want);
    for (name, f) in &routes[1..] {
        let mut got = Values::new(a.points);
        f(&p, &mut got);
        let same = got
            .f
            .iter()
            .chain([&got.pdf])
            .zip(want.f.iter().chain([&want.pdf]))
            .all(|(g, w)| g.iter().zip(w).all(|(x, y)| x.to_bits() == y.to_bits()));
        ensure!(same, "{name} does not give the renderer's bits");
    }
    outln!(
        "bench lanes: BRDF f·cos and pdf (bsdf::eval_pdf_lanes) at {} points × {} passes, \
         1 thread, medians of {}; matflow's lane width here: {}; same bits on every route",
        a.points,
        a.passes,
        a.runs,
        matflow_render::lanes::width()
    );
    let mut times = vec![Vec::new(); routes.len()];
    let mut out = Values::new(a.points);
    for _ in 0..a.runs.max(1) {
        for (k, (_, f)) in routes.iter().enumerate() {
            let t = Instant::now();
            for _ in 0..a.passes {
                f(std::hint::black_box(&p), &mut out);
            }
            times[k].push(t.elapsed().as_secs_f64() / (a.passes * a.points) as f64);
        }
    }
    let base = median(times[0].clone());
    outln!("| route | ns per evaluation | relative to matflow's lanes |\n|---|---|---|");
    for ((name, _), t) in routes.iter().zip(times) {
        let t = median(t);
        outln!("| {name} | {:.2} | {:.2}× |", t * 1e9, t / base);
    }
    Ok(())
}
