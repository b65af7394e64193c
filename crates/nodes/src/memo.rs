//! What a process keeps between runs of its stages: the last few decoded
//! kept-path artifacts and built scene geometries, by the BLAKE3 digest of
//! the bytes they came from. An edit re-rendered from kept paths (the
//! studio's preview, then its result; a `--set` re-run) decodes the same
//! paths and builds the same BVH and light guide every time; kept here,
//! the second time costs a hash and a copy. Values are pure functions of
//! the bytes, so a hit gives exactly what a rebuild would (tested); the
//! memo is bounded ([`SLOTS`] entries of each kind) and holds nothing a
//! later run could not recompute.

use std::sync::{Arc, Mutex};

use matflow_engine::NodeError;
use matflow_render::RenderScene;
use matflow_scene::{MaterialMaps, RgbImage};

use crate::data::Kept;

/// Entries kept of each kind: a preview and a result of one edit use two
/// kept-path artifacts (a quick trace and the full one) and one geometry.
pub const SLOTS: usize = 2;

type Key = [u8; 32];

/// A bounded most-recently-used list of shared values.
struct Recent<T> {
    items: Mutex<Vec<(Key, Arc<T>)>>,
}

impl<T> Recent<T> {
    const fn new() -> Self {
        Recent {
            items: Mutex::new(Vec::new()),
        }
    }

    fn get_or(
        &self,
        key: Key,
        make: impl FnOnce() -> Result<T, NodeError>,
    ) -> Result<Arc<T>, NodeError> {
        {
            let mut items = self.items.lock().unwrap_or_else(|e| e.into_inner());
            if let Some(i) = items.iter().position(|(k, _)| *k == key) {
                let hit = items.remove(i);
                let v = hit.1.clone();
                items.insert(0, hit);
                return Ok(v);
            }
        }
        // Built outside the lock: another stage may build its own meanwhile.
        let v = Arc::new(make()?);
        let mut items = self.items.lock().unwrap_or_else(|e| e.into_inner());
        items.insert(0, (key, v.clone()));
        items.truncate(SLOTS);
        Ok(v)
    }
}

static KEPT: Recent<Kept> = Recent::new();
static GEOMETRY: Recent<RenderScene> = Recent::new();
static RENDERS: Recent<RgbImage> = Recent::new();

fn digest(parts: &[&[u8]]) -> Key {
    let mut h = blake3::Hasher::new();
    for p in parts {
        h.update(&(p.len() as u64).to_le_bytes());
        h.update_rayon(p);
    }
    *h.finalize().as_bytes()
}

/// [`Kept::decode`], shared: the same bytes decode once per process (while
/// they stay among the last [`SLOTS`]).
pub fn kept(bytes: &[u8]) -> Result<Arc<Kept>, NodeError> {
    KEPT.get_or(digest(&[b"kept", bytes]), || Kept::decode(bytes))
}

/// A render that is a pure function of `parts` (the input bytes and the
/// options it was made with, each given), made once per process while it
/// stays among the last [`SLOTS`]: the plain scene behind inserted
/// objects, which moving an object does not change.
pub fn render(
    parts: &[&[u8]],
    make: impl FnOnce() -> Result<RgbImage, NodeError>,
) -> Result<Arc<RgbImage>, NodeError> {
    let mut all: Vec<&[u8]> = vec![b"render"];
    all.extend_from_slice(parts);
    RENDERS.get_or(digest(&all), make)
}

/// The scene of a mesh artifact with `maps` under `env` (no objects):
/// its geometry — the mesh, BVH, normals and light guide, which depend on
/// the mesh alone — built once per mesh and copied; the materials and the
/// envmap set on the copy. Materials with transparency (whose screen
/// glass depends on them) are built whole.
pub fn scene(mesh: &[u8], maps: &MaterialMaps, env: &RgbImage) -> Result<RenderScene, NodeError> {
    if maps.transparency.is_some() {
        return crate::data::render_scene(mesh, maps, env);
    }
    let geometry = GEOMETRY.get_or(digest(&[b"geometry", mesh]), || {
        crate::data::render_scene(mesh, maps, env)
    })?;
    let (w, h) = (geometry.camera.width, geometry.camera.height);
    if maps.width() != w || maps.height() != h {
        return Err(crate::err(format!(
            "materials are {}x{} but the mesh's camera is {w}x{h}",
            maps.width(),
            maps.height()
        )));
    }
    let mut s = (*geometry).clone();
    s.materials = matflow_render::scene::materials_from_maps(maps);
    s.set_env(matflow_render::envmap::EnvMap::new(env).map_err(crate::err)?);
    Ok(s)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testutil::{opts, small_room};
    use matflow_render::render;

    /// A scene from the memo (its geometry made for other materials and
    /// another envmap, its hierarchy read from the mesh artifact) renders
    /// bit for bit as one built whole, and a second mesh does not get the
    /// first's geometry.
    #[test]
    fn a_remembered_geometry_renders_as_a_fresh_build() {
        let (s, cam, tri) = small_room(24);
        let mesh = crate::data::encode_mesh(cam.width, cam.height, &tri);
        let mut red = s.maps.clone();
        for a in &mut red.albedo.data {
            *a = glam::Vec3::new(0.8, 0.1, 0.1);
        }
        let dim = s.envmap.map(|v| v * 0.3);
        // Remembered with the true materials and sky ...
        scene(&mesh, &s.maps, &s.envmap).unwrap();
        // ... then asked for others.
        let got = render(&scene(&mesh, &red, &dim).unwrap(), &opts(), &|_, _| {}).image;
        assert!(crate::artifact::Artifact::decode(&mesh, "mesh")
            .unwrap()
            .has("bvh"));
        let fresh = matflow_render::RenderScene::new(
            cam,
            tri.clone(),
            &red,
            matflow_render::envmap::EnvMap::new(&dim).unwrap(),
        )
        .unwrap();
        let want = render(&fresh, &opts(), &|_, _| {}).image;
        assert!(
            got.data == want.data,
            "the memo's render differs from a fresh build"
        );
        // Another mesh (another room) is its own geometry.
        let (s2, cam2, tri2) = small_room(20);
        let mesh2 = crate::data::encode_mesh(cam2.width, cam2.height, &tri2);
        let other = scene(&mesh2, &s2.maps, &s2.envmap).unwrap();
        assert_eq!(other.mesh.triangle_count(), tri2.triangle_count());
        // Materials of the wrong size are refused, not mis-indexed.
        assert!(scene(&mesh2, &s.maps, &s.envmap).is_err());
    }

    #[test]
    fn kept_paths_from_the_memo_are_the_artifacts() {
        let (s, cam, tri) = small_room(16);
        let sc = matflow_render::RenderScene::new(
            cam,
            tri,
            &s.maps,
            matflow_render::envmap::EnvMap::new(&s.envmap).unwrap(),
        )
        .unwrap();
        let k = crate::testutil::trace_kept(&sc, &s.maps, &s.envmap, &[], None);
        let bytes = k.encode();
        for _ in 0..2 {
            assert!(kept(&bytes).unwrap().encode() == bytes);
        }
    }

    /// The most recent [`SLOTS`] values are made once; an older one is
    /// made again.
    #[test]
    fn the_memo_keeps_the_most_recent_and_makes_each_once() {
        let memo: Recent<u32> = Recent::new();
        let made = std::sync::atomic::AtomicU32::new(0);
        let get = |k: u8| {
            *memo
                .get_or([k; 32], || {
                    made.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                    Ok(k as u32)
                })
                .unwrap()
        };
        assert_eq!((get(1), get(2), get(1), get(2)), (1, 2, 1, 2));
        assert_eq!(made.load(std::sync::atomic::Ordering::Relaxed), 2);
        get(3); // 1 is the oldest now, and goes
        get(1);
        assert_eq!(made.load(std::sync::atomic::Ordering::Relaxed), 4);
        assert!(memo.get_or([9; 32], || Err(crate::err("no"))).is_err());
        assert_eq!(memo.items.lock().unwrap().len(), SLOTS);
    }
}
