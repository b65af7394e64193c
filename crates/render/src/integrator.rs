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

use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

use glam::{Vec2, Vec3, Vec4};
use matflow_scene::{Image, RgbImage};
use rayon::prelude::*;

use matflow_geom::{Hit, PACKET};

use crate::bsdf;
use crate::dielectric;
use crate::filter::{FilterWeights, PixelFilter};
use crate::fmath;
use crate::lanes::{F, V3};
use crate::rng::{draws_1d, draws_2d, Keys1d, Keys2d, Sampler};
use crate::scene::{LampAt, RenderScene, Surface};
use crate::warp::{square_to_cosine_hemisphere, Frame};

/// Default [`RenderOptions::glass_depth`]: enough for a glass ball, torus
/// or jug to converge (their images change by less than the noise of a
/// 1024-spp render beyond it).
pub const DEFAULT_GLASS_DEPTH: u32 = 16;

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RenderOptions {
    pub spp: u32,
    /// Maximum number of ray segments per path (Mitsuba's `max_depth`),
    /// not counting segments that leave glass.
    pub max_depth: u32,
    /// Glass surfaces a path may pass or reflect off, on top of
    /// `max_depth`: a path through a glass object needs two or more
    /// segments inside it, which `max_depth` = 4 could not afford.
    pub glass_depth: u32,
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
            glass_depth: DEFAULT_GLASS_DEPTH,
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
    pub(crate) fn add(&mut self, o: &RenderStats) {
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
    /// An unoccluded sample of lamp `k` ([`crate::Lamp`]) in direction
    /// `l` at the current vertex, estimator weight 1/(pmf·r²) (a distant
    /// lamp: 1/pmf; the lamp's intensity times that, times f·cos, is its
    /// light).
    #[inline(always)]
    fn lamp(&mut self, _n: Vec3, _v: Vec3, _l: Vec3, _k: usize, _weight: f32) {}
    /// The BSDF sampled `l`, about to be traced; false ends the path here
    /// (for a recorder that cannot represent it).
    #[inline(always)]
    fn bsdf_dir(&mut self, _n: Vec3, _v: Vec3, _l: Vec3) -> bool {
        true
    }
    /// An object's surface (not a screen-space material) sampled a
    /// direction, about to be traced; false ends the path here. Such
    /// vertices carry no BRDF geometry for a recorder: it keeps them for
    /// what they show (which materials a pixel's light meets).
    #[inline(always)]
    fn object_dir(&mut self) -> bool {
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

/// One camera sample of a [`Wavefront`]: where it leaves the film and the
/// sampler that has drawn its jitter.
#[derive(Clone, Debug)]
pub struct CameraSample {
    pub film: Vec2,
    pub rng: Sampler,
}

/// The BSDF sample a vertex continues with: the direction traced, its
/// weight f·cos/pdf and pdf.
#[derive(Clone, Copy)]
struct Continuation {
    dir: Vec3,
    weight: Vec3,
    pdf: f32,
    /// Sampled from a delta lobe (smooth glass): the sky it reaches is
    /// not weighted against envmap sampling, which cannot produce it.
    delta: bool,
    /// Refracted through a transparent region: the path goes on at the
    /// background seen through this pixel, with no ray traced.
    teleport: Option<u32>,
}

/// An envmap sample towards which a shadow ray is traced: direction,
/// radiance, pdf and the shadow ray's index.
#[derive(Clone, Copy)]
struct LightSample {
    dir: Vec3,
    le: Vec3,
    pdf: f32,
    ray: u32,
}

/// A lamp towards which a shadow ray is traced: direction, which lamp,
/// estimator weight 1/(pmf·r²) (a distant lamp: 1/pmf) and the shadow
/// ray's index.
#[derive(Clone, Copy)]
struct LampSample {
    dir: Vec3,
    index: u32,
    weight: f32,
    ray: u32,
}

/// The far end of a lamp's shadow ray, whose direction spans the segment
/// to the lamp (t = 1 at the lamp; a distant lamp's ends past the scene).
const LAMP_TMAX: f32 = 1.0 - 1e-4;

/// The keys of a vertex's draws — envmap sample (2-D), lobe (1-D),
/// direction (2-D) — for a sampler standing at the vertex's first
/// dimension.
#[derive(Clone, Copy, Default)]
struct VertexKeys {
    light: Keys2d,
    lobe: Keys1d,
    direction: Keys2d,
}

impl VertexKeys {
    #[inline]
    fn of(rng: &Sampler) -> VertexKeys {
        let mut r = rng.clone();
        let light = r.keys_2d();
        r.skip(1);
        let lobe = r.keys_1d();
        r.skip(1);
        VertexKeys {
            light,
            lobe,
            direction: r.keys_2d(),
        }
    }
}

/// One path in flight: its sampler and radiance so far, and the vertex it
/// stands at (point `p`, triangle `prim`, material of pixel `q`, the
/// segment `dir` that reached it).
#[derive(Clone)]
struct Path {
    rng: Sampler,
    film: Vec2,
    l: Vec3,
    throughput: Vec3,
    dir: Vec3,
    p: Vec3,
    hit: Hit,
    q: usize,
    /// Counted ray segments so far (the camera ray is 1; segments leaving
    /// glass are not counted) and glass vertices shaded.
    seg: u32,
    glass: u32,
    /// Vertices shaded so far.
    vertices: u32,
    // What the vertex being shaded has drawn: its shading normal, the
    // geometric normal rays leave by, its material (`obj`: the object's
    // index for objects, [`NO_OBJECT`] for the depth mesh; `glass_vertex`
    // whether it is glass).
    n: Vec3,
    ng: Vec3,
    mat: bsdf::Material,
    obj: u32,
    glass_vertex: bool,
    /// An object's texture colour at the vertex (white otherwise).
    tex: Vec3,
    light: Option<LightSample>,
    /// The vertex's lamp sample (scenes with lamps), and the number that
    /// chooses it (drawn with the envmap sample).
    lamp: Option<LampSample>,
    u_lamp: f32,
    /// The vertex's draws, made in lanes for the step's paths
    /// ([`draw_vertices`]): envmap sample (2), lobe (1), direction (2).
    u: [f32; 5],
    /// f·cos and pdf of the vertex's envmap sample, evaluated with other
    /// paths' in lanes ([`eval_screen_lights`]) when it arrives.
    light_f: Vec3,
    light_pdf: f32,
    next: Option<Continuation>,
    /// The envmap's sampling cluster of the vertex being shaded
    /// ([`crate::EnvMap::cluster`]): its light sample and a BSDF sample
    /// that reaches the sky are weighted with that cluster's density.
    cluster: u32,
    /// Where the vertex's light sample left from
    /// ([`RenderScene::sample_sky`]): a BSDF sample that reaches the sky
    /// is weighted with the density there.
    sky_from: Vec3,
}

impl Path {
    /// A path leaving the camera through `film`.
    #[inline]
    fn new(scene: &RenderScene, film: Vec2, rng: Sampler) -> Path {
        Path {
            rng,
            film,
            l: Vec3::ZERO,
            throughput: Vec3::ONE,
            dir: scene.camera_ray(film),
            p: Vec3::ZERO,
            hit: Hit {
                t: 0.0,
                prim: 0,
                u: 0.0,
                v: 0.0,
            },
            q: 0,
            seg: 1,
            glass: 0,
            vertices: 0,
            n: Vec3::ZERO,
            ng: Vec3::ZERO,
            obj: NO_OBJECT,
            glass_vertex: false,
            tex: Vec3::ONE,
            mat: bsdf::Material {
                albedo: Vec3::ZERO,
                roughness: 1.0,
                metallic: 0.0,
            },
            light: None,
            lamp: None,
            u_lamp: 0.0,
            u: [0.0; 5],
            light_f: Vec3::ZERO,
            light_pdf: 0.0,
            next: None,
            cluster: crate::guide::NO_CLUSTER,
            sky_from: Vec3::ZERO,
        }
    }
}

/// The one path-tracing loop, run over a batch of paths in lock-step
/// (a wavefront): every path's camera ray, then vertex by vertex each live
/// path's envmap sample and BSDF sample, its shadow ray, its continuation
/// ray. The rays of a step are traced together — camera rays of a pixel
/// as one packet ([`matflow_geom::Bvh::intersect_packet`]), shadow and
/// continuation rays as streams ([`matflow_geom::Bvh::occluded_stream`],
/// [`matflow_geom::Bvh::intersect_stream`]) whose memory waits overlap —
/// and per-vertex tables (normals, materials) are prefetched a step
/// ahead. Each path does exactly what it would do alone, in the same
/// order: the same random numbers, the same sums, the same events for its
/// sink, so the result of a path does not depend on the batch it is in.
///
/// Per vertex the sampler is drawn in a fixed order — envmap sample (2-D),
/// lobe (1-D), direction (2-D) — after the pixel jitter, so a (pixel,
/// sample) pair gives the same path for every sink. A vertex whose point
/// projects to no pixel (at or behind the camera plane) has no material
/// and ends the path.
///
/// Holds its buffers between batches.
#[derive(Default)]
pub struct Wavefront {
    paths: Vec<Path>,
    active: Vec<u32>,
    next_active: Vec<u32>,
    rays: Vec<(Vec3, Vec3)>,
    ray_path: Vec<u32>,
    blocked: Vec<bool>,
    /// With partly open surfaces, per shadow ray the share of its light
    /// that arrives (else empty, and `blocked` says).
    transmit: Vec<f32>,
    /// Shadow rays towards lamps (origin, segment to the lamp) and their
    /// occlusion.
    lamp_rays: Vec<(Vec3, Vec3)>,
    lamp_blocked: Vec<bool>,
    hits: Vec<Option<Hit>>,
    dirs: Vec<Vec3>,
    /// Paths whose continuation went through a transparent region to a
    /// background vertex (no ray traced).
    teleported: Vec<u32>,
    /// Depth-mesh vertices of the step, whose BSDF samples and envmap
    /// samples' BSDF values are computed in lanes.
    screen: Vec<u32>,
}

/// Pixels per batch of the renderer's [`Wavefront`]: enough paths that
/// the ray streams keep their rays in flight, few enough that a batch's
/// state stays in cache.
pub const BATCH_PIXELS: usize = 16;

impl Wavefront {
    /// Traces every sample of each pixel (row-major index) of `pixels`:
    /// path `i` is sample `i % spp` of pixel `pixels[i / spp]`, with the
    /// render's per-(pixel, sample) sampler, and reports its events to
    /// `sinks[i]`. A pixel's camera rays form its packets.
    pub fn trace_pixels<S: PathSink>(
        &mut self,
        scene: &RenderScene,
        opts: &RenderOptions,
        pixels: &[u32],
        spp: u32,
        st: &mut RenderStats,
        sinks: &mut [S],
    ) {
        let w = scene.camera.width;
        let spp = spp.max(1);
        self.paths.clear();
        for &pix in pixels {
            let (x, y) = ((pix as usize % w) as f32, (pix as usize / w) as f32);
            // The pixel's key is hashed once for its samples.
            let pixel = Sampler::for_sample(opts.seed, pix as u64, 0, spp);
            let jitter = pixel.keys_2d();
            for s in 0..spp {
                let mut rng = pixel.for_sample_index(s);
                let (jx, jy) = rng.next_2d_with(jitter);
                let film = Vec2::new(x + jx, y + jy);
                self.paths.push(Path::new(scene, film, rng));
            }
        }
        self.run(scene, opts, spp as usize, st, sinks);
    }

    /// Traces the camera samples `samples`; consecutive groups of `group`
    /// of them (a pixel's) have their camera rays traced as packets.
    /// Reports path `i`'s events to `sinks[i]`.
    pub fn trace<S: PathSink>(
        &mut self,
        scene: &RenderScene,
        opts: &RenderOptions,
        samples: impl IntoIterator<Item = CameraSample>,
        group: usize,
        st: &mut RenderStats,
        sinks: &mut [S],
    ) {
        self.paths.clear();
        self.paths
            .extend(samples.into_iter().map(|c| Path::new(scene, c.film, c.rng)));
        self.run(scene, opts, group, st, sinks);
    }

    /// Traces the paths set up in `self.paths`.
    fn run<S: PathSink>(
        &mut self,
        scene: &RenderScene,
        opts: &RenderOptions,
        group: usize,
        st: &mut RenderStats,
        sinks: &mut [S],
    ) {
        assert_eq!(sinks.len(), self.paths.len(), "one sink per path");
        self.active.clear();
        if opts.max_depth == 0 {
            return;
        }
        self.camera(scene, opts, group.max(1), st, sinks);
        // A vertex is shaded only if a segment may leave it: the counted
        // segments that reached it are fewer than max_depth (any number
        // for glass, within glass_depth). Every step shades one vertex of
        // each active path, so the loop ends within max_depth − 1 +
        // glass_depth steps.
        while !self.active.is_empty() {
            self.shade(scene, opts, st, sinks);
            self.shadows(scene);
            self.continuations(scene, opts, st, sinks);
            self.vertices(scene, opts, sinks);
        }
    }

    /// Number of paths of the last batch.
    pub fn len(&self) -> usize {
        self.paths.len()
    }

    pub fn is_empty(&self) -> bool {
        self.paths.is_empty()
    }

    /// Film position and radiance of path `i` of the last batch.
    pub fn result(&self, i: usize) -> (Vec2, Vec3) {
        (self.paths[i].film, self.paths[i].l)
    }

    /// Camera rays, [`PACKET`] at a time within each group; the paths
    /// whose camera ray found a surface with a material become active.
    fn camera<S: PathSink>(
        &mut self,
        scene: &RenderScene,
        opts: &RenderOptions,
        group: usize,
        st: &mut RenderStats,
        sinks: &mut [S],
    ) {
        let n = self.paths.len();
        st.primary_rays += n as u64;
        self.hits.clear();
        self.hits.resize(n, None);
        let mut g0 = 0;
        while g0 < n {
            let g1 = (g0 + group).min(n);
            let mut s0 = g0;
            while s0 < g1 {
                let s1 = (s0 + PACKET).min(g1);
                self.dirs.clear();
                self.dirs.extend(self.paths[s0..s1].iter().map(|p| p.dir));
                scene.bvh.intersect_packet(
                    Vec3::ZERO,
                    &self.dirs,
                    0.0,
                    f32::INFINITY,
                    &mut self.hits[s0..s1],
                );
                s0 = s1;
            }
            g0 = g1;
        }
        for (i, (path, hit)) in self.paths.iter_mut().zip(&self.hits).enumerate() {
            let Some(hit) = *hit else {
                sinks[i].camera_sky(path.dir);
                path.l += scene.env.eval(path.dir);
                continue;
            };
            path.p = Vec3::ZERO + path.dir * hit.t;
            let Some(q) = scene.camera_vertex_material(hit.prim, path.p) else {
                continue;
            };
            if !may_shade(scene, opts, path, q) {
                continue;
            }
            path.hit = hit;
            path.q = q;
            prefetch(&scene.face_normals, hit.prim as usize);
            prefetch(&scene.materials, q);
            self.active.push(i as u32);
        }
    }

    /// Each active path's vertex: its envmap sample (queued as a shadow
    /// ray) and BSDF sample.
    fn shade<S: PathSink>(
        &mut self,
        scene: &RenderScene,
        opts: &RenderOptions,
        st: &mut RenderStats,
        sinks: &mut [S],
    ) {
        self.rays.clear();
        self.lamp_rays.clear();
        self.screen.clear();
        draw_vertices_now(&mut self.paths, &self.active);
        for &i in &self.active {
            let path = &mut self.paths[i as usize];
            sinks[i as usize].vertex(path.q, path.vertices == 0);
            path.vertices += 1;
            if let Some(&surface) = scene.object_surface(path.q) {
                let obj = path.q - scene.materials.len();
                path.obj = obj as u32;
                path.tex = scene.object_texture(obj, path.hit.prim, path.hit.u, path.hit.v);
                let surface = surface.textured(path.tex);
                shade_object(
                    scene,
                    path,
                    surface,
                    st,
                    &mut self.rays,
                    &mut self.lamp_rays,
                );
                continue;
            }
            if let Some(g) = scene.glass_pixel(path.q) {
                shade_screen_glass(scene, path, *g, st, &mut self.rays);
                continue;
            }
            let ng = scene.face_normals[path.hit.prim as usize];
            let n = scene.screen_shading_normal(path.hit.prim, path.hit.u, path.hit.v);
            let mat = scene.screen_material(path.q);
            path.n = n;
            path.ng = ng;
            path.mat = mat;
            path.obj = NO_OBJECT;
            path.glass_vertex = false;

            // Next-event estimation towards the environment map.
            sample_light(
                scene,
                path,
                true,
                n,
                |wl| n.dot(wl) > 0.0 && ng.dot(wl) > 0.0,
                st,
                &mut self.rays,
            );
            sample_lamp(
                scene,
                path,
                n,
                |l| n.dot(l) > 0.0 && ng.dot(l) > 0.0,
                st,
                &mut self.lamp_rays,
            );

            // The BSDF sample the path continues with: sampled below with
            // the step's other depth-mesh vertices.
            self.screen.push(i);
        }
        sample_screen_bsdfs_now(scene, opts, &mut self.paths, &self.screen);
    }

    /// Traces the shadow rays: occlusion, or with partly open surfaces what
    /// share of each one's light arrives ([`arrives`]).
    fn shadows(&mut self, scene: &RenderScene) {
        self.transmit.clear();
        if scene.has_openness() {
            crate::scene::transmittance_stream(
                &scene.bvh,
                &scene.mesh.openness,
                &self.rays,
                &mut self.hits,
                &mut self.transmit,
            );
        } else {
            self.blocked.clear();
            self.blocked.resize(self.rays.len(), false);
            scene
                .bvh
                .occluded_stream(&self.rays, 0.0, f32::INFINITY, &mut self.blocked);
        }
        self.lamp_blocked.clear();
        if !self.lamp_rays.is_empty() {
            self.lamp_blocked.resize(self.lamp_rays.len(), false);
            scene
                .bvh
                .occluded_stream(&self.lamp_rays, 0.0, LAMP_TMAX, &mut self.lamp_blocked);
        }
    }

    /// Adds the light of the unblocked envmap samples; traces the
    /// continuation rays of the paths that go on.
    fn continuations<S: PathSink>(
        &mut self,
        scene: &RenderScene,
        opts: &RenderOptions,
        st: &mut RenderStats,
        sinks: &mut [S],
    ) {
        self.rays.clear();
        self.ray_path.clear();
        self.teleported.clear();
        // The depth-mesh vertices' envmap samples that arrive, in lanes.
        self.screen.clear();
        for &i in &self.active {
            let path = &self.paths[i as usize];
            if let Some(ls) = path.light {
                if path.on_screen_material() && arrives(&self.transmit, &self.blocked, ls.ray) > 0.0
                {
                    self.screen.push(i);
                }
            }
        }
        eval_screen_lights_now(&mut self.paths, &self.screen);
        for &i in &self.active {
            let path = &mut self.paths[i as usize];
            let sink = &mut sinks[i as usize];
            let (n, v) = (path.n, -path.dir);
            if let Some(ls) = path.light {
                let t = arrives(&self.transmit, &self.blocked, ls.ray);
                if t > 0.0 {
                    let (f, pdf_b) = if path.on_screen_material() {
                        (path.light_f, path.light_pdf)
                    } else {
                        vertex_eval_pdf(scene, path, n, v, ls.dir)
                    };
                    let w = mis_power(ls.pdf, pdf_b) / ls.pdf * t;
                    sink.emitter(n, v, ls.dir, w);
                    path.l += path.throughput * f * ls.le * w;
                }
            }
            if let Some(lp) = path.lamp {
                if !self.lamp_blocked[lp.ray as usize] {
                    let (f, _) = vertex_eval_pdf(scene, path, n, v, lp.dir);
                    sink.lamp(n, v, lp.dir, lp.index as usize, lp.weight);
                    let intensity = scene.lamps[lp.index as usize].intensity;
                    path.l += path.throughput * f * intensity * lp.weight;
                }
            }
            let Some(c) = path.next else {
                continue;
            };
            if let Some(p2) = c.teleport {
                // Through a transparent region: the background seen
                // through pixel p2 is the next vertex.
                path.next = None;
                if !sink.object_dir() {
                    continue;
                }
                path.throughput *= c.weight;
                path.dir = c.dir;
                path.glass += 1;
                let sg = scene.screen_glass.as_ref().expect("teleports need regions");
                let (pt, prim) = sg.surface[p2 as usize];
                if prim == crate::scene::NO_SURFACE {
                    // The sky shows through.
                    sink.bsdf_sky(c.dir, 1.0 / c.pdf);
                    path.l += path.throughput * scene.env.eval(c.dir);
                    continue;
                }
                if !sink.bounce(1.0 / c.pdf) {
                    continue;
                }
                let q = scene.background_base() + p2 as usize;
                if !may_shade(scene, opts, path, q) {
                    continue;
                }
                path.p = pt;
                path.hit = Hit {
                    t: 0.0,
                    prim,
                    u: 0.0,
                    v: 0.0,
                };
                path.q = q;
                self.teleported.push(i);
                continue;
            }
            let go_on = if path.obj != NO_OBJECT {
                sink.object_dir()
            } else {
                sink.bsdf_dir(n, v, c.dir)
            };
            if !go_on {
                path.next = None;
                continue;
            }
            path.throughput *= c.weight;
            path.p = offset_origin(path.p, path.ng, c.dir);
            path.dir = c.dir;
            if path.glass_vertex {
                path.glass += 1;
            } else {
                path.seg += 1;
            }
            st.bounce_rays += 1;
            self.rays.push((path.p, c.dir));
            self.ray_path.push(i);
        }
        self.hits.clear();
        self.hits.resize(self.rays.len(), None);
        scene
            .bvh
            .intersect_stream(&self.rays, 0.0, f32::INFINITY, &mut self.hits);
    }

    /// Where the continuation rays went: the sky (light by MIS, the path
    /// ends) or the next vertex, whose paths stay active.
    fn vertices<S: PathSink>(
        &mut self,
        scene: &RenderScene,
        opts: &RenderOptions,
        sinks: &mut [S],
    ) {
        self.next_active.clear();
        for (&i, hit) in self.ray_path.iter().zip(&self.hits) {
            let path = &mut self.paths[i as usize];
            let sink = &mut sinks[i as usize];
            let Some(c) = path.next else {
                continue;
            };
            let Some(h) = *hit else {
                let (le, pdf_e) = scene.sky_eval_pdf(path.sky_from, path.cluster, path.dir);
                let w = if c.delta {
                    1.0
                } else {
                    mis_power(c.pdf, pdf_e)
                };
                sink.bsdf_sky(path.dir, w / c.pdf);
                path.l += path.throughput * le * w;
                continue;
            };
            // A partly open surface passes its share of the sky in the
            // ray's direction (weighted as a BSDF sample that escaped; the
            // envmap samples through it carry the same share) and is a
            // vertex for the rest.
            let open = scene.openness(h.prim);
            let mut keep = 1.0;
            if open > 0.0 {
                let (le, pdf_e) = scene.sky_eval_pdf(path.sky_from, path.cluster, path.dir);
                let w = if c.delta {
                    1.0
                } else {
                    mis_power(c.pdf, pdf_e)
                };
                sink.bsdf_sky(path.dir, open * w / c.pdf);
                path.l += path.throughput * le * (open * w);
                if open >= 1.0 {
                    continue;
                }
                keep = 1.0 - open;
            }
            // The next vertex contributes only if it has a material and a
            // segment may still leave it.
            path.p += path.dir * h.t;
            let Some(q) = scene.vertex_material(h.prim, path.p) else {
                continue;
            };
            if !may_shade(scene, opts, path, q) {
                continue;
            }
            if !sink.bounce(keep / c.pdf) {
                continue;
            }
            path.throughput *= keep;
            path.hit = h;
            path.q = q;
            prefetch(&scene.face_normals, h.prim as usize);
            prefetch(&scene.materials, q);
            self.next_active.push(i);
        }
        self.next_active.extend_from_slice(&self.teleported);
        std::mem::swap(&mut self.active, &mut self.next_active);
    }
}

crate::lane_kernel!(fn draw_vertices_now = draw_vertices(paths: &mut [Path], active: &[u32]));

/// The draws of the vertex each path of `active` stands at, into
/// [`Path::u`], `W` lanes at a time; the samplers move past them. The
/// samples of a pixel stand at the same dimension of its sampler: the
/// keys of a vertex's draws are computed once for them.
#[inline(always)]
fn draw_vertices<const W: usize>(paths: &mut [Path], active: &[u32]) {
    let mut cached: Option<(Sampler, VertexKeys)> = None;
    for group in active.chunks(W) {
        let mut keys = [VertexKeys::default(); W];
        let mut sample = [0u32; W];
        let mut spp = [1u32; W];
        for lane in 0..W {
            let rng = &paths[group[lane.min(group.len() - 1)] as usize].rng;
            keys[lane] = match &cached {
                Some((at, k)) if at.same_dimension(rng) => *k,
                _ => {
                    let k = VertexKeys::of(rng);
                    cached = Some((rng.clone(), k));
                    k
                }
            };
            (sample[lane], spp[lane]) = rng.index();
        }
        let (e1, e2) = draws_2d(sample, spp, keys.map(|k| k.light));
        let lobe = draws_1d(sample, spp, keys.map(|k| k.lobe));
        let (d1, d2) = draws_2d(sample, spp, keys.map(|k| k.direction));
        for (lane, &i) in group.iter().enumerate() {
            let path = &mut paths[i as usize];
            path.u = [e1[lane], e2[lane], lobe[lane], d1[lane], d2[lane]];
            path.rng.skip(3);
        }
    }
}

crate::lane_kernel!(fn sample_screen_bsdfs_now = sample_screen_bsdfs(
    scene: &RenderScene,
    opts: &RenderOptions,
    paths: &mut [Path],
    screen: &[u32],
));
crate::lane_kernel!(fn eval_screen_lights_now = eval_screen_lights(
    paths: &mut [Path],
    screen: &[u32],
));

/// The materials, normals and directions towards the viewer of the
/// paths of `group`, one a lane; lanes past its end repeat its first.
#[inline(always)]
fn gather_vertices<const W: usize>(
    paths: &[Path],
    group: &[u32],
) -> (bsdf::MaterialLanes<W>, V3<W>, V3<W>) {
    let at = |i: usize| &paths[group[i.min(group.len() - 1)] as usize];
    (
        bsdf::MaterialLanes::gather(|i| at(i).mat),
        V3::gather(|i| at(i).n),
        V3::gather(|i| -at(i).dir),
    )
}

/// The BSDF samples of the depth-mesh vertices `screen` (their draws in
/// [`Path::u`]), `W` lanes at a time; a short last group repeats its
/// first path in the lanes it lacks.
#[inline(always)]
fn sample_screen_bsdfs<const W: usize>(
    scene: &RenderScene,
    opts: &RenderOptions,
    paths: &mut [Path],
    screen: &[u32],
) {
    for group in screen.chunks(W) {
        let (m, n, v) = gather_vertices::<W>(paths, group);
        let at = |i: usize| &paths[group[i.min(group.len() - 1)] as usize];
        let u = |k: usize| F::<W>(std::array::from_fn(|i| at(i).u[k]));
        let s = bsdf::sample_lanes(&m, n, v, u(2), u(3), u(4));
        let positive = s.weight.max_element().gt(0.0);
        for (lane, &i) in group.iter().enumerate() {
            let path = &mut paths[i as usize];
            if !(s.valid.lane(lane) && positive.lane(lane)) {
                path.next = None;
                continue;
            }
            let mut dir = s.dir.lane(lane);
            if opts.reference_compat {
                let n = path.n;
                let n_sh = scene.shading_normal(path.hit.prim, path.hit.u, path.hit.v);
                let s0 = Frame::from_normal(n).s;
                let sx = (s0 - n_sh * n_sh.dot(s0)).normalize_or(Frame::from_normal(n_sh).s);
                let ty = n_sh.cross(sx);
                dir = (sx * dir.x + ty * dir.y + n_sh * dir.z).normalize_or(dir);
            }
            // With given shading normals, a direction sampled about the
            // shading normal may pass below the triangle: no light comes
            // from there (as for the light samples).
            if scene.given_normals && !(dir.dot(path.ng) > 0.0) {
                path.next = None;
                continue;
            }
            path.next = Some(Continuation {
                dir,
                weight: s.weight.lane(lane),
                pdf: s.pdf.0[lane],
                delta: false,
                teleport: None,
            });
        }
    }
}

/// f·cos and pdf of the envmap samples of the depth-mesh vertices
/// `screen`, into [`Path::light_f`] and [`Path::light_pdf`], `W` lanes at
/// a time.
#[inline(always)]
fn eval_screen_lights<const W: usize>(paths: &mut [Path], screen: &[u32]) {
    for group in screen.chunks(W) {
        let (m, n, v) = gather_vertices::<W>(paths, group);
        let at = |i: usize| &paths[group[i.min(group.len() - 1)] as usize];
        let l = V3::gather(|i| at(i).light.map_or(Vec3::Z, |l| l.dir));
        let (f, pdf) = bsdf::eval_pdf_lanes(&m, n, v, l);
        for (lane, &i) in group.iter().enumerate() {
            let path = &mut paths[i as usize];
            path.light_f = f.lane(lane);
            path.light_pdf = pdf.0[lane];
        }
    }
}

/// The share of shadow ray `ray`'s light that arrives, from
/// [`Wavefront::shadows`]: 0 or 1, or the openness of the partly open
/// surface it meets.
#[inline]
fn arrives(transmit: &[f32], blocked: &[bool], ray: u32) -> f32 {
    match transmit.get(ray as usize) {
        Some(&t) => t,
        None if blocked[ray as usize] => 0.0,
        None => 1.0,
    }
}

/// Whether a path that reached a vertex with material `q` shades it: a
/// segment must be allowed to leave it (glass has its own allowance).
#[inline]
fn may_shade(scene: &RenderScene, opts: &RenderOptions, path: &Path, q: usize) -> bool {
    if scene.is_glass(q) {
        path.glass < opts.glass_depth
    } else {
        path.seg < opts.max_depth
    }
}

/// Next-event estimation towards the environment map: with the vertex's
/// envmap draws (every vertex draws the same dimensions), and
/// when `enabled`, `accept(direction)` and its pdf is positive, queues the
/// shadow ray, leaving by the geometric normal `ng`.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn sample_light(
    scene: &RenderScene,
    path: &mut Path,
    enabled: bool,
    ng: Vec3,
    accept: impl Fn(Vec3) -> bool,
    st: &mut RenderStats,
    rays: &mut Vec<(Vec3, Vec3)>,
) {
    let [ue1, ue2, ..] = path.u;
    path.light = None;
    path.lamp = None;
    path.u_lamp = ue2;
    path.cluster = scene.env.cluster(path.p);
    path.sky_from = path.p;
    if !enabled {
        return;
    }
    if let Some((wl, le, pdf_e)) = scene.sample_sky(path.p, path.cluster, ue1, ue2) {
        if accept(wl) && pdf_e > 0.0 {
            st.shadow_rays += 1;
            path.light = Some(LightSample {
                dir: wl,
                le,
                pdf: pdf_e,
                ray: rays.len() as u32,
            });
            rays.push((offset_origin(path.p, ng, wl), wl));
        }
    }
}

/// Next-event estimation towards the scene's lamps (none: nothing), after
/// [`sample_light`] (which clears the vertex's lamp sample and draws the
/// number): one lamp, chosen uniformly by the number drawn with the
/// vertex's envmap sample (its own estimator, so sharing the number
/// biases neither), and when `accept(direction)` a shadow ray queued in
/// `rays` along the segment to it (a distant lamp: to past the scene),
/// leaving by the geometric normal `ng`.
#[inline(always)]
fn sample_lamp(
    scene: &RenderScene,
    path: &mut Path,
    ng: Vec3,
    accept: impl Fn(Vec3) -> bool,
    st: &mut RenderStats,
    rays: &mut Vec<(Vec3, Vec3)>,
) {
    let count = scene.lamps.len();
    if count == 0 {
        return;
    }
    let k = ((path.u_lamp * count as f32) as usize).min(count - 1);
    let (dir, weight, end) = match scene.lamps[k].at {
        LampAt::Point(position) => {
            let d = position - path.p;
            let r2 = d.length_squared();
            if !(r2 > 1e-12) || !r2.is_finite() {
                return;
            }
            (d / r2.sqrt(), count as f32 / r2, Some(position))
        }
        LampAt::Distant(dir) => (dir, count as f32, None),
    };
    if !accept(dir) {
        return;
    }
    let origin = offset_origin(path.p, ng, dir);
    st.shadow_rays += 1;
    path.lamp = Some(LampSample {
        dir,
        index: k as u32,
        weight,
        ray: rays.len() as u32,
    });
    let segment = end.map_or(dir * scene.lamp_far, |e| e - origin);
    rays.push((origin, segment));
}

/// f·cos and pdf of the vertex being shaded (depth mesh, transparent
/// region or object) for the outgoing direction `l`.
#[inline]
fn vertex_eval_pdf(scene: &RenderScene, path: &Path, n: Vec3, v: Vec3, l: Vec3) -> (Vec3, f32) {
    if path.obj == NO_OBJECT && path.glass_vertex {
        // A transparent region reflects the light only.
        let g = scene.glass_pixel(path.q).map(|g| g.interface);
        let fr = Frame::from_normal(n);
        g.map_or((Vec3::ZERO, 0.0), |g| {
            dielectric::eval_pdf(&g, fr.to_local(v), fr.to_local(l))
        })
    } else if path.obj == NO_OBJECT {
        bsdf::eval_pdf(&path.mat, n, v, l)
    } else {
        let s = scene.objects[path.obj as usize].textured(path.tex);
        surface_eval_pdf(&s, n, v, l)
    }
}

/// [`Path::obj`] of a vertex on the depth mesh.
const NO_OBJECT: u32 = u32::MAX;

impl Path {
    /// Whether the vertex being shaded is the depth mesh's own (a
    /// screen-space material, not an object or a transparent region): the
    /// vertices whose BSDF runs in lanes.
    #[inline(always)]
    fn on_screen_material(&self) -> bool {
        self.obj == NO_OBJECT && !self.glass_vertex
    }
}

/// f·cos and pdf of an object's surface for the outgoing direction `l`
/// (`n` the shading normal the vertex was shaded with).
#[inline]
fn surface_eval_pdf(s: &Surface, n: Vec3, v: Vec3, l: Vec3) -> (Vec3, f32) {
    match s {
        Surface::Principled(m) => bsdf::eval_pdf(m, n, v, l),
        Surface::Diffuse(a) => {
            let c = n.dot(l).max(0.0);
            (*a * (c / std::f32::consts::PI), c / std::f32::consts::PI)
        }
        Surface::Glass(g) => {
            let f = Frame::from_normal(n);
            dielectric::eval_pdf(g, f.to_local(v), f.to_local(l))
        }
    }
}

/// Shades a vertex on an object: its envmap and (opaque surfaces) lamp
/// samples (queued as shadow rays in `rays` and `lamp_rays`) and BSDF
/// sample, drawing the same dimensions in the same order as a depth-mesh
/// vertex.
#[inline(never)]
fn shade_object(
    scene: &RenderScene,
    path: &mut Path,
    surface: Surface,
    st: &mut RenderStats,
    rays: &mut Vec<(Vec3, Vec3)>,
    lamp_rays: &mut Vec<(Vec3, Vec3)>,
) {
    let v = -path.dir;
    let mut ng = scene.face_normals[path.hit.prim as usize];
    let mut n = scene.shading_normal(path.hit.prim, path.hit.u, path.hit.v);
    let glass = match surface {
        Surface::Glass(g) => Some(g),
        _ => None,
    };
    if glass.is_none() {
        // Opaque objects are two-sided.
        if ng.dot(v) < 0.0 {
            ng = -ng;
            n = -n;
        }
        if !(n.dot(v) > 0.0) {
            n = ng;
        }
    }
    path.n = n;
    path.ng = ng;
    path.glass_vertex = glass.is_some();
    // Next-event estimation (not for smooth glass: its lobes are deltas).
    let smooth = glass.is_some_and(|g| g.is_smooth());
    let facing = |wl: Vec3| glass.is_some() || (ng.dot(wl) > 0.0 && n.dot(wl) > 0.0);
    sample_light(scene, path, !smooth, ng, facing, st, rays);
    if glass.is_none() {
        sample_lamp(scene, path, ng, facing, st, lamp_rays);
    }
    let [_, _, u_lobe, u1, u2] = path.u;
    path.next = match surface {
        Surface::Principled(m) => bsdf::sample(&m, n, v, u_lobe, u1, u2).map(|s| Continuation {
            dir: s.dir,
            weight: s.weight,
            pdf: s.pdf,
            delta: false,
            teleport: None,
        }),
        Surface::Diffuse(a) => {
            let dir = Frame::from_normal(n).to_world(square_to_cosine_hemisphere(u1, u2));
            let pdf = n.dot(dir).max(0.0) / std::f32::consts::PI;
            (pdf > 1e-6).then_some(Continuation {
                dir,
                weight: a,
                pdf,
                delta: false,
                teleport: None,
            })
        }
        Surface::Glass(g) => {
            let f = Frame::from_normal(n);
            dielectric::sample(&g, f.to_local(v), u_lobe, u1, u2).map(|s| Continuation {
                dir: f.to_world(s.wo).normalize_or(s.wo),
                weight: s.weight,
                pdf: s.pdf,
                delta: s.delta,
                teleport: None,
            })
        }
    }
    .filter(|c| c.weight.max_element() > 0.0 && c.weight.is_finite());
}

/// Shades a vertex in a transparent region of the depth mesh (the paper's
/// single-view transparency, eqs. 22–23): the front surface is a glass
/// interface; a reflection goes on into the scene; a refraction ωt1 goes
/// d1 into the object, leaves through a back surface parallel to the front
/// surface seen where it is (the normal of the pixel x1 = x + d1·ωt1
/// projects to) in direction ωt2, and after d2 more reaches
/// x2 = x1 + d2·ωt2: the path goes on at the background seen through the
/// pixel x2 projects to, whose material is the region's (inpainted)
/// background. Refraction in and out carries √(T·tint) each and the
/// region's (1 − metallic), the exit (1 − F) too; total internal
/// reflection at the exit loses the light. Draws the same dimensions as
/// any vertex.
#[inline(never)]
fn shade_screen_glass(
    scene: &RenderScene,
    path: &mut Path,
    g: crate::scene::GlassPixel,
    st: &mut RenderStats,
    rays: &mut Vec<(Vec3, Vec3)>,
) {
    let n = scene.face_normals[path.hit.prim as usize];
    let v = -path.dir;
    path.n = n;
    path.ng = n;
    path.obj = NO_OBJECT;
    path.glass_vertex = true;
    path.mat = scene.materials[path.q];
    let frame = Frame::from_normal(n);
    // Only reflection reaches the envmap directly from here.
    let reflects = |wl: Vec3| n.dot(wl) > 0.0 && n.dot(v) > 0.0;
    sample_light(scene, path, !g.interface.is_smooth(), n, reflects, st, rays);
    let [_, _, u_lobe, u1, u2] = path.u;
    let wi = frame.to_local(v);
    path.next = dielectric::sample(&g.interface, wi, u_lobe, u1, u2).and_then(|s| {
        let dir = frame.to_world(s.wo).normalize_or(s.wo);
        if s.wo.z * wi.z > 0.0 {
            return Some(Continuation {
                dir,
                weight: s.weight,
                pdf: s.pdf,
                delta: s.delta,
                teleport: None,
            });
        }
        // Into the object, out through the back, to the background.
        let x1 = path.p + dir * g.d1;
        let p1 = scene.pixel_of(x1).unwrap_or(path.q);
        let sg = scene.screen_glass.as_ref()?;
        let nb = match sg.surface[p1].1 {
            crate::scene::NO_SURFACE => n,
            prim => scene.face_normals[prim as usize],
        };
        // Leaving: the back surface's outward normal is −nb; seen from
        // inside, the direction back along the ray is −dir.
        let m = -nb;
        let wi_exit = -dir;
        let (f2, cos_t, _, eta_ti) = dielectric::fresnel(wi_exit.dot(m), g.interface.eta);
        if f2 >= 1.0 {
            return None;
        }
        let out = dielectric::refract(wi_exit, m, cos_t, eta_ti).normalize_or_zero();
        if out == Vec3::ZERO {
            return None;
        }
        let weight = s.weight
            * g.interface.refraction_weight()
            * ((1.0 - f2) * eta_ti * eta_ti * (1.0 - path.mat.metallic));
        if !weight.is_finite() || !(weight.max_element() > 0.0) {
            return None;
        }
        let x2 = x1 + out * g.d2;
        let p2 = scene.pixel_of(x2).unwrap_or(path.q);
        Some(Continuation {
            dir: out,
            weight,
            pdf: s.pdf,
            delta: true,
            teleport: Some(p2 as u32),
        })
    });
}

/// Asks for the cache line of `v[i]` ahead of its use.
#[inline(always)]
fn prefetch<T>(v: &[T], i: usize) {
    #[cfg(target_arch = "x86_64")]
    if i < v.len() {
        // SAFETY: the address is inside the slice; prefetching has no
        // other effect.
        unsafe {
            use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
            _mm_prefetch::<_MM_HINT_T0>(v.as_ptr().add(i) as *const i8);
        }
    }
}

#[derive(Clone, Copy)]
struct Tile {
    x0: usize,
    y0: usize,
    x1: usize,
    y1: usize,
}

/// Where a tile's samples land: its buffer (the tile and a border of the
/// filter's reach, `bw` wide), the window rendered and the filter.
struct SplatFilm {
    tile: Tile,
    border: usize,
    bw: usize,
    window: (usize, usize, usize, usize),
    weights: FilterWeights,
}

/// A batch of a tile row: `spp` samples of each pixel from column `x0` on
/// in row `y`.
#[derive(Clone, Copy)]
struct SplatAt {
    x0: usize,
    y: usize,
    spp: usize,
}

crate::lane_kernel!(fn splat_wave_now = splat_wave(
    wave: &Wavefront,
    film: &SplatFilm,
    at: SplatAt,
    buf: &mut [Vec4],
    st: &mut RenderStats,
));

/// Adds each finite sample of the batch just traced to the pixels of its
/// footprint: (radiance, 1) times the filter's weight, in the buffer. A
/// Gaussian's 1-D weights of a footprint of up to 4×4 are one 8-lane
/// evaluation at every `W` (columns in lanes 0–3, rows in 4–7), so `W`
/// only picks the instructions it is compiled for.
#[inline(always)]
fn splat_wave<const W: usize>(
    wave: &Wavefront,
    film: &SplatFilm,
    at: SplatAt,
    buf: &mut [Vec4],
    st: &mut RenderStats,
) {
    let (t, border, bw) = (film.tile, film.border, film.bw);
    let r = film.weights.filter().radius();
    let (wx0, wy0, wx1, wy1) = film.window;
    let mut wx = [0f32; 8];
    let mut wy = [0f32; 8];
    let mut wide_x = Vec::new();
    let mut wide_y = Vec::new();
    for i in 0..wave.len() {
        let (pos, li) = wave.result(i);
        if !li.is_finite() {
            st.discarded_samples += 1;
            continue;
        }
        let x = at.x0 + i / at.spp;
        // (radiance, 1) · weight, lane by lane.
        let li1 = li.extend(1.0);
        match film.weights.filter() {
            PixelFilter::Box => {
                let k = (at.y - t.y0 + border) * bw + (x - t.x0 + border);
                buf[k] += li1;
            }
            PixelFilter::Gaussian { .. } => {
                let lo_x = (fmath::ceil(pos.x - 0.5 - r) as i64).max(wx0 as i64);
                let hi_x = (fmath::floor(pos.x - 0.5 + r) as i64).min(wx1 as i64 - 1);
                let lo_y = (fmath::ceil(pos.y - 0.5 - r) as i64).max(wy0 as i64);
                let hi_y = (fmath::floor(pos.y - 0.5 + r) as i64).min(wy1 as i64 - 1);
                // Separable: the 1-D weights of the footprint's columns
                // and rows, once per sample, in lanes.
                let nx = (hi_x - lo_x + 1).max(0) as usize;
                let ny = (hi_y - lo_y + 1).max(0) as usize;
                if nx == 0 || ny == 0 {
                    continue;
                }
                let (wx, wy) = if nx <= wx.len() && ny <= wy.len() {
                    (&mut wx[..nx], &mut wy[..ny])
                } else {
                    wide_x.resize(nx, 0.0);
                    wide_y.resize(ny, 0.0);
                    (&mut wide_x[..], &mut wide_y[..])
                };
                film.weights.footprint(pos, (lo_x, lo_y), wx, wy);
                // The footprint's first buffer row and column (the border
                // keeps them inside it). Zero weights are added too: the
                // sums start at +0 and li is finite, so adding li·0 leaves
                // every sum's bits as they are.
                let bx0 = (lo_x - t.x0 as i64 + border as i64).max(0) as usize;
                let by0 = (lo_y - t.y0 as i64 + border as i64).max(0) as usize;
                for (j, &wy) in wy.iter().enumerate() {
                    let row = &mut buf[(by0 + j) * bw + bx0..][..wx.len()];
                    for (b, &wx) in row.iter_mut().zip(wx.iter()) {
                        *b += li1 * (wy * wx);
                    }
                }
            }
        }
    }
}

/// Renders the scene. `progress(done, total)` is called after each tile.
pub fn render(
    scene: &RenderScene,
    opts: &RenderOptions,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> RenderOutput {
    render_until(scene, opts, progress, &|| false).unwrap_or_else(|| RenderOutput {
        image: Image::new(0, 0, Vec3::ZERO),
        stats: RenderStats::default(),
    })
}

/// [`render`], asking `stop()` before each tile: once it says yes, the
/// tiles not started are skipped and the render returns `None` (a front
/// end whose newer request supersedes this one does not wait for it).
/// When it never says yes, the image is [`render`]'s, bit for bit.
pub fn render_until(
    scene: &RenderScene,
    opts: &RenderOptions,
    progress: &(dyn Fn(usize, usize) + Sync),
    stop: &(dyn Fn() -> bool + Sync),
) -> Option<RenderOutput> {
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

    let stopped = AtomicBool::new(false);
    let results: Vec<(Vec<Vec4>, RenderStats)> = tiles
        .par_iter()
        .map(|t| {
            if stopped.load(Ordering::Relaxed) || stop() {
                stopped.store(true, Ordering::Relaxed);
                return (Vec::new(), RenderStats::default());
            }
            let bw = t.x1 - t.x0 + 2 * border;
            let bh = t.y1 - t.y0 + 2 * border;
            let mut buf = vec![Vec4::ZERO; bw * bh];
            let mut st = RenderStats::default();
            let film = SplatFilm {
                tile: *t,
                border,
                bw,
                window: (wx0, wy0, wx1, wy1),
                weights,
            };
            let mut wave = Wavefront::default();
            let mut sinks = Vec::new();
            let mut pixels = Vec::with_capacity(BATCH_PIXELS);
            for y in t.y0..t.y1 {
                for x0 in (t.x0..t.x1).step_by(BATCH_PIXELS) {
                    pixels.clear();
                    pixels.extend((x0..(x0 + BATCH_PIXELS).min(t.x1)).map(|x| (y * w + x) as u32));
                    sinks.resize(pixels.len() * spp as usize, ());
                    wave.trace_pixels(scene, opts, &pixels, spp, &mut st, &mut sinks);
                    let at = SplatAt {
                        x0,
                        y,
                        spp: spp as usize,
                    };
                    splat_wave_now(&wave, &film, at, &mut buf, &mut st);
                }
            }
            let d = done.fetch_add(1, Ordering::Relaxed) + 1;
            progress(d, total);
            (buf, st)
        })
        .collect();
    if stopped.load(Ordering::Relaxed) {
        return None;
    }

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
                let b = buf[by * bw + bx].to_array();
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
    Some(RenderOutput {
        image: Image::from_vec(ww, wh, data),
        stats,
    })
}

/// Box-filtered values of the listed pixels (row-major indices), each
/// bit-identical to what [`render`] with [`PixelFilter::Box`] and the same
/// options gives at that pixel: the same per-(pixel, sample) random
/// streams, summed in the same order. For re-rendering the part of an
/// image a change can reach.
pub fn render_pixels(scene: &RenderScene, opts: &RenderOptions, pixels: &[u32]) -> Vec<Vec3> {
    let spp = opts.spp.max(1);
    pixels
        .par_chunks(BATCH_PIXELS)
        .with_min_len(4)
        .map_init(
            || (Wavefront::default(), Vec::new()),
            |(wave, sinks), chunk| {
                let mut st = RenderStats::default();
                sinks.resize(chunk.len() * spp as usize, ());
                wave.trace_pixels(scene, opts, chunk, spp, &mut st, sinks);
                (0..chunk.len())
                    .map(|k| {
                        let mut b = [0f32; 4];
                        for i in k * spp as usize..(k + 1) * spp as usize {
                            let li = wave.result(i).1;
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
                    .collect::<Vec<_>>()
            },
        )
        .flatten_iter()
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::envmap::EnvMap;
    use matflow_geom::{mesh_from_depth, MeshParams, TriMesh};
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

    /// The depth mesh of a plane facing an `n`×`n` camera at depth 5.
    fn plane_mesh(n: usize) -> (Camera, TriMesh) {
        let cam = Camera::new(n, n);
        let depth = GrayImage::new(n, n, 5.0);
        let mesh = mesh_from_depth(&depth, &cam, &MeshParams::default())
            .unwrap()
            .mesh;
        (cam, mesh)
    }

    fn plane_scene(n: usize, mat: crate::Material) -> RenderScene {
        let (cam, mesh) = plane_mesh(n);
        let maps = MaterialMaps::uniform(n, n, mat.albedo, mat.roughness, mat.metallic);
        RenderScene::new(cam, mesh, &maps, EnvMap::new(&sky()).unwrap()).unwrap()
    }

    /// Given shading normals: the plane's own normal given leaves the
    /// render bit for bit as it was. Under a uniform sky, a shading normal
    /// tilted by α from the plane's sees the sky only where both
    /// hemispheres overlap: for a Lambertian surface (1 + cos α) / 2 of
    /// the cosine-weighted light, 0.93 at 30° and 0.75 at 60°. matflow's
    /// lobe (Fresnel-weighted diffuse and GGX) gives a little more, 0.94
    /// and 0.84; light from below the plane, sampled about the tilted
    /// normal and let through, would give 0.98 at 30°.
    #[test]
    fn given_shading_normals_shade_the_depth_mesh() {
        let n = 12;
        let maps = MaterialMaps::uniform(n, n, Vec3::splat(0.6), 1.0, 0.0);
        let white = Image::new(32, 16, Vec3::ONE);
        let opts = RenderOptions {
            spp: 256,
            seed: 5,
            max_depth: 2,
            ..Default::default()
        };
        let mean = |normal: Option<Vec3>| {
            let (cam, mut mesh) = plane_mesh(n);
            if let Some(v) = normal {
                mesh.normals = vec![v.normalize(); mesh.positions.len()];
            }
            let scene = RenderScene::new(cam, mesh, &maps, EnvMap::new(&white).unwrap()).unwrap();
            let img = render(&scene, &opts, &|_, _| {}).image;
            let m = img.data.iter().map(|v| v.x as f64).sum::<f64>() / img.data.len() as f64;
            (img, m)
        };
        let (own, m0) = mean(None);
        assert_eq!(mean(Some(Vec3::Z)).0.data, own.data);
        let tilted = |deg: f32| {
            let a = deg.to_radians();
            mean(Some(Vec3::new(a.sin(), 0.0, a.cos()))).1 / m0
        };
        let (r30, r60) = (tilted(30.0), tilted(60.0));
        assert!(r30 > 0.92 && r30 < 0.96, "30°: {r30}");
        assert!(r60 > 0.72 && r60 < 0.88 && r60 < r30, "60°: {r60}");
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

    /// A render that is never stopped is the plain render bit for bit; one
    /// stopped before it starts, or after some tiles, gives nothing and
    /// skips the tiles left.
    #[test]
    fn a_stopped_render_gives_nothing_and_skips_the_rest() {
        let scene = plane_scene(
            32,
            crate::Material {
                albedo: Vec3::splat(0.5),
                roughness: 0.4,
                metallic: 0.0,
            },
        );
        let opts = RenderOptions {
            spp: 4,
            seed: 3,
            tile_size: 8,
            ..Default::default()
        };
        let full = render(&scene, &opts, &|_, _| {});
        let kept = render_until(&scene, &opts, &|_, _| {}, &|| false).expect("not stopped");
        assert_eq!(kept.image.data, full.image.data);
        assert!(render_until(&scene, &opts, &|_, _| {}, &|| true).is_none());
        // Stopped after the third tile: 16 tiles, most never traced.
        let done = AtomicUsize::new(0);
        let out = render_until(
            &scene,
            &opts,
            &|_, _| {
                done.fetch_add(1, Ordering::Relaxed);
            },
            &|| done.load(Ordering::Relaxed) >= 3,
        );
        assert!(out.is_none());
        let traced = done.load(Ordering::Relaxed);
        assert!((3..16).contains(&traced), "{traced} of 16 tiles traced");
    }

    /// Triangles that name a material pixel (geometry completed past the
    /// frame) take that pixel's material wherever they are hit; the depth
    /// mesh's own take the pixel they project into; a pixel outside the
    /// image is refused when the scene is built.
    #[test]
    fn named_material_pixels_override_the_projection() {
        let n = 8;
        let (cam, mut mesh) = plane_mesh(n);
        let own = mesh.triangle_count();
        // A floor quad below the camera, named after pixel 42.
        let base = mesh.positions.len() as u32;
        mesh.positions.extend([
            Vec3::new(-5.0, -1.0, 1.0),
            Vec3::new(5.0, -1.0, 1.0),
            Vec3::new(5.0, -1.0, -4.0),
            Vec3::new(-5.0, -1.0, -4.0),
        ]);
        mesh.indices
            .extend([[base, base + 1, base + 2], [base, base + 2, base + 3]]);
        mesh.material_pixel = vec![matflow_geom::PROJECTED; own];
        mesh.material_pixel.extend([42, 42]);
        let maps = MaterialMaps::uniform(n, n, Vec3::splat(0.5), 0.5, 0.0);
        let env = EnvMap::new(&sky()).unwrap();
        let scene = RenderScene::new(cam, mesh.clone(), &maps, env.clone()).unwrap();
        let p = Vec3::new(0.3, -1.0, 0.5);
        assert_eq!(scene.vertex_material(own as u32, p), Some(42));
        assert_eq!(scene.vertex_material(own as u32 + 1, p), Some(42));
        let q = Vec3::new(0.0, 0.0, -5.0);
        assert_eq!(scene.vertex_material(0, q), scene.material_index(q));
        mesh.material_pixel[own] = (n * n) as u32;
        assert!(matches!(
            RenderScene::new(cam, mesh, &maps, env),
            Err(crate::RenderError::MaterialPixel { .. })
        ));
    }

    /// A triangle that names a material pixel (completion's fill behind an
    /// occluder) shows a camera ray that reaches it through a crack of the
    /// depth mesh the material of the pixel the ray passes through; to
    /// every other ray it is the pixel it names.
    #[test]
    fn camera_rays_through_a_crack_see_their_own_pixel_behind_it() {
        struct First(Option<usize>);
        impl PathSink for First {
            fn vertex(&mut self, q: usize, first: bool) {
                if first {
                    self.0 = Some(q);
                }
            }
        }
        let n = 8;
        let (cam, mut mesh) = plane_mesh(n);
        // A crack: the depth mesh's quad between pixel centres 3.5 and 4.5.
        let crack = |f: Vec2| f.x > 3.5 && f.x < 4.5 && f.y > 3.5 && f.y < 4.5;
        let film = mesh.film.clone();
        mesh.indices
            .retain(|t| !crack(t.iter().map(|&k| film[k as usize]).sum::<Vec2>() / 3.0));
        let own = mesh.triangle_count();
        // Behind it, at depth 6, a quad naming pixel 0.
        let base = mesh.positions.len() as u32;
        for (x, y) in [(3.0, 3.0), (5.0, 3.0), (5.0, 5.0), (3.0, 5.0)] {
            mesh.positions.push(cam.backproject(x, y, 6.0));
            mesh.film.push(Vec2::new(x, y));
        }
        mesh.indices
            .extend([[base, base + 1, base + 2], [base, base + 2, base + 3]]);
        let maps = MaterialMaps::uniform(n, n, Vec3::splat(0.5), 0.5, 0.0);
        let env = EnvMap::new(&sky()).unwrap();
        let opts = RenderOptions {
            spp: 64,
            max_depth: 2,
            seed: 5,
            ..Default::default()
        };
        mesh.material_pixel = vec![matflow_geom::PROJECTED; own];
        mesh.material_pixel.extend([0, 0]);
        let scene = RenderScene::new(cam, mesh, &maps, env).unwrap();
        let p = cam.backproject(4.0, 4.0, 6.0);
        assert_eq!(scene.vertex_material(own as u32, p), Some(0));
        assert_eq!(
            scene.camera_vertex_material(own as u32, p),
            scene.material_index(p)
        );
        assert_ne!(scene.material_index(p), Some(0));
        let pixels: Vec<u32> = (0..(n * n) as u32).collect();
        let mut sinks: Vec<First> = (0..pixels.len() * 64).map(|_| First(None)).collect();
        let mut wave = Wavefront::default();
        let mut st = RenderStats::default();
        wave.trace_pixels(&scene, &opts, &pixels, 64, &mut st, &mut sinks);
        let mut through = 0;
        for (i, sink) in sinks.iter().enumerate() {
            let f = wave.result(i).0;
            if crack(f) {
                through += 1;
                let pixel = f.y as usize * n + f.x as usize;
                assert_eq!(sink.0, Some(pixel), "sample at {f}");
            }
        }
        // A quarter of each of the four pixels around the crack.
        assert!(through > 40, "{through} samples through the crack");
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
            let quad = hemisphere_quadrature(1500, |l| {
                let f = crate::bsdf::eval(&mat, Vec3::Z, v, l);
                (f * scene.env.eval(l)).element_sum() as f64
            });
            let (mean, se) = pixel_mean(&scene, &opts, film, 200_000);
            assert!(
                (mean - quad).abs() < 4.0 * se + 1e-3 * quad,
                "{mat:?}: MC {mean} ± {se} vs quadrature {quad}"
            );
        }
    }

    /// ∫ f(l) dl over the hemisphere around +z, on a midpoint grid of `q`
    /// steps in cos θ and 2`q` in φ.
    fn hemisphere_quadrature(q: usize, f: impl Fn(Vec3) -> f64) -> f64 {
        let mut sum = 0.0f64;
        for i in 0..q {
            let ct = (i as f64 + 0.5) / q as f64;
            let st = (1.0 - ct * ct).sqrt();
            for j in 0..2 * q {
                let phi = std::f64::consts::PI * (j as f64 + 0.5) / q as f64;
                sum += f(Vec3::new(
                    (st * phi.cos()) as f32,
                    (st * phi.sin()) as f32,
                    ct as f32,
                ));
            }
        }
        sum * 2.0 * std::f64::consts::PI / (2 * q * q) as f64
    }

    /// Mean and standard error of the channel sum of `m` samples of the
    /// renderer's own estimator at film position `film`.
    fn pixel_mean(scene: &RenderScene, opts: &RenderOptions, film: Vec2, m: u32) -> (f64, f64) {
        let (mut s1, mut s2) = (0.0f64, 0.0f64);
        let mut st = RenderStats::default();
        let mut wave = Wavefront::default();
        for k0 in (0..m).step_by(4096) {
            let k1 = (k0 + 4096).min(m);
            let samples = (k0..k1).map(|k| CameraSample {
                film,
                rng: Sampler::for_sample(9, 0, k, m),
            });
            let mut sinks = vec![(); (k1 - k0) as usize];
            wave.trace(scene, opts, samples, 64, &mut st, &mut sinks);
            for i in 0..wave.len() {
                let x = wave.result(i).1.element_sum() as f64;
                s1 += x;
                s2 += x * x;
            }
        }
        let mean = s1 / m as f64;
        (
            mean,
            ((s2 / m as f64 - mean * mean) / m as f64).max(0.0).sqrt(),
        )
    }

    /// Adds to the depth mesh of [`plane_mesh`] a square of half-size `r`
    /// centred on (`c`, `z`) in the plane z = `z`, its two triangles
    /// naming pixel 0 (the depth mesh's own are projected).
    fn add_square(mesh: &mut TriMesh, c: Vec2, r: f32, z: f32) {
        let own = mesh.triangle_count();
        let base = mesh.positions.len() as u32;
        mesh.positions.extend([
            Vec3::new(c.x - r, c.y - r, z),
            Vec3::new(c.x + r, c.y - r, z),
            Vec3::new(c.x + r, c.y + r, z),
            Vec3::new(c.x - r, c.y + r, z),
        ]);
        mesh.film.resize(mesh.positions.len(), Vec2::ZERO);
        mesh.indices
            .extend([[base, base + 1, base + 2], [base, base + 2, base + 3]]);
        mesh.material_pixel = vec![matflow_geom::PROJECTED; own];
        mesh.material_pixel.extend([0, 0]);
    }

    /// Known answer: the plane of [`plane_under_envmap_matches_quadrature`]
    /// with a large surface behind the camera that lets a share `open` of
    /// light through: the sky it covers reaches the plane scaled by that
    /// share (direct light only, so the surface's own reflection does not
    /// enter), against a quadrature that applies the share to the
    /// directions meeting it. Fully open, it is as if it were not there.
    #[test]
    fn a_partly_open_surface_passes_its_share_of_the_sky() {
        let mat = crate::Material {
            albedo: Vec3::new(0.7, 0.5, 0.3),
            roughness: 0.6,
            metallic: 0.0,
        };
        let n = 8;
        let (cam, mut mesh) = plane_mesh(n);
        let own = mesh.triangle_count();
        // A 12×12 square at z = +1 facing the plane.
        let (z, r) = (1.0f32, 6.0f32);
        add_square(&mut mesh, Vec2::ZERO, r, z);
        let maps = MaterialMaps::uniform(n, n, mat.albedo, mat.roughness, mat.metallic);
        let opts = RenderOptions {
            max_depth: 2,
            ..Default::default()
        };
        let film = Vec2::new(4.0, 4.0);
        for open in [0.3f32, 1.0] {
            let mut m = mesh.clone();
            m.openness = vec![0.0; own];
            m.openness.extend([open, open]);
            let scene = RenderScene::new(cam, m, &maps, EnvMap::new(&sky()).unwrap()).unwrap();
            assert!(scene.has_openness());
            let d = scene.camera_ray(film);
            let p = d * (5.0 / -d.z);
            let v = -d;
            let quad = hemisphere_quadrature(1200, |l| {
                let at = p + l * ((z - p.z) / l.z);
                let share = if at.x.abs() < r && at.y.abs() < r {
                    open
                } else {
                    1.0
                };
                let f = crate::bsdf::eval(&mat, Vec3::Z, v, l);
                (f * scene.env.eval(l) * share).element_sum() as f64
            });
            let (mean, se) = pixel_mean(&scene, &opts, film, 100_000);
            assert!(
                (mean - quad).abs() < 4.0 * se + 1e-3 * quad,
                "open {open}: MC {mean} ± {se} vs quadrature {quad}"
            );
        }
    }

    /// A glossy plane lit by an envmap, three lamps and three suns: one
    /// lamp in front of it, one behind it (its back faces the lamp: no
    /// light) and one hidden behind a small square, and suns in the same
    /// three directions from the pixel's point: the estimator's mean equals
    /// the envmap's quadrature (with the square's solid angle taken out)
    /// plus f·cos·I/r² of the lamp in front and f·cos·E of the sun in
    /// front alone.
    #[test]
    fn lamps_and_suns_add_their_light_where_they_are_seen() {
        let mat = crate::Material {
            albedo: Vec3::new(0.7, 0.5, 0.3),
            roughness: 0.35,
            metallic: 0.0,
        };
        let n = 8;
        let (cam, mut mesh) = plane_mesh(n);
        let p = Vec3::new(0.0, 0.0, -5.0);
        let seen = Vec3::new(0.6, 0.4, -2.0);
        let behind = Vec3::new(-0.5, 0.4, -7.0);
        let hidden = Vec3::new(0.0, -0.6, -3.5);
        // The square, half-size h, where the segment to the hidden lamp
        // crosses z = zs.
        let zs = -4.2f32;
        let c = p + (hidden - p) * ((zs - p.z) / (hidden.z - p.z));
        let h = 0.1f32;
        add_square(&mut mesh, Vec2::new(c.x, c.y), h, zs);
        let maps = MaterialMaps::uniform(n, n, mat.albedo, mat.roughness, mat.metallic);
        let mut scene = RenderScene::new(cam, mesh, &maps, EnvMap::new(&sky()).unwrap()).unwrap();
        let intensity = Vec3::new(2.0, 1.5, 1.0);
        let irradiance = Vec3::new(0.3, 0.35, 0.4);
        let sun_in_front = Vec3::new(-0.5, 0.3, 1.0).normalize();
        let lamps = [seen, behind, hidden]
            .map(|position| crate::Lamp::point(position, intensity))
            .into_iter()
            .chain([sun_in_front, behind - p, hidden - p].map(|d| crate::Lamp::sun(d, irradiance)));
        scene.set_lamps(lamps.collect()).unwrap();
        let opts = RenderOptions {
            max_depth: 2,
            ..Default::default()
        };
        let film = Vec2::new(4.0, 4.0);
        let v = -scene.camera_ray(film);
        let env = hemisphere_quadrature(1200, |l| {
            let at = p + l * ((zs - p.z) / l.z);
            if (at.x - c.x).abs() < h && (at.y - c.y).abs() < h {
                return 0.0;
            }
            let f = crate::bsdf::eval(&mat, Vec3::Z, v, l);
            (f * scene.env.eval(l)).element_sum() as f64
        });
        let d = seen - p;
        let l = d.normalize();
        let lamp =
            (crate::bsdf::eval(&mat, Vec3::Z, v, l) * intensity / d.length_squared()).element_sum();
        let sun = (crate::bsdf::eval(&mat, Vec3::Z, v, sun_in_front) * irradiance).element_sum();
        let expected = env + lamp as f64 + sun as f64;
        let (mean, se) = pixel_mean(&scene, &opts, film, 200_000);
        assert!(
            (mean - expected).abs() < 4.0 * se + 1e-3 * expected,
            "MC {mean} ± {se} vs {expected} (envmap {env}, lamp {lamp}, sun {sun})"
        );
        assert!(
            lamp > 0.05 * env as f32 && sun > 0.05 * env as f32,
            "the lamp and the sun must matter: {lamp}, {sun} vs {env}"
        );
        assert!(!crate::Lamp::point(Vec3::ZERO, Vec3::new(1.0, -1.0, 0.0)).is_valid());
        assert!(!crate::Lamp::sun(Vec3::ZERO, Vec3::ONE).is_valid());
        assert!(crate::Lamp::sun(Vec3::new(0.0, 3.0, 0.0), Vec3::ONE).is_valid());
        assert!(scene
            .set_lamps(vec![crate::Lamp::point(Vec3::NAN, Vec3::ONE)])
            .is_err());
        assert!(scene
            .set_lamps(vec![crate::Lamp {
                at: crate::LampAt::Distant(Vec3::new(0.0, 0.5, 0.0)),
                intensity: Vec3::ONE,
            }])
            .is_err());
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
