//! Small scenes for the crate's tests.

use glam::Vec3;
use matflow_geom::{mesh_from_depth, MeshParams};
use matflow_procgen::synthetic;
use matflow_render::{EnvMap, RenderScene};
use matflow_scene::{Camera, MaterialMaps, RgbImage};

pub struct TestScene {
    pub scene: RenderScene,
    pub maps: MaterialMaps,
    pub env: RgbImage,
}

/// A procedural room corner (floor, walls, objects) at `n`×`n`.
pub fn room(seed: u64, n: usize) -> TestScene {
    room_with(seed, n, None)
}

/// [`room`] completed past the frame and closed, its assumed walls and
/// ceiling letting a share `open` of light through.
pub fn partly_open_room(seed: u64, n: usize, open: f32) -> TestScene {
    room_with(seed, n, Some(open))
}

fn room_with(seed: u64, n: usize, closed_open: Option<f32>) -> TestScene {
    let s = synthetic::generate(seed, n, n);
    let cam = Camera::new(n, n);
    let mut mesh = mesh_from_depth(&s.depth, &cam, &MeshParams::default())
        .expect("mesh")
        .mesh;
    if let Some(open) = closed_open {
        let p = matflow_geom::CompleteParams {
            assumed_openness: open,
            ..matflow_geom::CompleteParams::for_mode("room").expect("room")
        };
        matflow_geom::complete_beyond_frame(&mut mesh, &s.depth, &cam, &p);
    }
    let scene =
        RenderScene::new(cam, mesh, &s.maps, EnvMap::new(&s.envmap).expect("env")).expect("scene");
    TestScene {
        scene,
        maps: s.maps,
        env: s.envmap,
    }
}

pub use matflow_render::scene::materials_from_maps as materials_of;

/// A deterministic pseudo-random value in [0, 1) from an index.
pub fn hash01(i: u64) -> f32 {
    (matflow_render::rng::mix64(i) >> 40) as f32 / (1u64 << 24) as f32
}

pub fn texels(img: &RgbImage) -> Vec<Vec3> {
    img.data.clone()
}

/// A path cache of `scene` with default options and `spp` paths per pixel.
pub fn cache_of(scene: &RenderScene, spp: u32) -> crate::paths::PathCache {
    crate::paths::PathCache::build(
        scene,
        &crate::paths::CacheOptions {
            spp,
            ..Default::default()
        },
        &|_, _| {},
    )
    .expect("cache")
}

/// A known-answer material problem: the tables of room `seed` at `n`×`n`
/// (8 paths per pixel, true envmap), the true materials, and as target
/// the tables' own image for them (so the true materials fit exactly).
pub struct TableProblem {
    pub tables: Vec<crate::tables::PixelTable>,
    pub truth: Vec<matflow_render::Material>,
    pub image: Vec<Vec3>,
    pub target: crate::loss::Target,
}

pub fn table_problem(seed: u64, n: usize) -> TableProblem {
    let t = room(seed, n);
    let cache = cache_of(&t.scene, 8);
    let truth = materials_of(&t.maps);
    let tables = crate::tables::build_tables(&cache, &truth, &texels(&t.env));
    let image: Vec<Vec3> = tables
        .iter()
        .zip(&truth)
        .map(|(t, m)| t.eval(m).i)
        .collect();
    let target = crate::loss::Target::new(cache.width, cache.height, &image);
    TableProblem {
        tables,
        truth,
        image,
        target,
    }
}
