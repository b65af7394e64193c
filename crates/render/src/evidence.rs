//! Which geometry past the frame the photo supports, when the materials
//! and the light are given.
//!
//! Every completion of a view ([`matflow_geom::complete`]) is a
//! hypothesis about what the photo does not show. With the light and the
//! materials known, each hypothesis predicts the photo: a closed room
//! shuts out the sky an open room is lit by, an extended floor hides the
//! ground below a stage. [`choose_completion`] renders every hypothesis
//! cheaply (a few samples per pixel in two independent halves), compares
//! each with the photo over blocks of pixels, and takes the least-assuming
//! hypothesis whose agreement is within [`EvidenceOptions::tolerance_db`]
//! of the best's.
//!
//! The error of a hypothesis is estimated without its own noise: for two
//! independent halves A, B of its samples, E[(A − P)(B − P)] = (μ − P)²,
//! the squared difference of its noise-free render μ from the photo P. The
//! comparison is made after gamma encoding (as every PSNR matflow reports)
//! on the means of `block`×`block` pixel blocks, and over the blocks where
//! the hypotheses' renders differ (elsewhere they all score alike).

use matflow_geom::{CompleteParams, MeshParams, RAISE_SEEN_WALLS, RAISE_WALLS_HIGH};
use matflow_scene::color::linear_to_gamma;
use matflow_scene::{GrayImage, MaterialMaps, RgbImage};

use crate::{render, EnvMap, PixelFilter, RenderError, RenderOptions};

/// A geometry past the frame to be tested: its name and its completion
/// (`None`: the depth mesh alone).
#[derive(Clone, Debug)]
pub struct Hypothesis {
    pub name: String,
    pub params: Option<CompleteParams>,
}

/// The completions of [`matflow_geom::COMPLETE_MODES`] as hypotheses, from
/// the least assuming (none) to the most (closed).
pub fn completion_hypotheses() -> Vec<Hypothesis> {
    matflow_geom::COMPLETE_MODES
        .iter()
        .map(|m| Hypothesis {
            name: m.to_string(),
            params: CompleteParams::for_mode(m),
        })
        .collect()
}

/// How [`choose_completion`] renders and decides.
#[derive(Clone, Debug)]
pub struct EvidenceOptions {
    /// Samples per pixel of each of the two halves.
    pub spp_half: u32,
    /// Side of the pixel blocks compared.
    pub block: usize,
    pub max_depth: u32,
    pub filter: PixelFilter,
    pub seed: u64,
    /// A hypothesis that assumes less is taken while its PSNR over the
    /// blocks where the hypotheses differ is within this of the best's.
    pub tolerance_db: f64,
    /// Blocks whose hypotheses' renders spread by less than this (gamma
    /// encoded, mean over the channels) do not tell them apart.
    pub min_spread: f32,
    /// Guide the light samples by the sky's visibility
    /// ([`crate::RenderScene::set_light_guide`]); at a few samples per
    /// pixel building the guide costs more than it saves.
    pub light_guide: bool,
    /// Lamps that light the scene besides the envmap (the photo's own).
    pub lamps: Vec<crate::Lamp>,
}

impl Default for EvidenceOptions {
    fn default() -> Self {
        EvidenceOptions {
            spp_half: 2,
            block: 8,
            max_depth: 4,
            filter: PixelFilter::default(),
            seed: 0x0e71_d3c3,
            tolerance_db: 0.5,
            min_spread: 0.02,
            light_guide: false,
            lamps: Vec::new(),
        }
    }
}

/// One hypothesis's agreement with the photo.
#[derive(Clone, Debug, PartialEq)]
pub struct HypothesisScore {
    pub name: String,
    /// PSNR (gamma 2.2, noise removed) over the blocks where the
    /// hypotheses differ.
    pub psnr_differing: f64,
    /// The same over every block.
    pub psnr_all: f64,
    /// The factor on the light that brings the render closest to the
    /// photo over the blocks where the hypotheses differ (least squares,
    /// linear): how much more (or less) light the hypothesis needs.
    pub gain: f64,
    /// The PSNR over those blocks with the render times that gain.
    pub psnr_gained: f64,
    /// Another hypothesis built the same mesh: its score is reused.
    pub same_as: Option<String>,
    pub seconds: f64,
}

/// What the photo says of the hypotheses.
#[derive(Clone, Debug, PartialEq)]
pub struct CompletionChoice {
    /// Index of the hypothesis taken.
    pub chosen: usize,
    pub scores: Vec<HypothesisScore>,
    /// Share of the blocks where the hypotheses' renders differ.
    pub differing: f64,
    /// The taken hypothesis's PSNR over the differing blocks less the best
    /// of the others' (negative when a more assuming one scored higher,
    /// within the tolerance).
    pub margin_db: f64,
    /// Whether the photo told them apart: false when they render alike, or
    /// the taken one was taken as the least assuming within the tolerance
    /// of one that scored higher.
    pub decisive: bool,
    /// In words.
    pub reason: String,
    pub seconds: f64,
}

/// A render's two independent halves, as block means.
type Halves = [Vec<[f32; 3]>; 2];

/// Block means of `img`, linear, per channel, row by row.
fn block_means(img: &RgbImage, block: usize) -> Vec<[f32; 3]> {
    let bw = img.width.div_ceil(block);
    let mut sum = vec![[0.0f64; 4]; bw * img.height.div_ceil(block)];
    for y in 0..img.height {
        for x in 0..img.width {
            let v = img.get(x, y);
            let s = &mut sum[(y / block) * bw + x / block];
            for c in 0..3 {
                // Non-finite input counts as black (a stage never emits
                // it; a hostile photo might).
                s[c] += if v[c].is_finite() { v[c] as f64 } else { 0.0 };
            }
            s[3] += 1.0;
        }
    }
    sum.iter()
        .map(|s| {
            let n = s[3].max(1.0);
            [0, 1, 2].map(|c| (s[c] / n) as f32)
        })
        .collect()
}

/// Mean of the noise-free squared error estimates over the blocks where
/// `mask` holds (all when `None`), gamma encoded, of the halves (linear
/// block means) times `gain`, as a PSNR; 100 dB when nothing is left.
fn psnr_over(
    halves: &[Vec<[f32; 3]>; 2],
    photo: &[[f32; 3]],
    mask: Option<&[bool]>,
    gain: f32,
) -> f64 {
    let mut sum = 0.0f64;
    let mut n = 0usize;
    for (i, p) in photo.iter().enumerate() {
        if mask.is_some_and(|m| !m[i]) {
            continue;
        }
        for c in 0..3 {
            let pg = linear_to_gamma(p[c]);
            let a = (linear_to_gamma(gain * halves[0][i][c]) - pg) as f64;
            let b = (linear_to_gamma(gain * halves[1][i][c]) - pg) as f64;
            sum += a * b;
        }
        n += 3;
    }
    if n == 0 {
        return 100.0;
    }
    // The estimate is unbiased but can dip below zero where the error is
    // under the noise: no hypothesis explains a photo better than exactly.
    let mse = (sum / n as f64).max(1e-10);
    -10.0 * mse.log10()
}

/// The least-squares factor g on the render (linear block means, both
/// halves' product for the render's square so its noise does not pull g
/// down) that brings it closest to the photo over the masked blocks.
fn light_gain(halves: &[Vec<[f32; 3]>; 2], photo: &[[f32; 3]], mask: Option<&[bool]>) -> f64 {
    let (mut pr, mut rr) = (0.0f64, 0.0f64);
    for (i, p) in photo.iter().enumerate() {
        if mask.is_some_and(|m| !m[i]) {
            continue;
        }
        for c in 0..3 {
            let (a, b) = (halves[0][i][c] as f64, halves[1][i][c] as f64);
            pr += p[c] as f64 * 0.5 * (a + b);
            rr += a * b;
        }
    }
    if rr > 1e-20 && pr.is_finite() {
        (pr / rr).clamp(1e-6, 1e6)
    } else {
        1.0
    }
}

/// Renders every hypothesis on the view `depth` with `maps` under `env`,
/// compares each with `photo`, and takes the first hypothesis (they are
/// listed from the least assuming to the most) whose PSNR over the blocks
/// where they differ is within the tolerance of the best's.
pub fn choose_completion(
    depth: &GrayImage,
    maps: &MaterialMaps,
    env: &EnvMap,
    mesh_params: MeshParams,
    photo: &RgbImage,
    hypotheses: &[Hypothesis],
    opts: &EvidenceOptions,
) -> Result<CompletionChoice, RenderError> {
    let view = PhotoView {
        depth,
        maps,
        env,
        mesh_params,
        photo,
    };
    view.choose(hypotheses, opts, &mut Vec::new())
}

/// Meshes rendered already in one search (same view, same options), by
/// [`mesh_key`]: a hypothesis tested again (the room so far, in every
/// round) is not rendered again.
type Rendered = Vec<(u64, Halves)>;

/// [`choose_completion`] on `view`, taking the halves of meshes in `cache`
/// and adding those it renders.
fn choose_cached(
    view: &PhotoView,
    hypotheses: &[Hypothesis],
    opts: &EvidenceOptions,
    cache: &mut Rendered,
) -> Result<CompletionChoice, RenderError> {
    let PhotoView {
        depth,
        maps,
        env,
        mesh_params,
        photo,
    } = *view;
    let t_all = std::time::Instant::now();
    assert!(!hypotheses.is_empty(), "choose_completion: no hypothesis");
    let block = opts.block.max(1);
    let photo_blocks = block_means(photo, block);
    use rayon::prelude::*;
    if (depth.width, depth.height) != (photo.width, photo.height) {
        return Err(RenderError::MaterialSize {
            maps_width: photo.width,
            maps_height: photo.height,
            width: depth.width,
            height: depth.height,
        });
    }
    // The hypotheses a few at a time (as many as there are threads: a
    // mesh and its BVH are built mostly serially), each distinct mesh
    // rendered once: a hypothesis that builds a mesh listed before it
    // takes that one's halves.
    let mut halves: Vec<Halves> = Vec::with_capacity(hypotheses.len());
    let mut scores: Vec<HypothesisScore> = Vec::with_capacity(hypotheses.len());
    let mut keys: Vec<u64> = Vec::with_capacity(hypotheses.len());
    let chunk = rayon::current_num_threads().max(1);
    // The depth mesh is every hypothesis's own: built once, each
    // completion added to a copy.
    let t_mesh = std::time::Instant::now();
    let (cam, depth_mesh) = matflow_geom::mesh_for_view(depth, &mesh_params)?;
    let mesh_seconds = t_mesh.elapsed().as_secs_f64();
    for group in hypotheses.chunks(chunk) {
        let built: Vec<(matflow_scene::Camera, matflow_geom::TriMesh, f64)> = group
            .par_iter()
            .map(|h| {
                let t0 = std::time::Instant::now();
                let mut m = depth_mesh.mesh.clone();
                if let Some(p) = h.params.as_ref() {
                    matflow_geom::complete_beyond_frame(&mut m, depth, &cam, p);
                }
                Ok((cam, m, mesh_seconds + t0.elapsed().as_secs_f64()))
            })
            .collect::<Result<_, RenderError>>()?;
        // Earlier hypotheses, this group's included, are pushed below
        // before a later one needs their halves.
        let mut same = Vec::with_capacity(group.len());
        let mut cached: Vec<Option<Halves>> = Vec::with_capacity(group.len());
        for (_, m, _) in &built {
            let k = mesh_key(m);
            let s = keys.iter().position(|&o| o == k);
            cached.push(
                s.is_none()
                    .then(|| cache.iter().find(|(o, _)| *o == k).map(|(_, h)| h.clone()))
                    .flatten(),
            );
            same.push(s);
            keys.push(k);
        }
        let skip: Vec<bool> = (0..group.len())
            .map(|i| same[i].is_some() || cached[i].is_some())
            .collect();
        let rendered: Vec<Option<(Halves, f64)>> = built
            .into_par_iter()
            .zip(skip.par_iter())
            .map(|((cam, mesh, tb), &skip)| {
                if skip {
                    return Ok(None);
                }
                let t0 = std::time::Instant::now();
                let mut scene =
                    crate::RenderScene::new_guided(cam, mesh, maps, env.clone(), opts.light_guide)?;
                if !opts.lamps.is_empty() {
                    scene.set_lamps(opts.lamps.clone())?;
                }
                let half = |k: u64| {
                    let o = RenderOptions {
                        spp: opts.spp_half.max(1),
                        max_depth: opts.max_depth,
                        seed: opts.seed.wrapping_add(k),
                        filter: opts.filter,
                        ..Default::default()
                    };
                    block_means(&render(&scene, &o, &|_, _| {}).image, block)
                };
                Ok(Some(([half(0), half(1)], tb + t0.elapsed().as_secs_f64())))
            })
            .collect::<Result<_, RenderError>>()?;
        for (i, (h, r)) in group.iter().zip(rendered).enumerate() {
            let (pair, seconds) = match (r, same[i]) {
                (Some(r), _) => {
                    cache.push((keys[keys.len() - group.len() + i], r.0.clone()));
                    r
                }
                (None, Some(j)) => (halves[j].clone(), 0.0),
                (None, None) => (cached[i].take().unwrap_or_default(), 0.0),
            };
            halves.push(pair);
            scores.push(HypothesisScore {
                name: h.name.clone(),
                psnr_differing: 0.0,
                psnr_all: 0.0,
                gain: 1.0,
                psnr_gained: 0.0,
                same_as: same[i].map(|j| hypotheses[j].name.clone()),
                seconds,
            });
        }
    }
    // Where the hypotheses differ: the spread of their mean renders.
    let nb = photo_blocks.len();
    let mut differ = vec![false; nb];
    for (i, d) in differ.iter_mut().enumerate() {
        let mut lo = f32::INFINITY;
        let mut hi = f32::NEG_INFINITY;
        for hv in &halves {
            let m = (0..3)
                .map(|c| 0.5 * (linear_to_gamma(hv[0][i][c]) + linear_to_gamma(hv[1][i][c])))
                .sum::<f32>()
                / 3.0;
            lo = lo.min(m);
            hi = hi.max(m);
        }
        *d = hi - lo >= opts.min_spread;
    }
    let differing = differ.iter().filter(|&&d| d).count() as f64 / nb.max(1) as f64;
    let region = if differing > 0.0 {
        Some(&differ[..])
    } else {
        None
    };
    for (s, hv) in scores.iter_mut().zip(&halves) {
        s.psnr_differing = psnr_over(hv, &photo_blocks, Some(&differ), 1.0);
        s.psnr_all = psnr_over(hv, &photo_blocks, None, 1.0);
        s.gain = light_gain(hv, &photo_blocks, region);
        s.psnr_gained = psnr_over(hv, &photo_blocks, region, s.gain as f32);
    }
    let best = best_scored(&scores);
    let (chosen, decisive, reason) = if differing == 0.0 {
        (
            0,
            false,
            "the hypotheses render alike: no evidence, the least assuming taken".to_string(),
        )
    } else {
        let top = scores[best].psnr_differing;
        let c = (0..scores.len())
            .find(|&i| scores[i].psnr_differing >= top - opts.tolerance_db)
            .unwrap_or(best);
        if c == best {
            (c, true, "it explains the photo best".to_string())
        } else {
            (
                c,
                false,
                format!(
                    "within {:.1} dB of {} (the best), and assumes less",
                    opts.tolerance_db, scores[best].name
                ),
            )
        }
    };
    Ok(CompletionChoice {
        chosen,
        margin_db: margin_db(&scores, chosen),
        scores,
        differing,
        decisive,
        reason,
        seconds: t_all.elapsed().as_secs_f64(),
    })
}

/// The score `chosen`'s PSNR where the hypotheses differ less the best
/// of the others' (hypotheses that reuse another's score aside); 0 when
/// there is no other.
fn margin_db(scores: &[HypothesisScore], chosen: usize) -> f64 {
    let others = (0..scores.len())
        .filter(|&i| i != chosen && scores[i].same_as.is_none())
        .map(|i| scores[i].psnr_differing)
        .fold(f64::NEG_INFINITY, f64::max);
    if others.is_finite() {
        scores[chosen].psnr_differing - others
    } else {
        0.0
    }
}

/// The index of the score with the highest PSNR where the hypotheses
/// differ (the first on ties; 0 when there is none).
fn best_scored(scores: &[HypothesisScore]) -> usize {
    (0..scores.len())
        .max_by(|&a, &b| {
            scores[a]
                .psnr_differing
                .total_cmp(&scores[b].psnr_differing)
                .then(b.cmp(&a))
        })
        .unwrap_or(0)
}

/// What the finer tests ([`choose_windows`], [`choose_walls`]) test
/// against: the view's depth and maps, the photo, and its light.
#[derive(Clone, Copy)]
pub struct PhotoView<'a> {
    pub depth: &'a GrayImage,
    pub maps: &'a MaterialMaps,
    pub env: &'a EnvMap,
    pub mesh_params: MeshParams,
    pub photo: &'a RgbImage,
}

impl PhotoView<'_> {
    fn choose(
        &self,
        hypotheses: &[Hypothesis],
        opts: &EvidenceOptions,
        cache: &mut Rendered,
    ) -> Result<CompletionChoice, RenderError> {
        choose_cached(self, hypotheses, opts, cache)
    }
}

/// What [`add_greedily`] found: the bits set, the indices (into its
/// `bits`) in the order they were added, and each round's test.
struct Greedy {
    mask: u32,
    added: Vec<usize>,
    rounds: Vec<CompletionChoice>,
}

/// The greedy search of [`choose_windows`] and [`choose_walls`]: from
/// `with(0)`, each round tests the hypothesis so far (first, the least
/// assuming) against it with one more of the free `bits` set, and keeps
/// the one [`choose_completion`] takes, until it takes the one so far,
/// none is free, or `max` were added. With `shortlist`, rounds after the
/// first try only that many bits, those that scored best alone.
fn add_greedily(
    view: &PhotoView,
    bits: &[u32],
    with: &dyn Fn(u32) -> Hypothesis,
    max: usize,
    shortlist: Option<usize>,
    opts: &EvidenceOptions,
    cache: &mut Rendered,
) -> Result<Greedy, RenderError> {
    let mut mask = 0u32;
    let mut added = Vec::new();
    let mut rounds = Vec::new();
    let mut left: Vec<usize> = (0..bits.len()).collect();
    for _ in 0..max {
        let free: Vec<usize> = left
            .iter()
            .copied()
            .filter(|&k| mask >> bits[k] & 1 == 0)
            .collect();
        if free.is_empty() {
            break;
        }
        let mut hyps = vec![with(mask)];
        hyps.extend(free.iter().map(|&k| with(mask | 1 << bits[k])));
        let c = view.choose(&hyps, opts, cache)?;
        let chosen = c.chosen;
        if let (Some(n), true) = (shortlist, rounds.is_empty()) {
            let mut by: Vec<usize> = (1..c.scores.len()).collect();
            by.sort_by(|&a, &b| {
                c.scores[b]
                    .psnr_differing
                    .total_cmp(&c.scores[a].psnr_differing)
                    .then(a.cmp(&b))
            });
            left = by.iter().take(n).map(|&i| free[i - 1]).collect();
            left.sort_unstable();
        }
        rounds.push(c);
        if chosen == 0 {
            break;
        }
        mask |= 1 << bits[free[chosen - 1]];
        added.push(free[chosen - 1]);
    }
    Ok(Greedy {
        mask,
        added,
        rounds,
    })
}

/// How many windows [`choose_windows`] opens at most.
pub const MAX_WINDOWS: usize = 2;
/// After its first round, [`choose_windows`] tries only the slots that
/// scored best alone, this many.
pub const WINDOW_SHORTLIST: usize = 4;

/// Where the photo puts a closed room's windows past the frame.
#[derive(Clone, Debug, PartialEq)]
pub struct WindowChoice {
    /// [`CompleteParams::windows`] of the room taken.
    pub mask: u32,
    /// Every place the room may have a window.
    pub slots: Vec<matflow_geom::WindowSlot>,
    /// The windows opened, in the order they were.
    pub opened: Vec<matflow_geom::WindowSlot>,
    /// Each round's test: the room so far (first), and with one more
    /// window in each free slot.
    pub rounds: Vec<CompletionChoice>,
    /// The last test: the room found against the typical one (a window
    /// centred in each assumed wall); `typical` when that one won.
    pub against_typical: Option<CompletionChoice>,
    pub typical: bool,
    pub seconds: f64,
}

/// Where the windows of the room that `base` closes are, as far as the
/// photo tells (materials and light given): starting from the room with
/// no window, each round tests one more window in each free slot
/// ([`matflow_geom::window_slots`]: thirds of the walls and the ceiling
/// past the frame) with [`choose_completion`], and opens the one that
/// explains the photo best, while one beats the room so far by more than
/// the tolerance, up to [`MAX_WINDOWS`]. The room found is then tested
/// against `base`'s typical windows, which it must beat by the tolerance.
/// `None` when `base` closes no room in this view.
pub fn choose_windows(
    view: &PhotoView,
    base: &CompleteParams,
    opts: &EvidenceOptions,
) -> Result<Option<WindowChoice>, RenderError> {
    let t0 = std::time::Instant::now();
    let cam = matflow_scene::Camera::new(view.depth.width, view.depth.height);
    let slots = matflow_geom::window_slots(view.depth, &cam, base);
    if slots.is_empty() {
        return Ok(None);
    }
    let with = |mask: u32| Hypothesis {
        name: window_name(&slots, mask),
        params: Some(CompleteParams {
            close: true,
            windows: Some(mask),
            ..*base
        }),
    };
    let bits: Vec<u32> = slots.iter().map(|s| s.bit).collect();
    let mut cache = Rendered::new();
    let found = add_greedily(
        view,
        &bits,
        &with,
        MAX_WINDOWS,
        Some(WINDOW_SHORTLIST),
        opts,
        &mut cache,
    )?;
    let mask = found.mask;
    let opened: Vec<matflow_geom::WindowSlot> = found.added.iter().map(|&k| slots[k]).collect();
    let rounds = found.rounds;
    let typical = Hypothesis {
        name: "typical windows".to_string(),
        params: Some(*base),
    };
    let last = view.choose(&[with(mask), typical], opts, &mut cache)?;
    let is_typical = last.chosen == 1;
    Ok(Some(WindowChoice {
        mask,
        slots,
        opened,
        rounds,
        against_typical: Some(last),
        typical: is_typical,
        seconds: t0.elapsed().as_secs_f64(),
    }))
}

/// How many assumed walls (or the ceiling) [`choose_walls`] adds at most.
pub const MAX_WALLS: usize = 2;

/// Which of a room's unseen walls (and its ceiling) the photo shows the
/// effect of, in a view it found open.
#[derive(Clone, Debug, PartialEq)]
pub struct WallChoice {
    /// [`CompleteParams::assumed`] of the room taken.
    pub mask: u32,
    /// Every ceiling and wall that closing the room would assume.
    pub planes: Vec<matflow_geom::AssumedPlane>,
    /// Those added, in order.
    pub added: Vec<matflow_geom::AssumedPlane>,
    /// Each round's test: the view so far (first), and with one more.
    pub rounds: Vec<CompletionChoice>,
    /// When walls were raised: the test of their height
    /// ([`WALL_HEIGHTS`]), and the height taken (camera heights above
    /// the floor, [`CompleteParams::wall_height`]).
    pub height_test: Option<CompletionChoice>,
    pub height: Option<f32>,
    /// The last test: the completion the first test took (`start`)
    /// against the one found; `kept_start` when that one stayed.
    pub against_start: Option<CompletionChoice>,
    pub kept_start: bool,
    pub seconds: f64,
}

impl WallChoice {
    /// The completion found, from the room `base` would close.
    pub fn params(&self, base: &CompleteParams) -> CompleteParams {
        walled_at(base, self.mask, self.height)
    }
}

/// The heights [`choose_walls`] tries for walls it found raised past the
/// frame, in camera heights above the floor: from a room's (the ceiling
/// [`CompleteParams::ceiling_ratio`] would assume) to a courtyard's. How
/// far a wall's shadow reaches across the floor seen tells its height.
pub const WALL_HEIGHTS: [f32; 8] = [1.8, 2.2, 2.6, 3.0, 3.5, 4.0, 5.0, 6.0];

/// Whether the photo shows the effect of unseen walls (or a ceiling) in
/// a view whose first test took an open completion (`start`: none or
/// planes): from the planes seen, each round adds one of the walls and
/// the ceiling that closing the room `base` would assume (solid, as high
/// as its ceiling would be), or raises the walls
/// ([`matflow_geom::assumed_planes`] lists both), and keeps
/// the one that explains the photo best while it beats the view so far
/// by the tolerance, up to [`MAX_WALLS`]: a wall out of view casting its
/// shadow on the floor seen, say. What it found is then tested against
/// `start`, which it must beat by the tolerance. `None` when the view
/// closes no room.
pub fn choose_walls(
    view: &PhotoView,
    start: &Hypothesis,
    base: &CompleteParams,
    opts: &EvidenceOptions,
) -> Result<Option<WallChoice>, RenderError> {
    let t0 = std::time::Instant::now();
    let cam = matflow_scene::Camera::new(view.depth.width, view.depth.height);
    let planes = matflow_geom::assumed_planes(view.depth, &cam, base);
    if planes.is_empty() {
        return Ok(None);
    }
    let raise = RAISE_SEEN_WALLS | RAISE_WALLS_HIGH;
    // The walls of `mask`, raised to `height` camera heights if given.
    let at = |mask: u32, height: Option<f32>| Hypothesis {
        name: match height {
            Some(h) => raised_name(&planes, mask & !raise, h),
            None => wall_name(&planes, mask),
        },
        params: Some(walled_at(base, mask, height)),
    };
    let with = |mask: u32| at(mask, None);
    let bits: Vec<u32> = planes.iter().map(|p| p.bit).collect();
    let mut cache = Rendered::new();
    let found = add_greedily(view, &bits, &with, MAX_WALLS, None, opts, &mut cache)?;
    let mut mask = found.mask;
    // Walls raised past the frame: how high, the photo tells (the
    // shadows their tops cast). The best of the heights tried is taken,
    // and then the best of it and the heights halfway to its neighbours.
    let (height_test, height) = if mask & raise != 0 {
        mask = mask & !RAISE_SEEN_WALLS | RAISE_WALLS_HIGH;
        let test = |heights: &[f32], cache: &mut Rendered| {
            let hyps: Vec<Hypothesis> = heights.iter().map(|&h| at(mask, Some(h))).collect();
            view.choose(&hyps, opts, cache)
        };
        let k = best_scored(&test(&WALL_HEIGHTS, &mut cache)?.scores);
        let mut fine = vec![WALL_HEIGHTS[k]];
        if k > 0 {
            fine.push(0.5 * (WALL_HEIGHTS[k - 1] + WALL_HEIGHTS[k]));
        }
        if k + 1 < WALL_HEIGHTS.len() {
            fine.push(0.5 * (WALL_HEIGHTS[k] + WALL_HEIGHTS[k + 1]));
        }
        let last = test(&fine, &mut cache)?;
        let h = fine[best_scored(&last.scores)];
        (Some(last), Some(h))
    } else {
        (None, None)
    };
    let added: Vec<matflow_geom::AssumedPlane> = found.added.iter().map(|&k| planes[k]).collect();
    let rounds = found.rounds;
    let (against_start, kept_start) = if mask == 0 {
        (None, true)
    } else {
        let last = view.choose(&[start.clone(), at(mask, height)], opts, &mut cache)?;
        let kept = last.chosen == 0;
        (Some(last), kept)
    };
    Ok(Some(WallChoice {
        mask,
        planes,
        added,
        rounds,
        height_test,
        height,
        against_start,
        kept_start,
        seconds: t0.elapsed().as_secs_f64(),
    }))
}

/// The completion of `base`'s room with only the assumed ceiling and
/// walls of `mask` ([`CompleteParams::assumed`]), solid (no window).
pub fn walled(base: &CompleteParams, mask: u32) -> CompleteParams {
    CompleteParams {
        close: true,
        assumed: Some(mask),
        windows: Some(0),
        ..*base
    }
}

/// [`walled`], its walls raised to `height` camera heights
/// ([`CompleteParams::wall_height`]) if given.
pub fn walled_at(base: &CompleteParams, mask: u32, height: Option<f32>) -> CompleteParams {
    CompleteParams {
        wall_height: height.unwrap_or(base.wall_height),
        ..walled(base, mask)
    }
}

/// The assumed walls of `mask` in words: "the planes seen", else each.
pub fn wall_name(planes: &[matflow_geom::AssumedPlane], mask: u32) -> String {
    let on: Vec<String> = planes
        .iter()
        .filter(|p| mask >> p.bit & 1 == 1)
        .map(|p| p.describe())
        .collect();
    if on.is_empty() {
        "the planes seen".to_string()
    } else {
        format!("the planes seen and {}", on.join(", "))
    }
}

/// The assumed walls of `mask` with every wall raised to `h` camera
/// heights, in words.
pub fn raised_name(planes: &[matflow_geom::AssumedPlane], mask: u32, h: f32) -> String {
    format!(
        "{}, every wall raised to {h:.2} camera heights",
        wall_name(planes, mask)
    )
}

/// A room's windows in words: "no window", else each slot opened.
pub fn window_name(slots: &[matflow_geom::WindowSlot], mask: u32) -> String {
    let open: Vec<String> = slots
        .iter()
        .filter(|s| mask >> s.bit & 1 == 1)
        .map(|s| s.describe())
        .collect();
    if open.is_empty() {
        "no window".to_string()
    } else {
        format!("window: {}", open.join("; "))
    }
}

/// A hash of a mesh's triangles, positions and openness: hypotheses that
/// complete a view alike are rendered once.
fn mesh_key(m: &matflow_geom::TriMesh) -> u64 {
    use std::hash::{Hash, Hasher};
    let mut h = std::collections::hash_map::DefaultHasher::new();
    m.indices.hash(&mut h);
    for p in &m.positions {
        p.x.to_bits().hash(&mut h);
        p.y.to_bits().hash(&mut h);
        p.z.to_bits().hash(&mut h);
    }
    for o in &m.openness {
        o.to_bits().hash(&mut h);
    }
    m.portals.len().hash(&mut h);
    h.finish()
}

/// The sky a photo shows, as a light to test hypotheses under when the
/// light is not known (inversion): [`seen_sky_light`].
#[derive(Clone, Debug)]
pub struct SeenSky {
    /// The envmap (camera frame, matflow's lat-long layout).
    pub env: RgbImage,
    /// Unsaturated sky pixels used.
    pub pixels: usize,
    /// Texels they fall in.
    pub seen_texels: usize,
    /// Their mean radiance (linear RGB).
    pub level: [f32; 3],
    /// Of those, the ones seen past the scene, not through an opening in
    /// what the view shows: none with geometry above it in its column (a
    /// window under its lintel, a missing wall under the ceiling), nor in
    /// a patch of sky framed left and right by one surface
    /// ([`framed_sky`]: a window whose top the frame cuts).
    pub open_pixels: usize,
}

/// Share of a sky patch's rows whose two ends must lie on one surface
/// for [`framed_sky`] to call it an opening in that surface.
pub const FRAMED_ROWS: f64 = 0.5;

/// Pixels past each end of a row of sky where the framing surface is
/// looked for (and twice as far).
pub const FRAMED_REACH: usize = 3;

/// Distance from the framing surface, as a share of the point's depth,
/// within which a row's end lies on it (the plane fit's own tolerance,
/// [`matflow_geom::PlaneParams`]).
pub const FRAMED_TOLERANCE: f32 = 0.01;

/// Which pixels of `depth` (no geometry: not positive) are sky seen
/// through an opening of one surface: a 4-connected patch of sky at
/// least [`FRAMED_ROWS`] of whose rows end, left and right, inside the
/// frame on one plane: the surface seen [`FRAMED_REACH`] and twice that
/// many pixels past each end lies on it (within [`FRAMED_TOLERANCE`] of
/// its depth). A window in a wall whose top the frame cuts is such a patch;
/// the sky above a wall's top, beside a wall that ends, or between two
/// different surfaces is not.
///
/// The plane is searched among those through the near points of both
/// sides of one row and one side of another, on at most 24 rows spread over the patch
/// (deterministic).
pub fn framed_sky(depth: &GrayImage, cam: &matflow_scene::Camera) -> Vec<bool> {
    let (w, h) = (depth.width, depth.height);
    let sky = |x: usize, y: usize| !(depth.get(x, y) > 0.0);
    let mut seen = vec![false; w * h];
    let mut framed = vec![false; w * h];
    let mut stack = Vec::new();
    for start in 0..w * h {
        if seen[start] || !sky(start % w, start / w) {
            continue;
        }
        // The patch, by flood fill; its extent in each row.
        let mut rows: std::collections::BTreeMap<usize, (usize, usize)> = Default::default();
        let mut members = Vec::new();
        seen[start] = true;
        stack.push(start);
        while let Some(i) = stack.pop() {
            let (x, y) = (i % w, i / w);
            members.push(i);
            let e = rows.entry(y).or_insert((x, x));
            e.0 = e.0.min(x);
            e.1 = e.1.max(x);
            let mut visit = |j: usize| {
                if !seen[j] && sky(j % w, j / w) {
                    seen[j] = true;
                    stack.push(j);
                }
            };
            if x > 0 {
                visit(i - 1);
            }
            if x + 1 < w {
                visit(i + 1);
            }
            if y > 0 {
                visit(i - w);
            }
            if y + 1 < h {
                visit(i + w);
            }
        }
        // Rows ending on geometry on both sides inside the frame, with
        // the surface seen FRAMED_REACH and twice that many pixels past
        // each end (not the end pixels themselves: a window's reveal is
        // set back from its wall). Two such points a side, as two
        // parallel lines lie on one plane and a second point tells one
        // wall from two.
        let point = |x: usize, y: usize| {
            let z = depth.get(x, y);
            (z > 0.0 && z.is_finite()).then(|| cam.backproject(x as f32, y as f32, z))
        };
        let far = 2 * FRAMED_REACH;
        let ends: Vec<[glam::Vec3; 4]> = rows
            .iter()
            .filter(|(_, &(lo, hi))| lo > far && hi + far < w)
            .filter_map(|(&y, &(lo, hi))| {
                Some([
                    point(lo - FRAMED_REACH, y)?,
                    point(hi + FRAMED_REACH, y)?,
                    point(lo - far, y)?,
                    point(hi + far, y)?,
                ])
            })
            .collect();
        let need = (FRAMED_ROWS * rows.len() as f64).ceil() as usize;
        if ends.len() < need.max(2) {
            continue;
        }
        let on = |n: glam::Vec3, d: f32, p: &glam::Vec3| {
            (n.dot(*p) + d).abs() <= FRAMED_TOLERANCE * -p.z
        };
        // At most 24 rows, spread evenly from the first to the last.
        let (n, m) = (ends.len(), ends.len().min(24));
        let picks: Vec<usize> = (0..m).map(|k| k * (n - 1) / (m - 1).max(1)).collect();
        let mut best = 0;
        for &a in &picks {
            for &b in &picks {
                if a == b {
                    continue;
                }
                let [l, r, ..] = ends[a];
                for c in [ends[b][0], ends[b][1]] {
                    let Some(n) = (r - l).cross(c - l).try_normalize() else {
                        continue;
                    };
                    let d = -n.dot(l);
                    let held = ends
                        .iter()
                        .filter(|e| e.iter().all(|p| on(n, d, p)))
                        .count();
                    best = best.max(held);
                }
            }
        }
        if best >= need {
            for i in members {
                framed[i] = true;
            }
        }
    }
    framed
}

/// Radiance of the ground (below the horizon) in [`seen_sky_light`], as a
/// share of the seen sky's mean: a ground of albedo 0.25 under a uniform
/// sky of that radiance.
pub const SEEN_SKY_GROUND: f32 = 0.25;

/// Least share of the image the unsaturated sky must cover for
/// [`seen_sky_light`] to build a light from it.
pub const SEEN_SKY_MIN_SHARE: f64 = 0.002;

/// A light built from the sky the photo shows: pixels without geometry
/// (`depth` not positive) whose every channel is finite and under
/// `saturated` are the sky's radiance in their directions. Each texel of a
/// `w`×`h` map that such pixels fall in takes their mean; every other
/// texel above the horizon (`up`: the view's up, camera space) the seen
/// sky's mean, and below it [`SEEN_SKY_GROUND`] of that. `None` when the
/// sky covers less than [`SEEN_SKY_MIN_SHARE`] of the image (or 16
/// pixels). The sky the view does not show is assumed like the sky it
/// shows: what light a hypothesis needs beyond that is its assumption.
pub fn seen_sky_light(
    photo: &RgbImage,
    depth: &GrayImage,
    cam: &matflow_scene::Camera,
    up: glam::Vec3,
    w: usize,
    h: usize,
    saturated: f32,
) -> Option<SeenSky> {
    use crate::envmap::{dir_to_uv, uv_to_dir};
    if !photo.same_size(depth) || w < 2 || h < 2 {
        return None;
    }
    let up = up.try_normalize().unwrap_or(glam::Vec3::Y);
    let mut acc = vec![[0.0f64; 4]; w * h];
    let mut total = [0.0f64; 3];
    let mut pixels = 0usize;
    let mut open_pixels = 0usize;
    let framed = framed_sky(depth, cam);
    // Per column, the first row (from the top) that shows geometry.
    let top: Vec<usize> = (0..depth.width)
        .map(|x| {
            (0..depth.height)
                .find(|&y| depth.get(x, y) > 0.0)
                .unwrap_or(depth.height)
        })
        .collect();
    for y in 0..photo.height {
        for x in 0..photo.width {
            let z = depth.get(x, y);
            let v = photo.get(x, y);
            if z > 0.0 || !v.is_finite() || v.max_element() >= saturated || v.min_element() < 0.0 {
                continue;
            }
            if y < top[x] && !framed[y * depth.width + x] {
                open_pixels += 1;
            }
            let d = cam
                .film_to_dir(glam::Vec2::new(x as f32 + 0.5, y as f32 + 0.5))
                .normalize_or_zero();
            let (u, vv) = dir_to_uv(d);
            let col = ((u * w as f32) as usize).min(w - 1);
            let row = ((vv * (h - 1) as f32).round() as usize).min(h - 1);
            let a = &mut acc[row * w + col];
            for c in 0..3 {
                a[c] += v[c] as f64;
                total[c] += v[c] as f64;
            }
            a[3] += 1.0;
            pixels += 1;
        }
    }
    let min = ((SEEN_SKY_MIN_SHARE * (photo.width * photo.height) as f64).ceil() as usize).max(16);
    if pixels < min {
        return None;
    }
    let level = total.map(|t| (t / pixels as f64) as f32);
    let mean = glam::Vec3::from_array(level);
    let mut seen_texels = 0;
    let env = RgbImage::from_fn(w, h, |col, row| {
        let a = acc[row * w + col];
        if a[3] > 0.0 {
            return glam::Vec3::new(
                (a[0] / a[3]) as f32,
                (a[1] / a[3]) as f32,
                (a[2] / a[3]) as f32,
            );
        }
        let d = uv_to_dir((col as f32 + 0.5) / w as f32, row as f32 / (h - 1) as f32);
        if d.dot(up) > 0.0 {
            mean
        } else {
            mean * SEEN_SKY_GROUND
        }
    });
    for a in &acc {
        if a[3] > 0.0 {
            seen_texels += 1;
        }
    }
    Some(SeenSky {
        env,
        pixels,
        seen_texels,
        level,
        open_pixels,
    })
}

/// The level at which `photo`'s pixels are clipped: a photo whose values
/// stay within [0, 1] (8 bits, or an EXR of one) is clipped near 1, and
/// its sky there measures nothing; an HDR photo is clipped nowhere.
pub fn clip_level(photo: &RgbImage) -> f32 {
    let max = photo
        .data
        .iter()
        .filter(|v| v.is_finite())
        .map(|v| v.max_element())
        .fold(0.0f32, f32::max);
    if max > 1.0 {
        f32::INFINITY
    } else {
        0.98
    }
}

/// What the photo says of the hypotheses when the light is not known
/// (inversion, the pipeline's `mesh` stage): each is rendered with the
/// predicted `maps` under the sky the photo shows ([`seen_sky_light`],
/// 32×16, "up" from the view's planes) and tested as
/// [`choose_completion`] tests them. `None` when the photo shows too
/// little unclipped open sky: then every hypothesis explains the photo
/// with a light of its own, and nothing weighs them. When the hypothesis
/// taken needs more than [`UNSEEN_LIGHT_GAIN`] times the seen sky's
/// light, that sky is not the view's light either: the choice is `room`
/// (when among `hypotheses`), not decisive, with the scores kept.
pub fn choose_under_seen_sky(
    depth: &GrayImage,
    maps: &MaterialMaps,
    mesh_params: MeshParams,
    photo: &RgbImage,
    hypotheses: &[Hypothesis],
    opts: &EvidenceOptions,
) -> Result<Option<(CompletionChoice, SeenSky)>, RenderError> {
    let cam = matflow_scene::Camera::new(depth.width, depth.height);
    let up = matflow_geom::view_up(depth, &cam, &matflow_geom::PlaneParams::default());
    let Some(sky) = seen_sky_light(photo, depth, &cam, up, 32, 16, clip_level(photo)) else {
        return Ok(None);
    };
    // Sky seen only through openings of what the view shows (a window
    // under its lintel): a room's windows, which let in more than the
    // sky they show (the sun, lamps); the view is not open.
    if (sky.open_pixels as f64) < SEEN_SKY_MIN_SHARE * (photo.width * photo.height) as f64 {
        return Ok(None);
    }
    let env = EnvMap::new(&sky.env)?;
    let mut choice = choose_completion(depth, maps, &env, mesh_params, photo, hypotheses, opts)?;
    let gain = choice.scores[choice.chosen].gain;
    let room = hypotheses.iter().position(|h| h.name == "room");
    if let Some(room) = room.filter(|_| gain > UNSEEN_LIGHT_GAIN) {
        // The seen sky is not what lights the view: every hypothesis is
        // weighed under a light that is not the photo's.
        choice.reason = format!(
            "{} is what the photo supports under the sky it shows, but needs {gain:.1} times that \
             sky's light (more than {UNSEEN_LIGHT_GAIN}): the light comes from what the view \
             does not show (lamps, the sun through openings), so the seen sky weighs nothing; \
             room, which closes a room only where the view shows one",
            choice.scores[choice.chosen].name
        );
        choice.margin_db = margin_db(&choice.scores, room);
        choice.chosen = room;
        choice.decisive = false;
    }
    Ok(Some((choice, sky)))
}

/// Most light, as a factor on the sky a photo shows, that the hypothesis
/// [`choose_under_seen_sky`] takes may need for that sky to count as the
/// view's light. Views open to the sky need about the sky they show, or
/// a few times it with the sun out of view (0.5–5.5 on matflow's
/// validation scenes: open rooms, stages, outdoors, some at a low sun);
/// a room lit by lamps that shows a dark sky through a missing wall
/// needed 17. Beyond it the test takes `room`, as without a sky.
pub const UNSEEN_LIGHT_GAIN: f64 = 10.0;

impl SeenSky {
    /// In words, for reports.
    pub fn describe(&self) -> String {
        format!(
            "the sky the photo shows ({} pixels in {} texels, mean ({:.4}, {:.4}, {:.4})), \
             elsewhere above the horizon alike",
            self.pixels, self.seen_texels, self.level[0], self.level[1], self.level[2]
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene_from_depth;
    use glam::Vec3;
    use matflow_scene::Camera;

    const N: usize = 48;

    /// Depth of a floor 1.2 below the camera and a wall 5 ahead, 2.4 high
    /// above the floor, wider than the view: sky above the wall.
    fn floor_and_wall() -> GrayImage {
        let cam = Camera::new(N, N);
        GrayImage::from_fn(N, N, |x, y| {
            let d = cam.backproject(x as f32, y as f32, 1.0);
            let mut best = f32::INFINITY;
            // Floor y = -1.2 (n = +y), wall z = -5 (n = +z), up to y = 1.2.
            if d.y < 0.0 {
                best = best.min(1.2 / -d.y);
            }
            let t = 5.0 / -d.z;
            if (d * t).y <= 1.2 {
                best = best.min(t);
            }
            if best.is_finite() {
                best
            } else {
                0.0
            }
        })
    }

    /// A sky brighter above than at the horizon, a dim ground.
    fn sky() -> EnvMap {
        EnvMap::new(&RgbImage::from_fn(32, 16, |_, r| {
            if r < 8 {
                Vec3::new(0.8, 0.9, 1.2) * (1.5 - r as f32 / 16.0)
            } else {
                Vec3::splat(0.1)
            }
        }))
        .unwrap()
    }

    /// The view of `depth` with `maps`, lit by `env`, photographed as
    /// `photo`, on the default mesh.
    fn photo_view<'a>(
        depth: &'a GrayImage,
        maps: &'a MaterialMaps,
        env: &'a EnvMap,
        photo: &'a RgbImage,
    ) -> PhotoView<'a> {
        PhotoView {
            depth,
            maps,
            env,
            mesh_params: MeshParams::default(),
            photo,
        }
    }

    /// Grey, rough, dielectric maps of the test view.
    fn grey_maps() -> MaterialMaps {
        MaterialMaps::uniform(N, N, Vec3::splat(0.6), 0.8, 0.0)
    }

    /// Four samples a half, 4×4 blocks: the tests' view is small.
    fn fine_opts() -> EvidenceOptions {
        EvidenceOptions {
            spp_half: 4,
            block: 4,
            ..Default::default()
        }
    }

    fn hyps() -> Vec<Hypothesis> {
        completion_hypotheses()
    }

    /// The choice among every hypothesis under the test sky, on the
    /// default mesh.
    fn choose_on_sky(
        depth: &GrayImage,
        maps: &MaterialMaps,
        photo: &RgbImage,
        opts: &EvidenceOptions,
    ) -> CompletionChoice {
        choose_completion(
            depth,
            maps,
            &sky(),
            MeshParams::default(),
            photo,
            &hyps(),
            opts,
        )
        .unwrap()
    }

    /// The photo: the view rendered on hypothesis `k`'s completion.
    fn photo(depth: &GrayImage, maps: &MaterialMaps, k: usize) -> RgbImage {
        let h = &hyps()[k];
        let (scene, _, _) =
            scene_from_depth(depth, maps, sky(), MeshParams::default(), h.params.as_ref()).unwrap();
        let o = RenderOptions {
            spp: 64,
            seed: 99,
            ..Default::default()
        };
        render(&scene, &o, &|_, _| {}).image
    }

    #[test]
    fn the_photo_picks_the_geometry_it_was_rendered_with() {
        let depth = floor_and_wall();
        let maps = grey_maps();
        let opts = fine_opts();
        // The choice on the photo rendered with hypothesis k.
        let choose = |k: usize| {
            let photo = photo(&depth, &maps, k);
            choose_on_sky(&depth, &maps, &photo, &opts)
        };
        // Open: the sky lights the floor and the wall; a closed room
        // would shut most of it out.
        let open = choose(0);
        assert_eq!(open.chosen, 0, "{open:?}");
        assert!(open.differing > 0.1, "{open:?}");
        let room = &open.scores[2];
        assert!(
            open.scores[0].psnr_differing > room.psnr_differing + 6.0,
            "{open:?}"
        );
        // A closed room needs more light than the open view does.
        assert!(room.gain > 1.2 * open.scores[0].gain, "{open:?}");
        // Closed with windows: room.
        let closed = choose(2);
        assert_eq!(closed.chosen, 2, "{closed:?}");
        assert!(closed.decisive && closed.margin_db > 1.0, "{closed:?}");
        // The same inputs give the same answer.
        let again = choose(2);
        let numbers = |c: &CompletionChoice| {
            c.scores
                .iter()
                .map(|s| (s.psnr_differing, s.psnr_all, s.gain, s.psnr_gained))
                .collect::<Vec<_>>()
        };
        assert_eq!(numbers(&closed), numbers(&again));
    }

    #[test]
    fn the_photo_places_a_closed_room_s_windows_where_they_explain_it() {
        let depth = floor_and_wall();
        let maps = grey_maps();
        let cam = Camera::new(N, N);
        let base = CompleteParams::for_mode("room").unwrap();
        let slots = matflow_geom::window_slots(&depth, &cam, &base);
        let opts = fine_opts();
        let shot = |p: &CompleteParams, seed: u64| {
            let (scene, _, _) =
                scene_from_depth(&depth, &maps, sky(), MeshParams::default(), Some(p)).unwrap();
            let o = RenderOptions {
                spp: 256,
                seed,
                ..Default::default()
            };
            render(&scene, &o, &|_, _| {}).image
        };
        let psnr = |a: &RgbImage, b: &RgbImage| {
            let mut se = 0.0f64;
            for (x, y) in a.data.iter().zip(&b.data) {
                for c in 0..3 {
                    let d = linear_to_gamma(x[c]) - linear_to_gamma(y[c]);
                    se += (d * d) as f64;
                }
            }
            -10.0 * (se / (3 * a.data.len()) as f64).log10()
        };
        // The room lit through one window: the left wall's middle third,
        // then a skylight's last third.
        for want in ["wall left (assumed), third 2", "ceiling (assumed), third 3"] {
            let slot = slots
                .iter()
                .find(|s| s.describe() == want)
                .unwrap_or_else(|| panic!("{want} in {slots:?}"));
            let truth = CompleteParams {
                windows: Some(1 << slot.bit),
                ..base
            };
            let photo = shot(&truth, 99);
            let env = sky();
            let view = photo_view(&depth, &maps, &env, &photo);
            let w = choose_windows(&view, &base, &opts)
                .unwrap()
                .expect("a closed room");
            assert_eq!(w.slots, slots);
            assert!(!w.typical && !w.opened.is_empty(), "{want}: {w:?}");
            // The first round tested every slot.
            assert_eq!(w.rounds[0].scores.len(), slots.len() + 1);
            // The room found, rendered anew, explains the photo about as
            // well as the truth does (another render of it: the noise
            // floor), and far better than no window or the typical ones.
            let found = CompleteParams {
                windows: Some(w.mask),
                ..base
            };
            let floor = psnr(&shot(&truth, 7), &photo);
            let got = psnr(&shot(&found, 7), &photo);
            let closed = psnr(
                &shot(
                    &CompleteParams {
                        windows: Some(0),
                        ..base
                    },
                    7,
                ),
                &photo,
            );
            let typical = psnr(&shot(&base, 7), &photo);
            assert!(
                got > floor - 1.5,
                "{want}: {got:.2} dB, the truth's {floor:.2}: {w:?}"
            );
            assert!(
                got > closed + 3.0 && got > typical + 3.0,
                "{want}: {got:.2} against closed {closed:.2}, typical {typical:.2}"
            );
        }
        // A view that closes no room has no window to place.
        let sky_only = GrayImage::new(16, 16, 0.0);
        let m16 = MaterialMaps::uniform(16, 16, Vec3::splat(0.5), 0.5, 0.0);
        let photo = RgbImage::new(16, 16, Vec3::splat(0.7));
        let env = sky();
        let view = photo_view(&sky_only, &m16, &env, &photo);
        assert!(choose_windows(&view, &base, &opts).unwrap().is_none());
    }

    #[test]
    fn the_photo_adds_an_unseen_wall_whose_effect_it_shows() {
        let depth = floor_and_wall();
        let maps = grey_maps();
        let cam = Camera::new(N, N);
        let room = CompleteParams::for_mode("room").unwrap();
        let planes = matflow_geom::assumed_planes(&depth, &cam, &room);
        let opts = fine_opts();
        let start = hyps()[1].clone();
        let shot = |p: Option<&CompleteParams>| {
            let (scene, _, _) =
                scene_from_depth(&depth, &maps, sky(), MeshParams::default(), p).unwrap();
            let o = RenderOptions {
                spp: 256,
                seed: 99,
                ..Default::default()
            };
            render(&scene, &o, &|_, _| {}).image
        };
        // The photo of the planes seen and a wall behind the camera that
        // shuts out half the sky: the wall is found and taken.
        let behind = planes
            .iter()
            .find(|p| p.describe() == "wall behind")
            .expect("a wall behind");
        let photo = shot(Some(&walled(&room, 1 << behind.bit)));
        let env = sky();
        let view = |photo| photo_view(&depth, &maps, &env, photo);
        let w = choose_walls(&view(&photo), &start, &room, &opts)
            .unwrap()
            .expect("a room to close");
        assert_eq!(w.planes, planes);
        assert_eq!(w.added.first(), Some(behind), "{w:?}");
        assert!(!w.kept_start, "{w:?}");
        // The photo of the planes seen alone: nothing is added.
        let photo = shot(start.params.as_ref());
        let w = choose_walls(&view(&photo), &start, &room, &opts)
            .unwrap()
            .expect("a room to close");
        assert!(w.kept_start, "{w:?}");
    }

    #[test]
    fn the_photo_tells_how_high_unseen_walls_stand_from_their_shadows() {
        // A floor 1.2 below the camera and a wall 7 ahead that runs past
        // the frame's top (seen up to 2.8 camera heights above the floor).
        let n = 96;
        let cam = Camera::new(n, n);
        let depth = GrayImage::from_fn(n, n, |x, y| {
            let d = cam.backproject(x as f32, y as f32, 1.0);
            let wall = 7.0 / -d.z;
            if d.y < 0.0 {
                wall.min(1.2 / -d.y)
            } else {
                wall
            }
        });
        let maps = MaterialMaps::uniform(n, n, Vec3::splat(0.6), 0.8, 0.0);
        let room = CompleteParams::for_mode("room").unwrap();
        // The sky and a sun beyond the wall, 60 degrees up: the wall's
        // shadow reaches across the floor towards the camera as far as
        // its height takes it (at 3.25 camera heights to 4.75 ahead, at 4
        // to 4.2; the floor is seen from 3.8 ahead to the wall).
        let sun = Vec3::new(0.0, 0.866, -0.5);
        let env = EnvMap::new(&RgbImage::from_fn(64, 32, |c, r| {
            let d = crate::envmap::uv_to_dir((c as f32 + 0.5) / 64.0, r as f32 / 31.0);
            if d.dot(sun) > 0.985 {
                Vec3::splat(60.0)
            } else if d.y > 0.0 {
                Vec3::new(0.4, 0.45, 0.6)
            } else {
                Vec3::splat(0.05)
            }
        }))
        .unwrap();
        let opts = fine_opts();
        let start = hyps()[1].clone();
        for truth in [3.25f32, 4.0] {
            let walls = CompleteParams {
                wall_height: truth,
                ..walled(&room, RAISE_WALLS_HIGH)
            };
            let (scene, _, _) = scene_from_depth(
                &depth,
                &maps,
                env.clone(),
                MeshParams::default(),
                Some(&walls),
            )
            .unwrap();
            let o = RenderOptions {
                spp: 256,
                seed: 99,
                ..Default::default()
            };
            let photo = render(&scene, &o, &|_, _| {}).image;
            let view = photo_view(&depth, &maps, &env, &photo);
            let w = choose_walls(&view, &start, &room, &opts)
                .unwrap()
                .expect("a room to close");
            assert!(!w.kept_start, "{truth}: {w:?}");
            assert!(w.mask & RAISE_WALLS_HIGH != 0, "{truth}: {w:?}");
            let got = w.height.expect("a height tried");
            // 3.25 is halfway between two heights of the first test:
            // the second finds it.
            assert!((got - truth).abs() < 0.2, "{truth}: {got}: {w:?}");
            assert_eq!(w.params(&room).wall_height, got);
        }
    }

    #[test]
    fn the_choice_is_the_same_on_any_number_of_threads() {
        let depth = floor_and_wall();
        let maps = grey_maps();
        let photo = photo(&depth, &maps, 2);
        let opts = EvidenceOptions {
            spp_half: 2,
            block: 4,
            ..Default::default()
        };
        let on = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| choose_on_sky(&depth, &maps, &photo, &opts))
        };
        let numbers = |c: &CompletionChoice| {
            c.scores
                .iter()
                .map(|s| {
                    (
                        s.psnr_differing.to_bits(),
                        s.gain.to_bits(),
                        s.same_as.clone(),
                    )
                })
                .collect::<Vec<_>>()
        };
        let one = on(1);
        for threads in [2, 3] {
            let other = on(threads);
            assert_eq!(other.chosen, one.chosen);
            assert_eq!(numbers(&other), numbers(&one), "{threads} threads");
        }
    }

    #[test]
    fn hypotheses_that_render_alike_are_no_evidence() {
        // A view of the sky alone: nothing to complete, every hypothesis
        // builds the same (empty) mesh.
        let depth = GrayImage::new(16, 16, 0.0);
        let maps = MaterialMaps::uniform(16, 16, Vec3::splat(0.5), 0.5, 0.0);
        let photo = RgbImage::new(16, 16, Vec3::splat(0.7));
        let c = choose_on_sky(&depth, &maps, &photo, &EvidenceOptions::default());
        assert_eq!(c.chosen, 0);
        assert!(!c.decisive && c.differing == 0.0, "{c:?}");
        assert!(
            c.scores[1..]
                .iter()
                .all(|s| s.same_as.as_deref() == Some("none")),
            "{c:?}"
        );
    }

    #[test]
    fn the_noise_free_error_of_a_render_equal_to_the_photo_is_nil() {
        let p = vec![[0.2f32, 0.4, 0.1]; 10];
        // Halves with opposite noise around the photo: their product
        // estimate is below zero, clamped: no better than exact.
        let a: Vec<[f32; 3]> = p.iter().map(|v| v.map(|x| x + 0.01)).collect();
        let b: Vec<[f32; 3]> = p.iter().map(|v| v.map(|x| x - 0.01)).collect();
        assert_eq!(psnr_over(&[a.clone(), b.clone()], &p, None, 1.0), 100.0);
        // Twice as bright a render needs half the light.
        let twice: Vec<[f32; 3]> = p.iter().map(|v| v.map(|x| 2.0 * x)).collect();
        let g = light_gain(&[twice.clone(), twice], &p, None);
        assert!((g - 0.5).abs() < 1e-6, "{g}");
    }

    #[test]
    fn the_seen_sky_lights_what_the_view_does_not_show_alike() {
        let depth = floor_and_wall();
        let cam = Camera::new(N, N);
        let blue = Vec3::new(0.3, 0.5, 0.9);
        let mut photo = RgbImage::from_fn(N, N, |x, y| {
            if depth.get(x, y) > 0.0 {
                Vec3::splat(0.2)
            } else {
                blue
            }
        });
        let sky = seen_sky_light(&photo, &depth, &cam, Vec3::Y, 32, 16, 0.98).unwrap();
        let sky_pixels = depth.data.iter().filter(|&&z| z == 0.0).count();
        assert_eq!(sky.pixels, sky_pixels);
        // All of it above the wall: open sky.
        assert_eq!(sky.open_pixels, sky_pixels);
        // A window in the wall, under its lintel: sky, not open.
        let mut windowed = depth.clone();
        let (rows, cols) = (30..36, 10..20);
        for y in rows.clone() {
            for x in cols.clone() {
                assert!(windowed.get(x, y) > 0.0, "the wall at {x},{y}");
                windowed.data[y * N + x] = 0.0;
            }
        }
        let through = seen_sky_light(&photo, &windowed, &cam, Vec3::Y, 32, 16, 0.98).unwrap();
        assert_eq!(through.pixels, sky_pixels + rows.len() * cols.len());
        assert_eq!(through.open_pixels, sky_pixels);
        assert!(
            sky.seen_texels > 0 && sky.seen_texels < 32 * 16 / 4,
            "{sky:?}"
        );
        // Every texel above the horizon is the seen sky, below it a
        // quarter of it.
        for r in 0..16 {
            for c in 0..32 {
                let v = sky.env.get(c, r);
                let want = if r < 8 { blue } else { blue * SEEN_SKY_GROUND };
                assert!((v - want).abs().max_element() < 1e-5, "texel {c},{r}: {v}");
            }
        }
        // Saturated sky is no measure, and too little sky no light.
        for v in photo.data.iter_mut() {
            if *v == blue {
                *v = Vec3::new(1.0, 1.0, 1.0);
            }
        }
        assert!(seen_sky_light(&photo, &depth, &cam, Vec3::Y, 32, 16, 0.98).is_none());
        let full = GrayImage::new(N, N, 3.0);
        assert!(seen_sky_light(&photo, &full, &cam, Vec3::Y, 32, 16, 0.98).is_none());
    }

    /// Depth of a view whose upper part is walls: `wall(x)` gives the
    /// depth of the wall at column x at the centre row (slanted walls
    /// have depth changing along the row), a floor 1.2 below the camera,
    /// and sky where `hole(x, y)`.
    fn walls_with_hole(
        wall: impl Fn(f32) -> (f32, f32),
        hole: impl Fn(usize, usize) -> bool,
    ) -> GrayImage {
        let cam = Camera::new(N, N);
        GrayImage::from_fn(N, N, |x, y| {
            if hole(x, y) {
                return 0.0;
            }
            let d = cam.backproject(x as f32, y as f32, 1.0);
            // The wall through (0, 0, -z0) whose depth grows by `slope`
            // per unit of camera x: z = z0 + slope * px.
            let (z0, slope) = wall(x as f32);
            let t_wall = z0 / (-d.z - slope * d.x);
            let t_floor = if d.y < 0.0 { 1.2 / -d.y } else { f32::INFINITY };
            t_wall.min(t_floor)
        })
    }

    #[test]
    fn a_window_whose_top_the_frame_cuts_is_no_open_sky() {
        let cam = Camera::new(N, N);
        let window = |x: usize, y: usize| (14..30).contains(&x) && y < 16;
        let sky_share = |depth: &GrayImage| {
            let photo = RgbImage::from_fn(N, N, |_, _| Vec3::new(0.3, 0.5, 0.9));
            let s = seen_sky_light(&photo, depth, &cam, Vec3::Y, 32, 16, 0.98).unwrap();
            (s.pixels, s.open_pixels)
        };
        // A window in one wall, facing the camera or turned away from it:
        // sky framed left and right by one surface, seen through it.
        for slope in [0.0, 0.6, -0.4] {
            let mut depth = walls_with_hole(|_| (5.0, slope), window);
            // Its reveal, set back from the wall, seen beside the sky.
            for y in 0..16 {
                for x in [13, 30] {
                    depth.data[y * N + x] += 0.15;
                }
            }
            let framed = framed_sky(&depth, &cam);
            for y in 0..N {
                for x in 0..N {
                    assert_eq!(framed[y * N + x], window(x, y), "slope {slope}: {x},{y}");
                }
            }
            assert_eq!(sky_share(&depth), (16 * 16, 0), "slope {slope}");
        }
        // The same patch between two different walls (the right one
        // further back): the sky past their ends, not a window.
        let two = walls_with_hole(|x| (if x < 22.0 { 5.0 } else { 6.0 }, 0.0), window);
        assert!(framed_sky(&two, &cam).iter().all(|&f| !f));
        assert_eq!(sky_share(&two), (16 * 16, 16 * 16));
        // A wall that ends inside the frame, sky beside it and above:
        // open.
        let ends = walls_with_hole(|_| (5.0, 0.0), |x, y| x >= 30 && y < 16 || y < 4);
        assert!(framed_sky(&ends, &cam).iter().all(|&f| !f));
        let (pixels, open) = sky_share(&ends);
        assert_eq!(open, pixels);
        // Most of the patch's rows reach the frame's side (the sky above
        // a wall, with a notch in it): open.
        let notch = walls_with_hole(
            |_| (5.0, 0.0),
            |x, y| y < 10 || (14..30).contains(&x) && y < 13,
        );
        assert!(framed_sky(&notch, &cam).iter().all(|&f| !f));
        // And under the lintel, as before: not open.
        let lintel = walls_with_hole(
            |_| (5.0, 0.0),
            |x, y| (14..30).contains(&x) && (4..16).contains(&y),
        );
        assert_eq!(sky_share(&lintel), (16 * 12, 0));
    }

    #[test]
    fn a_view_lit_by_far_more_than_its_sky_is_tested_as_a_room() {
        let depth = floor_and_wall();
        let maps = grey_maps();
        let opts = fine_opts();
        // The open view rendered under its own sky: the sky it shows is
        // its light, and the test takes the depth mesh alone.
        let photo = photo(&depth, &maps, 0);
        let lit = |k: f32| {
            let mut p = photo.clone();
            for (i, v) in p.data.iter_mut().enumerate() {
                if depth.data[i] > 0.0 {
                    *v *= k;
                }
            }
            let (c, _) =
                choose_under_seen_sky(&depth, &maps, MeshParams::default(), &p, &hyps(), &opts)
                    .unwrap()
                    .expect("open sky");
            c
        };
        let own = lit(1.0);
        assert_eq!(own.chosen, 0, "{own:?}");
        assert!((own.scores[0].gain - 1.0).abs() < 0.2, "{own:?}");
        // Three times brighter (a sun out of view): still its sky's view.
        let sun = lit(3.0);
        assert_eq!(sun.chosen, 0, "{sun:?}");
        // (Blocks with sky in them keep their level: the gain over the
        // blocks is less than 3.)
        assert!(sun.scores[0].gain > 2.0, "{sun:?}");
        // Twenty times (lamps it does not show, a dark sky through a
        // missing wall): the seen sky weighs nothing; room.
        let lamps = lit(20.0);
        assert_eq!(lamps.chosen, 2, "{lamps:?}");
        assert!(!lamps.decisive, "{lamps:?}");
        assert!(lamps.scores[0].gain > UNSEEN_LIGHT_GAIN, "{lamps:?}");
        assert!(lamps.reason.contains("times that sky's light"), "{lamps:?}");
    }
}
