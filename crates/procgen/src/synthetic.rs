//! Procedural scenes with known ground truth, so matflow runs (and is
//! tested) on a fresh clone with no external data.
//!
//! A scene is a corner of a room seen by the standard camera: a floor, a
//! back wall and a side wall (open ceiling and open side, so the sky lights
//! it), with a few spheres and boxes standing on the floor. Every surface
//! has its own albedo, roughness and metallic; the floor carries a tile
//! pattern. The camera's rays through the pixel centres give the per-pixel
//! depth (camera-space z), normals and materials; the environment map is a
//! procedural sky with a sun. Everything is a pure function of the seed.

use glam::{Vec2, Vec3};

pub use matflow_scene::rng::Rng;
use matflow_scene::{Camera, GrayImage, Image, MaterialMaps, RgbImage};

/// What a procedural scene provides: geometry as per-pixel camera depth
/// (0 where a pixel sees only sky), true materials and normals, and the
/// true lighting.
#[derive(Clone, Debug)]
pub struct SyntheticScene {
    pub depth: GrayImage,
    pub maps: MaterialMaps,
    pub envmap: RgbImage,
}

#[derive(Clone, Copy, Debug)]
struct Mat {
    albedo: Vec3,
    roughness: f32,
    metallic: f32,
}

#[derive(Clone, Copy, Debug)]
enum Shape {
    /// Plane n·p = d, bounded by an AABB.
    Plane {
        n: Vec3,
        d: f32,
        lo: Vec3,
        hi: Vec3,
    },
    Sphere {
        c: Vec3,
        r: f32,
    },
    Box {
        lo: Vec3,
        hi: Vec3,
    },
}

struct Object {
    shape: Shape,
    mat: Mat,
    tiles: bool,
}

/// HSV (each in [0, 1], hue wrapping) to linear RGB.
pub fn hsv(h: f32, s: f32, v: f32) -> Vec3 {
    let h6 = (h.rem_euclid(1.0)) * 6.0;
    let c = v * s;
    let x = c * (1.0 - ((h6 % 2.0) - 1.0).abs());
    let (r, g, b) = match h6 as u32 {
        0 => (c, x, 0.0),
        1 => (x, c, 0.0),
        2 => (0.0, c, x),
        3 => (0.0, x, c),
        4 => (x, 0.0, c),
        _ => (c, 0.0, x),
    };
    Vec3::new(r, g, b) + Vec3::splat(v - c)
}

fn intersect(shape: &Shape, o: Vec3, d: Vec3) -> Option<(f32, Vec3)> {
    match *shape {
        Shape::Plane { n, d: pd, lo, hi } => {
            let den = n.dot(d);
            if den.abs() < 1e-9 {
                return None;
            }
            let t = (pd - n.dot(o)) / den;
            if t <= 1e-4 {
                return None;
            }
            let p = o + d * t;
            let eps = 1e-4;
            if p.cmplt(lo - eps).any() || p.cmpgt(hi + eps).any() {
                return None;
            }
            Some((t, n))
        }
        Shape::Sphere { c, r } => {
            let oc = o - c;
            let b = oc.dot(d);
            let cc = oc.dot(oc) - r * r;
            let disc = b * b - cc;
            if disc < 0.0 {
                return None;
            }
            let t = -b - disc.sqrt();
            if t <= 1e-4 {
                return None;
            }
            let p = o + d * t;
            Some((t, ((p - c) / r).normalize()))
        }
        Shape::Box { lo, hi } => {
            let inv = d.recip();
            let t0 = (lo - o) * inv;
            let t1 = (hi - o) * inv;
            let tmin = t0.min(t1);
            let tmax = t0.max(t1);
            let tn = tmin.max_element();
            let tf = tmax.min_element();
            if tn > tf || tn <= 1e-4 {
                return None;
            }
            let p = o + d * tn;
            let c = (lo + hi) * 0.5;
            let q = (p - c) / ((hi - lo) * 0.5);
            let a = q.abs();
            let n = if a.x >= a.y && a.x >= a.z {
                Vec3::new(q.x.signum(), 0.0, 0.0)
            } else if a.y >= a.z {
                Vec3::new(0.0, q.y.signum(), 0.0)
            } else {
                Vec3::new(0.0, 0.0, q.z.signum())
            };
            Some((tn, n))
        }
    }
}

/// A procedural sky: horizon-to-zenith gradient, a warm ground, and a sun
/// (a few texels of high radiance), in Mitsuba's lat-long layout.
pub fn procedural_sky(seed: u64, width: usize, height: usize) -> RgbImage {
    let mut rng = Rng(seed ^ 0x5ca1_ab1e);
    let sun_u = rng.range(0.15, 0.85);
    let sun_v = rng.range(0.12, 0.35);
    let sun_power = rng.range(6.0, 14.0);
    let zenith = hsv(
        rng.range(0.55, 0.65),
        rng.range(0.3, 0.6),
        rng.range(0.15, 0.35),
    );
    let horizon = hsv(
        rng.range(0.08, 0.15),
        rng.range(0.05, 0.25),
        rng.range(0.25, 0.45),
    );
    let ground = hsv(
        rng.range(0.05, 0.12),
        rng.range(0.2, 0.4),
        rng.range(0.05, 0.12),
    );
    let sun_dir = sph(sun_u, sun_v);
    Image::from_fn(width, height, |x, y| {
        let u = (x as f32 + 0.5) / width as f32;
        let v = y as f32 / (height - 1).max(1) as f32;
        let d = sph(u, v);
        let base = if d.y >= 0.0 {
            horizon.lerp(zenith, d.y.sqrt())
        } else {
            ground
        };
        let cosang = d.dot(sun_dir).clamp(-1.0, 1.0);
        let sun = sun_power * ((cosang - 1.0) * 40.0).exp();
        base + Vec3::new(1.0, 0.92, 0.8) * sun
    })
}

pub(crate) fn sph(u: f32, v: f32) -> Vec3 {
    let phi = 2.0 * std::f32::consts::PI * u;
    let theta = std::f32::consts::PI * v;
    Vec3::new(
        theta.sin() * phi.sin(),
        theta.cos(),
        -theta.sin() * phi.cos(),
    )
}

/// Builds the procedural scene for `seed` at `width`×`height`.
pub fn generate(seed: u64, width: usize, height: usize) -> SyntheticScene {
    let mut rng = Rng(seed.wrapping_mul(0x2545_f491_4f6c_dd1d) ^ 0x1234_5678);
    let cam = Camera::new(width, height);
    let floor_y = -rng.range(1.2, 1.8);
    let back_z = -rng.range(9.0, 12.0);
    let left_x = -rng.range(2.2, 2.8);
    let mut objects = vec![
        Object {
            shape: Shape::Plane {
                n: Vec3::Y,
                d: floor_y,
                lo: Vec3::new(left_x, floor_y, back_z),
                hi: Vec3::new(6.0, floor_y, -1.0),
            },
            mat: Mat {
                albedo: hsv(rng.f(), rng.range(0.1, 0.4), rng.range(0.4, 0.8)),
                roughness: rng.range(0.3, 0.7),
                metallic: 0.0,
            },
            tiles: true,
        },
        Object {
            shape: Shape::Plane {
                n: Vec3::Z,
                d: back_z,
                lo: Vec3::new(left_x, floor_y, back_z),
                hi: Vec3::new(6.0, floor_y + 4.0, back_z),
            },
            mat: Mat {
                albedo: hsv(rng.f(), rng.range(0.05, 0.3), rng.range(0.5, 0.9)),
                roughness: rng.range(0.6, 1.0),
                metallic: 0.0,
            },
            tiles: false,
        },
        Object {
            shape: Shape::Plane {
                n: Vec3::X,
                d: left_x,
                lo: Vec3::new(left_x, floor_y, back_z),
                hi: Vec3::new(left_x, floor_y + 4.0, -1.0),
            },
            mat: Mat {
                albedo: hsv(rng.f(), rng.range(0.1, 0.5), rng.range(0.4, 0.8)),
                roughness: rng.range(0.5, 1.0),
                metallic: 0.0,
            },
            tiles: false,
        },
    ];
    let n_obj = 3 + (rng.next_u64() % 2) as usize;
    for k in 0..n_obj {
        let x = -2.0 + 4.0 * (k as f32 + rng.range(0.2, 0.8)) / n_obj as f32;
        let z = rng.range(-7.0, -4.5);
        let metallic = if rng.f() < 0.3 { 1.0 } else { 0.0 };
        let mat = Mat {
            albedo: hsv(rng.f(), rng.range(0.3, 0.9), rng.range(0.3, 0.9)),
            roughness: rng.range(0.1, 0.9),
            metallic,
        };
        let shape = if rng.f() < 0.6 {
            let r = rng.range(0.4, 0.8);
            Shape::Sphere {
                c: Vec3::new(x, floor_y + r, z),
                r,
            }
        } else {
            let s = Vec3::new(
                rng.range(0.5, 0.9),
                rng.range(0.5, 1.4),
                rng.range(0.5, 0.9),
            );
            Shape::Box {
                lo: Vec3::new(x - s.x * 0.5, floor_y, z - s.z * 0.5),
                hi: Vec3::new(x + s.x * 0.5, floor_y + s.y, z + s.z * 0.5),
            }
        };
        objects.push(Object {
            shape,
            mat,
            tiles: false,
        });
    }

    let mut depth = Image::new(width, height, 0.0f32);
    let mut albedo = Image::new(width, height, Vec3::splat(0.5));
    let mut rough = Image::new(width, height, 0.5f32);
    let mut metal = Image::new(width, height, 0.0f32);
    let mut normal = Image::new(width, height, Vec3::Z);
    for y in 0..height {
        for x in 0..width {
            let d = cam.film_to_dir(Vec2::new(x as f32 + 0.5, y as f32 + 0.5));
            let dn = d.normalize();
            let mut best: Option<(f32, Vec3, &Object)> = None;
            for o in &objects {
                if let Some((t, n)) = intersect(&o.shape, Vec3::ZERO, dn) {
                    if best.map(|b| t < b.0).unwrap_or(true) {
                        best = Some((t, n, o));
                    }
                }
            }
            if let Some((t, n, o)) = best {
                let p = dn * t;
                depth.set(x, y, -p.z);
                let n = if n.dot(dn) > 0.0 { -n } else { n };
                normal.set(x, y, n);
                let mut a = o.mat.albedo;
                if o.tiles {
                    let cell =
                        ((p.x * 1.25).floor() as i64 + (p.z * 1.25).floor() as i64).rem_euclid(2);
                    if cell == 1 {
                        a *= 0.6;
                    }
                }
                albedo.set(x, y, a);
                rough.set(x, y, o.mat.roughness);
                metal.set(x, y, o.mat.metallic);
            }
        }
    }
    SyntheticScene {
        depth,
        maps: MaterialMaps {
            albedo,
            roughness: rough,
            metallic: metal,
            normal: Some(normal),
            transparency: None,
        },
        envmap: procedural_sky(seed, 32, 16),
    }
}

/// MatNet-like predictions made from the ground truth, so the inverse
/// stages have something realistic to correct: albedo blurred (σ 1.5 px),
/// with a per-channel gain of 0.75–1.25 and noise (σ 0.03); roughness
/// blurred, shifted by ±0.15–0.3 and noisy (σ 0.05); metallic pulled
/// halfway towards 0.3 (metals under-, dielectrics over-predicted) plus
/// noise. All clamped to the valid ranges; normals are kept (geometry is
/// not what is being recovered). A pure function of `maps` and `seed`.
pub fn degrade(maps: &MaterialMaps, seed: u64) -> MaterialMaps {
    let mut rng = Rng(seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) ^ 0xdeca_f000);
    let gain = Vec3::new(
        rng.range(0.75, 1.25),
        rng.range(0.75, 1.25),
        rng.range(0.75, 1.25),
    );
    let r_shift = rng.range(0.15, 0.3) * if rng.f() < 0.5 { -1.0 } else { 1.0 };
    let (w, h) = (maps.albedo.width, maps.albedo.height);
    // Per-pixel noise from a hash of (seed, pixel, channel): uniform with
    // the stated standard deviation (σ·√3 half-width).
    let noise = |p: usize, c: u64, sigma: f32| -> f32 {
        let mut r = Rng(seed ^ (p as u64).wrapping_mul(0x2545_f491_4f6c_dd1d) ^ (c << 56));
        (r.f() * 2.0 - 1.0) * sigma * 3f32.sqrt()
    };
    let blur_a = blur(&maps.albedo, 1.5);
    let blur_r = blur(&maps.roughness.map(Vec3::splat), 1.5);
    let albedo = Image::from_fn(w, h, |x, y| {
        let p = y * w + x;
        let a = blur_a.get(x, y) * gain
            + Vec3::new(noise(p, 0, 0.03), noise(p, 1, 0.03), noise(p, 2, 0.03));
        a.clamp(Vec3::ZERO, Vec3::ONE)
    });
    let roughness = Image::from_fn(w, h, |x, y| {
        let p = y * w + x;
        (blur_r.get(x, y).x + r_shift + noise(p, 3, 0.05)).clamp(0.0, 1.0)
    });
    let metallic = Image::from_fn(w, h, |x, y| {
        let p = y * w + x;
        (0.5 * maps.metallic.get(x, y) + 0.15 + noise(p, 4, 0.05)).clamp(0.0, 1.0)
    });
    MaterialMaps {
        albedo,
        roughness,
        metallic,
        normal: maps.normal.clone(),
        transparency: None,
    }
}

/// Separable Gaussian blur with renormalised border windows.
fn blur(img: &RgbImage, sigma: f32) -> RgbImage {
    let r = (3.0 * sigma).ceil() as i64;
    let g: Vec<f32> = (-r..=r)
        .map(|i| (-(i * i) as f32 / (2.0 * sigma * sigma)).exp())
        .collect();
    let (w, h) = (img.width as i64, img.height as i64);
    let pass = |src: &RgbImage, dx: i64, dy: i64| -> RgbImage {
        Image::from_fn(src.width, src.height, |x, y| {
            let (mut s, mut n) = (Vec3::ZERO, 0.0);
            for (k, gk) in g.iter().enumerate() {
                let o = k as i64 - r;
                let (xx, yy) = (x as i64 + o * dx, y as i64 + o * dy);
                if xx >= 0 && xx < w && yy >= 0 && yy < h {
                    s += src.get(xx as usize, yy as usize) * *gk;
                    n += gk;
                }
            }
            s / n
        })
    };
    pass(&pass(img, 1, 0), 0, 1)
}

/// The relighting envmap for a scene: a different procedural sky (another
/// seed) turned half way round, so sun direction, colours and intensity
/// all change.
pub fn relight_sky(seed: u64, width: usize, height: usize) -> RgbImage {
    let sky = procedural_sky(seed ^ 0x7e11_9470, width, height);
    Image::from_fn(width, height, |x, y| sky.get((x + width / 2) % width, y))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn deterministic_and_varied() {
        let a = generate(3, 64, 64);
        let b = generate(3, 64, 64);
        let c = generate(4, 64, 64);
        assert_eq!(a.depth, b.depth);
        assert_eq!(a.maps, b.maps);
        assert_ne!(a.maps.albedo, c.maps.albedo);
    }

    #[test]
    fn degraded_predictions_differ_but_stay_valid() {
        let s = generate(2, 48, 48);
        let d = degrade(&s.maps, 2);
        assert_eq!(d, degrade(&s.maps, 2));
        let mut diff = [0f64; 3];
        for k in 0..48 * 48 {
            let a = d.albedo.data[k];
            assert!(a.min_element() >= 0.0 && a.max_element() <= 1.0);
            assert!((0.0..=1.0).contains(&d.roughness.data[k]));
            assert!((0.0..=1.0).contains(&d.metallic.data[k]));
            diff[0] += (a - s.maps.albedo.data[k]).abs().element_sum() as f64;
            diff[1] += (d.roughness.data[k] - s.maps.roughness.data[k]).abs() as f64;
            diff[2] += (d.metallic.data[k] - s.maps.metallic.data[k]).abs() as f64;
        }
        let n = (48 * 48) as f64;
        assert!(diff[0] / (3.0 * n) > 0.02, "albedo barely changed");
        assert!(diff[1] / n > 0.1, "roughness barely changed");
        assert!(diff[2] / n > 0.05, "metallic barely changed");
        assert_eq!(d.normal, s.maps.normal);
        let r = relight_sky(2, 32, 16);
        assert_ne!(r, s.envmap);
        assert!(r
            .data
            .iter()
            .all(|v| v.is_finite() && v.min_element() >= 0.0));
    }

    #[test]
    fn geometry_and_materials_are_valid() {
        let s = generate(1, 96, 96);
        // The floor fills the bottom row, the sky (z = 0) may fill the top.
        assert!((0..96).all(|x| s.depth.get(x, 95) > 0.0));
        for (k, &z) in s.depth.data.iter().enumerate() {
            assert!(z.is_finite() && z >= 0.0);
            let n = s.maps.normal.as_ref().unwrap().data[k];
            assert!((n.length() - 1.0).abs() < 1e-4);
            let a = s.maps.albedo.data[k];
            assert!(a.min_element() >= 0.0 && a.max_element() <= 1.0);
        }
        let sky = s.envmap;
        assert_eq!((sky.width, sky.height), (32, 16));
        assert!(sky
            .data
            .iter()
            .all(|v| v.is_finite() && v.min_element() >= 0.0));
        // The sun is much brighter than the sky.
        let max = sky.data.iter().map(|v| v.x).fold(0.0, f32::max);
        assert!(max > 3.0);
    }
}
