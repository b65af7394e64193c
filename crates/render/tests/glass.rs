//! Known answers for glass and inserted objects in the path tracer.

use glam::Vec3;
use matflow_geom::{mesh_from_depth, MeshParams, TriMesh};
use matflow_procgen::shapes::{cuboid, sphere, Shape};
use matflow_render::envmap::uv_to_dir;
use matflow_render::integrator::render_pixels;
use matflow_render::{
    render, Dielectric, EnvMap, Material, PixelFilter, RenderOptions, RenderScene, SceneObject,
    Surface,
};
use matflow_scene::{Camera, GrayImage, Image, MaterialMaps, RgbImage};

/// An envmap of `w`×`h` texels valued `f(direction)` at texel centres.
fn envmap(w: usize, h: usize, f: impl Fn(Vec3) -> Vec3) -> EnvMap {
    let img: RgbImage = Image::from_fn(w, h, |x, y| {
        f(uv_to_dir(
            (x as f32 + 0.5) / w as f32,
            y as f32 / (h - 1) as f32,
        ))
    });
    EnvMap::new(&img).unwrap()
}

/// A scene of `n`×`n` pixels: a wall facing the camera at depth `wall`
/// (none for 0) with material `mat`, and the objects.
fn scene(n: usize, wall: f32, mat: Material, env: EnvMap, objects: &[SceneObject]) -> RenderScene {
    let cam = Camera::new(n, n);
    let mesh = if wall > 0.0 {
        mesh_from_depth(&GrayImage::new(n, n, wall), &cam, &MeshParams::default())
            .unwrap()
            .mesh
    } else {
        TriMesh::default()
    };
    let maps = MaterialMaps::uniform(n, n, mat.albedo, mat.roughness, mat.metallic);
    RenderScene::with_objects(cam, mesh, &maps, env, objects).unwrap()
}

fn object(s: Shape, surface: Surface) -> SceneObject {
    SceneObject {
        mesh: s.mesh,
        normals: s.normals,
        surface,
        uvs: Vec::new(),
        texture: None,
    }
}

fn white() -> Material {
    Material {
        albedo: Vec3::splat(0.8),
        roughness: 1.0,
        metallic: 0.0,
    }
}

fn opts(spp: u32, max_depth: u32) -> RenderOptions {
    RenderOptions {
        spp,
        max_depth,
        filter: PixelFilter::Box,
        ..Default::default()
    }
}

fn mean(v: &[Vec3]) -> Vec3 {
    let s: glam::DVec3 = v.iter().map(|x| x.as_dvec3()).sum();
    (s / v.len() as f64).as_vec3()
}

#[test]
fn a_smooth_slab_at_normal_incidence_transmits_t_one_minus_f_squared_with_interreflections() {
    // Bright only within 20° of −z, behind the slab; the camera's centre
    // pixel looks through the slab within 3° of its normal.
    let env = envmap(64, 32, |d| {
        if d.dot(-Vec3::Z) > 20f32.to_radians().cos() {
            Vec3::ONE
        } else {
            Vec3::ZERO
        }
    });
    for (t, tint, eta) in [
        (1.0, Vec3::ONE, 1.5),
        (0.5, Vec3::new(1.0, 0.5, 0.25), 1.5),
        (1.0, Vec3::ONE, 2.4),
    ] {
        let glass = Dielectric {
            eta,
            transmission: t,
            tint,
            roughness: 0.0,
        };
        let slab = cuboid(Vec3::new(-50.0, -50.0, -3.0), Vec3::new(50.0, 50.0, -2.0));
        let s = scene(
            9,
            0.0,
            white(),
            env.clone(),
            &[object(slab, Surface::Glass(glass))],
        );
        let got = render_pixels(&s, &opts(65536, 4), &[4 * 9 + 4])[0];
        let f = ((eta - 1.0) / (eta + 1.0)).powi(2);
        let p = (1.0 - f).powi(2) / (1.0 - f * f);
        for c in 0..3 {
            let want = t * tint[c] * p;
            // Each path carries T·tint or 0: binomial noise.
            let sd = t * tint[c] * (p * (1.0 - p) / 65536.0).sqrt();
            assert!(
                (got[c] - want).abs() < 5.0 * sd + 1e-4,
                "η={eta} T={t} channel {c}: {} vs {want} (sd {sd})",
                got[c]
            );
        }
    }
}

#[test]
fn a_lossless_glass_sphere_in_a_white_furnace_disappears() {
    let env = envmap(32, 16, |_| Vec3::splat(0.5));
    for roughness in [0.0, 0.3] {
        let ball = sphere(1.0, 48, 96).transformed(1.0, Vec3::new(0.0, 0.0, -4.0));
        let glass = Dielectric {
            roughness,
            ..Default::default()
        };
        let s = scene(
            16,
            0.0,
            white(),
            env.clone(),
            &[object(ball, Surface::Glass(glass))],
        );
        let img = render(&s, &opts(256, 4), &|_, _| {}).image;
        // Rough microfacet glass loses energy to the single-scattering
        // model (light that would scatter between microfacets), most at
        // grazing angles near the silhouette; it never gains any.
        let (tol, mean_tol) = if roughness == 0.0 {
            (0.04, 0.005)
        } else {
            (0.2, 0.05)
        };
        for (i, v) in img.data.iter().enumerate() {
            for c in 0..3 {
                assert!(
                    v[c] < 0.5 * 1.04 && v[c] > 0.5 * (1.0 - tol),
                    "roughness {roughness} pixel {i}: {v}"
                );
            }
        }
        let m = mean(&img.data);
        assert!(
            (m.x - 0.5).abs() < mean_tol * 0.5,
            "roughness {roughness}: mean {m}"
        );
    }
}

#[test]
fn index_matched_clear_glass_changes_nothing_but_noise() {
    // A wall lit by a sky with a broad sun, with a smooth η = 1 ball in
    // front of it, casting its "shadow" on the wall and covering part of
    // the view: light then reaches the wall only by BSDF sampling through
    // the ball, which is unbiased, so only the noise changes.
    let env = envmap(64, 32, |d| {
        let sun = Vec3::new(0.4, 0.5, 1.0).normalize();
        Vec3::new(0.3, 0.4, 0.6) + Vec3::splat(if d.dot(sun) > 0.9 { 8.0 } else { 0.0 })
    });
    let ball = || sphere(0.6, 32, 64).transformed(1.0, Vec3::new(0.2, 0.1, -3.5));
    let glass = Dielectric {
        eta: 1.0,
        ..Default::default()
    };
    let n = 12;
    let pixels: Vec<u32> = (0..(n * n) as u32).collect();
    let plain = scene(n, 5.0, white(), env.clone(), &[]);
    let with = scene(
        n,
        5.0,
        white(),
        env,
        &[object(ball(), Surface::Glass(glass))],
    );
    let a = render_pixels(&plain, &opts(1024, 4), &pixels);
    let b = render_pixels(&with, &opts(1024, 4), &pixels);
    let b2 = render_pixels(
        &with,
        &RenderOptions {
            seed: 1,
            ..opts(1024, 4)
        },
        &pixels,
    );
    // The seed-to-seed spread of the noisier render bounds the noise.
    let spread: f32 = b
        .iter()
        .zip(&b2)
        .map(|(x, y)| (*x - *y).abs().x)
        .sum::<f32>()
        / b.len() as f32;
    let diff: f32 = a.iter().zip(&b).map(|(x, y)| (*x - *y).x).sum::<f32>() / a.len() as f32;
    let level = mean(&a).x;
    assert!(
        diff.abs() < 0.01 * level,
        "mean moved {diff} (level {level})"
    );
    for (i, (x, y)) in a.iter().zip(&b).enumerate() {
        assert!(
            (*x - *y).abs().max_element() < 4.0 * spread + 0.02 * level,
            "pixel {i}: {x} vs {y} (spread {spread})"
        );
    }
}

#[test]
fn an_opaque_sphere_shadows_the_wall_exactly_where_the_analytic_shadow_falls() {
    // A small bright light region of the sky behind the camera, a wall
    // facing the camera at z = −5 and a sphere between them. Direct light
    // only (max_depth 2), so the wall is lit by the light unless the
    // sphere is in the way.
    let n = 48;
    let light = Vec3::new(0.5, 0.5, 1.0).normalize();
    let cone = 2f32.to_radians();
    let env = envmap(256, 128, |d| {
        Vec3::splat(0.02)
            + Vec3::splat(if d.dot(light) > cone.cos() {
                200.0
            } else {
                0.0
            })
    });
    let (c, r) = (Vec3::new(0.3, 0.2, -3.5), 0.4);
    let ball = sphere(r, 48, 96).transformed(1.0, c);
    let grey = Surface::Diffuse(Vec3::splat(0.5));
    let plain = scene(n, 5.0, white(), env.clone(), &[]);
    let with = scene(n, 5.0, white(), env, &[object(ball, grey)]);
    let pixels: Vec<u32> = (0..(n * n) as u32).collect();
    let a = render_pixels(&plain, &opts(256, 2), &pixels);
    let b = render_pixels(&with, &opts(256, 2), &pixels);
    // The light's support: its cone plus the bilinear blend (1.4° texels)
    // and a pixel's footprint on the wall (0.066 units, ~2° from the sphere).
    let margin = cone + 2.0f32.to_radians() + 2.5f32.to_radians();
    let (mut umbra, mut lit) = (0, 0);
    for y in 0..n {
        for x in 0..n {
            let ray = with.camera_ray(glam::Vec2::new(x as f32 + 0.5, y as f32 + 0.5));
            // Pixels that see the sphere itself (with a margin) are not wall.
            let tc = c.dot(ray);
            if (c - ray * tc).length() < r + 0.1 {
                continue;
            }
            let p = ray * (5.0 / -ray.z);
            let to_c = c - p;
            let half = (r / to_c.length()).asin();
            let angle = to_c.normalize().dot(light).clamp(-1.0, 1.0).acos();
            let k = y * n + x;
            if angle < half - margin {
                umbra += 1;
                assert!(
                    b[k].x < 0.15 * a[k].x,
                    "umbra pixel ({x}, {y}): {} vs unshadowed {}",
                    b[k].x,
                    a[k].x
                );
            } else if angle > half + margin {
                lit += 1;
                assert!(
                    (b[k].x - a[k].x).abs() < 0.05 * a[k].x,
                    "lit pixel ({x}, {y}): {} vs unshadowed {}",
                    b[k].x,
                    a[k].x
                );
            }
        }
    }
    assert!(umbra > 20 && lit > 1000, "umbra {umbra}, lit {lit}");
}

/// Maps of `n`×`n` whose centre square `lo..hi` is a transparent region
/// (index-matched, clear, no thickness) over a background of colour `bg`.
fn transparent_centre(n: usize, lo: usize, hi: usize, bg: Vec3) -> MaterialMaps {
    use matflow_scene::transparency::Transparency;
    let mut maps = MaterialMaps::uniform(n, n, Vec3::new(0.7, 0.3, 0.3), 0.6, 0.0);
    let mut t = Transparency::none(&maps.albedo, &maps.roughness, &maps.metallic);
    for y in lo..hi {
        for x in lo..hi {
            let k = y * n + x;
            t.ior.data[k] = 1.0;
            t.transmission.data[k] = 1.0;
            t.bg_albedo.data[k] = bg;
            t.bg_roughness.data[k] = 1.0;
            t.bg_metallic.data[k] = 0.0;
        }
    }
    maps.transparency = Some(t);
    maps
}

#[test]
fn a_clear_index_matched_region_without_thickness_shows_its_background_in_place() {
    // d1 = d2 = 0 and η = 1: the background albedo A_BG shows at the same
    // pixel, i.e. the image equals the photo with the region's material
    // replaced by the background's.
    let n = 16;
    let bg = Vec3::new(0.1, 0.7, 0.2);
    let env = envmap(64, 32, |d| {
        let sun = Vec3::new(0.4, 0.5, 1.0).normalize();
        Vec3::new(0.3, 0.4, 0.6) + Vec3::splat(if d.dot(sun) > 0.95 { 10.0 } else { 0.0 })
    });
    let cam = Camera::new(n, n);
    let mesh = mesh_from_depth(&GrayImage::new(n, n, 5.0), &cam, &MeshParams::default())
        .unwrap()
        .mesh;
    let glassy = transparent_centre(n, 4, 12, bg);
    let mut painted = MaterialMaps::uniform(n, n, Vec3::new(0.7, 0.3, 0.3), 0.6, 0.0);
    for y in 4..12 {
        for x in 4..12 {
            painted.albedo.set(x, y, bg);
            painted.roughness.set(x, y, 1.0);
        }
    }
    let a = RenderScene::new(cam, mesh.clone(), &glassy, env.clone()).unwrap();
    let b = RenderScene::new(cam, mesh, &painted, env).unwrap();
    let pixels: Vec<u32> = (0..(n * n) as u32).collect();
    let ra = render_pixels(&a, &opts(2048, 4), &pixels);
    let rb = render_pixels(&b, &opts(2048, 4), &pixels);
    let rb2 = render_pixels(
        &b,
        &RenderOptions {
            seed: 3,
            ..opts(2048, 4)
        },
        &pixels,
    );
    let spread: f32 = rb
        .iter()
        .zip(&rb2)
        .map(|(x, y)| (*x - *y).abs().max_element())
        .sum::<f32>()
        / rb.len() as f32;
    for y in 4..12 {
        for x in 4..12 {
            let k = y * n + x;
            // The region shows green (the background), not the photo's red.
            assert!(ra[k].y > ra[k].x, "pixel ({x},{y}): {}", ra[k]);
            assert!(
                (ra[k] - rb[k]).abs().max_element() < 5.0 * spread + 0.01 * rb[k].max_element(),
                "pixel ({x},{y}): {} vs {} (spread {spread})",
                ra[k],
                rb[k]
            );
        }
    }
}

#[test]
fn an_opaque_glass_region_only_reflects() {
    // T = 0: nothing comes through; what is left is the Fresnel
    // reflection of the sky (a few per cent at normal incidence).
    let n = 12;
    let env = envmap(32, 16, |_| Vec3::ONE);
    let cam = Camera::new(n, n);
    let mesh = mesh_from_depth(&GrayImage::new(n, n, 5.0), &cam, &MeshParams::default())
        .unwrap()
        .mesh;
    let mut maps = transparent_centre(n, 0, n, Vec3::ONE);
    let t = maps.transparency.as_mut().unwrap();
    t.ior.data.iter_mut().for_each(|v| *v = 1.5);
    t.transmission.data.iter_mut().for_each(|v| *v = 0.0);
    let s = RenderScene::new(cam, mesh, &maps, env).unwrap();
    let img = render(&s, &opts(256, 4), &|_, _| {}).image;
    // Inside the outermost ring of pixels (half of which sees the sky
    // past the mesh's edge).
    let inner: Vec<Vec3> = (1..n - 1)
        .flat_map(|y| (1..n - 1).map(move |x| (x, y)))
        .map(|(x, y)| img.get(x, y))
        .collect();
    let m = mean(&inner);
    // F at 0–15° off normal for η 1.5 is 0.040–0.041; the sky is 1.
    assert!((m.x - 0.04).abs() < 0.003, "{m}");
}
