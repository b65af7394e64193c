//! The lat-long environment map in Mitsuba 3's `envmap` orientation, with
//! bilinear lookup and importance sampling proportional to luminance × sin θ.
//!
//! Direction d ↦ u = atan2(d.x, −d.z)/2π (mod 1), v = acos(d.y)/π. Column j
//! is centred at u = (j + ½)/W (lookup wraps in u); row i sits at
//! θ = π·i/(H − 1): row 0 straight up, the last row straight down.
//!
//! Sampling works on the cells between texel centres: cell (r, c) spans rows
//! r..r+1 and columns c..c+1 (wrapping), inside which the radiance is the
//! bilinear blend of its four corner texels. A cell is chosen with
//! probability ∝ mean corner luminance × its solid angle, then a direction
//! uniformly in solid angle inside it. The pdf is therefore exact and
//! positive wherever the radiance is.

use std::f32::consts::PI;

use glam::Vec3;
use matflow_scene::color::luminance;
use matflow_scene::{Image, RgbImage};

use std::sync::Arc;

use crate::fmath::{self, ONE_BELOW};
use crate::guide::{Draw, Guide, Visibility, NO_CLUSTER};
use crate::lanes::{self, F};
use crate::RenderError;

/// The sampling cell (row, column) at (u, v).
#[inline]
fn cell_at(width: usize, height: usize, u: f32, v: f32) -> (usize, usize) {
    let (r, c, _, _) = cell_of_uv(width, height, u, v);
    (r, c)
}

/// Values are clamped to this magnitude so no sum can overflow f32.
pub const MAX_RADIANCE: f32 = 1e18;

#[derive(Clone, Debug)]
pub struct EnvMap {
    width: usize,
    height: usize,
    texels: Vec<Vec3>,
    /// Marginal CDF over cell rows (H − 1 rows), f64 normalised.
    row_cdf: Vec<f64>,
    /// Conditional CDF over columns per cell row (W per row).
    col_cdf: Vec<f64>,
    /// Probability of each cell, row-major ((H − 1) × W).
    cell_prob: Vec<f32>,
    /// Solid angle of the cells of each row.
    row_solid_angle: Vec<f32>,
    /// cos θ of each row boundary (H values), as [`EnvMap::sample`] needs.
    row_cos: Vec<f32>,
    total_weight: f64,
    /// Visibility-guided sampling for points in the scene it was measured
    /// in ([`EnvMap::guided`]); `None` samples by radiance alone.
    guide: Option<Arc<Guide>>,
}

/// sin and cos of one angle, by the lanes' polynomial.
#[inline(always)]
fn sin_cos1(x: f32) -> (f32, f32) {
    let (s, c) = lanes::sin_cos(F::<1>([x]));
    (s.0[0], c.0[0])
}

/// Direction → (u, v) in [0, 1)².
#[inline]
pub fn dir_to_uv(d: Vec3) -> (f32, f32) {
    let mut u = lanes::atan2(F::<1>([d.x]), F::<1>([-d.z])).0[0] * (0.5 / PI);
    if u < 0.0 {
        u += 1.0;
    }
    if u >= 1.0 {
        u -= 1.0;
    }
    let v = lanes::acos(F::<1>([d.y.clamp(-1.0, 1.0)])).0[0] / PI;
    (u, v)
}

/// (u, v) → unit direction.
#[inline]
pub fn uv_to_dir(u: f32, v: f32) -> Vec3 {
    let phi = 2.0 * PI * u;
    let theta = PI * v;
    let (st, ct) = sin_cos1(theta);
    let (sp, cp) = sin_cos1(phi);
    Vec3::new(st * sp, ct, -st * cp)
}

/// The bilinear cell of a `width`×`height` map that direction `d` falls in:
/// (row r, column c, fx, fy), blending texels (c, r), (c+1 mod W, r),
/// (c, r+1), (c+1 mod W, r+1) with weights (1−fx)(1−fy), fx(1−fy),
/// (1−fx)fy, fx·fy. This is the lookup [`EnvMap::eval`] uses.
#[inline]
pub fn locate_cell(width: usize, height: usize, d: Vec3) -> (usize, usize, f32, f32) {
    let (u, v) = dir_to_uv(d);
    cell_of_uv(width, height, u, v)
}

/// [`locate_cell`] of the direction at (u, v) ([`dir_to_uv`]).
#[inline]
pub fn cell_of_uv(width: usize, height: usize, u: f32, v: f32) -> (usize, usize, f32, f32) {
    let x = u * width as f32 - 0.5;
    let xf = fmath::floor(x);
    let fx = x - xf;
    let c = (xf as i64).rem_euclid(width as i64) as usize;
    let y = v * (height - 1) as f32;
    let r = (fmath::floor(y) as i64).clamp(0, height as i64 - 2) as usize;
    let fy = (y - r as f32).clamp(0.0, 1.0);
    (r, c, fx.clamp(0.0, 1.0), fy)
}

impl EnvMap {
    /// Builds the map. Rejects non-finite texels (naming the count) and maps
    /// smaller than 2×2; negative values are clamped to zero.
    pub fn new(img: &RgbImage) -> Result<EnvMap, RenderError> {
        let (w, h) = (img.width, img.height);
        if w < 2 || h < 2 {
            return Err(RenderError::EnvmapTooSmall {
                width: w,
                height: h,
            });
        }
        let bad = img.data.iter().filter(|v| !v.is_finite()).count();
        if bad > 0 {
            return Err(RenderError::EnvmapNotFinite { count: bad });
        }
        let texels: Vec<Vec3> = img
            .data
            .iter()
            .map(|v| v.clamp(Vec3::ZERO, Vec3::splat(MAX_RADIANCE)))
            .collect();
        let rows = h - 1;
        let dphi = 2.0 * std::f64::consts::PI / w as f64;
        let mut row_solid_angle = Vec::with_capacity(rows);
        let mut weights = vec![0f64; rows * w];
        let lum: Vec<f64> = texels.iter().map(|&v| luminance(v) as f64).collect();
        for r in 0..rows {
            let t0 = std::f64::consts::PI * r as f64 / rows as f64;
            let t1 = std::f64::consts::PI * (r + 1) as f64 / rows as f64;
            let omega = dphi * (t0.cos() - t1.cos());
            row_solid_angle.push(omega as f32);
            for c in 0..w {
                let c1 = (c + 1) % w;
                let l = 0.25
                    * (lum[r * w + c]
                        + lum[r * w + c1]
                        + lum[(r + 1) * w + c]
                        + lum[(r + 1) * w + c1]);
                weights[r * w + c] = l * omega;
            }
        }
        let total: f64 = weights.iter().sum();
        let mut row_cdf = Vec::with_capacity(rows + 1);
        let mut col_cdf = Vec::with_capacity(rows * (w + 1));
        let mut cell_prob = vec![0f32; rows * w];
        row_cdf.push(0.0);
        let mut acc = 0.0;
        for r in 0..rows {
            let row = &weights[r * w..(r + 1) * w];
            let rs: f64 = row.iter().sum();
            acc += rs;
            row_cdf.push(if total > 0.0 { acc / total } else { 0.0 });
            let mut a = 0.0;
            col_cdf.push(0.0);
            for (c, &x) in row.iter().enumerate() {
                a += x;
                col_cdf.push(if rs > 0.0 {
                    a / rs
                } else {
                    (c + 1) as f64 / w as f64
                });
                if total > 0.0 {
                    cell_prob[r * w + c] = (x / total) as f32;
                }
            }
        }
        let row_cos = (0..=rows)
            .map(|r| (PI * r as f32 / rows as f32).cos())
            .collect();
        Ok(EnvMap {
            width: w,
            height: h,
            texels,
            row_cdf,
            col_cdf,
            cell_prob,
            row_solid_angle,
            row_cos,
            total_weight: total,
            guide: None,
        })
    }

    /// The map sampling by what each region of the scene `vis` was
    /// measured in sees ([`crate::guide`]): [`EnvMap::sample_in`] and
    /// [`EnvMap::eval_pdf_in`] then draw a point's light samples mostly
    /// from the directions its cluster sees. A black map stays unguided.
    pub fn guided(mut self, vis: Arc<Visibility>) -> EnvMap {
        self.guide = (self.can_sample() && vis.clusters() > 0).then(|| {
            Arc::new(Guide::bind(
                vis,
                self.width,
                self.height,
                &self.cell_prob,
                &self.row_solid_angle,
            ))
        });
        self
    }

    /// The same map sampling by radiance alone.
    pub fn unguided(mut self) -> EnvMap {
        self.guide = None;
        self
    }

    /// How many of the guide's clusters sample by visibility (0 when
    /// unguided).
    pub fn guided_clusters(&self) -> usize {
        self.guide.as_ref().map_or(0, |g| g.active_clusters())
    }

    /// The visibility the map is guided by, if any.
    pub fn visibility(&self) -> Option<&Arc<Visibility>> {
        self.guide.as_ref().map(|g| &g.vis)
    }

    /// The cluster whose light samples a vertex at `p` draws
    /// ([`EnvMap::sample_in`]); [`NO_CLUSTER`] for an unguided map.
    #[inline]
    pub fn cluster(&self, p: Vec3) -> u32 {
        match &self.guide {
            Some(g) => g.vis.cluster_of(p),
            None => NO_CLUSTER,
        }
    }

    pub fn width(&self) -> usize {
        self.width
    }
    pub fn height(&self) -> usize {
        self.height
    }
    pub fn texels(&self) -> &[Vec3] {
        &self.texels
    }

    /// False when the map is black everywhere (nothing to sample).
    pub fn can_sample(&self) -> bool {
        self.total_weight > 0.0 && self.total_weight.is_finite()
    }

    #[inline]
    fn texel(&self, x: usize, y: usize) -> Vec3 {
        self.texels[y * self.width + x]
    }

    /// Continuous texel coordinates and the cell containing d.
    #[inline]
    fn locate(&self, d: Vec3) -> (usize, usize, f32, f32) {
        locate_cell(self.width, self.height, d)
    }

    /// Radiance arriving from direction `d` (unit), bilinear.
    #[inline]
    pub fn eval(&self, d: Vec3) -> Vec3 {
        let (r, c, fx, fy) = self.locate(d);
        let c1 = (c + 1) % self.width;
        let a = self.texel(c, r) * (1.0 - fx) + self.texel(c1, r) * fx;
        let b = self.texel(c, r + 1) * (1.0 - fx) + self.texel(c1, r + 1) * fx;
        a * (1.0 - fy) + b * fy
    }

    /// [`EnvMap::eval`] and [`EnvMap::pdf`] with one lookup of the cell.
    #[inline]
    pub fn eval_pdf(&self, d: Vec3) -> (Vec3, f32) {
        let (r, c, fx, fy) = self.locate(d);
        let c1 = (c + 1) % self.width;
        let a = self.texel(c, r) * (1.0 - fx) + self.texel(c1, r) * fx;
        let b = self.texel(c, r + 1) * (1.0 - fx) + self.texel(c1, r + 1) * fx;
        (a * (1.0 - fy) + b * fy, self.cell_pdf(r, c))
    }

    /// Solid-angle density of [`EnvMap::sample`] for direction `d`.
    #[inline]
    pub fn pdf(&self, d: Vec3) -> f32 {
        let (r, c, _, _) = self.locate(d);
        self.cell_pdf(r, c)
    }

    #[inline]
    fn cell_pdf(&self, r: usize, c: usize) -> f32 {
        if !self.can_sample() {
            return 0.0;
        }
        let omega = self.row_solid_angle[r];
        if omega <= 0.0 {
            return 0.0;
        }
        self.cell_prob[r * self.width + c] / omega
    }

    /// Samples a direction by radiance alone; returns (direction,
    /// radiance, pdf) or `None` for a black map.
    #[inline]
    pub fn sample(&self, u1: f32, u2: f32) -> Option<(Vec3, Vec3, f32)> {
        if !self.can_sample() {
            return None;
        }
        let (r, c, ur, uc) = self.draw_cell(u1, u2);
        let s = self.in_cell(r, c, ur, uc)?;
        Some((s.dir, s.radiance, s.pdf))
    }

    /// The cell (row, column) the radiance-proportional density draws
    /// from (u1, u2), and the positions left in each draw.
    #[inline]
    fn draw_cell(&self, u1: f32, u2: f32) -> (usize, usize, f64, f64) {
        let (r, ur) = sample_cdf(&self.row_cdf, u1 as f64);
        let w = self.width;
        let (c, uc) = sample_cdf(&self.col_cdf[r * (w + 1)..(r + 1) * (w + 1)], u2 as f64);
        (r, c, ur, uc)
    }

    /// Samples a direction for a vertex in cluster `cluster`
    /// ([`EnvMap::cluster`]): by radiance alone for an unguided map or a
    /// point in no guided cluster; otherwise from the guide's defensive
    /// mixture (`u1` also chooses the component). Returns (direction,
    /// radiance, pdf), the pdf being [`EnvMap::eval_pdf_in`]'s.
    #[inline]
    pub fn sample_in(&self, cluster: u32, u1: f32, u2: f32) -> Option<(Vec3, Vec3, f32)> {
        let Some(g) = self.guide.as_ref().filter(|g| g.active(cluster)) else {
            return self.sample(u1, u2);
        };
        let b = g.defensive();
        let in_cell = |(r, c, ur, uc)| {
            self.in_cell(r, c, ur, uc)
                .map(|s| (s.dir, s.radiance, s.u, s.v))
        };
        let (d, le, u, v) = if u1 < b {
            in_cell(self.draw_cell((u1 / b).min(ONE_BELOW), u2))?
        } else {
            let u = ((u1 - b) / (1.0 - b)).clamp(0.0, ONE_BELOW);
            match g.sample(cluster, u as f64, u2 as f64)? {
                Draw::Cell(k, r1, r2) => in_cell((k / self.width, k % self.width, r1, r2))?,
                Draw::Direction(d, u, v) => (d, self.eval(d), u, v),
            }
        };
        let (r, c) = cell_at(self.width, self.height, u, v);
        let pdf = g.pdf(cluster, u, v, r * self.width + c, self.cell_pdf(r, c));
        (pdf > 0.0 && pdf.is_finite()).then_some((d, le, pdf))
    }

    /// [`EnvMap::eval_pdf`] for a vertex in cluster `cluster`: the density
    /// [`EnvMap::sample_in`] draws `d` with.
    #[inline]
    pub fn eval_pdf_in(&self, cluster: u32, d: Vec3) -> (Vec3, f32) {
        let Some(g) = self.guide.as_ref().filter(|g| g.active(cluster)) else {
            return self.eval_pdf(d);
        };
        let (u, v) = dir_to_uv(d);
        let (r, c, fx, fy) = cell_of_uv(self.width, self.height, u, v);
        let c1 = (c + 1) % self.width;
        let a = self.texel(c, r) * (1.0 - fx) + self.texel(c1, r) * fx;
        let b = self.texel(c, r + 1) * (1.0 - fx) + self.texel(c1, r + 1) * fx;
        let pdf = g.pdf(cluster, u, v, r * self.width + c, self.cell_pdf(r, c));
        (a * (1.0 - fy) + b * fy, pdf)
    }

    /// A direction uniform in solid angle inside cell (r, c), at `ur`
    /// across its columns and `uc` across its rows, with its radiance, the
    /// plain density and its (u, v); `None` for a cell that is never
    /// drawn.
    #[inline]
    fn in_cell(&self, r: usize, c: usize, ur: f64, uc: f64) -> Option<CellSample> {
        let rows = self.height - 1;
        let w = self.width;
        let p = self.cell_prob[r * w + c];
        if p <= 0.0 {
            return None;
        }
        // Uniform in solid angle inside the cell.
        let (c0, c1) = (self.row_cos[r], self.row_cos[r + 1]);
        let cos_t = (c0 + (c1 - c0) * uc as f32).clamp(-1.0, 1.0);
        // In [0, 2): wrapped by one subtraction (exact, as fmod is).
        let u = (c as f32 + 0.5 + ur as f32) / w as f32;
        let u = if u >= 1.0 { u - 1.0 } else { u };
        let sin_t = (1.0 - cos_t * cos_t).max(0.0).sqrt();
        let phi = 2.0 * PI * u;
        let (sp, cp) = sin_cos1(phi);
        let d = Vec3::new(sin_t * sp, cos_t, -sin_t * cp);
        let pdf = p / self.row_solid_angle[r];
        // Radiance by bilinear blend inside the known cell (no atan2/acos).
        let fx = ur as f32;
        let v = lanes::acos(F::<1>([cos_t])).0[0] / PI;
        let fy = (v * rows as f32 - r as f32).clamp(0.0, 1.0);
        let c1 = (c + 1) % w;
        let a = self.texel(c, r) * (1.0 - fx) + self.texel(c1, r) * fx;
        let b = self.texel(c, r + 1) * (1.0 - fx) + self.texel(c1, r + 1) * fx;
        Some(CellSample {
            dir: d,
            radiance: a * (1.0 - fy) + b * fy,
            pdf,
            u: u.min(ONE_BELOW),
            v,
        })
    }
}

/// What [`EnvMap::in_cell`] draws.
struct CellSample {
    dir: Vec3,
    radiance: Vec3,
    pdf: f32,
    u: f32,
    v: f32,
}

/// Inverts a CDF table (`cdf[0] = 0`, last = 1); returns the bin and the
/// position of `u` inside it, in [0, 1).
#[inline]
pub(crate) fn sample_cdf(cdf: &[f64], u: f64) -> (usize, f64) {
    let n = cdf.len() - 1;
    // First index with cdf[i+1] > u: the number of bin ends ≤ u (the
    // ends are non-decreasing). A branch-free halving narrows the range
    // to at most 32 ends, which are counted with a vectorised compare (a
    // sampled u makes every branch of a binary search a coin toss, and
    // its loads a chain).
    let ends = &cdf[1..];
    let mut base = 0usize;
    let mut len = n;
    while len > 32 {
        let half = len / 2;
        let mid = base + half;
        base = if ends[mid] <= u { mid } else { base };
        len -= half;
    }
    let lo = base
        + ends[base..base + len]
            .iter()
            .map(|&e| usize::from(e <= u))
            .sum::<usize>();
    let i = lo.min(n - 1);
    // Skip empty bins at the end.
    let (a, b) = (cdf[i], cdf[i + 1]);
    let t = if b > a {
        ((u - a) / (b - a)).clamp(0.0, 1.0 - 1e-9)
    } else {
        0.5
    };
    (i, t)
}

/// The layout the reference's optimisation loop gives Mitsuba when it
/// assigns a W-column array to the emitter at run time: W − 1 longitude
/// intervals, with columns 0 and W − 1 merged (averaged) into column 0.
/// Its stored `rendered_img.exr` files were rendered this way.
pub fn merge_seam_columns(img: &RgbImage) -> RgbImage {
    let w = img.width;
    if w < 3 {
        return img.clone();
    }
    matflow_scene::Image::from_fn(w - 1, img.height, |x, y| {
        if x == 0 {
            (img.get(0, y) + img.get(w - 1, y)) * 0.5
        } else {
            img.get(x, y)
        }
    })
}

/// Rotates a lat-long map by `deg` about the vertical axis (a horizontal
/// shift that wraps, linear between columns) and scales it by 2^ev.
pub fn rotate_and_expose(env: &RgbImage, deg: f64, ev: f64) -> RgbImage {
    let w = env.width;
    let shift = (deg / 360.0).rem_euclid(1.0) * w as f64;
    let k = 2f64.powf(ev) as f32;
    Image::from_fn(w, env.height, |x, y| {
        let src = (x as f64 - shift).rem_euclid(w as f64);
        let x0 = src.floor() as usize % w;
        let x1 = (x0 + 1) % w;
        let t = (src - src.floor()) as f32;
        (env.get(x0, y) * (1.0 - t) + env.get(x1, y) * t) * k
    })
}

/// The map seen from a turned frame: the texel for direction `d` takes
/// the bilinear lookup of `env` at `to_env · d` (`to_env` a rotation from
/// the new frame into the map's). How a dataset views an object from
/// above while its camera keeps matflow's fixed orientation.
pub fn rotated(env: &RgbImage, to_env: glam::Mat3) -> RgbImage {
    let (w, h) = (env.width, env.height);
    if w < 2 || h < 2 {
        return env.clone();
    }
    Image::from_fn(w, h, |x, y| {
        let u = (x as f32 + 0.5) / w as f32;
        let v = y as f32 / (h - 1) as f32;
        let d = (to_env * uv_to_dir(u, v)).normalize_or(Vec3::Y);
        let (r, c, fx, fy) = locate_cell(w, h, d);
        let c1 = (c + 1) % w;
        let a = env.get(c, r) * (1.0 - fx) + env.get(c1, r) * fx;
        let b = env.get(c, r + 1) * (1.0 - fx) + env.get(c1, r + 1) * fx;
        a * (1.0 - fy) + b * fy
    })
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    #[test]
    fn a_turned_map_looks_up_the_turned_direction() {
        let env = Image::from_fn(64, 32, |x, y| Vec3::new(x as f32, y as f32, 1.0));
        assert_eq!(
            rotated(&env, glam::Mat3::IDENTITY).data.len(),
            env.data.len()
        );
        // The identity keeps texels (the pole rows are one direction each,
        // whose column is arbitrary); x is a column index, so 1e-3 of it
        // is the f32 round trip through angles.
        let same = rotated(&env, glam::Mat3::IDENTITY);
        for y in 1..31 {
            for x in 1..63 {
                let e = (same.get(x, y) - env.get(x, y)).abs().max_element();
                assert!(e < 1e-2, "texel ({x}, {y}) off by {e}");
            }
        }
        // Turning about x by 90 degrees sends the zenith to the horizon.
        let m = glam::Mat3::from_rotation_x(std::f32::consts::FRAC_PI_2);
        let up = EnvMap::new(&env).unwrap().eval(m * Vec3::Y);
        let r = EnvMap::new(&rotated(&env, m)).unwrap().eval(Vec3::Y);
        assert!((up - r).abs().max_element() < 1.0, "{up} vs {r}");
    }

    #[test]
    fn cdf_inversion_finds_the_bin_a_plain_search_finds() {
        let mut r = crate::rng::Pcg32::new(11, 3);
        for n in [1usize, 2, 3, 31, 32, 33, 64, 65, 100, 1024, 1025, 4099] {
            // Random weights with runs of empty bins.
            let w: Vec<f64> = (0..n)
                .map(|_| {
                    let x = r.next_f32() as f64;
                    if x < 0.3 {
                        0.0
                    } else {
                        x
                    }
                })
                .collect();
            let total: f64 = w.iter().sum();
            let mut cdf = vec![0.0];
            let mut acc = 0.0;
            for x in &w {
                acc += x;
                cdf.push(if total > 0.0 { acc / total } else { 0.0 });
            }
            let mut us: Vec<f64> = (0..2000).map(|_| r.next_f32() as f64).collect();
            us.extend(cdf.iter().copied().filter(|&c| c < 1.0)); // exactly on ends
            us.push(0.0);
            for u in us {
                let want = cdf[1..].partition_point(|&e| e <= u).min(n - 1);
                let (i, t) = sample_cdf(&cdf, u);
                assert_eq!(i, want, "n {n} u {u}");
                assert!((0.0..1.0).contains(&t));
            }
        }
    }

    fn test_map() -> RgbImage {
        Image::from_fn(32, 16, |x, y| {
            let base = 0.05 + 0.02 * ((x * 7 + y * 3) % 5) as f32;
            if (20..23).contains(&x) && (3..5).contains(&y) {
                Vec3::new(40.0, 35.0, 30.0)
            } else {
                Vec3::new(base, base * 1.2, base * 1.5)
            }
        })
    }

    #[test]
    fn orientation_matches_mitsuba() {
        // u = 0 is straight ahead (−z), 0.25 is +x, 0.5 behind (+z), 0.75 is −x.
        let cases = [
            (Vec3::NEG_Z, 0.0),
            (Vec3::X, 0.25),
            (Vec3::Z, 0.5),
            (Vec3::NEG_X, 0.75),
        ];
        for (d, u) in cases {
            let (uu, v) = dir_to_uv(d);
            assert!((uu - u).abs() < 1e-6, "{d}: {uu}");
            assert!((v - 0.5).abs() < 1e-6);
        }
        assert!(dir_to_uv(Vec3::Y).1.abs() < 1e-6);
        for (u, v) in [(0.1, 0.2), (0.6, 0.9), (0.99, 0.5)] {
            let (uu, vv) = dir_to_uv(uv_to_dir(u, v));
            assert!((uu - u).abs() < 1e-5 && (vv - v).abs() < 1e-5);
        }
    }

    #[test]
    fn texel_centres_reproduce_texels() {
        let img = test_map();
        let env = EnvMap::new(&img).unwrap();
        for y in 1..15 {
            for x in 0..32 {
                let u = (x as f32 + 0.5) / 32.0;
                let v = y as f32 / 15.0;
                let got = env.eval(uv_to_dir(u, v));
                assert!(
                    (got - img.get(x, y)).abs().max_element()
                        < 1e-3 * (1.0 + img.get(x, y).max_element()),
                    "({x},{y})"
                );
            }
        }
    }

    /// Midpoint rule over the sphere on an n×n (u, cos θ) grid.
    pub(crate) fn sphere_integral(n: usize, f: impl Fn(Vec3) -> f64) -> f64 {
        let mut acc = 0.0f64;
        for i in 0..n {
            for j in 0..n {
                let u = (i as f32 + 0.5) / n as f32;
                let ct = 1.0 - 2.0 * (j as f32 + 0.5) / n as f32;
                let st = (1.0 - ct * ct).sqrt();
                let phi = 2.0 * PI * u;
                acc += f(Vec3::new(st * phi.sin(), ct, -st * phi.cos()));
            }
        }
        acc * 4.0 * std::f64::consts::PI / (n * n) as f64
    }

    #[test]
    fn pdf_integrates_to_one_and_matches_sampling() {
        let env = EnvMap::new(&test_map()).unwrap();
        // Integrate pdf over the sphere with a fine (u, cos θ) grid.
        let total = sphere_integral(1024, |d| env.pdf(d) as f64);
        assert!((total - 1.0).abs() < 2e-3, "∫pdf = {total}");
        // Sampled directions report the same pdf as pdf() and radiance as eval().
        let mut rng = crate::rng::Pcg32::new(3, 4);
        for _ in 0..10_000 {
            let (d, l, p) = env.sample(rng.next_f32(), rng.next_f32()).unwrap();
            assert!((d.length() - 1.0).abs() < 1e-4);
            let q = env.pdf(d);
            assert!((p - q).abs() <= 1e-3 * p.max(q), "{p} vs {q}");
            assert!((l - env.eval(d)).abs().max_element() < 1e-3 * (1.0 + l.max_element()));
            assert_eq!(
                env.eval_pdf(d),
                (env.eval(d), q),
                "one lookup, same answers"
            );
        }
    }

    #[test]
    fn importance_sampled_irradiance_matches_quadrature() {
        let env = EnvMap::new(&test_map()).unwrap();
        // E = ∫ L(ω) max(0, ω·n) dω for n = +y, by sampling and by quadrature.
        let n = Vec3::new(0.3, 0.8, -0.2).normalize();
        let mut rng = crate::rng::Pcg32::new(11, 5);
        let m = 200_000;
        let mut est = 0.0f64;
        for _ in 0..m {
            let (d, l, p) = env.sample(rng.next_f32(), rng.next_f32()).unwrap();
            est += (luminance(l) * d.dot(n).max(0.0) / p) as f64;
        }
        est /= m as f64;
        let quad = sphere_integral(1024, |d| {
            (luminance(env.eval(d)) * d.dot(n).max(0.0)) as f64
        });
        assert!((est - quad).abs() / quad < 0.01, "{est} vs {quad}");
    }

    #[test]
    fn black_and_invalid_maps() {
        let env = EnvMap::new(&Image::new(8, 4, Vec3::ZERO)).unwrap();
        assert!(!env.can_sample());
        assert!(env.sample(0.3, 0.3).is_none());
        assert_eq!(env.pdf(Vec3::Y), 0.0);
        let mut bad = Image::new(8, 4, Vec3::ONE);
        bad.set(1, 1, Vec3::new(f32::NAN, 0.0, 0.0));
        assert!(EnvMap::new(&bad)
            .unwrap_err()
            .to_string()
            .contains("1 texel"));
        let huge = EnvMap::new(&Image::new(8, 4, Vec3::splat(f32::MAX))).unwrap();
        assert!(huge.eval(Vec3::X).is_finite());
        assert!(huge.pdf(Vec3::X).is_finite() && huge.pdf(Vec3::X) > 0.0);
    }

    #[test]
    fn rotation_shifts_columns_and_exposure_scales() {
        let env = Image::from_fn(8, 2, |x, _| Vec3::splat(x as f32));
        let r = rotate_and_expose(&env, 90.0, 1.0);
        // 90° = 2 columns: output column 2 reads input column 0.
        assert_eq!(r.get(2, 0), Vec3::splat(0.0));
        assert_eq!(r.get(3, 1), Vec3::splat(2.0));
        let full = rotate_and_expose(&env, 360.0, 0.0);
        assert_eq!(full.data, env.data);
    }
}
