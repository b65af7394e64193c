//! Frozen light paths: the path tracer's random decisions, traced once.
//!
//! Geometry never changes during inverse rendering, so every ray the path
//! tracer would shoot for a given (pixel, sample) can be traced once and
//! kept. What is kept per path vertex is only what the estimator needs to
//! be re-evaluated for *any* materials and *any* environment map: the pixel
//! whose material the vertex uses, and per direction the four cached angles
//! ([`Geo`]), a fixed weight (MIS weight over pdf, visibility folded in)
//! and, for directions that reach the sky, the envmap cell they look up.
//!
//! The estimator re-evaluated this way is the ordinary path-traced one with
//! its sampling densities frozen at the values of the scene the cache was
//! traced with ("path replay" with fixed random numbers). It stays unbiased
//! for other materials and envmaps as long as those densities are positive
//! wherever the integrand is, which holds for the BSDF mixture (its diffuse
//! half covers the hemisphere) and for an envmap sampled with a floor.
//!
//! Lamps ([`matflow_render::Lamp`]) are light sources like the envmap's
//! texels: a scene traced with `k` lamps records each unoccluded lamp
//! sample as a sky record whose cell is texel `W·H + k` of the *light
//! vector* (the W·H texels, then two rows of W: the lamps, padded so that
//! a record's bilinear taps stay inside; [`light_len`]), with weights 0 on
//! the other taps, and a lamp's entry is its intensity over
//! `lamp_scale`²; a distant lamp's (the sun's) is its irradiance over
//! [`sun_scale`], the solid angle of a mean texel, so that the entry is
//! the radiance one texel would need to give that light. Every estimator
//! is linear in the light vector alike.
//!
//! Layout: one [`RowPaths`] per image row (built in parallel, never
//! concatenated); inside a row, per pixel, its paths' vertices in order,
//! each vertex followed in the record array by its sky records and then, if
//! the path continues, its continuation record.

use std::sync::atomic::{AtomicUsize, Ordering};

use glam::Vec3;
use matflow_render::envmap::locate_cell;
use matflow_render::integrator::{PathSink, Wavefront, BATCH_PIXELS};
use matflow_render::{RenderOptions, RenderScene, RenderStats};
use rayon::prelude::*;

use crate::brdf::Geo;

/// Vertex `q` of a camera ray that escaped: its single record is the sky
/// seen directly (weight 1, no BSDF).
pub const NO_MATERIAL: u32 = u32::MAX;
/// First vertex of a path.
pub const V_START: u16 = 1;
/// The vertex's last record continues the path to the next vertex.
pub const V_CONT: u16 = 2;
/// Longest path the evaluators accept (segments).
pub const MAX_DEPTH: u32 = 8;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(C)]
pub struct Vertex {
    /// Pixel whose material this vertex uses, or [`NO_MATERIAL`].
    pub q: u32,
    /// Number of sky records.
    pub n_env: u16,
    pub flags: u16,
}

impl Vertex {
    #[inline]
    pub fn is_start(&self) -> bool {
        self.flags & V_START != 0
    }
    #[inline]
    pub fn has_cont(&self) -> bool {
        self.flags & V_CONT != 0
    }
    #[inline]
    pub fn n_records(&self) -> usize {
        self.n_env as usize + self.has_cont() as usize
    }
}

/// One direction at a vertex.
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(C)]
pub struct Record {
    pub geo: Geo,
    /// Fixed estimator weight: MIS weight / pdf (sky records), 1 / pdf
    /// (continuations), 1 (sky seen by the camera).
    pub w: f32,
    /// Envmap cell r·W + c (sky records only).
    pub cell: u16,
    /// Bilinear position inside the cell, quantised to 1/65535.
    pub fx: u16,
    pub fy: u16,
    pub _pad: u16,
}

/// Bilinear taps of a sky record: texel indices and weights.
#[inline]
pub fn taps(rec: &Record, env_w: usize) -> ([usize; 4], [f32; 4]) {
    let cell = rec.cell as usize;
    let (r, c) = (cell / env_w, cell % env_w);
    let c1 = if c + 1 == env_w { 0 } else { c + 1 };
    let fx = rec.fx as f32 * (1.0 / 65535.0);
    let fy = rec.fy as f32 * (1.0 / 65535.0);
    (
        [
            r * env_w + c,
            r * env_w + c1,
            (r + 1) * env_w + c,
            (r + 1) * env_w + c1,
        ],
        [
            (1.0 - fx) * (1.0 - fy),
            fx * (1.0 - fy),
            (1.0 - fx) * fy,
            fx * fy,
        ],
    )
}

/// Radiance a sky record receives from `env` (W×H texels, row-major).
#[inline]
pub fn sky(rec: &Record, env: &[Vec3], env_w: usize) -> Vec3 {
    let (i, w) = taps(rec, env_w);
    env[i[0]] * w[0] + env[i[1]] * w[1] + env[i[2]] * w[2] + env[i[3]] * w[3]
}

#[derive(Clone, Debug, Default)]
pub struct RowPaths {
    /// Per pixel of the row, start of its vertices (len = width + 1).
    pub vert_start: Vec<u32>,
    /// Per pixel of the row, start of its records (len = width + 1).
    pub rec_start: Vec<u32>,
    pub vertices: Vec<Vertex>,
    pub records: Vec<Record>,
}

#[derive(Clone, Copy, Debug)]
pub struct CacheOptions {
    pub spp: u32,
    /// Mitsuba's `max_depth`: ray segments per path (4 = three bounces).
    pub max_depth: u32,
    pub seed: u64,
    /// Size of the envmap that will be optimised (the taps refer to it).
    pub env_width: usize,
    pub env_height: usize,
    /// A lamp's entry in the light vector is its intensity over this,
    /// squared (a length of the scene's: the entry is then the
    /// irradiance the lamp gives at that distance, comparable with the
    /// envmap's radiance).
    pub lamp_scale: f32,
}

impl Default for CacheOptions {
    fn default() -> Self {
        CacheOptions {
            spp: 16,
            max_depth: 4,
            seed: 0,
            env_width: 32,
            env_height: 16,
            lamp_scale: 1.0,
        }
    }
}

/// What a distant lamp's entry in the light vector of a `w`×`h` envmap is
/// measured in: its irradiance over this, the mean texel's solid angle.
pub fn sun_scale(w: usize, h: usize) -> f32 {
    (4.0 * std::f64::consts::PI / (w * h).max(1) as f64) as f32
}

/// Length of the light vector of a `w`×`h` envmap and `lamps` lamps (see
/// the module documentation).
pub fn light_len(w: usize, h: usize, lamps: usize) -> usize {
    w * h + if lamps > 0 { 2 * w } else { 0 }
}

/// Whether `lamps` lamps fit the light vector of a `w`×`h` envmap (at
/// most one per column, at most 65535 entries) with entries scaled by a
/// positive finite `scale`; no lamps always do.
pub fn check_lamps(lamps: usize, w: usize, h: usize, scale: f32) -> Result<(), CacheError> {
    if lamps == 0 {
        return Ok(());
    }
    if lamps > w || light_len(w, h, lamps) > 65535 {
        return Err(CacheError::Lamps { lamps, width: w });
    }
    if !(scale > 0.0 && scale.is_finite()) {
        return Err(CacheError::LampScale(scale));
    }
    Ok(())
}

#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub struct CacheStats {
    pub rays: u64,
    pub vertices: u64,
    pub records: u64,
    pub bytes: u64,
}

pub struct PathCache {
    pub width: usize,
    pub height: usize,
    pub spp: u32,
    pub max_depth: u32,
    pub env_width: usize,
    pub env_height: usize,
    /// Lamps of the scene traced (their records' cells follow the
    /// envmap's), and the scale of their entries.
    pub lamps: usize,
    pub lamp_scale: f32,
    /// Per lamp, whether it is distant (the sun: its entry is measured in
    /// [`sun_scale`]).
    pub distant: Vec<bool>,
    pub rows: Vec<RowPaths>,
    pub stats: CacheStats,
}

#[derive(Debug, thiserror::Error)]
pub enum CacheError {
    #[error("frozen paths need at least 1 sample per pixel")]
    NoSamples,
    #[error("max_depth must be in 2..={max}, got {got}")]
    Depth { got: u32, max: u32 },
    #[error("envmap size {width}x{height} unsupported (2x2 up to 65535 texels)")]
    EnvmapSize { width: usize, height: usize },
    #[error("{lamps} lamps for a {width}-texel-wide envmap (at most one per column, and a 65535-texel light vector)")]
    Lamps { lamps: usize, width: usize },
    #[error("lamp scale {0} is not a positive finite length")]
    LampScale(f32),
    #[error("row {row} holds more than 4 294 967 295 records; lower spp")]
    Overflow { row: usize },
    #[error("stored paths: {0}")]
    Layout(&'static str),
}

/// Which materials each pixel's kept paths meet (texel indices as the
/// render scene numbers them: pixels, then objects, then background
/// vertices), sorted, each once: all an edit needs to find the pixels it
/// can reach, a small part of the paths' size.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Reach {
    pub width: usize,
    pub height: usize,
    /// Pixel `p`'s materials are `texels[offsets[p]..offsets[p + 1]]`.
    offsets: Vec<u32>,
    texels: Vec<u32>,
}

impl Reach {
    /// From its arrays, checked: one offset per pixel and one more,
    /// starting at 0, never decreasing, ending at the texel count.
    pub fn from_parts(
        width: usize,
        height: usize,
        offsets: Vec<u32>,
        texels: Vec<u32>,
    ) -> Result<Reach, CacheError> {
        let npix = width
            .checked_mul(height)
            .ok_or(CacheError::Layout("size"))?;
        if offsets.len() != npix + 1
            || offsets[0] != 0
            || offsets[npix] as usize != texels.len()
            || offsets.windows(2).any(|p| p[0] > p[1])
        {
            return Err(CacheError::Layout("reach offsets are inconsistent"));
        }
        Ok(Reach {
            width,
            height,
            offsets,
            texels,
        })
    }

    /// The per-pixel offsets (`width·height + 1`) and the texels.
    pub fn parts(&self) -> (&[u32], &[u32]) {
        (&self.offsets, &self.texels)
    }

    /// The materials pixel `p`'s paths meet.
    #[inline]
    pub fn texels_of(&self, p: usize) -> &[u32] {
        &self.texels[self.offsets[p] as usize..self.offsets[p + 1] as usize]
    }

    /// Pixels whose value a change of the materials at `changed` texels
    /// can alter: those whose own texel changed or whose paths meet a
    /// changed texel (row-major, ascending).
    pub fn pixels_reaching(&self, changed: &[bool]) -> Vec<u32> {
        let w = self.width;
        let rows: Vec<Vec<u32>> = (0..self.height)
            .into_par_iter()
            .map(|y| {
                (y * w..(y + 1) * w)
                    .filter(|&p| {
                        changed.get(p) == Some(&true)
                            || self
                                .texels_of(p)
                                .iter()
                                .any(|&q| changed.get(q as usize) == Some(&true))
                    })
                    .map(|p| p as u32)
                    .collect()
            })
            .collect();
        rows.concat()
    }

    /// An image rendered with `opts` from a scene whose materials have
    /// changed at the `changed` texels since `base` was rendered (with
    /// the same options, geometry and lighting): the pixels these paths
    /// say the change can reach are re-traced with the base render's own
    /// sample streams (so they equal a full re-render bit for bit), the
    /// rest keep their base value.
    pub fn rerender_changed(
        &self,
        base: &matflow_scene::RgbImage,
        edited: &RenderScene,
        opts: &RenderOptions,
        changed: &[bool],
    ) -> matflow_scene::RgbImage {
        let px = self.pixels_reaching(changed);
        let mut img = base.clone();
        if !px.is_empty() {
            let vals = matflow_render::integrator::render_pixels(edited, opts, &px);
            for (p, v) in px.iter().zip(vals) {
                img.data[*p as usize] = v;
            }
        }
        img
    }
}

impl PathCache {
    pub fn npix(&self) -> usize {
        self.width * self.height
    }

    /// Length of the light vector the records index ([`light_len`]).
    pub fn light_len(&self) -> usize {
        light_len(self.env_width, self.env_height, self.lamps)
    }

    /// Traces `spp` paths per pixel through `scene`, whose materials and
    /// envmap define the sampling densities that are then frozen. Pixel
    /// footprints are box-filtered (each sample belongs to its own pixel).
    /// `progress(rows_done, rows)` is called as rows finish.
    pub fn build(
        scene: &RenderScene,
        opts: &CacheOptions,
        progress: &(dyn Fn(usize, usize) + Sync),
    ) -> Result<PathCache, CacheError> {
        if opts.spp == 0 {
            return Err(CacheError::NoSamples);
        }
        if !(2..=MAX_DEPTH).contains(&opts.max_depth) {
            return Err(CacheError::Depth {
                got: opts.max_depth,
                max: MAX_DEPTH,
            });
        }
        if opts.env_width < 2 || opts.env_height < 2 || opts.env_width * opts.env_height > 65535 {
            return Err(CacheError::EnvmapSize {
                width: opts.env_width,
                height: opts.env_height,
            });
        }
        let lamps = scene.lamps.len();
        check_lamps(lamps, opts.env_width, opts.env_height, opts.lamp_scale)?;
        let (w, h) = (scene.camera.width, scene.camera.height);
        let done = AtomicUsize::new(0);
        let rows: Vec<Result<(RowPaths, u64), CacheError>> = (0..h)
            .into_par_iter()
            .map(|y| {
                let r = trace_row(scene, opts, y);
                let d = done.fetch_add(1, Ordering::Relaxed) + 1;
                progress(d, h);
                r
            })
            .collect();
        let mut out = Vec::with_capacity(h);
        let mut stats = CacheStats::default();
        for r in rows {
            let (row, rays) = r?;
            stats.rays += rays;
            stats.vertices += row.vertices.len() as u64;
            stats.records += row.records.len() as u64;
            stats.bytes += (row.vertices.capacity() * std::mem::size_of::<Vertex>()
                + row.records.capacity() * std::mem::size_of::<Record>()
                + (row.vert_start.capacity() + row.rec_start.capacity()) * 4)
                as u64;
            out.push(row);
        }
        Ok(PathCache {
            width: w,
            height: h,
            spp: opts.spp,
            max_depth: opts.max_depth,
            env_width: opts.env_width,
            env_height: opts.env_height,
            lamps,
            lamp_scale: opts.lamp_scale,
            distant: scene.lamps.iter().map(|l| l.is_distant()).collect(),
            rows: out,
            stats,
        })
    }

    /// Vertices and records of pixel (x, y).
    #[inline]
    /// How many pixels have a path that starts on a surface (the others
    /// see only the sky).
    pub fn surface_pixels(&self) -> usize {
        (0..self.height)
            .map(|y| {
                (0..self.width)
                    .filter(|&x| self.pixel(x, y).0.iter().any(|v| v.q != NO_MATERIAL))
                    .count()
            })
            .sum()
    }

    pub fn pixel(&self, x: usize, y: usize) -> (&[Vertex], &[Record]) {
        let row = &self.rows[y];
        let (v0, v1) = (row.vert_start[x] as usize, row.vert_start[x + 1] as usize);
        let (r0, r1) = (row.rec_start[x] as usize, row.rec_start[x + 1] as usize);
        (&row.vertices[v0..v1], &row.records[r0..r1])
    }

    /// Per pixel, the materials its paths meet: what an edit needs of
    /// these paths to know which pixels it reaches ([`Reach`]).
    pub fn reach(&self) -> Reach {
        let (w, h) = (self.width, self.height);
        let mut offsets = Vec::with_capacity(w * h + 1);
        let mut texels = Vec::new();
        offsets.push(0u32);
        let mut seen = Vec::new();
        for y in 0..h {
            for x in 0..w {
                seen.clear();
                seen.extend(
                    self.pixel(x, y)
                        .0
                        .iter()
                        .map(|v| v.q)
                        .filter(|&q| q != NO_MATERIAL),
                );
                seen.sort_unstable();
                seen.dedup();
                texels.extend_from_slice(&seen);
                offsets.push(texels.len() as u32);
            }
        }
        Reach {
            width: w,
            height: h,
            offsets,
            texels,
        }
    }
}

fn sky_record(geo: Geo, w: f32, d: Vec3, ew: usize, eh: usize) -> Record {
    let (r, c, fx, fy) = locate_cell(ew, eh, d);
    Record {
        geo,
        w,
        cell: (r * ew + c) as u16,
        fx: (fx.clamp(0.0, 1.0) * 65535.0 + 0.5) as u16,
        fy: (fy.clamp(0.0, 1.0) * 65535.0 + 0.5) as u16,
        _pad: 0,
    }
}

/// The path tracer's events for one path, kept as vertices and records
/// (see the module documentation for the layout); a row is its pixels'
/// paths' in order.
#[derive(Default, Clone)]
struct Recorder {
    vertices: Vec<Vertex>,
    records: Vec<Record>,
    ew: usize,
    eh: usize,
    /// Per lamp, what its entry is measured in: lamp_scale² for a point,
    /// [`sun_scale`] for a distant lamp.
    lamp_area: std::sync::Arc<[f32]>,
    /// Index of the current vertex in `vertices`.
    vi: usize,
    /// Cached angles of the BSDF sample being traced.
    geo: Geo,
}

impl Recorder {
    fn sky(&mut self, geo: Geo, w: f32, d: Vec3) {
        if w.is_finite() && w > 0.0 {
            self.records.push(sky_record(geo, w, d, self.ew, self.eh));
            self.vertices[self.vi].n_env += 1;
        }
    }
}

impl PathSink for Recorder {
    fn camera_sky(&mut self, dir: Vec3) {
        self.vertices.push(Vertex {
            q: NO_MATERIAL,
            n_env: 1,
            flags: V_START,
        });
        self.records
            .push(sky_record(Geo::default(), 1.0, dir, self.ew, self.eh));
    }

    fn vertex(&mut self, q: usize, first: bool) {
        self.vi = self.vertices.len();
        self.vertices.push(Vertex {
            q: q as u32,
            n_env: 0,
            flags: if first { V_START } else { 0 },
        });
    }

    fn emitter(&mut self, n: Vec3, v: Vec3, l: Vec3, weight: f32) {
        let geo = Geo::new(n, v, l);
        if geo.lit() {
            self.sky(geo, weight, l);
        }
    }

    fn lamp(&mut self, n: Vec3, v: Vec3, l: Vec3, k: usize, weight: f32) {
        let geo = Geo::new(n, v, l);
        let w = weight * self.lamp_area.get(k).copied().unwrap_or(0.0);
        if geo.lit() && w.is_finite() && w > 0.0 {
            self.records.push(Record {
                geo,
                w,
                cell: (self.ew * self.eh + k) as u16,
                fx: 0,
                fy: 0,
                _pad: 0,
            });
            self.vertices[self.vi].n_env += 1;
        }
    }

    fn bsdf_dir(&mut self, n: Vec3, v: Vec3, l: Vec3) -> bool {
        self.geo = Geo::new(n, v, l);
        // A direction whose n·l quantises to 0 reflects nothing here.
        self.geo.lit()
    }

    fn object_dir(&mut self) -> bool {
        // Kept for reachability only: no BRDF geometry (the frozen-path
        // estimators work on screen-space materials; inverse rendering
        // has no objects).
        self.geo = Geo::default();
        true
    }

    fn bsdf_sky(&mut self, l: Vec3, weight: f32) {
        self.sky(self.geo, weight, l);
    }

    fn bounce(&mut self, weight: f32) -> bool {
        if !weight.is_finite() {
            return false;
        }
        self.records.push(Record {
            geo: self.geo,
            w: weight,
            cell: 0,
            fx: 0,
            fy: 0,
            _pad: 0,
        });
        self.vertices[self.vi].flags |= V_CONT;
        true
    }
}

/// Traces row `y` with the renderer's own loop (its [`Wavefront`], in
/// batches of [`BATCH_PIXELS`] pixels) and a [`Recorder`] per path as the
/// sink, box-filtered (each sample in its pixel).
fn trace_row(
    scene: &RenderScene,
    opts: &CacheOptions,
    y: usize,
) -> Result<(RowPaths, u64), CacheError> {
    let w = scene.camera.width;
    let mut row = RowPaths {
        vert_start: Vec::with_capacity(w + 1),
        rec_start: Vec::with_capacity(w + 1),
        vertices: Vec::new(),
        records: Vec::new(),
    };
    let render_opts = RenderOptions {
        spp: opts.spp,
        max_depth: opts.max_depth,
        seed: opts.seed,
        ..Default::default()
    };
    let spp = opts.spp.max(1) as usize;
    let mut st = RenderStats::default();
    let push_start = |row: &mut RowPaths| -> Result<(), CacheError> {
        let (nv, nr) = (row.vertices.len(), row.records.len());
        if nv > u32::MAX as usize || nr > u32::MAX as usize {
            return Err(CacheError::Overflow { row: y });
        }
        row.vert_start.push(nv as u32);
        row.rec_start.push(nr as u32);
        Ok(())
    };
    let mut wave = Wavefront::default();
    let mut sinks = vec![
        Recorder {
            ew: opts.env_width,
            eh: opts.env_height,
            lamp_area: scene
                .lamps
                .iter()
                .map(|l| {
                    if l.is_distant() {
                        sun_scale(opts.env_width, opts.env_height)
                    } else {
                        opts.lamp_scale * opts.lamp_scale
                    }
                })
                .collect(),
            ..Default::default()
        };
        BATCH_PIXELS * spp
    ];
    let mut pixels = Vec::with_capacity(BATCH_PIXELS);
    for x0 in (0..w).step_by(BATCH_PIXELS) {
        pixels.clear();
        pixels.extend((x0..(x0 + BATCH_PIXELS).min(w)).map(|x| (y * w + x) as u32));
        let n = pixels.len() * spp;
        for r in &mut sinks[..n] {
            r.vertices.clear();
            r.records.clear();
        }
        wave.trace_pixels(
            scene,
            &render_opts,
            &pixels,
            opts.spp,
            &mut st,
            &mut sinks[..n],
        );
        for paths in sinks[..n].chunks(spp) {
            push_start(&mut row)?;
            for r in paths {
                row.vertices.extend_from_slice(&r.vertices);
                row.records.extend_from_slice(&r.records);
            }
        }
    }
    push_start(&mut row)?;
    row.vertices.shrink_to_fit();
    row.records.shrink_to_fit();
    Ok((row, st.total_rays()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testutil::{materials_of, room, texels};
    use crate::transport::pixel_sum;

    /// The recorder is the renderer's loop with a sink: replaying each
    /// recorded path with the materials and envmap it was traced with gives
    /// the radiance the forward renderer computes for that (pixel, sample),
    /// up to the recorder's 16-bit quantisation of angles and envmap taps.
    /// With lamps and a sun too: their records index the light vector
    /// after the envmap's texels, each entry the lamp's intensity over the
    /// lamp scale squared, the sun's irradiance over the mean texel's
    /// solid angle.
    /// A pixel is reached by a change exactly when its own texel or a
    /// texel one of its paths' vertices uses changed; the reach lists are
    /// each pixel's vertex texels, sorted, once each.
    #[test]
    fn reach_lists_each_pixels_vertex_texels_once() {
        let t = room(5, 24);
        let opts = CacheOptions {
            spp: 4,
            max_depth: 4,
            seed: 2,
            env_width: t.env.width,
            env_height: t.env.height,
            lamp_scale: 1.0,
        };
        let cache = PathCache::build(&t.scene, &opts, &|_, _| {}).unwrap();
        let reach = cache.reach();
        let n = cache.npix();
        let (offsets, texels) = reach.parts();
        for p in 0..n {
            let mine = reach.texels_of(p);
            assert!(mine.windows(2).all(|w| w[0] < w[1]), "sorted, once each");
            let (v, _) = cache.pixel(p % cache.width, p / cache.width);
            for q in v.iter().map(|v| v.q).filter(|&q| q != NO_MATERIAL) {
                assert!(mine.binary_search(&q).is_ok());
            }
            assert!(mine.iter().all(|q| v.iter().any(|v| v.q == *q)));
        }
        for k in [1usize, 7, 40] {
            let changed: Vec<bool> = (0..n).map(|i| i % 97 < k).collect();
            let brute: Vec<u32> = (0..n)
                .filter(|&p| {
                    let (v, _) = cache.pixel(p % cache.width, p / cache.width);
                    changed[p]
                        || v.iter()
                            .any(|v| v.q != NO_MATERIAL && changed[v.q as usize])
                })
                .map(|p| p as u32)
                .collect();
            assert_eq!(reach.pixels_reaching(&changed), brute);
        }
        let rebuilt =
            Reach::from_parts(reach.width, reach.height, offsets.to_vec(), texels.to_vec());
        assert_eq!(rebuilt.unwrap(), reach);
        let mut bad = offsets.to_vec();
        bad[3] = bad[4] + 1;
        assert!(Reach::from_parts(reach.width, reach.height, bad, texels.to_vec()).is_err());
        assert!(
            Reach::from_parts(reach.width, reach.height + 1, offsets.to_vec(), vec![]).is_err()
        );
    }

    #[test]
    fn recorded_paths_replay_to_the_renderers_radiance() {
        for (seed, lamps) in [(3u64, false), (8, false), (3, true)] {
            let mut t = room(seed, 40);
            let (ew, eh) = (t.env.width, t.env.height);
            let lamp_scale = 2.0f32;
            let mut env = texels(&t.env);
            if lamps {
                let depth = t.scene.mesh.positions.iter().map(|p| -p.z).sum::<f32>()
                    / t.scene.mesh.positions.len() as f32;
                let sites = [
                    (Vec3::new(0.2, 0.3, -0.4 * depth), Vec3::new(3.0, 2.0, 1.0)),
                    (Vec3::new(-0.3, 0.1, -0.6 * depth), Vec3::new(0.5, 1.0, 2.0)),
                ];
                let sun = matflow_render::Lamp::sun(
                    Vec3::new(0.3, 0.8, 0.4),
                    texels(&t.env)[0] * sun_scale(ew, eh) * 20.0,
                );
                let lit: Vec<_> = sites
                    .iter()
                    .map(|&(position, i)| matflow_render::Lamp::point(position, i * depth * depth))
                    .chain([sun])
                    .collect();
                t.scene.set_lamps(lit.clone()).unwrap();
                env.extend(lit.iter().map(|l| {
                    if l.is_distant() {
                        l.intensity / sun_scale(ew, eh)
                    } else {
                        l.intensity / (lamp_scale * lamp_scale)
                    }
                }));
                env.resize(light_len(ew, eh, lit.len()), Vec3::ZERO);
            }
            let opts = CacheOptions {
                spp: 1,
                max_depth: 4,
                seed: 11,
                env_width: ew,
                env_height: eh,
                lamp_scale,
            };
            let cache = PathCache::build(&t.scene, &opts, &|_, _| {}).unwrap();
            assert_eq!(cache.light_len(), env.len());
            let mats = materials_of(&t.maps);
            let ropts = RenderOptions {
                spp: 1,
                max_depth: 4,
                seed: 11,
                ..Default::default()
            };
            let mut st = RenderStats::default();
            let mut wave = Wavefront::default();
            let (mut worst, mut lit) = (0.0f32, 0);
            let (mut sum_diff, mut sum_abs) = (0.0f64, 0.0f64);
            for y in 0..cache.height {
                for x in 0..cache.width {
                    // The renderer's own route for the pixel's sample.
                    let pix = (y * cache.width + x) as u32;
                    wave.trace_pixels(&t.scene, &ropts, &[pix], 1, &mut st, &mut [()]);
                    let a = wave.result(0).1;
                    let b = pixel_sum(&cache, x, y, &mats, &env);
                    let err = (a - b).abs().max_element() / (a.max_element() + 1e-3);
                    worst = worst.max(err);
                    lit += (a.max_element() > 0.0) as usize;
                    assert!(
                        err < 1e-2,
                        "seed {seed} (lamps {lamps}) pixel ({x}, {y}): render {a} replay {b}"
                    );
                    sum_diff += (a - b).abs().element_sum() as f64;
                    sum_abs += a.element_sum() as f64;
                }
            }
            assert!(lit > cache.npix() / 2, "most pixels carry light");
            assert!(worst > 0.0, "quantisation shows somewhere");
            let rel = sum_diff / sum_abs;
            assert!(rel < 1e-4, "seed {seed}: mean relative difference {rel}");
        }
    }
}
