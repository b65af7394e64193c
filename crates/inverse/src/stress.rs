//! The stress suite: extreme materials, geometry, images and lighting must
//! leave no NaN or Inf in losses, gradients or outputs, and the recovery
//! must finish (or stop with a clear error).

use glam::Vec3;
use matflow_geom::{mesh_from_depth, MeshParams};
use matflow_procgen::synthetic;
use matflow_render::{EnvMap, Material, RenderOptions, RenderScene};
use matflow_scene::{Camera, GrayImage, Image, MaterialMaps, RgbImage};

use crate::invert::{invert, InvertOptions, InvertResult};
use crate::routes::{env_route, mat_route};
use crate::testutil::{cache_of, hash01, materials_of};

const N: usize = 20;

struct Case {
    scene: RenderScene,
    depth: GrayImage,
    maps: MaterialMaps,
    env: RgbImage,
}

fn build(depth: &GrayImage, maps: &MaterialMaps, env: &RgbImage) -> RenderScene {
    let cam = Camera::new(N, N);
    let mesh = mesh_from_depth(depth, &cam, &MeshParams::default())
        .expect("mesh")
        .mesh;
    RenderScene::new(cam, mesh, maps, EnvMap::new(env).expect("env")).expect("scene")
}

fn case_from(depth: &GrayImage, maps: MaterialMaps, env: RgbImage) -> Case {
    Case {
        scene: build(depth, &maps, &env),
        depth: depth.clone(),
        maps,
        env,
    }
}

fn room(seed: u64) -> (GrayImage, MaterialMaps, RgbImage) {
    let s = synthetic::generate(seed, N, N);
    (s.depth, s.maps, s.envmap)
}

fn with_maps(f: impl Fn(&mut MaterialMaps)) -> Case {
    let (d, mut m, e) = room(4);
    f(&mut m);
    case_from(&d, m, e)
}

fn target_of(c: &Case) -> RgbImage {
    matflow_render::render(
        &c.scene,
        &RenderOptions {
            spp: 8,
            ..Default::default()
        },
        &|_, _| {},
    )
    .image
}

fn opts(env: &str, mat: &str) -> InvertOptions {
    InvertOptions {
        budget_seconds: 1.0,
        env_route: env_route(env, &[]).expect("env route"),
        mat_route: mat_route(mat, &[]).expect("mat route"),
        trust_rm: true,
        spp: Some(4),
        final_spp: Some(2),
        loops: Some(1),
        env_steps: Some(25),
        mat_steps: Some(25),
        ..Default::default()
    }
}

fn finite3(v: Vec3) -> bool {
    v.is_finite()
}

/// Every number that leaves the recovery is finite and in range.
fn check(name: &str, r: &InvertResult) {
    for st in &r.report.stages {
        // Tracing and rendering stages have no loss (NaN by convention).
        if st.name.starts_with("envmap") || st.name.starts_with("materials") {
            for l in [st.loss_start, st.loss_end] {
                assert!(l.is_finite(), "{name}: stage {} loss {l}", st.name);
            }
        }
    }
    assert!(r.report.fit_loss.is_finite(), "{name}: fit loss");
    for m in &r.materials {
        assert!(
            finite3(m.albedo)
                && m.albedo.min_element() >= 0.0
                && m.albedo.max_element() <= 1.0
                && (0.0..=1.0).contains(&m.roughness)
                && (0.0..=1.0).contains(&m.metallic),
            "{name}: material {m:?}"
        );
    }
    assert!(
        r.envmap
            .data
            .iter()
            .all(|v| finite3(*v) && v.min_element() >= 0.0),
        "{name}: envmap"
    );
    assert!(
        r.rendered.data.iter().all(|v| finite3(*v)),
        "{name}: render"
    );
    assert!(r.fit_image.data.iter().all(|v| finite3(*v)), "{name}: fit");
}

fn run_all_routes(name: &str, c: &Case, target: &RgbImage) {
    let pred = materials_of(&c.maps);
    for (e, m) in [("texel", "solve"), ("texel", "pixel"), ("mlp", "mlp")] {
        let r = invert(
            build(&c.depth, &c.maps, &c.env),
            target,
            &pred,
            &opts(e, m),
            &|_| {},
        )
        .unwrap_or_else(|err| panic!("{name} ({e}, {m}): {err}"));
        check(&format!("{name} ({e:?}, {m:?})"), &r);
    }
}

/// What production differentiates stays finite: the envmap transport
/// (values and its transpose, the envmap gradient) and the per-pixel
/// tables the material routes fit (values and derivatives in A, R, M).
fn check_gradients(name: &str, c: &Case, mats: &[Material], env: &[Vec3]) {
    let cache = cache_of(&c.scene, 2);
    let img = crate::transport::render(&cache, mats, env);
    assert!(img.iter().all(|v| finite3(*v)), "{name}: frozen render");
    let pixels = crate::envfit::strided_pixels(cache.width, cache.height, 1);
    let tr = crate::envfit::EnvTransport::build(&cache, mats, pixels);
    assert!(
        tr.apply(env).iter().all(|v| finite3(*v)),
        "{name}: envmap transport"
    );
    let adj: Vec<Vec3> = (0..img.len())
        .map(|p| Vec3::splat(hash01(p as u64) - 0.5))
        .collect();
    assert!(
        tr.apply_t(&adj).iter().all(|v| finite3(*v)),
        "{name}: envmap gradient"
    );
    let (tables, var, _) = crate::tables::build_tables_with_variance(&cache, mats, env);
    assert!(var.iter().all(|v| v.is_finite()), "{name}: table variance");
    for (t, m) in tables.iter().zip(mats) {
        let e = t.eval(m);
        assert!(
            finite3(e.i) && finite3(e.da) && finite3(e.dr) && finite3(e.dm),
            "{name}: material gradients"
        );
    }
}

#[test]
fn extreme_materials() {
    type Edit = Box<dyn Fn(&mut MaterialMaps)>;
    let cases: Vec<(&str, Edit)> = vec![
        (
            "roughness pinned at 0.07",
            Box::new(|m: &mut MaterialMaps| m.roughness.data.fill(0.07)),
        ),
        (
            "metallic 0",
            Box::new(|m: &mut MaterialMaps| m.metallic.data.fill(0.0)),
        ),
        (
            "metallic 1",
            Box::new(|m: &mut MaterialMaps| m.metallic.data.fill(1.0)),
        ),
        (
            "albedo 0",
            Box::new(|m: &mut MaterialMaps| m.albedo.data.fill(Vec3::ZERO)),
        ),
        (
            "albedo 1",
            Box::new(|m: &mut MaterialMaps| m.albedo.data.fill(Vec3::ONE)),
        ),
    ];
    for (name, edit) in cases {
        let c = with_maps(edit);
        let target = target_of(&c);
        run_all_routes(name, &c, &target);
        check_gradients(name, &c, &materials_of(&c.maps), &c.env.data);
    }
}

#[test]
fn extreme_geometry() {
    let (_, maps, env) = room(6);
    // A floor seen at grazing incidence: depth grows steeply towards the
    // top of the image, so normals are nearly perpendicular to the rays.
    let grazing = Image::from_fn(N, N, |_, y| {
        let t = (N - y) as f32 / N as f32;
        1.0 + 200.0 * t.powi(4)
    });
    // Depth discontinuities: a checkerboard of near and far blocks.
    let steps = Image::from_fn(
        N,
        N,
        |x, y| {
            if (x / 5 + y / 5) % 2 == 0 {
                1.0
            } else {
                30.0
            }
        },
    );
    for (name, depth) in [
        ("grazing normals", grazing),
        ("depth discontinuities", steps),
    ] {
        // Normals from the depth (the synthetic ones belong to the room).
        let m = MaterialMaps {
            normal: None,
            ..maps.clone()
        };
        let c = case_from(&depth, m, env.clone());
        let target = target_of(&c);
        run_all_routes(name, &c, &target);
        check_gradients(name, &c, &materials_of(&c.maps), &c.env.data);
    }
}

#[test]
fn extreme_images_and_lighting() {
    let (d, m, e) = room(8);
    let c = case_from(&d, m, e);
    let base = target_of(&c);
    let scaled = |k: f32| base.map(|v| v * k);
    // Saturated: a block far above 1 (clipped highlights in a photo).
    let mut saturated = base.clone();
    for y in 0..N / 2 {
        for x in 0..N / 2 {
            saturated.set(x, y, Vec3::splat(50.0));
        }
    }
    for (name, target) in [
        ("saturated pixels", saturated),
        ("near-black image", scaled(1e-7)),
        ("very bright image", scaled(1e5)),
        ("black image", scaled(0.0)),
    ] {
        run_all_routes(name, &c, &target);
    }
    // Envmaps near zero and huge: gradients and renders stay finite.
    let mats = materials_of(&c.maps);
    for (name, k) in [("envmap near zero", 1e-7f32), ("envmap huge", 1e6)] {
        let env: Vec<Vec3> = c.env.data.iter().map(|v| *v * k).collect();
        check_gradients(name, &c, &mats, &env);
    }
}
