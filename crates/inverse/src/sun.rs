//! The sun as a light of its own.
//!
//! A 32×16 envmap texel spans 11°×11°; the sun spans half a degree. Fitted
//! into texels, a sun's light comes from a patch of sky twenty times wider
//! than it is (and the scout's fit, from a few paths per pixel, spreads it
//! wider still, wherever the surfaces in view cannot tell directions
//! apart), so the shadows it casts come out soft and the inverse stages
//! paint the sharp edges the photo shows into the albedo, where a new
//! light brings them back wrongly. So where the photo shows a sun, it
//! becomes a distant lamp ([`matflow_render::Lamp::sun`]) fitted with the
//! texels ([`crate::paths`]: one more entry of the light vector).
//!
//! Whether there is one, and where, is read from the pattern of light and
//! shadow, at each pixel's first hit (point p, normal n, diffuse albedo
//! over π a, the photo's light r there). A sun in direction d gives
//! E·x_p, x_p = a_p·max(0, n_p·d)·V_p(d), V the visibility towards d:
//! direct light only. Light from everywhere else is, to first order in
//! the normal, a_p·(g₀ + g·n_p) (the irradiance of a smooth sky and of
//! what the walls return), four *ambient* regressors. Per channel, least
//! squares of r on the ambient regressors and x: the sun's share is what
//! x explains of what the ambient ones leave ([`score`]; E ≤ 0 explains
//! nothing). The search scores every texel centre of the upper sky
//! ([`sky_directions`]), then a finer grid around the best
//! ([`candidates`]); the scene has a sun when the best explains at least
//! [`SunParams::explained`] in a colour near white
//! ([`SunParams::whiteness`]). Overcast skies and interiors lit through
//! windows leave no shadow pattern one direction explains, get no sun and
//! pay only the search. Where a sun is found, the scout's envmap with its
//! brightest texels brought down to the sky's level ([`baseline`]) and
//! the sun at the irradiance the search fitted start the fit.

use glam::{DMat4, DVec3, DVec4, Vec3};
use matflow_render::envmap::{dir_to_uv, uv_to_dir};
use matflow_render::integrator::offset_origin;
use matflow_render::RenderScene;
use matflow_scene::color::luminance;
use rayon::prelude::*;

/// When the photo shows a sun, and how its direction is searched.
#[derive(Clone, Copy, Debug)]
pub struct SunParams {
    /// Luminance quantile of the scout envmap's texels above which they
    /// are brought down to it, where a sun takes their light.
    pub quantile: f32,
    /// Least share of the photo's light that the ambient terms leave
    /// (all channels) the best direction must explain.
    pub explained: f32,
    /// Least ratio of the sun's weakest channel to its strongest: a sun
    /// is near white; light one colour alone explains (an orange object
    /// lit from one side) is not a sun.
    pub whiteness: f32,
    /// The coarse search covers texel rows whose centre lies above this
    /// (v, 0 = straight up in the camera's frame, 0.5 = its horizon).
    pub max_v: f32,
    /// Candidate directions per side of the fine grid (odd: the coarse
    /// best is one of them).
    pub grid: usize,
    /// Half-width of the fine grid, in texels.
    pub span: f32,
    /// Most pixels the search looks at (spread evenly over those given).
    pub pixels: usize,
}

impl Default for SunParams {
    fn default() -> Self {
        SunParams {
            quantile: 0.75,
            explained: 0.3,
            whiteness: 0.15,
            max_v: 0.6,
            grid: 9,
            span: 1.0,
            pixels: 16384,
        }
    }
}

/// The first `w`·`h` entries of `env` (an envmap's texels) with every
/// texel brighter than the `quantile` of their luminances scaled down to
/// it (its colour kept): the sky without a peak.
pub fn baseline(env: &[Vec3], w: usize, h: usize, quantile: f32) -> Vec<Vec3> {
    let n = (w * h).min(env.len());
    let mut lum: Vec<f32> = env[..n].iter().map(|e| luminance(*e).max(0.0)).collect();
    lum.sort_by(f32::total_cmp);
    let k = ((quantile.clamp(0.0, 1.0) * n as f32) as usize).min(n.saturating_sub(1));
    let cap = lum.get(k).copied().unwrap_or(0.0);
    env[..n]
        .iter()
        .map(|&e| {
            let l = luminance(e);
            if l > cap && l > 0.0 {
                e * (cap / l)
            } else {
                e
            }
        })
        .collect()
}

/// Texel centres of a `w`×`h` map in rows above `max_v` (the coarse
/// search).
pub fn sky_directions(w: usize, h: usize, max_v: f32) -> Vec<Vec3> {
    (0..h)
        .filter(|&y| (y as f32 + 0.5) / (h as f32) < max_v)
        .flat_map(|y| {
            (0..w).map(move |x| uv_to_dir((x as f32 + 0.5) / w as f32, (y as f32 + 0.5) / h as f32))
        })
        .collect()
}

/// The fine search: a `grid`×`grid` lattice of (u, v) around `centre`'s,
/// `span` texels of a `w`×`h` map each way (u wraps; v stays inside the
/// sphere).
pub fn candidates(centre: Vec3, w: usize, h: usize, params: &SunParams) -> Vec<Vec3> {
    let (u0, v0) = dir_to_uv(centre);
    let g = params.grid.max(1) | 1;
    let half = (g / 2) as f32;
    let step = |i: usize, size: usize| {
        if half > 0.0 {
            (i as f32 - half) / half * params.span / size as f32
        } else {
            0.0
        }
    };
    let mut out = Vec::with_capacity(g * g);
    for j in 0..g {
        for i in 0..g {
            let u = (u0 + step(i, w)).rem_euclid(1.0);
            let v = (v0 + step(j, h)).clamp(1e-4, 1.0 - 1e-4);
            out.push(uv_to_dir(u, v));
        }
    }
    out
}

/// One pixel of the search: its first hit (camera space), the normal
/// there facing the camera, its diffuse albedo over π and the photo's
/// light there (linear).
#[derive(Clone, Copy, Debug)]
pub struct SearchPixel {
    pub point: Vec3,
    pub normal: Vec3,
    pub albedo: Vec3,
    pub light: Vec3,
}

/// A sun in one direction, fitted to the photo's light.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SunFit {
    pub direction: Vec3,
    /// Per channel, the best irradiance (≥ 0).
    pub irradiance: Vec3,
    /// Share of what the ambient terms alone leave of the photo's light
    /// that the sun explains.
    pub explained: f64,
}

impl SunFit {
    /// Whether it explains enough, in a colour near enough white, to be
    /// taken for the sun.
    pub fn is_sun(&self, params: &SunParams) -> bool {
        let e = self.irradiance;
        self.explained >= params.explained as f64
            && e.max_element() > 0.0
            && e.min_element() >= params.whiteness * e.max_element()
    }
}

/// The sun in direction `d` fitted to `pixels`' light besides the
/// ambient terms (see the module documentation); sums over the pixels in
/// order.
pub fn score(scene: &RenderScene, pixels: &[SearchPixel], d: Vec3) -> SunFit {
    score_with(scene, pixels, &ambient(pixels), d, scene.beyond())
}

/// Per channel, the ambient regressors' normal equations: AᵀA (with a
/// small ridge) inverted, Aᵀr, and what A explains of rᵀr.
struct Ambient {
    inv: [DMat4; 3],
    beta: [DVec4; 3],
    left: [f64; 3],
}

fn ambient_regressors(p: &SearchPixel, c: usize) -> DVec4 {
    let a = p.albedo[c] as f64;
    let n = p.normal.as_dvec3();
    DVec4::new(a, a * n.x, a * n.y, a * n.z)
}

fn ambient(pixels: &[SearchPixel]) -> Ambient {
    let mut out = Ambient {
        inv: [DMat4::ZERO; 3],
        beta: [DVec4::ZERO; 3],
        left: [0.0; 3],
    };
    for c in 0..3 {
        let (mut ata, mut atr, mut rr) = (DMat4::ZERO, DVec4::ZERO, 0.0);
        for p in pixels {
            let a = ambient_regressors(p, c);
            let r = p.light[c] as f64;
            ata += DMat4::from_cols(a * a.x, a * a.y, a * a.z, a * a.w);
            atr += a * r;
            rr += r * r;
        }
        let ridge = 1e-9 * (ata.x_axis.x + ata.y_axis.y + ata.z_axis.z + ata.w_axis.w) + 1e-30;
        let inv = (ata + DMat4::from_diagonal(DVec4::splat(ridge))).inverse();
        let beta = inv * atr;
        out.inv[c] = inv;
        out.beta[c] = if beta.is_finite() { beta } else { DVec4::ZERO };
        out.left[c] = (rr - atr.dot(out.beta[c])).max(0.0);
    }
    out
}

fn score_with(
    scene: &RenderScene,
    pixels: &[SearchPixel],
    amb: &Ambient,
    d: Vec3,
    far: f32,
) -> SunFit {
    let mut rays = Vec::with_capacity(pixels.len());
    let mut lit = Vec::with_capacity(pixels.len());
    for (i, p) in pixels.iter().enumerate() {
        let c = p.normal.dot(d);
        if c > 0.0 {
            rays.push((offset_origin(p.point, p.normal, d), d * far));
            lit.push((i, c));
        }
    }
    let mut blocked = vec![false; rays.len()];
    scene
        .bvh
        .occluded_stream(&rays, 0.0, 1.0 - 1e-4, &mut blocked);
    // Per channel: xᵀx, xᵀr and Aᵀx over the lit pixels.
    let (mut xx, mut xr) = ([0f64; 3], [0f64; 3]);
    let mut xa = [DVec4::ZERO; 3];
    for (&(i, cos), b) in lit.iter().zip(&blocked) {
        if !*b {
            let p = &pixels[i];
            for c in 0..3 {
                let x = (p.albedo[c] * cos) as f64;
                xx[c] += x * x;
                xr[c] += x * p.light[c] as f64;
                xa[c] += ambient_regressors(p, c) * x;
            }
        }
    }
    let (mut gain, mut left) = (0.0, 0.0);
    let mut e = DVec3::ZERO;
    for c in 0..3 {
        left += amb.left[c];
        // x less its projection on the ambient regressors, and what that
        // explains of what they leave.
        let num = xr[c] - xa[c].dot(amb.beta[c]);
        let den = xx[c] - xa[c].dot(amb.inv[c] * xa[c]);
        if num > 0.0 && den > 1e-12 * xx[c] && num.is_finite() {
            e[c] = num / den;
            gain += num * num / den;
        }
    }
    SunFit {
        direction: d,
        irradiance: e.as_vec3(),
        explained: if left > 0.0 {
            (gain / left).min(1.0)
        } else {
            0.0
        },
    }
}

/// The best of `directions` (most explained; the first of equals).
fn best_of(scene: &RenderScene, pixels: &[SearchPixel], directions: &[Vec3]) -> Option<SunFit> {
    let far = scene.beyond();
    let amb = ambient(pixels);
    let fits: Vec<SunFit> = directions
        .par_iter()
        .map(|&d| score_with(scene, pixels, &amb, d, far))
        .collect();
    fits.into_iter()
        .fold(None, |best: Option<SunFit>, f| match best {
            Some(b) if b.explained >= f.explained => Some(b),
            _ => Some(f),
        })
        .filter(|f| f.explained > 0.0)
}

/// The search (see the module documentation): the best texel centre of
/// the upper sky of a `w`×`h` map, refined on the finer grid around it;
/// `None` when no direction explains anything.
pub fn search(
    scene: &RenderScene,
    pixels: &[SearchPixel],
    w: usize,
    h: usize,
    params: &SunParams,
) -> Option<SunFit> {
    let coarse = best_of(scene, pixels, &sky_directions(w, h, params.max_v))?;
    best_of(scene, pixels, &candidates(coarse.direction, w, h, params))
}

#[cfg(test)]
mod tests {
    use super::*;
    use matflow_geom::TriMesh;
    use matflow_render::EnvMap;
    use matflow_scene::{Camera, Image, MaterialMaps};

    /// The baseline brings texels above the quantile down to it, colour
    /// kept, and leaves the rest.
    #[test]
    fn the_baseline_is_the_sky_without_its_peak() {
        let (w, h) = (8usize, 4usize);
        let sky = Vec3::new(0.2, 0.3, 0.5);
        let mut env = vec![sky; w * h];
        env[5] = Vec3::new(60.0, 50.0, 40.0);
        env[6] = sky * 2.0;
        let b = baseline(&env, w, h, 0.75);
        for (t, e) in b.iter().enumerate().filter(|(t, _)| *t != 5) {
            assert!((*e - sky).abs().max_element() < 1e-6, "texel {t}: {e}");
        }
        let e5 = Vec3::new(60.0, 50.0, 40.0);
        assert!((luminance(b[5]) - luminance(sky)).abs() < 1e-6, "{}", b[5]);
        assert!((b[5] / b[5].x - e5 / e5.x).abs().max_element() < 1e-5);
    }

    /// The fine candidates span the texels around the centre, which is one
    /// of them, and wrap in longitude; the coarse ones are the upper
    /// rows' texel centres.
    #[test]
    fn candidates_surround_the_centre() {
        let p = SunParams::default();
        let c = uv_to_dir(0.001, 0.3);
        let cands = candidates(c, 32, 16, &p);
        assert_eq!(cands.len(), 81);
        assert!(cands.iter().any(|d| d.dot(c) > 0.99999));
        let widest = cands.iter().map(|d| d.dot(c)).fold(1.0f32, f32::min);
        // About one texel (11.25° in u at sin v = 0.81, 11.25° in v).
        assert!(widest < (8f32).to_radians().cos() && widest > (20f32).to_radians().cos());
        assert!(cands
            .iter()
            .all(|d| d.is_finite() && (d.length() - 1.0).abs() < 1e-5));
        let sky = sky_directions(32, 16, 0.6);
        assert_eq!(sky.len(), 32 * 10);
        assert!(sky.iter().all(|d| d.y > -0.31));
    }

    /// A floor with a block standing on it, lit by a sun (the block's
    /// shadow on it): the search finds that sun within a fraction of a
    /// texel, at its irradiance, explaining nearly all the light; light
    /// in a pattern no sun's shadow explains (a checkerboard unrelated to
    /// the block) is not a sun.
    #[test]
    fn the_search_finds_the_sun_whose_shadow_the_photo_shows() {
        let mut mesh = TriMesh::default();
        let quad = |m: &mut TriMesh, a: Vec3, b: Vec3, c: Vec3, d: Vec3| {
            let i = m.positions.len() as u32;
            m.positions.extend([a, b, c, d]);
            m.indices.push([i, i + 1, i + 2]);
            m.indices.push([i, i + 2, i + 3]);
        };
        // Floor y = −1 over x ∈ [−3, 3], z ∈ [−8, −2].
        let v = Vec3::new;
        quad(
            &mut mesh,
            v(-3.0, -1.0, -2.0),
            v(3.0, -1.0, -2.0),
            v(3.0, -1.0, -8.0),
            v(-3.0, -1.0, -8.0),
        );
        // The block: x ∈ [−0.5, 0.5], y ∈ [−1, 0.5], z ∈ [−5.5, −4.5].
        mesh.add_box(v(-0.5, -1.0, -5.5), v(0.5, 0.5, -4.5));
        let cam = Camera::new(16, 16);
        let maps = MaterialMaps::uniform(16, 16, Vec3::splat(0.5), 0.5, 0.0);
        let env = EnvMap::new(&Image::from_vec(4, 4, vec![Vec3::ONE; 16])).unwrap();
        let scene = RenderScene::new(cam, mesh, &maps, env).unwrap();
        let (w, h) = (32usize, 16usize);
        let truth = uv_to_dir(0.6137, 0.2861);
        let e = Vec3::new(3.0, 2.5, 2.0);
        let albedo = Vec3::new(0.5, 0.4, 0.3) / std::f32::consts::PI;
        let sees = |p: Vec3| {
            !scene.bvh.occluded(
                offset_origin(p, Vec3::Y, truth),
                truth * 100.0,
                0.0,
                1.0 - 1e-4,
            )
        };
        let floor = |f: &dyn Fn(usize, Vec3) -> Vec3| {
            let mut out = Vec::new();
            for j in 0..80 {
                for i in 0..80 {
                    let p = v(
                        -3.0 + 0.075 * i as f32 + 0.03,
                        -1.0,
                        -2.0 - 0.075 * j as f32 - 0.03,
                    );
                    out.push(SearchPixel {
                        point: p,
                        normal: Vec3::Y,
                        albedo,
                        light: f(j * 80 + i, p),
                    });
                }
            }
            out
        };
        let pixels = floor(&|_, p| {
            if sees(p) {
                albedo * truth.y * e
            } else {
                Vec3::ZERO
            }
        });
        let shade = pixels.iter().filter(|p| p.light == Vec3::ZERO).count();
        assert!(
            shade > 100,
            "the block casts a shadow on the floor: {shade}"
        );
        let fit = search(&scene, &pixels, w, h, &SunParams::default()).expect("a sun");
        assert!(
            fit.direction.dot(truth) > 1.5f32.to_radians().cos(),
            "found {} for {truth}",
            fit.direction
        );
        assert!(fit.explained > 0.9, "{}", fit.explained);
        assert!(
            (fit.irradiance / e - 1.0).abs().max_element() < 0.05,
            "{}",
            fit.irradiance
        );
        // Light that no sun's shadow explains: a checkerboard of patches.
        let noise = floor(&|k, _| {
            let (i, j) = (k % 80 / 10, k / 80 / 10);
            albedo * if (i + j) % 2 == 0 { 2.0 } else { 0.0 }
        });
        let fit = search(&scene, &noise, w, h, &SunParams::default());
        assert!(
            fit.map_or(0.0, |f| f.explained) < SunParams::default().explained as f64,
            "{fit:?}"
        );
    }
}
