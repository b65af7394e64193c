//! What the kept-path tests share: the render and kept paths of a small
//! scene as a `trace` stage keeps them, and the check that a re-edit from
//! them is bit-identical to a full render wherever it re-traced.

use std::collections::BTreeSet;

use matflow_geom::TriMesh;
use matflow_inverse::paths::{CacheOptions, PathCache};
use matflow_procgen::synthetic::SyntheticScene;
use matflow_render::{render, PixelFilter, RenderOptions, RenderScene, SceneObject};
use matflow_scene::{Camera, MaterialMaps, RgbImage};

use crate::data::Kept;

/// The procedural room at `n`², its camera and depth mesh.
pub(crate) fn small_room(n: usize) -> (SyntheticScene, Camera, TriMesh) {
    let s = matflow_procgen::synthetic::generate(3, n, n);
    let cam = Camera::new(n, n);
    let tri = matflow_geom::mesh_from_depth(&s.depth, &cam, &Default::default())
        .unwrap()
        .mesh;
    (s, cam, tri)
}

/// The base render's options (box filter, as `trace` renders).
pub(crate) fn opts() -> RenderOptions {
    RenderOptions {
        spp: 6,
        max_depth: 4,
        seed: 11,
        filter: PixelFilter::Box,
        ..Default::default()
    }
}

/// The render of `scene` (made with `maps`, `envmap` and `objects`) and 4
/// kept paths per pixel, passed through the `paths` artifact's bytes.
pub(crate) fn trace_kept(
    scene: &RenderScene,
    maps: &MaterialMaps,
    envmap: &RgbImage,
    objects: &[SceneObject],
    background: Option<RgbImage>,
) -> Kept {
    let o = opts();
    let cache = PathCache::build(
        scene,
        &CacheOptions {
            spp: 4,
            max_depth: o.max_depth,
            seed: 5,
            env_width: envmap.width,
            env_height: envmap.height,
            lamp_scale: 1.0,
        },
        &|_, _| {},
    )
    .unwrap();
    let kept = Kept {
        reach: cache.reach(),
        spp: o.spp,
        max_depth: o.max_depth,
        seed: o.seed,
        materials: maps.clone(),
        envmap: envmap.clone(),
        image: render(scene, &o, &|_, _| {}).image,
        coverage: (!objects.is_empty()).then(|| scene.object_coverage(4)),
        objects: objects.to_vec(),
        background,
    };
    let back = Kept::decode(&kept.encode()).unwrap();
    assert_eq!(back.reach, kept.reach, "the reach lists round-trip");
    assert_eq!(
        (back.spp, back.max_depth, back.seed),
        (o.spp, o.max_depth, o.seed)
    );
    back
}

/// Checks `got` (a re-edit from `kept`'s paths for the texels `changed`)
/// against `full` (a full render of the edited scene): equal bit for bit
/// on every pixel the kept paths say the change reaches, the base render
/// elsewhere. Returns how many pixels were re-traced and how many kept
/// ones a full render would have changed (what the kept paths missed).
pub(crate) fn check_retrace(
    kept: &Kept,
    changed: &[bool],
    got: &RgbImage,
    full: &RgbImage,
) -> (usize, usize) {
    let hit: BTreeSet<u32> = kept.reach.pixels_reaching(changed).into_iter().collect();
    let mut missed = 0;
    for p in 0..got.data.len() {
        if hit.contains(&(p as u32)) {
            assert_eq!(got.data[p], full.data[p], "re-traced pixel {p}");
        } else {
            assert_eq!(got.data[p], kept.image.data[p], "kept pixel {p}");
            missed += (full.data[p] != kept.image.data[p]) as usize;
        }
    }
    (hit.len(), missed)
}

/// A node's parameters: its defaults, normalised as the loader does, with
/// `extra` on top.
pub(crate) fn params_of(
    info: &matflow_engine::NodeInfo,
    extra: &[(&str, matflow_engine::Value)],
) -> matflow_engine::node::Params {
    use matflow_engine::Value;
    let mut m = std::collections::BTreeMap::new();
    for p in info.params {
        let v = match p.default {
            Some(d) => matflow_engine::value::parse_override(d).unwrap(),
            None => Value::Null,
        };
        let v = p.ty.normalize(&v).unwrap_or(v);
        m.insert(p.name.to_string(), v);
    }
    for (k, v) in extra {
        m.insert(k.to_string(), v.clone());
    }
    matflow_engine::node::Params(m)
}

/// `node` run on `inputs` with parameters `params` and `seed`, its
/// progress, metrics and images unobserved, never cancelled.
pub(crate) fn run_node(
    node: &dyn matflow_engine::Node,
    params: &matflow_engine::node::Params,
    inputs: std::collections::BTreeMap<String, matflow_engine::node::Bytes>,
    seed: u64,
) -> Result<std::collections::BTreeMap<String, Vec<u8>>, matflow_engine::NodeError> {
    node.run(&matflow_engine::RunContext {
        stage: "test",
        params,
        inputs,
        seed,
        progress: &|_, _| {},
        metric: &|_, _| {},
        cancelled: &matflow_engine::node::never_cancelled,
        image: None,
    })
}
