//! The renderer's lanes: every vector width, and every thread count,
//! gives the same image, bit for bit. The only test of this binary, as it
//! forces the process-wide width.

use glam::Vec3;
use matflow_geom::{mesh_from_depth, MeshParams};
use matflow_procgen::shapes::sphere;
use matflow_render::envmap::uv_to_dir;
use matflow_render::integrator::render_pixels;
use matflow_render::lanes;
use matflow_render::{
    render, Dielectric, EnvMap, Material, PixelFilter, RenderOptions, RenderScene, SceneObject,
    Surface,
};
use matflow_scene::{Camera, GrayImage, Image, MaterialMaps, RgbImage};

/// A room corner (floor and two walls at varying depth) with a material
/// per pixel spanning roughness, metallic and albedo, a rough principled
/// sphere and a glass ball, under a sky with a sun.
fn scene() -> RenderScene {
    let n = 40;
    let cam = Camera::new(n, n);
    let depth = GrayImage::from_fn(n, n, |x, y| {
        let (u, v) = (x as f32 / n as f32, y as f32 / n as f32);
        let wall = 3.0 - 1.5 * (u - 0.5).abs();
        let floor = 0.6 / (v - 0.45).max(0.05);
        wall.min(floor)
    });
    let mesh = mesh_from_depth(&depth, &cam, &MeshParams::default())
        .unwrap()
        .mesh;
    let hash = |x: usize, y: usize, k: u32| {
        let mut h = (x as u32).wrapping_mul(0x9e37_79b9) ^ (y as u32).wrapping_mul(0x85eb_ca6b) ^ k;
        h ^= h >> 15;
        h = h.wrapping_mul(0x2c1b_3c6d);
        h ^= h >> 12;
        (h & 0xffff) as f32 / 65535.0
    };
    let mut maps = MaterialMaps::uniform(n, n, Vec3::splat(0.5), 0.5, 0.0);
    maps.albedo = Image::from_fn(n, n, |x, y| {
        Vec3::new(hash(x, y, 1), hash(x, y, 2), hash(x, y, 3))
    });
    maps.roughness = Image::from_fn(n, n, |x, y| hash(x, y, 4));
    maps.metallic = Image::from_fn(n, n, |x, y| if hash(x, y, 5) > 0.7 { 1.0 } else { 0.0 });
    let sky: RgbImage = Image::from_fn(64, 32, |x, y| {
        let d = uv_to_dir((x as f32 + 0.5) / 64.0, y as f32 / 31.0);
        let sun = if d.dot(Vec3::new(0.4, 0.8, 0.3).normalize()) > 0.97 {
            Vec3::splat(40.0)
        } else {
            Vec3::ZERO
        };
        Vec3::new(0.3, 0.5, 0.9) * d.y.max(0.05) + sun
    });
    let env = EnvMap::new(&sky).unwrap();
    let ball = |c: Vec3, r: f32, surface: Surface| {
        let mut s = sphere(r, 12, 24);
        for p in &mut s.mesh.positions {
            *p += c;
        }
        SceneObject {
            mesh: s.mesh,
            normals: s.normals,
            surface,
            uvs: Vec::new(),
            texture: None,
        }
    };
    let objects = [
        ball(
            Vec3::new(-0.35, -0.25, -2.2),
            0.25,
            Surface::Principled(Material {
                albedo: Vec3::new(0.8, 0.3, 0.2),
                roughness: 0.3,
                metallic: 0.5,
            }),
        ),
        ball(
            Vec3::new(0.35, -0.2, -2.0),
            0.2,
            Surface::Glass(Dielectric {
                eta: 1.5,
                roughness: 0.2,
                ..Default::default()
            }),
        ),
    ];
    RenderScene::with_objects(cam, mesh, &maps, env, &objects).unwrap()
}

fn bits(img: &RgbImage) -> Vec<u32> {
    img.data
        .iter()
        .flat_map(|v| [v.x.to_bits(), v.y.to_bits(), v.z.to_bits()])
        .collect()
}

#[test]
fn every_lane_width_and_thread_count_renders_the_same_bits() {
    let scene = scene();
    let opts = RenderOptions {
        spp: 12,
        max_depth: 4,
        seed: 7,
        ..Default::default()
    };
    let pixels: Vec<u32> = (0..40 * 40).step_by(7).collect();
    let run = |w: usize, threads: usize| {
        lanes::force_width(Some(w)).unwrap();
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        let (img, px) = pool.install(|| {
            let img = render(&scene, &opts, &|_, _| {}).image;
            let box_opts = RenderOptions {
                filter: PixelFilter::Box,
                ..opts
            };
            (img, render_pixels(&scene, &box_opts, &pixels))
        });
        lanes::force_width(None).unwrap();
        (bits(&img), px, img)
    };
    let (want, want_px, img) = run(1, 1);
    // A picture, not a blank: light on walls, floor and objects.
    let lit = img.data.iter().filter(|v| v.max_element() > 0.01).count();
    assert!(lit > img.data.len() * 9 / 10, "{lit} lit pixels");
    assert!(img.data.iter().all(|v| v.is_finite()));
    for (w, threads) in [(4, 2), (8, 1), (8, 2), (16, 2)] {
        let (got, got_px, _) = run(w, threads);
        assert!(
            got == want,
            "width {w}, {threads} thread(s): the image differs"
        );
        assert!(
            got_px
                .iter()
                .zip(&want_px)
                .all(|(a, b)| a.to_array().map(f32::to_bits) == b.to_array().map(f32::to_bits)),
            "width {w}, {threads} thread(s): render_pixels differs"
        );
    }
    assert!(lanes::force_width(Some(3)).is_err());
}
