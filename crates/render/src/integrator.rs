//! The forward path tracer (unidirectional, next-event estimation towards
//! the environment map, power-heuristic MIS), following Mitsuba 3's `path`
//! integrator as the reference uses it: `max_depth` counts ray segments
//! (4 = camera ray + up to three bounces), no Russian roulette below that,
//! emitters visible to camera rays.
//!
//! Determinism: every (pixel, sample) draws from its own [`Sampler`] stream
//! keyed by (seed, pixel, sample); tiles are rendered in parallel into private
//! buffers and merged in tile order, so the image bytes do not depend on the
//! thread count.

use std::sync::atomic::{AtomicUsize, Ordering};

use glam::{Vec2, Vec3};
use matflow_scene::{Image, RgbImage};
use rayon::prelude::*;

use matflow_geom::{Hit, PACKET};

use crate::bsdf;
use crate::filter::PixelFilter;
use crate::rng::Sampler;
use crate::scene::RenderScene;
use crate::warp::Frame;

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RenderOptions {
    pub spp: u32,
    /// Maximum number of ray segments per path (Mitsuba's `max_depth`).
    pub max_depth: u32,
    pub seed: u64,
    pub filter: PixelFilter,
    /// Reproduce the reference's sampling-frame defect: its BSDF returns the
    /// sampled direction in world space where Mitsuba expects the local
    /// shading frame, so the ray actually traced is that vector mapped
    /// through the shading frame a second time. Off by default (physically
    /// correct); on to compare with the reference's stored renders.
    pub reference_compat: bool,
    pub tile_size: usize,
    /// Render only this window of the film (the image has its size);
    /// pixels keep their random streams, so the window equals that part
    /// of the full render except within the filter radius of its edges,
    /// which samples from outside would also reach.
    pub crop: Option<Crop>,
}

/// A window of the film, in pixels.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Crop {
    pub x: usize,
    pub y: usize,
    pub width: usize,
    pub height: usize,
}

impl Default for RenderOptions {
    fn default() -> Self {
        RenderOptions {
            spp: 64,
            max_depth: 4,
            seed: 0,
            filter: PixelFilter::default(),
            reference_compat: false,
            tile_size: 16,
            crop: None,
        }
    }
}

#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RenderStats {
    pub primary_rays: u64,
    pub bounce_rays: u64,
    pub shadow_rays: u64,
    /// Samples whose radiance was NaN/Inf and were dropped (should be 0).
    pub discarded_samples: u64,
}

impl RenderStats {
    pub fn total_rays(&self) -> u64 {
        self.primary_rays + self.bounce_rays + self.shadow_rays
    }
    fn add(&mut self, o: &RenderStats) {
        self.primary_rays += o.primary_rays;
        self.bounce_rays += o.bounce_rays;
        self.shadow_rays += o.shadow_rays;
        self.discarded_samples += o.discarded_samples;
    }
}

pub struct RenderOutput {
    pub image: RgbImage,
    pub stats: RenderStats,
}

#[inline]
pub fn mis_power(a: f32, b: f32) -> f32 {
    let (a2, b2) = (a * a, b * b);
    let w = a2 / (a2 + b2);
    if w.is_finite() {
        w
    } else {
        0.0
    }
}

/// Offset for rays leaving a surface, relative to the point's magnitude.
#[inline]
pub fn offset_origin(p: Vec3, n: Vec3, d: Vec3) -> Vec3 {
    let eps = 1e-5 * (1.0 + p.abs().max_element());
    if n.dot(d) >= 0.0 {
        p + n * eps
    } else {
        p - n * eps
    }
}

/// What a path-tracing pass does with each light-transport event besides
/// summing radiance. The forward render passes `()`, which does nothing;
/// inverse rendering's frozen-path recorder keeps the events so the same
/// estimator can be re-evaluated for other materials and envmaps (path
/// replay, as Mitsuba 3 reuses its forward loop). Both therefore trace the
/// same rays with the same random numbers in one loop, [`trace_path`].
pub trait PathSink {
    /// The camera ray escaped; the pixel sees the sky in `dir`.
    #[inline(always)]
    fn camera_sky(&mut self, _dir: Vec3) {}
    /// A surface vertex shaded with the material of pixel `q`; `first` for
    /// the camera ray's hit.
    #[inline(always)]
    fn vertex(&mut self, _q: usize, _first: bool) {}
    /// An unoccluded envmap sample `l` at the current vertex (normal `n`,
    /// towards the viewer `v`), estimator weight MIS/pdf.
    #[inline(always)]
    fn emitter(&mut self, _n: Vec3, _v: Vec3, _l: Vec3, _weight: f32) {}
    /// The BSDF sampled `l`, about to be traced; false ends the path here
    /// (for a recorder that cannot represent it).
    #[inline(always)]
    fn bsdf_dir(&mut self, _n: Vec3, _v: Vec3, _l: Vec3) -> bool {
        true
    }
    /// The BSDF sample escaped to the sky, estimator weight MIS/pdf.
    #[inline(always)]
    fn bsdf_sky(&mut self, _l: Vec3, _weight: f32) {}
    /// The BSDF sample reached the next vertex, estimator weight 1/pdf;
    /// false ends the path here.
    #[inline(always)]
    fn bounce(&mut self, _weight: f32) -> bool {
        true
    }
}

/// The forward render's sink: radiance only.
impl PathSink for () {}

/// The one path-tracing loop: radiance along the camera ray through `film`,
/// with every event also reported to `sink`.
///
/// Per vertex the sampler is drawn in a fixed order — envmap sample (2-D),
/// lobe (1-D), direction (2-D) — after the pixel jitter the caller drew, so
/// a (pixel, sample) pair gives the same path for every sink. A vertex whose
/// point projects to no pixel (at or behind the camera plane) has no
/// material and ends the path.
#[inline]
pub fn trace_path<S: PathSink>(
    scene: &RenderScene,
    opts: &RenderOptions,
    rng: &mut Sampler,
    film: Vec2,
    st: &mut RenderStats,
    sink: &mut S,
) -> Vec3 {
    if opts.max_depth == 0 {
        return Vec3::ZERO;
    }
    let dir = scene.camera_ray(film);
    st.primary_rays += 1;
    let hit = scene.bvh.intersect(Vec3::ZERO, dir, 0.0, f32::INFINITY);
    continue_path(scene, opts, rng, dir, hit, st, sink)
}

/// [`trace_path`] once the camera ray `dir` (from the camera at the
/// origin) and its closest hit are known — found for a whole pixel's
/// samples at once by [`CameraPacket`]. The sampler has drawn only the
/// pixel jitter.
#[inline]
pub fn continue_path<S: PathSink>(
    scene: &RenderScene,
    opts: &RenderOptions,
    rng: &mut Sampler,
    camera_dir: Vec3,
    camera_hit: Option<Hit>,
    st: &mut RenderStats,
    sink: &mut S,
) -> Vec3 {
    let mut l = Vec3::ZERO;
    if opts.max_depth == 0 {
        return l;
    }
    let mut dir = camera_dir;
    let mut origin = Vec3::ZERO;
    let mut throughput = Vec3::ONE;
    let env = &scene.env;
    let Some(mut hit) = camera_hit else {
        sink.camera_sky(dir);
        return l + env.eval(dir);
    };
    if opts.max_depth < 2 {
        return l;
    }
    let mut p = origin + dir * hit.t;
    let Some(mut q) = scene.material_index(p) else {
        return l;
    };
    // Vertex `depth` is the end of ray segment `depth + 1`; segment
    // `depth + 2` leaves it, so it may continue while depth + 2 < max_depth.
    for depth in 0..opts.max_depth - 1 {
        let n = scene.face_normals[hit.prim as usize];
        let v = -dir;
        let mat = scene.materials[q];
        sink.vertex(q, depth == 0);

        // Next-event estimation towards the environment map.
        let (ue1, ue2) = rng.next_2d();
        if let Some((wl, le, pdf_e)) = env.sample(ue1, ue2) {
            if n.dot(wl) > 0.0 && pdf_e > 0.0 {
                st.shadow_rays += 1;
                if !scene
                    .bvh
                    .occluded(offset_origin(p, n, wl), wl, 0.0, f32::INFINITY)
                {
                    let (f, pdf_b) = bsdf::eval_pdf(&mat, n, v, wl);
                    let w = mis_power(pdf_e, pdf_b) / pdf_e;
                    sink.emitter(n, v, wl, w);
                    l += throughput * f * le * w;
                }
            }
        }

        // Continue the path by sampling the BSDF.
        let u_lobe = rng.next_f32();
        let (u1, u2) = rng.next_2d();
        let Some(s) = bsdf::sample(&mat, n, v, u_lobe, u1, u2) else {
            break;
        };
        if s.weight.max_element() <= 0.0 {
            break;
        }
        let d = if opts.reference_compat {
            let n_sh = scene.shading_normal(hit.prim, hit.u, hit.v);
            let s0 = Frame::from_normal(n).s;
            let sx = (s0 - n_sh * n_sh.dot(s0)).normalize_or(Frame::from_normal(n_sh).s);
            let ty = n_sh.cross(sx);
            (sx * s.dir.x + ty * s.dir.y + n_sh * s.dir.z).normalize_or(s.dir)
        } else {
            s.dir
        };
        if !sink.bsdf_dir(n, v, d) {
            break;
        }
        throughput *= s.weight;
        origin = offset_origin(p, n, d);
        dir = d;
        st.bounce_rays += 1;
        let Some(h) = scene.bvh.intersect(origin, dir, 0.0, f32::INFINITY) else {
            let (le, pdf_e) = env.eval_pdf(dir);
            let w = mis_power(s.pdf, pdf_e);
            sink.bsdf_sky(dir, w / s.pdf);
            l += throughput * le * w;
            break;
        };
        // The next vertex contributes only if a segment may still leave it,
        // and only if it has a material.
        if depth + 3 > opts.max_depth {
            break;
        }
        p = origin + dir * h.t;
        let Some(q2) = scene.material_index(p) else {
            break;
        };
        if !sink.bounce(1.0 / s.pdf) {
            break;
        }
        hit = h;
        q = q2;
    }
    l
}

/// Radiance along the camera ray through `film` (the forward render's
/// [`trace_path`]).
#[inline]
pub fn radiance(
    scene: &RenderScene,
    opts: &RenderOptions,
    rng: &mut Sampler,
    film: Vec2,
    st: &mut RenderStats,
) -> Vec3 {
    trace_path(scene, opts, rng, film, st, &mut ())
}

/// The camera samples of one pixel, traced together. A pixel's camera rays
/// leave one point in nearly one direction, so
/// [`matflow_geom::Bvh::intersect_packet`] finds their hits in one
/// traversal (the hits of one ray at a time, up to the rounding exception
/// the BVH documents). Holds its buffers between pixels.
#[derive(Default)]
pub struct CameraPacket {
    samplers: Vec<Sampler>,
    films: Vec<Vec2>,
    dirs: Vec<Vec3>,
    hits: Vec<Option<Hit>>,
}

impl CameraPacket {
    /// Every sample of pixel (x, y), in sample order: draws each one's
    /// pixel jitter from its sampler, traces the camera rays [`PACKET`] at
    /// a time (none when `max_depth` is 0), then calls `path(film,
    /// sampler, camera ray, camera hit, stats)` for each sample, which
    /// continues it (with [`continue_path`]).
    pub fn pixel(
        &mut self,
        scene: &RenderScene,
        opts: &RenderOptions,
        (x, y): (usize, usize),
        spp: u32,
        st: &mut RenderStats,
        mut path: impl FnMut(Vec2, &mut Sampler, Vec3, Option<Hit>, &mut RenderStats),
    ) {
        let pix = (y * scene.camera.width + x) as u64;
        for s0 in (0..spp).step_by(PACKET) {
            self.samplers.clear();
            self.films.clear();
            self.dirs.clear();
            for s in s0..(s0 + PACKET as u32).min(spp) {
                let mut rng = Sampler::for_sample(opts.seed, pix, s, spp);
                let (jx, jy) = rng.next_2d();
                let film = Vec2::new(x as f32 + jx, y as f32 + jy);
                self.samplers.push(rng);
                self.films.push(film);
                self.dirs.push(scene.camera_ray(film));
            }
            self.hits.clear();
            self.hits.resize(self.dirs.len(), None);
            if opts.max_depth > 0 {
                st.primary_rays += self.dirs.len() as u64;
                scene.bvh.intersect_packet(
                    Vec3::ZERO,
                    &self.dirs,
                    0.0,
                    f32::INFINITY,
                    &mut self.hits,
                );
            }
            for i in 0..self.dirs.len() {
                path(
                    self.films[i],
                    &mut self.samplers[i],
                    self.dirs[i],
                    self.hits[i],
                    st,
                );
            }
        }
    }
}

struct Tile {
    x0: usize,
    y0: usize,
    x1: usize,
    y1: usize,
}

/// Renders the scene. `progress(done, total)` is called after each tile.
pub fn render(
    scene: &RenderScene,
    opts: &RenderOptions,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> RenderOutput {
    let (w, h) = (scene.camera.width, scene.camera.height);
    // The window rendered: [wx0, wx1) × [wy0, wy1), inside the film.
    let (wx0, wy0, wx1, wy1) = match opts.crop {
        Some(c) => {
            let x0 = c.x.min(w);
            let y0 = c.y.min(h);
            (x0, y0, (x0 + c.width).min(w), (y0 + c.height).min(h))
        }
        None => (0, 0, w, h),
    };
    let (ww, wh) = (wx1 - wx0, wy1 - wy0);
    let ts = opts.tile_size.max(1);
    let mut tiles = Vec::new();
    // Tiles of the full film's grid, cut to the window: a pixel's sums
    // then run in the same order as in the full render.
    for ty in (wy0 / ts * ts..wy1).step_by(ts) {
        for tx in (wx0 / ts * ts..wx1).step_by(ts) {
            tiles.push(Tile {
                x0: tx.max(wx0),
                y0: ty.max(wy0),
                x1: (tx + ts).min(wx1),
                y1: (ty + ts).min(wy1),
            });
        }
    }
    let total = tiles.len();
    let done = AtomicUsize::new(0);
    let r = opts.filter.radius();
    let border = r.ceil() as usize;
    let spp = opts.spp.max(1);
    let weights = opts.filter.weights();

    let results: Vec<(Vec<[f32; 4]>, RenderStats)> = tiles
        .par_iter()
        .map(|t| {
            let bw = t.x1 - t.x0 + 2 * border;
            let bh = t.y1 - t.y0 + 2 * border;
            let mut buf = vec![[0f32; 4]; bw * bh];
            let mut st = RenderStats::default();
            // 1-D filter weights of a sample's footprint columns.
            let mut wx = vec![0f32; 2 * border + 2];
            let mut packet = CameraPacket::default();
            for y in t.y0..t.y1 {
                for x in t.x0..t.x1 {
                    packet.pixel(
                        scene,
                        opts,
                        (x, y),
                        spp,
                        &mut st,
                        |film, rng, dir, hit, st| {
                            let li = continue_path(scene, opts, rng, dir, hit, st, &mut ());
                            if !li.is_finite() {
                                st.discarded_samples += 1;
                                return;
                            }
                            match opts.filter {
                                PixelFilter::Box => {
                                    let k = (y - t.y0 + border) * bw + (x - t.x0 + border);
                                    let b = &mut buf[k];
                                    b[0] += li.x;
                                    b[1] += li.y;
                                    b[2] += li.z;
                                    b[3] += 1.0;
                                }
                                PixelFilter::Gaussian { .. } => {
                                    let lo_x = ((film.x - 0.5 - r).ceil() as i64).max(wx0 as i64);
                                    let hi_x =
                                        ((film.x - 0.5 + r).floor() as i64).min(wx1 as i64 - 1);
                                    let lo_y = ((film.y - 0.5 - r).ceil() as i64).max(wy0 as i64);
                                    let hi_y =
                                        ((film.y - 0.5 + r).floor() as i64).min(wy1 as i64 - 1);
                                    // Separable: the 1-D weights of the
                                    // footprint's columns, once per sample.
                                    for (i, px) in (lo_x..=hi_x).enumerate() {
                                        wx[i] = weights.weight_1d(px as f32 + 0.5 - film.x);
                                    }
                                    for py in lo_y..=hi_y {
                                        let wy = weights.weight_1d(py as f32 + 0.5 - film.y);
                                        if wy <= 0.0 {
                                            continue;
                                        }
                                        let by = (py - t.y0 as i64 + border as i64) as usize;
                                        for (i, px) in (lo_x..=hi_x).enumerate() {
                                            let wgt = wy * wx[i];
                                            if wgt <= 0.0 {
                                                continue;
                                            }
                                            let bx = (px - t.x0 as i64 + border as i64) as usize;
                                            let b = &mut buf[by * bw + bx];
                                            b[0] += li.x * wgt;
                                            b[1] += li.y * wgt;
                                            b[2] += li.z * wgt;
                                            b[3] += wgt;
                                        }
                                    }
                                }
                            }
                        },
                    );
                }
            }
            let d = done.fetch_add(1, Ordering::Relaxed) + 1;
            progress(d, total);
            (buf, st)
        })
        .collect();

    // Merge tiles in a fixed order (deterministic whatever the threads did).
    let mut acc = vec![[0f64; 4]; ww * wh];
    let mut stats = RenderStats::default();
    for (t, (buf, st)) in tiles.iter().zip(results.iter()) {
        stats.add(st);
        let bw = t.x1 - t.x0 + 2 * border;
        let bh = t.y1 - t.y0 + 2 * border;
        for by in 0..bh {
            let py = t.y0 as i64 + by as i64 - border as i64;
            if py < wy0 as i64 || py >= wy1 as i64 {
                continue;
            }
            for bx in 0..bw {
                let px = t.x0 as i64 + bx as i64 - border as i64;
                if px < wx0 as i64 || px >= wx1 as i64 {
                    continue;
                }
                let b = buf[by * bw + bx];
                let a = &mut acc[(py as usize - wy0) * ww + (px as usize - wx0)];
                for c in 0..4 {
                    a[c] += b[c] as f64;
                }
            }
        }
    }
    let data = acc
        .iter()
        .map(|a| {
            if a[3] > 0.0 {
                let v = Vec3::new(
                    (a[0] / a[3]) as f32,
                    (a[1] / a[3]) as f32,
                    (a[2] / a[3]) as f32,
                );
                v.clamp(Vec3::ZERO, Vec3::splat(f32::MAX))
            } else {
                Vec3::ZERO
            }
        })
        .collect();
    RenderOutput {
        image: Image::from_vec(ww, wh, data),
        stats,
    }
}

/// Box-filtered values of the listed pixels (row-major indices), each
/// bit-identical to what [`render`] with [`PixelFilter::Box`] and the same
/// options gives at that pixel: the same per-(pixel, sample) random
/// streams, summed in the same order. For re-rendering the part of an
/// image a change can reach.
pub fn render_pixels(scene: &RenderScene, opts: &RenderOptions, pixels: &[u32]) -> Vec<Vec3> {
    let w = scene.camera.width;
    let spp = opts.spp.max(1);
    pixels
        .par_iter()
        .with_min_len(16)
        .map(|&p| {
            let (x, y) = (p as usize % w, p as usize / w);
            let mut st = RenderStats::default();
            let mut b = [0f32; 4];
            for s in 0..spp {
                let mut rng = Sampler::for_sample(opts.seed, p as u64, s, spp);
                let (jx, jy) = rng.next_2d();
                let film = Vec2::new(x as f32 + jx, y as f32 + jy);
                let li = radiance(scene, opts, &mut rng, film, &mut st);
                if !li.is_finite() {
                    continue;
                }
                b[0] += li.x;
                b[1] += li.y;
                b[2] += li.z;
                b[3] += 1.0;
            }
            if b[3] > 0.0 {
                let n = b[3] as f64;
                Vec3::new(
                    (b[0] as f64 / n) as f32,
                    (b[1] as f64 / n) as f32,
                    (b[2] as f64 / n) as f32,
                )
                .clamp(Vec3::ZERO, Vec3::splat(f32::MAX))
            } else {
                Vec3::ZERO
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::envmap::EnvMap;
    use matflow_geom::{mesh_from_depth, MeshParams};
    use matflow_scene::{Camera, GrayImage, MaterialMaps};

    fn sky() -> RgbImage {
        Image::from_fn(32, 16, |x, y| {
            let base = Vec3::new(0.2, 0.3, 0.5)
                * (1.0 + 0.5 * (x as f32 * 0.4).sin())
                * (1.0 - y as f32 / 20.0);
            if (6..8).contains(&x) && (4..6).contains(&y) {
                base + Vec3::splat(20.0)
            } else {
                base
            }
        })
    }

    fn plane_scene(n: usize, mat: crate::Material) -> RenderScene {
        let cam = Camera::new(n, n);
        let depth = GrayImage::new(n, n, 5.0);
        let mesh = mesh_from_depth(&depth, &cam, &MeshParams::default())
            .unwrap()
            .mesh;
        let maps = MaterialMaps::uniform(n, n, mat.albedo, mat.roughness, mat.metallic);
        RenderScene::new(cam, mesh, &maps, EnvMap::new(&sky()).unwrap()).unwrap()
    }

    /// Known answer: a plane facing the camera, lit only by the envmap
    /// (depth 2 = direct light only, nothing occludes its front hemisphere).
    /// The estimator's mean must agree with an independent quadrature of the
    /// reflected-radiance integral (eq. 4) within a few standard errors.
    #[test]
    fn pixel_subsets_equal_the_full_box_render_bit_for_bit() {
        let scene = plane_scene(
            12,
            crate::Material {
                albedo: Vec3::new(0.6, 0.4, 0.2),
                roughness: 0.3,
                metallic: 0.5,
            },
        );
        let opts = RenderOptions {
            spp: 8,
            seed: 7,
            filter: PixelFilter::Box,
            ..Default::default()
        };
        let full = render(&scene, &opts, &|_, _| {});
        let px = [0u32, 5, 13, 77, 143];
        let part = render_pixels(&scene, &opts, &px);
        for (k, &p) in px.iter().enumerate() {
            assert_eq!(part[k], full.image.data[p as usize], "pixel {p}");
        }
    }

    /// A cropped render is that window of the full render, bit for bit,
    /// away from the filter radius of its edges.
    #[test]
    fn crop_is_the_window_of_the_full_render() {
        let scene = plane_scene(
            20,
            crate::Material {
                albedo: Vec3::new(0.3, 0.6, 0.2),
                roughness: 0.5,
                metallic: 0.2,
            },
        );
        let opts = RenderOptions {
            spp: 4,
            seed: 3,
            tile_size: 8,
            ..Default::default()
        };
        let full = render(&scene, &opts, &|_, _| {}).image;
        let c = Crop {
            x: 5,
            y: 3,
            width: 11,
            height: 9,
        };
        let part = render(
            &scene,
            &RenderOptions {
                crop: Some(c),
                ..opts
            },
            &|_, _| {},
        )
        .image;
        assert_eq!((part.width, part.height), (11, 9));
        for y in 2..c.height - 2 {
            for x in 2..c.width - 2 {
                assert_eq!(
                    part.data[y * c.width + x],
                    full.data[(y + c.y) * 20 + x + c.x],
                    "({x}, {y})"
                );
            }
        }
    }

    #[test]
    fn plane_under_envmap_matches_quadrature() {
        let mats = [
            crate::Material {
                albedo: Vec3::new(0.7, 0.5, 0.3),
                roughness: 0.6,
                metallic: 0.0,
            },
            crate::Material {
                albedo: Vec3::new(0.9, 0.8, 0.6),
                roughness: 0.25,
                metallic: 1.0,
            },
        ];
        for mat in mats {
            let scene = plane_scene(8, mat);
            let opts = RenderOptions {
                max_depth: 2,
                ..Default::default()
            };
            let film = Vec2::new(4.0, 4.0);
            let v = -scene.camera_ray(film);
            let n = Vec3::Z;
            // Quadrature over the hemisphere in (cos θ, φ), fine grid.
            let q = 1500;
            let mut quad = 0.0f64;
            for i in 0..q {
                let ct = (i as f64 + 0.5) / q as f64;
                let st = (1.0 - ct * ct).sqrt();
                for j in 0..2 * q {
                    let phi = std::f64::consts::PI * (j as f64 + 0.5) / q as f64;
                    let l = Vec3::new((st * phi.cos()) as f32, (st * phi.sin()) as f32, ct as f32);
                    let f = crate::bsdf::eval(&mat, n, v, l);
                    quad += (f * scene.env.eval(l)).element_sum() as f64;
                }
            }
            quad *= 2.0 * std::f64::consts::PI / (2 * q * q) as f64;
            // Monte Carlo with the renderer's own estimator.
            let m = 200_000;
            let (mut s1, mut s2) = (0.0f64, 0.0f64);
            let mut st = RenderStats::default();
            for k in 0..m {
                let mut rng = Sampler::for_sample(9, 0, k, m);
                let x = radiance(&scene, &opts, &mut rng, film, &mut st).element_sum() as f64;
                s1 += x;
                s2 += x * x;
            }
            let mean = s1 / m as f64;
            let se = ((s2 / m as f64 - mean * mean) / m as f64).sqrt();
            assert!(
                (mean - quad).abs() < 4.0 * se + 1e-3 * quad,
                "{mat:?}: MC {mean} ± {se} vs quadrature {quad}"
            );
        }
    }

    #[test]
    fn bit_identical_across_thread_counts() {
        let scene = plane_scene(
            24,
            crate::Material {
                albedo: Vec3::splat(0.5),
                roughness: 0.4,
                metallic: 0.5,
            },
        );
        let opts = RenderOptions {
            spp: 4,
            tile_size: 8,
            ..Default::default()
        };
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| render(&scene, &opts, &|_, _| {})).image
        };
        let a = run(1);
        let b = run(2);
        let c = run(3);
        assert_eq!(a, b);
        assert_eq!(a, c);
        let other_seed = render(&scene, &RenderOptions { seed: 1, ..opts }, &|_, _| {}).image;
        assert_ne!(a, other_seed);
    }

    #[test]
    fn extreme_envmaps_and_materials_give_finite_images() {
        for env_val in [0.0f32, 1e-30, 1e15] {
            for (r, m) in [(0.0, 0.0), (0.07, 1.0), (1.0, 0.0)] {
                let n = 12;
                let cam = Camera::new(n, n);
                // A wall with a step (depth discontinuity) and a grazing floor.
                let depth = GrayImage::from_fn(n, n, |x, y| {
                    if y > 8 {
                        3.0 + (n - y) as f32 * 2.0
                    } else if x < 6 {
                        4.0
                    } else {
                        9.0
                    }
                });
                let mesh = mesh_from_depth(&depth, &cam, &MeshParams::default())
                    .unwrap()
                    .mesh;
                let maps = MaterialMaps::uniform(n, n, Vec3::ONE, r, m);
                let env = EnvMap::new(&Image::new(8, 4, Vec3::splat(env_val))).unwrap();
                let scene = RenderScene::new(cam, mesh, &maps, env).unwrap();
                let out = render(
                    &scene,
                    &RenderOptions {
                        spp: 8,
                        ..Default::default()
                    },
                    &|_, _| {},
                );
                assert!(out
                    .image
                    .data
                    .iter()
                    .all(|v| v.is_finite() && v.min_element() >= 0.0));
                assert_eq!(out.stats.discarded_samples, 0);
                if env_val == 0.0 {
                    assert!(out.image.data.iter().all(|v| *v == Vec3::ZERO));
                }
            }
        }
    }
}
