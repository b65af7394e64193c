//! Procedural environment maps, so that datasets made on a fresh clone see
//! varied lighting without any HDR files: outdoor skies (a gradient sky,
//! ground and a sun: [`crate::synthetic::procedural_sky`]) and rooms — a
//! box around the viewer with painted walls, a planked floor, ceiling
//! lamps and windows onto a bright sky. Lat-long, Mitsuba's layout (as
//! every envmap in matflow), linear radiance; a pure function of the seed.

use glam::Vec3;

use crate::synthetic::{hsv, procedural_sky, sph, Rng};
use matflow_scene::{Image, RgbImage};

/// The kinds of procedural environment map.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum EnvKind {
    Sky,
    Room,
}

impl EnvKind {
    pub const NAMES: &'static [&'static str] = &["sky", "room"];

    pub fn name(self) -> &'static str {
        match self {
            EnvKind::Sky => "sky",
            EnvKind::Room => "room",
        }
    }

    pub fn from_name(s: &str) -> Option<EnvKind> {
        match s {
            "sky" => Some(EnvKind::Sky),
            "room" => Some(EnvKind::Room),
            _ => None,
        }
    }
}

/// The procedural envmap of `kind` and `seed` at `width`×`height`.
pub fn procedural_envmap(kind: EnvKind, seed: u64, width: usize, height: usize) -> RgbImage {
    match kind {
        EnvKind::Sky => procedural_sky(seed, width, height),
        EnvKind::Room => room(seed, width, height),
    }
}

/// An axis-aligned rectangle on a face: [a0, a1] × [b0, b1] in the face's
/// two coordinates.
#[derive(Clone, Copy, Debug)]
struct Rect {
    a0: f32,
    a1: f32,
    b0: f32,
    b1: f32,
}

impl Rect {
    fn contains(&self, a: f32, b: f32) -> bool {
        a >= self.a0 && a <= self.a1 && b >= self.b0 && b <= self.b1
    }
}

/// A room seen from inside: the viewer at the origin, walls at
/// x = −wx0, +wx1 and z = −wz0, +wz1, the floor at y = −floor, the ceiling
/// at y = +ceil. Walls and floor reflect an ambient level of light; lamps
/// on the ceiling and windows in one or two walls emit.
pub fn room(seed: u64, width: usize, height: usize) -> RgbImage {
    let mut rng = Rng(seed.wrapping_mul(0xa076_1d64_78bd_642f) ^ 0x0e17_a9e5);
    let lo = Vec3::new(
        rng.range(1.5, 5.0),
        rng.range(0.8, 1.6),
        rng.range(1.5, 5.0),
    );
    let hi = Vec3::new(
        rng.range(1.5, 5.0),
        rng.range(1.2, 2.4),
        rng.range(1.5, 5.0),
    );
    let ambient = rng.range(0.15, 0.7);
    // Walls: -x, +x, -z, +z.
    let wall_albedo: Vec<Vec3> = (0..4)
        .map(|_| hsv(rng.f(), rng.range(0.05, 0.45), rng.range(0.35, 0.9)))
        .collect();
    let floor_albedo = hsv(
        rng.range(0.03, 0.12),
        rng.range(0.3, 0.7),
        rng.range(0.15, 0.6),
    );
    let plank = rng.range(0.12, 0.3);
    let ceiling_albedo = Vec3::splat(rng.range(0.7, 0.95));
    let lamp_colour = hsv(rng.range(0.07, 0.14), rng.range(0.0, 0.35), 1.0);
    let lamp_power = rng.range(8.0, 40.0);
    let lamps: Vec<Rect> = (0..1 + (rng.next_u64() % 3) as usize)
        .map(|_| {
            let (cx, cz) = (rng.range(-lo.x, hi.x) * 0.7, rng.range(-lo.z, hi.z) * 0.7);
            let (sx, sz) = (rng.range(0.15, 0.6), rng.range(0.15, 0.6));
            Rect {
                a0: cx - sx,
                a1: cx + sx,
                b0: cz - sz,
                b1: cz + sz,
            }
        })
        .collect();
    // Windows: on walls chosen at random, spanning part of the wall.
    let sky_top = hsv(rng.range(0.55, 0.63), rng.range(0.2, 0.6), 1.0);
    let sky_power = rng.range(2.0, 12.0);
    let outside_ground = hsv(
        rng.range(0.1, 0.35),
        rng.range(0.2, 0.6),
        rng.range(0.1, 0.3),
    );
    let windows: Vec<(usize, Rect)> = (0..1 + (rng.next_u64() % 2) as usize)
        .map(|_| {
            let wall = (rng.next_u64() % 4) as usize;
            let half_span = if wall < 2 {
                lo.z.min(hi.z)
            } else {
                lo.x.min(hi.x)
            };
            let c = rng.range(-0.5, 0.5) * half_span;
            let s = rng.range(0.3, 0.9) * half_span * 0.6;
            let y0 = rng.range(-0.2, 0.4);
            let y1 = (y0 + rng.range(0.6, 1.6)).min(hi.y - 0.1);
            (
                wall,
                Rect {
                    a0: c - s,
                    a1: c + s,
                    b0: y0,
                    b1: y1.max(y0 + 0.1),
                },
            )
        })
        .collect();
    Image::from_fn(width, height, |x, y| {
        let u = (x as f32 + 0.5) / width as f32;
        let v = y as f32 / (height - 1).max(1) as f32;
        let d = sph(u, v);
        // Distance to each face along d (infinite when parallel).
        let t_axis = |c: f32, neg: f32, pos: f32| {
            if c > 1e-9 {
                pos / c
            } else if c < -1e-9 {
                neg / -c
            } else {
                f32::INFINITY
            }
        };
        let tx = t_axis(d.x, lo.x, hi.x);
        let ty = t_axis(d.y, lo.y, hi.y);
        let tz = t_axis(d.z, lo.z, hi.z);
        let t = tx.min(ty).min(tz);
        let p = d * if t.is_finite() { t } else { 0.0 };
        if ty <= tx && ty <= tz {
            if d.y < 0.0 {
                // Floor: planks along x, each a little lighter or darker.
                let k = (p.z / plank).floor();
                let shade = 0.8 + 0.4 * (((k * 12.9898).sin() * 43_758.547).fract().abs());
                floor_albedo * shade * ambient
            } else if lamps.iter().any(|r| r.contains(p.x, p.z)) {
                lamp_colour * lamp_power
            } else {
                ceiling_albedo * ambient * 0.8
            }
        } else {
            let (wall, along) = if tx <= tz {
                (if d.x < 0.0 { 0 } else { 1 }, p.z)
            } else {
                (if d.z < 0.0 { 2 } else { 3 }, p.x)
            };
            let in_window = windows
                .iter()
                .any(|(w, r)| *w == wall && r.contains(along, p.y));
            if in_window {
                // The view out: sky above the horizon, ground below.
                let elev = d.y;
                if elev > -0.02 {
                    Vec3::splat(1.0).lerp(sky_top, elev.clamp(0.0, 1.0).sqrt()) * sky_power
                } else {
                    outside_ground * sky_power * 0.3
                }
            } else {
                // Painted wall, a little brighter towards the ceiling.
                let g = 0.85 + 0.3 * ((p.y + lo.y) / (lo.y + hi.y)).clamp(0.0, 1.0);
                wall_albedo[wall] * ambient * g
            }
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn procedural_envmaps_are_deterministic_valid_and_varied() {
        for kind in [EnvKind::Sky, EnvKind::Room] {
            let a = procedural_envmap(kind, 5, 64, 32);
            assert_eq!(a, procedural_envmap(kind, 5, 64, 32));
            assert_ne!(a, procedural_envmap(kind, 6, 64, 32));
            assert!(a
                .data
                .iter()
                .all(|v| v.is_finite() && v.min_element() >= 0.0));
            // Something emits well above the diffuse surroundings.
            let lum: Vec<f32> = a.data.iter().map(|v| v.element_sum() / 3.0).collect();
            let max = lum.iter().copied().fold(0.0, f32::max);
            let mut sorted = lum.clone();
            sorted.sort_by(f32::total_cmp);
            let median = sorted[sorted.len() / 2];
            assert!(max > 4.0 * median, "{kind:?}: max {max}, median {median}");
        }
        assert_eq!(EnvKind::from_name("room"), Some(EnvKind::Room));
        assert_eq!(EnvKind::from_name("attic"), None);
    }

    #[test]
    fn a_room_has_lamps_above_and_a_floor_below() {
        for seed in 0..8 {
            let r = room(seed, 64, 32);
            // The brightest texel is a lamp or a window, never the floor.
            let (k, _) = r
                .data
                .iter()
                .enumerate()
                .max_by(|a, b| a.1.element_sum().total_cmp(&b.1.element_sum()))
                .unwrap();
            assert!(
                k / 64 < 20,
                "seed {seed}: brightest texel in row {}",
                k / 64
            );
            // Straight down is floor: dim.
            assert!(r.get(0, 31).max_element() < 1.0);
        }
    }
}
