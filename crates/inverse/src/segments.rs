//! Roughness and metallic per segment, before the per-pixel solve
//! (issue 19: "metals and roughness from highlights").
//!
//! Per pixel, a dielectric whose albedo is free matches any colour the
//! photo shows, so the per-pixel solve never has a reason to leave the
//! predicted roughness and metallic: a metal predicted as a dull
//! dielectric stays one. What tells a metal from a dielectric is how its
//! appearance *varies* over a surface of one material: a metal of one
//! colour shows the room it reflects, a dielectric of one colour shows
//! smooth shading with a highlight. So the image is cut into segments of
//! one material (connected pixels of similar predicted albedo, no depth
//! jump between neighbours), and each segment is scored with *one* albedo
//! for all its pixels under every (R, M) of a coarse grid on the frozen
//! tables (metals only up to roughness 0.5: a rougher one looks like a
//! coloured diffuse surface). Where the best candidate explains the segment clearly better
//! (by `margin`) than its anchor — the prediction's R and M — the anchor
//! moves there, and the per-pixel solve then refines around it.
//!
//! Everything is a pure function of its inputs: segments grow in scan
//! order, each segment's score is a serial sum, segments are scored in
//! parallel but independently, so the choice is the same for any thread
//! count.

use std::collections::VecDeque;

use glam::Vec3;
use matflow_render::Material;
use rayon::prelude::*;

use crate::loss::Target;
use crate::solve::{channel_loss, golden};
use crate::tables::PixelTable;

/// The label of a pixel in no segment (it sees the sky).
pub const NONE: u32 = u32::MAX;

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SegmentParams {
    /// Largest difference (in any channel) between a pixel's predicted
    /// albedo and the mean of the segment it joins.
    pub albedo_tolerance: f32,
    /// Largest jump of the distance to the camera between neighbours, as
    /// a share of the nearer one.
    pub depth_tolerance: f32,
}

impl Default for SegmentParams {
    fn default() -> Self {
        SegmentParams {
            albedo_tolerance: 0.1,
            depth_tolerance: 0.05,
        }
    }
}

/// Segments of a `w`×`h` image (row-major): connected (4-neighbour)
/// pixels with a finite distance `dist`, no jump between neighbours and a
/// predicted albedo near their segment's mean, grown in scan order. Returns
/// each pixel's label ([`NONE`] for pixels without geometry) and the
/// number of segments.
pub fn segment(
    albedo: &[Vec3],
    dist: &[f32],
    w: usize,
    h: usize,
    p: &SegmentParams,
) -> (Vec<u32>, usize) {
    let n = w * h;
    assert!(
        albedo.len() == n && dist.len() == n,
        "segment: sizes differ"
    );
    let mut label = vec![NONE; n];
    let mut count = 0u32;
    let mut queue = VecDeque::new();
    let ok = |d: f32| d.is_finite() && d > 0.0;
    for seed in 0..n {
        if label[seed] != NONE || !ok(dist[seed]) {
            continue;
        }
        let id = count;
        count += 1;
        label[seed] = id;
        let mut sum = albedo[seed].as_dvec3();
        let mut members = 1.0f64;
        queue.push_back(seed);
        while let Some(q) = queue.pop_front() {
            let (x, y) = (q % w, q / w);
            let mut near = [None; 4];
            if x > 0 {
                near[0] = Some(q - 1);
            }
            if x + 1 < w {
                near[1] = Some(q + 1);
            }
            if y > 0 {
                near[2] = Some(q - w);
            }
            if y + 1 < h {
                near[3] = Some(q + w);
            }
            for r in near.into_iter().flatten() {
                if label[r] != NONE || !ok(dist[r]) {
                    continue;
                }
                let jump = (dist[r] - dist[q]).abs();
                if jump > p.depth_tolerance * dist[r].min(dist[q]) {
                    continue;
                }
                let mean = (sum / members).as_vec3();
                if (albedo[r] - mean).abs().max_element() > p.albedo_tolerance {
                    continue;
                }
                label[r] = id;
                sum += albedo[r].as_dvec3();
                members += 1.0;
                queue.push_back(r);
            }
        }
    }
    (label, count as usize)
}

#[derive(Clone, Debug, PartialEq)]
pub struct SearchParams {
    /// Segments with fewer pixels keep their anchor.
    pub min_pixels: usize,
    /// At most this many of a segment's pixels (evenly strided) score it.
    pub max_samples: usize,
    /// Relative loss decrease the best candidate needs over the anchor.
    pub margin: f64,
    /// The roughness values of the grid (each with metallic 0, and those
    /// up to `metal_max_roughness` also with metallic 1).
    pub roughness: Vec<f32>,
    /// Roughest metal the search may choose. A metal is told from a
    /// dielectric by the sharp reflections and tinted highlights it shows;
    /// a rough one shows neither, and explains a photo as well as a
    /// coloured diffuse surface does, so it is left to the prediction.
    pub metal_max_roughness: f32,
}

impl SearchParams {
    /// The default grid from `min_roughness` (the roughness the frozen
    /// directions still resolve) to 1.
    pub fn new(min_roughness: f32) -> SearchParams {
        let lo = min_roughness.clamp(0.05, 0.5);
        let mut roughness = vec![lo];
        for r in [0.3f32, 0.45, 0.6, 0.8, 1.0] {
            if r > lo + 0.05 {
                roughness.push(r);
            }
        }
        SearchParams {
            min_pixels: 256,
            max_samples: 1024,
            margin: 0.1,
            roughness,
            metal_max_roughness: 0.5,
        }
    }
}

/// What the search found for one segment.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SegmentChoice {
    pub label: u32,
    pub pixels: usize,
    pub roughness: f32,
    pub metallic: f32,
    /// The segment's loss (mean per scored pixel and channel) with one
    /// albedo, at the best candidate and at the anchor.
    pub loss: f64,
    pub anchor_loss: f64,
    /// Whether the anchor moved to the candidate.
    pub moved: bool,
}

/// Mean loss per pixel and channel of the pixels `pix` with one shared
/// albedo (the best in [0, 1] per channel) and each pixel's roughness and
/// metallic from `rm`, exposure `k`.
fn shared_albedo_loss(
    tables: &[PixelTable],
    target: &Target,
    pix: &[usize],
    rm: impl Fn(usize) -> (f32, f32),
    k: f32,
) -> f64 {
    // Each pixel is affine in the albedo for fixed R, M: I = P + A ⊙ Q.
    let pq: Vec<(Vec3, Vec3)> = pix
        .iter()
        .map(|&p| {
            let (roughness, metallic) = rm(p);
            let m = Material {
                albedo: Vec3::splat(0.5),
                roughness,
                metallic,
            };
            let e = tables[p].eval(&m);
            (e.i - m.albedo * e.da, e.da)
        })
        .collect();
    let channel = |c: usize, a: f32| -> f64 {
        pix.iter()
            .zip(&pq)
            .map(|(&p, (pp, q))| {
                let i = k * (pp[c] + a * q[c]);
                let v = channel_loss(i, target.gamma[p][c], target.saturated[p][c], 1.0);
                if v.is_finite() {
                    v as f64
                } else {
                    1.0
                }
            })
            .sum()
    };
    let mut total = 0.0;
    for c in 0..3 {
        let a = golden(0.0, 1.0, 16, |a| channel(c, a) as f32);
        total += channel(c, a);
    }
    total / (3 * pix.len()).max(1) as f64
}

/// Scores every segment of `labels` (with `count` segments) on the tables
/// under the grid of `p`, against the anchor materials `anchor`, at
/// exposure `k`; one choice per segment large enough, in label order.
pub fn search_rm(
    tables: &[PixelTable],
    target: &Target,
    labels: &[u32],
    count: usize,
    anchor: &[Material],
    k: f32,
    p: &SearchParams,
) -> Vec<SegmentChoice> {
    let mut members: Vec<Vec<usize>> = vec![Vec::new(); count];
    for (i, &l) in labels.iter().enumerate() {
        if l != NONE {
            members[l as usize].push(i);
        }
    }
    let candidates: Vec<(f32, f32)> = [0.0f32, 1.0]
        .iter()
        .flat_map(|&m| p.roughness.iter().map(move |&r| (r, m)))
        .filter(|&(r, m)| m == 0.0 || r <= p.metal_max_roughness)
        .collect();
    members
        .par_iter()
        .enumerate()
        .filter(|(_, px)| px.len() >= p.min_pixels.max(1))
        .map(|(l, px)| {
            let stride = px.len().div_ceil(p.max_samples.max(1));
            let pix: Vec<usize> = px.iter().copied().step_by(stride.max(1)).collect();
            let anchor_loss = shared_albedo_loss(
                tables,
                target,
                &pix,
                |q| (anchor[q].roughness, anchor[q].metallic),
                k,
            );
            let mut best = (f64::INFINITY, 0.0, 0.0);
            for &(r, m) in &candidates {
                let v = shared_albedo_loss(tables, target, &pix, |_| (r, m), k);
                if v < best.0 {
                    best = (v, r, m);
                }
            }
            let moved = best.0 < (1.0 - p.margin) * anchor_loss;
            SegmentChoice {
                label: l as u32,
                pixels: px.len(),
                roughness: best.1,
                metallic: best.2,
                loss: best.0,
                anchor_loss,
                moved,
            }
        })
        .collect()
}

/// Moves the anchor (and the starting materials) of every segment whose
/// choice moved to that choice's roughness and metallic; returns the
/// pixels moved.
pub fn apply(
    choices: &[SegmentChoice],
    labels: &[u32],
    anchor: &mut [Material],
    start: &mut [Material],
) -> usize {
    let mut to: Vec<Option<(f32, f32)>> = Vec::new();
    for c in choices.iter().filter(|c| c.moved) {
        let l = c.label as usize;
        if to.len() <= l {
            to.resize(l + 1, None);
        }
        to[l] = Some((c.roughness, c.metallic));
    }
    let mut moved = 0;
    for (i, &l) in labels.iter().enumerate() {
        if let Some(&Some((r, m))) = to.get(l as usize) {
            for x in [&mut anchor[i], &mut start[i]] {
                x.roughness = r;
                x.metallic = m;
            }
            moved += 1;
        }
    }
    moved
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testutil::table_problem;

    fn labels_of(albedo: &[Vec3], dist: &[f32], w: usize, h: usize) -> (Vec<u32>, usize) {
        segment(albedo, dist, w, h, &SegmentParams::default())
    }

    #[test]
    fn segments_follow_albedo_and_depth_and_leave_the_sky_out() {
        let (w, h) = (16, 8);
        // Left half red, right half blue; the top row sees the sky.
        let albedo: Vec<Vec3> = (0..w * h)
            .map(|i| {
                if i % w < 8 {
                    Vec3::new(0.8, 0.1, 0.1)
                } else {
                    Vec3::new(0.1, 0.1, 0.8)
                }
            })
            .collect();
        let mut dist = vec![2.0f32; w * h];
        for d in dist.iter_mut().take(w) {
            *d = f32::INFINITY;
        }
        let (l, n) = labels_of(&albedo, &dist, w, h);
        assert_eq!(n, 2);
        assert!(l[..w].iter().all(|&x| x == NONE));
        assert!((w..w * h).all(|i| l[i] == if i % w < 8 { 0 } else { 1 }));
        // One albedo, but the lower half 20 % farther: two segments.
        let grey = vec![Vec3::splat(0.5); w * h];
        let step: Vec<f32> = (0..w * h)
            .map(|i| if i / w < 4 { 2.0 } else { 2.4 })
            .collect();
        let (l, n) = labels_of(&grey, &step, w, h);
        assert_eq!(n, 2);
        assert_ne!(l[0], l[w * h - 1]);
        // A smooth ramp of albedo (a blurred edge, 1/40 per pixel) does
        // not join its ends: pixels are held to the segment's mean, not
        // to their neighbour.
        let ramp: Vec<Vec3> = (0..40 * 2)
            .map(|i| Vec3::splat((i % 40) as f32 / 40.0))
            .collect();
        let (l, n) = labels_of(&ramp, &[1.0; 80], 40, 2);
        assert!(n >= 4, "{n}");
        assert_ne!(l[0], l[39]);
    }

    /// Known answer: the target is the tables' own image with a block of
    /// one gold-coloured metal (R 0.3) painted into a room; from the
    /// photo's anchor (R 0.7, M 0.05 everywhere, true albedo) the search
    /// moves the block to metal at R 0.3, keeps a block of one
    /// dielectric whose anchor is its truth, does not call a rough (R 0.8)
    /// metal block a metal, and never moves a segment to a worse loss. The same choice on 1 and 2 threads.
    #[test]
    fn a_metal_block_is_found_and_a_true_dielectric_is_kept() {
        let n = 32;
        let mut pb = table_problem(11, n);
        let gold = Vec3::new(0.95, 0.7, 0.3);
        let white = Vec3::splat(0.92);
        let metal = |i: usize| (8..20).contains(&(i % n)) && (12..24).contains(&(i / n));
        let plain = |i: usize| (22..30).contains(&(i % n)) && (2..10).contains(&(i / n));
        let rough = |i: usize| (1..9).contains(&(i % n)) && (24..31).contains(&(i / n));
        for i in 0..n * n {
            if metal(i) {
                pb.truth[i] = Material {
                    albedo: gold,
                    roughness: 0.3,
                    metallic: 1.0,
                };
            } else if rough(i) {
                pb.truth[i] = Material {
                    albedo: Vec3::new(0.3, 0.5, 0.9),
                    roughness: 0.8,
                    metallic: 1.0,
                };
            } else if plain(i) {
                pb.truth[i] = Material {
                    albedo: white,
                    roughness: 0.7,
                    metallic: 0.05,
                };
            }
        }
        let image: Vec<Vec3> = pb
            .tables
            .iter()
            .zip(&pb.truth)
            .map(|(t, m)| t.eval(m).i)
            .collect();
        let target = Target::new(n, n, &image);
        let mut anchor: Vec<Material> = pb
            .truth
            .iter()
            .map(|m| Material {
                albedo: m.albedo,
                roughness: 0.7,
                metallic: 0.05,
            })
            .collect();
        let albedo: Vec<Vec3> = anchor.iter().map(|m| m.albedo).collect();
        let (labels, count) = segment(&albedo, &vec![1.0; n * n], n, n, &SegmentParams::default());
        let p = SearchParams {
            min_pixels: 32,
            ..SearchParams::new(0.2)
        };
        let run = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| search_rm(&pb.tables, &target, &labels, count, &anchor, 1.0, &p))
        };
        let choices = run(2);
        assert_eq!(choices, run(1));
        let of = |i: usize| {
            choices
                .iter()
                .find(|c| c.label == labels[i])
                .expect("scored")
        };
        let m = of(12 * n + 10);
        assert!(m.moved && m.metallic == 1.0 && m.roughness == 0.3, "{m:?}");
        assert!(m.pixels >= 12 * 12 && m.loss < 0.2 * m.anchor_loss, "{m:?}");
        // A rough metal looks like a coloured diffuse surface: never
        // chosen as metal.
        let r = of(27 * n + 4);
        assert!(r.metallic == 0.0, "{r:?}");
        let d = of(4 * n + 24);
        assert!(!d.moved, "{d:?}");
        assert!(d.anchor_loss < 1e-3, "{d:?}");
        for c in &choices {
            assert!(
                !c.moved || c.loss < (1.0 - p.margin) * c.anchor_loss,
                "{c:?}"
            );
        }
        let mut start = anchor.clone();
        let moved = apply(&choices, &labels, &mut anchor, &mut start);
        assert!(moved >= 144);
        assert!((0..n * n)
            .filter(|&i| metal(i))
            .all(|i| anchor[i].metallic == 1.0 && start[i].roughness == 0.3));
        assert!((0..n * n)
            .filter(|&i| plain(i))
            .all(|i| anchor[i].metallic == 0.05));
    }
}
