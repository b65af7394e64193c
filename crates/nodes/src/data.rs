//! The artifacts kinds exchange (scene, image, materials, envmap, mesh,
//! kept paths) and the helpers that read them into numeric types.

use std::path::Path;

use glam::{Vec2, Vec3};
use matflow_engine::{NodeError, ParamSpec, ParamType};
use matflow_geom::{mesh_for_view, MeshParams, Portal, TriMesh};
use matflow_inverse::paths::Reach;
use matflow_render::{EnvMap, PixelFilter, RenderOptions, RenderScene};
use matflow_scene::{io, Camera, GrayImage, MaterialMaps, RgbImage};

use crate::artifact::Artifact;
use crate::{err, failed};

pub(crate) const SCENE: ParamSpec = ParamSpec {
    name: "scene",
    ty: ParamType::Ref(&["scene"]),
    default: None,
    unit: "",
    doc: "the scene (input image, starting materials)",
};
pub(crate) const MESH: ParamSpec = ParamSpec {
    name: "mesh",
    ty: ParamType::Ref(&["mesh"]),
    default: None,
    unit: "",
    doc: "geometry and camera",
};

/// Which engine runs a stage's ONNX model (`refraction_length`, `matnet`).
pub(crate) const BACKEND: ParamSpec = ParamSpec {
    name: "backend",
    ty: ParamType::Choice(matflow_onnx::Backend::NAMES),
    default: Some("tract"),
    unit: "",
    doc: "tract (built in) or onnxruntime (ORT_DYLIB_PATH or the onnxruntime wheel)",
};

/// The backend a stage asked for (the parameter is checked on load).
pub(crate) fn backend_of(p: &matflow_engine::node::Params) -> matflow_onnx::Backend {
    matflow_onnx::Backend::from_name(p.str("backend")).unwrap_or(matflow_onnx::Backend::Tract)
}

/// Adds output file `name` of a kind whose outputs are files, encoded by
/// `encode` (given the name, for its errors).
pub(crate) fn put_file(
    out: &mut std::collections::BTreeMap<String, Vec<u8>>,
    name: &str,
    encode: impl FnOnce(&Path) -> Result<Vec<u8>, matflow_scene::SceneError>,
) -> Result<(), NodeError> {
    out.insert(name.to_string(), encode(Path::new(name)).map_err(failed)?);
    Ok(())
}

/// What a `scene` artifact holds.
pub struct SceneData {
    /// Camera-space depth z (0: sky).
    pub depth: GrayImage,
    /// The linear input image, when there is one.
    pub target: Option<RgbImage>,
    /// Predicted (starting) materials.
    pub pred: MaterialMaps,
}

impl SceneData {
    pub fn encode(&self) -> Vec<u8> {
        let mut a = Artifact::new("scene");
        a.put_gray("depth", &self.depth);
        if let Some(t) = &self.target {
            a.put_rgb("target", t);
        }
        a.put_materials("pred_", &self.pred);
        a.encode()
    }
    pub fn decode(b: &[u8]) -> Result<SceneData, NodeError> {
        let a = Artifact::decode(b, "scene")?;
        Ok(SceneData {
            depth: a.gray("depth")?,
            target: if a.has("target") {
                Some(a.rgb("target")?)
            } else {
                None
            },
            pred: a.materials("pred_")?,
        })
    }
}

pub fn encode_image(ty: &str, name: &str, img: &RgbImage) -> Vec<u8> {
    let mut a = Artifact::new(ty);
    a.put_rgb(name, img);
    a.encode()
}

pub fn encode_materials(m: &MaterialMaps) -> Vec<u8> {
    let mut a = Artifact::new("materials");
    a.put_materials("", m);
    a.encode()
}

/// Materials from a reference that may name a `materials` or a `scene`
/// artifact (then its predictions).
pub fn materials_from(b: &[u8]) -> Result<MaterialMaps, NodeError> {
    match Artifact::decode(b, "materials") {
        Ok(a) => a.materials(""),
        Err(_) => Ok(SceneData::decode(b)?.pred),
    }
}

pub fn envmap_from(b: &[u8]) -> Result<RgbImage, NodeError> {
    Artifact::decode(b, "envmap")?.rgb("envmap")
}

pub fn encode_mesh(width: usize, height: usize, m: &TriMesh) -> Vec<u8> {
    let mut a = Artifact::new("mesh");
    a.put_u32("camera", 2, 1, vec![width as u32, height as u32]);
    a.put_f32(
        "positions",
        m.positions.len() as u32,
        3,
        m.positions.iter().flat_map(|p| [p.x, p.y, p.z]).collect(),
    );
    a.put_u32(
        "indices",
        m.indices.len() as u32,
        3,
        m.indices.iter().flatten().copied().collect(),
    );
    a.put_f32(
        "film",
        m.film.len() as u32,
        2,
        m.film.iter().flat_map(|p| [p.x, p.y]).collect(),
    );
    // Only meshes completed past the frame name material pixels (so a
    // plain depth mesh encodes as it always did).
    if !m.material_pixel.is_empty() {
        a.put_u32(
            "material_pixel",
            m.material_pixel.len() as u32,
            1,
            m.material_pixel.clone(),
        );
    }
    // Likewise only rooms closed with partly open assumed surfaces.
    if !m.openness.is_empty() {
        a.put_f32("openness", m.openness.len() as u32, 1, m.openness.clone());
    }
    // The mesh's ray-tracing hierarchy, so that the stages (and re-runs)
    // reading it do not build it again.
    if let Some(w) = matflow_geom::Bvh::build(m).to_words() {
        a.put_u32("bvh", 2, 1, vec![w.root, w.triangle_count]);
        a.put_u32("bvh_nodes", w.nodes.len() as u32, 1, w.nodes.into_owned());
        a.put_u32("bvh_prims", w.prims.len() as u32, 1, w.prims.into_owned());
    }
    // And only closed rooms with windows have portals.
    if !m.portals.is_empty() {
        a.put_f32(
            "portals",
            m.portals.len() as u32,
            9,
            m.portals
                .iter()
                .flat_map(|p| [p.corner, p.u, p.v])
                .flat_map(|v| v.to_array())
                .collect(),
        );
    }
    // And only meshes shaded with given (e.g. predicted) normals.
    if !m.normals.is_empty() {
        a.put_f32(
            "normals",
            m.normals.len() as u32,
            3,
            m.normals.iter().flat_map(|v| v.to_array()).collect(),
        );
    }
    a.encode()
}

pub fn decode_mesh(b: &[u8]) -> Result<(Camera, TriMesh), NodeError> {
    mesh_of_artifact(&Artifact::decode(b, "mesh")?)
}

/// The hierarchy stored with `mesh` (`None` in
/// a mesh artifact written before hierarchies were stored).
fn stored_bvh(a: &Artifact, mesh: &TriMesh) -> Result<Option<matflow_geom::Bvh>, NodeError> {
    if !a.has("bvh") {
        return Ok(None);
    }
    let [root, triangle_count] = a.u32_list("bvh", 1)?[..] else {
        return Err(err("mesh artifact: the bvh section is not 2 words"));
    };
    let words = matflow_geom::BvhWords {
        root,
        triangle_count,
        nodes: a.u32_list("bvh_nodes", 1)?.into(),
        prims: a.u32_list("bvh_prims", 1)?.into(),
    };
    matflow_geom::Bvh::from_words(&words, mesh)
        .map(Some)
        .map_err(|e| err(format!("mesh artifact: {e}")))
}

fn mesh_of_artifact(a: &Artifact) -> Result<(Camera, TriMesh), NodeError> {
    let cam = a.u32_list("camera", 1)?;
    if cam.len() != 2 {
        return Err(err("mesh artifact: bad camera"));
    }
    let positions: Vec<Vec3> = a
        .f32_list("positions", 3)?
        .chunks_exact(3)
        .map(|c| Vec3::new(c[0], c[1], c[2]))
        .collect();
    let indices: Vec<[u32; 3]> = a
        .u32_list("indices", 3)?
        .chunks_exact(3)
        .map(|c| [c[0], c[1], c[2]])
        .collect();
    if indices
        .iter()
        .flatten()
        .any(|&i| i as usize >= positions.len())
    {
        return Err(err("mesh artifact: index out of range"));
    }
    let film = a
        .f32_list("film", 2)?
        .chunks_exact(2)
        .map(|c| Vec2::new(c[0], c[1]))
        .collect();
    let material_pixel = per_triangle(a, "material_pixel", indices.len(), |a, n| a.u32_list(n, 1))?;
    let openness = per_triangle(a, "openness", indices.len(), |a, n| a.f32_list(n, 1))?;
    if openness.iter().any(|o| !(0.0..=1.0).contains(o)) {
        return Err(err("mesh artifact: openness outside [0, 1]"));
    }
    let portals: Vec<Portal> = if a.has("portals") {
        a.f32_list("portals", 9)?
            .chunks_exact(9)
            .map(|c| Portal {
                corner: Vec3::new(c[0], c[1], c[2]),
                u: Vec3::new(c[3], c[4], c[5]),
                v: Vec3::new(c[6], c[7], c[8]),
            })
            .collect()
    } else {
        Vec::new()
    };
    if let Some(k) = portals.iter().position(|p| !p.is_valid()) {
        return Err(err(format!(
            "mesh artifact: portal {k} is not a rectangle (two perpendicular edges of positive length)"
        )));
    }
    let normals: Vec<Vec3> = if a.has("normals") {
        a.f32_list("normals", 3)?
            .chunks_exact(3)
            .map(|c| Vec3::new(c[0], c[1], c[2]))
            .collect()
    } else {
        Vec::new()
    };
    if normals.len() > positions.len() || normals.iter().any(|n| !n.is_finite()) {
        return Err(err(
            "mesh artifact: more shading normals than vertices, or one not finite",
        ));
    }
    Ok((
        Camera::new(cam[0] as usize, cam[1] as usize),
        TriMesh {
            positions,
            indices,
            film,
            material_pixel,
            openness,
            portals,
            normals,
        },
    ))
}

/// A mesh artifact's optional per-triangle list `name` (empty when absent),
/// refused unless it has one entry per triangle.
fn per_triangle<'a, T: Copy + 'a>(
    a: &'a Artifact,
    name: &str,
    triangles: usize,
    list: impl Fn(&'a Artifact, &str) -> Result<&'a [T], NodeError>,
) -> Result<Vec<T>, NodeError> {
    if !a.has(name) {
        return Ok(Vec::new());
    }
    let v = list(a, name)?;
    if !v.is_empty() && v.len() != triangles {
        return Err(err(format!(
            "mesh artifact: {name} is not one per triangle"
        )));
    }
    Ok(v.to_vec())
}

/// A renderable scene from a mesh artifact, materials and an envmap.
pub fn render_scene(
    mesh: &[u8],
    maps: &MaterialMaps,
    env: &RgbImage,
) -> Result<RenderScene, NodeError> {
    let a = Artifact::decode(mesh, "mesh")?;
    let (cam, tri) = mesh_of_artifact(&a)?;
    match stored_bvh(&a, &tri)? {
        Some(bvh) => {
            check_material_size(&cam, maps)?;
            RenderScene::with_bvh(cam, tri, maps, EnvMap::new(env).map_err(err)?, bvh)
                .map_err(failed)
        }
        None => scene_of(cam, tri, maps, env, &[]),
    }
}

fn check_material_size(cam: &Camera, maps: &MaterialMaps) -> Result<(), NodeError> {
    if maps.width() != cam.width || maps.height() != cam.height {
        return Err(err(format!(
            "materials are {}x{} but the mesh's camera is {}x{}",
            maps.width(),
            maps.height(),
            cam.width,
            cam.height
        )));
    }
    Ok(())
}

/// A renderable scene from a decoded mesh, materials, an envmap and
/// inserted objects; the materials must be the camera's size.
pub fn scene_of(
    cam: Camera,
    tri: TriMesh,
    maps: &MaterialMaps,
    env: &RgbImage,
    objects: &[matflow_render::SceneObject],
) -> Result<RenderScene, NodeError> {
    check_material_size(&cam, maps)?;
    RenderScene::with_objects(cam, tri, maps, EnvMap::new(env).map_err(err)?, objects)
        .map_err(failed)
}

pub(crate) fn mesh_of(depth: &GrayImage, params: &MeshParams) -> Result<TriMesh, NodeError> {
    Ok(mesh_for_view(depth, params)
        .map_err(|e| err(format!("meshing the depth map: {e}")))?
        .1
        .mesh)
}

/// Reads a photo (PNG/JPEG: centre-cropped, resized, linearised with
/// power 2.2), or a linear EXR / Radiance HDR as is; rejects NaN/Inf.
pub fn read_image(path: &Path, size: usize) -> Result<RgbImage, NodeError> {
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_lowercase())
        .unwrap_or_default();
    let img = match ext.as_str() {
        "exr" => io::read_exr_rgb(path).map_err(err)?,
        "hdr" => io::read_hdr(path).map_err(err)?,
        "png" | "jpg" | "jpeg" => {
            let raw = io::read_ldr_raw(path).map_err(err)?;
            let s = if size == 0 {
                raw.width.min(raw.height)
            } else {
                size
            };
            io::load_photo(path, s).map_err(err)?
        }
        _ => {
            return Err(err(format!(
                "{}: unknown image type (use .png, .jpg, .exr or .hdr)",
                path.display()
            )))
        }
    };
    io::ensure_finite_rgb(path, &img).map_err(err)?;
    if img.width == 0 || img.height == 0 {
        return Err(err(format!("{}: the image is empty", path.display())));
    }
    Ok(img)
}

/// What a `paths` artifact holds: a `trace` stage's kept paths and the
/// base render they belong to.
pub struct Kept {
    /// Which materials each pixel's kept paths meet.
    pub reach: Reach,
    /// Samples per pixel, depth and seed of the base render (box filter).
    pub spp: u32,
    pub max_depth: u32,
    pub seed: u64,
    pub materials: MaterialMaps,
    pub envmap: RgbImage,
    pub image: RgbImage,
    /// Objects in the traced scene (placed, with their surfaces).
    pub objects: Vec<matflow_render::SceneObject>,
    /// With objects: the same render without them (same sample streams),
    /// for differential compositing.
    pub background: Option<RgbImage>,
    /// With objects: their pixel coverage (it depends on geometry only, so
    /// material re-edits reuse it).
    pub coverage: Option<Vec<f32>>,
}

impl Kept {
    /// Options of the base render (re-used for re-traced pixels).
    pub fn render_options(&self) -> RenderOptions {
        RenderOptions {
            spp: self.spp,
            max_depth: self.max_depth,
            seed: self.seed,
            filter: PixelFilter::Box,
            ..Default::default()
        }
    }

    /// The `paths` artifact: the base render, its materials and envmap,
    /// and per pixel the materials its kept paths meet, stored as counts
    /// and sorted texel indices delta-coded (the first against the pixel
    /// itself), byte-plane shuffled and deflated in fixed chunks (in
    /// parallel; the bytes do not depend on the thread count).
    pub fn encode(&self) -> Vec<u8> {
        let (w, h) = (self.reach.width, self.reach.height);
        let meta = vec![
            w as u32,
            h as u32,
            self.max_depth,
            self.spp,
            self.seed as u32,
            (self.seed >> 32) as u32,
        ];
        let mut a = Artifact::new("paths");
        a.put_u32("meta", 6, 1, meta);
        let (offsets, texels) = self.reach.parts();
        let counts: Vec<u32> = offsets.windows(2).map(|p| p[1] - p[0]).collect();
        let mut deltas = Vec::with_capacity(texels.len());
        for (p, o) in offsets.windows(2).enumerate() {
            let mut prev = p as u32;
            for &q in &texels[o[0] as usize..o[1] as usize] {
                deltas.push(q.wrapping_sub(prev));
                prev = q;
            }
        }
        a.put_bytes("z_reach_counts", pack::deflate_words(&counts));
        a.put_bytes("z_reach_texels", pack::deflate_words(&deltas));
        a.put_materials("base_", &self.materials);
        a.put_rgb("envmap", &self.envmap);
        a.put_rgb("image", &self.image);
        if !self.objects.is_empty() {
            crate::objects::put_objects(&mut a, "obj_", &self.objects);
        }
        if let Some(bg) = &self.background {
            a.put_rgb("background", bg);
        }
        if let Some(c) = &self.coverage {
            a.put_f32("coverage", c.len() as u32, 1, c.clone());
        }
        a.encode()
    }

    pub fn decode(b: &[u8]) -> Result<Kept, NodeError> {
        let a = Artifact::decode(b, "paths")?;
        let meta = a.u32_list("meta", 1)?;
        let [w, h, max_depth, spp, seed_lo, seed_hi] = meta[..] else {
            return Err(err("paths artifact: the meta section is not 6 words"));
        };
        let (w, h) = (w as usize, h as usize);
        let npix = w
            .checked_mul(h)
            .filter(|&n| n < u32::MAX as usize)
            .ok_or_else(|| err("paths artifact: the image is too large"))?;
        let counts = pack::inflate_words(a.bytes("z_reach_counts")?, npix, "reach counts")?;
        let mut offsets = Vec::with_capacity(npix + 1);
        let mut total = 0u32;
        offsets.push(0);
        for &c in &counts {
            total = total
                .checked_add(c)
                .ok_or_else(|| err("paths artifact: reach counts overflow"))?;
            offsets.push(total);
        }
        let mut texels =
            pack::inflate_words(a.bytes("z_reach_texels")?, total as usize, "reach texels")?;
        for (p, o) in offsets.windows(2).enumerate() {
            let mut prev = p as u32;
            for q in &mut texels[o[0] as usize..o[1] as usize] {
                prev = prev.wrapping_add(*q);
                *q = prev;
            }
        }
        let reach = Reach::from_parts(w, h, offsets, texels).map_err(failed)?;
        Ok(Kept {
            reach,
            spp,
            max_depth,
            seed: seed_lo as u64 | (seed_hi as u64) << 32,
            materials: a.materials("base_")?,
            envmap: a.rgb("envmap")?,
            image: a.rgb("image")?,
            objects: crate::objects::get_objects(&a, "obj_")?,
            background: if a.has("background") {
                Some(a.rgb("background")?)
            } else {
                None
            },
            coverage: if a.has("coverage") {
                let c = a.f32_list("coverage", 1)?;
                if c.len() != w * h {
                    return Err(err("paths artifact: coverage does not match the image"));
                }
                Some(c.to_vec())
            } else {
                None
            },
        })
    }
}

/// Compact storage of word arrays: byte-plane shuffled, deflated in chunks.
mod pack {
    use super::{err, NodeError};
    use rayon::prelude::*;

    /// Words per deflated chunk (4 MiB): fixed, so the bytes do not
    /// depend on how many threads compress them.
    const CHUNK: usize = 1 << 20;
    /// Deflate level: the fastest of miniz's (ratio within 2 % of 6 here).
    const LEVEL: u8 = 1;

    /// Byte planes of little-endian words (every word's byte 0, then
    /// byte 1, …): neighbouring words' high bytes repeat, which deflate
    /// finds.
    fn shuffle(words: &[u32]) -> Vec<u8> {
        let mut out = vec![0u8; 4 * words.len()];
        let n = words.len();
        for (i, w) in words.iter().enumerate() {
            for (b, x) in w.to_le_bytes().into_iter().enumerate() {
                out[b * n + i] = x;
            }
        }
        out
    }

    fn unshuffle(bytes: &[u8]) -> Vec<u32> {
        let n = bytes.len() / 4;
        (0..n)
            .map(|i| {
                u32::from_le_bytes([bytes[i], bytes[n + i], bytes[2 * n + i], bytes[3 * n + i]])
            })
            .collect()
    }

    /// Layout: word count (u64), then per chunk of [`CHUNK`] words its
    /// deflated length (u64) and bytes.
    pub fn deflate_words(words: &[u32]) -> Vec<u8> {
        let parts: Vec<Vec<u8>> = words
            .par_chunks(CHUNK)
            .map(|c| miniz_oxide::deflate::compress_to_vec(&shuffle(c), LEVEL))
            .collect();
        let mut out = Vec::with_capacity(8 + parts.iter().map(|p| p.len() + 8).sum::<usize>());
        out.extend_from_slice(&(words.len() as u64).to_le_bytes());
        for p in parts {
            out.extend_from_slice(&(p.len() as u64).to_le_bytes());
            out.extend_from_slice(&p);
        }
        out
    }

    /// The words of [`deflate_words`]; their number must be `expect`
    /// (known from the artifact's counts), so a damaged or forged blob
    /// cannot inflate to more.
    pub fn inflate_words(bytes: &[u8], expect: usize, what: &str) -> Result<Vec<u32>, NodeError> {
        let bad = |m: &str| err(format!("paths artifact: packed {what}: {m}"));
        let take = |at: usize, n: usize| bytes.get(at..at.checked_add(n)?);
        let count = take(0, 8).ok_or_else(|| bad("truncated"))?;
        let count = u64::from_le_bytes(count.try_into().unwrap());
        if count != expect as u64 {
            return Err(bad(&format!("{count} words where the counts say {expect}")));
        }
        let mut chunks = Vec::new();
        let mut at = 8usize;
        let mut left = expect;
        while left > 0 {
            let len = take(at, 8).ok_or_else(|| bad("truncated"))?;
            let len = usize::try_from(u64::from_le_bytes(len.try_into().unwrap()))
                .map_err(|_| bad("chunk too long"))?;
            let z = take(at + 8, len).ok_or_else(|| bad("truncated chunk"))?;
            let words = left.min(CHUNK);
            chunks.push((z, words));
            at += 8 + len;
            left -= words;
        }
        if at != bytes.len() {
            return Err(bad("trailing bytes"));
        }
        let parts: Vec<Result<Vec<u32>, NodeError>> = chunks
            .par_iter()
            .map(|&(z, words)| {
                let raw = miniz_oxide::inflate::decompress_to_vec_with_limit(z, 4 * words)
                    .map_err(|e| bad(&format!("{e:?}")))?;
                if raw.len() != 4 * words {
                    return Err(bad("a chunk inflates to the wrong length"));
                }
                Ok(unshuffle(&raw))
            })
            .collect();
        let mut out = Vec::with_capacity(expect);
        for p in parts {
            out.extend(p?);
        }
        Ok(out)
    }

    #[cfg(test)]
    mod tests {
        use super::*;

        #[test]
        fn words_round_trip_across_chunks_and_damage_is_an_error() {
            for n in [0, 1, 7, CHUNK, CHUNK + 3, 2 * CHUNK + 1] {
                let w: Vec<u32> = (0..n as u32)
                    .map(|i| i.wrapping_mul(2654435761) >> (i % 7))
                    .collect();
                let z = deflate_words(&w);
                assert_eq!(inflate_words(&z, n, "t").unwrap(), w);
                assert!(inflate_words(&z, n + 1, "t").is_err());
                if n > 0 {
                    assert!(inflate_words(&z[..z.len() - 1], n, "t").is_err());
                    let mut bad = z.clone();
                    let k = bad.len() / 2;
                    bad[k] ^= 0x55;
                    // A flipped byte is an error or other words, never a panic.
                    let _ = inflate_words(&bad, n, "t");
                }
            }
        }
    }
}

/// Estimated seconds to path-trace a `film`-sized image at `spp` samples
/// per pixel and `depth` segments on the reference 2-core machine: the
/// inverse planner's cost per ray, with rays per sample scaled from its
/// depth-4 count. An upper bound for re-renders that trace only part of
/// the image. Zero when the size is unknown.
pub fn render_seconds(film: Option<(usize, usize)>, spp: i64, depth: i64) -> f64 {
    use matflow_inverse::plan::cost;
    let Some((w, h)) = film else {
        return 0.0;
    };
    let rays = 1.0 + (cost::RAYS_PER_SAMPLE - 1.0) * (depth.max(1) - 1) as f64 / 3.0;
    cost::RENDER_PER_RAY * rays * (w * h) as f64 * spp.max(0) as f64
}

#[cfg(test)]
mod cost_tests {
    use super::render_seconds;
    use matflow_inverse::plan::cost;

    #[test]
    fn render_estimate_is_the_cost_model_per_ray() {
        // Depth 4: the planner's rays per sample.
        let s = render_seconds(Some((512, 512)), 64, 4);
        let want = cost::RENDER_PER_RAY * cost::RAYS_PER_SAMPLE * 512.0 * 512.0 * 64.0;
        assert!((s - want).abs() < 1e-9 * want, "{s} vs {want}");
        // Linear in pixels and samples; one segment is one ray.
        assert!((render_seconds(Some((1024, 512)), 128, 4) - 4.0 * s).abs() < 1e-9 * s);
        let one = render_seconds(Some((10, 10)), 1, 1);
        assert!((one - cost::RENDER_PER_RAY * 100.0).abs() < 1e-15);
        assert_eq!(render_seconds(None, 64, 4), 0.0);
        // The example is days, not minutes.
        assert!(render_seconds(Some((4096, 4096)), 65536, 4) > 86400.0);
    }
}

#[cfg(test)]
mod mesh_tests {
    use super::{decode_mesh, encode_mesh};
    use glam::Vec3;
    use matflow_geom::{Portal, TriMesh, PROJECTED};

    #[test]
    fn a_mesh_keeps_its_material_pixels_and_a_plain_one_encodes_as_before() {
        let mut m = TriMesh::default();
        m.add_box(Vec3::splat(-1.0), Vec3::ONE);
        let plain = encode_mesh(4, 3, &m);
        let (_, back) = decode_mesh(&plain).unwrap();
        assert_eq!(back, m);
        m.material_pixel = (0..m.triangle_count() as u32)
            .map(|k| if k % 2 == 0 { PROJECTED } else { k % 12 })
            .collect();
        let named = encode_mesh(4, 3, &m);
        assert_ne!(named, plain);
        let (cam, back) = decode_mesh(&named).unwrap();
        assert_eq!((cam.width, cam.height), (4, 3));
        assert_eq!(back, m);
        assert_eq!(back.material_pixel_of(1), Some(1));
        assert_eq!(back.material_pixel_of(0), None);
        // One entry per triangle, or the artifact is refused.
        m.material_pixel.pop();
        let e = decode_mesh(&encode_mesh(4, 3, &m)).unwrap_err().to_string();
        assert!(e.contains("material_pixel"), "{e}");
    }

    #[test]
    fn a_mesh_keeps_its_openness_which_must_be_a_share_per_triangle() {
        let mut m = TriMesh::default();
        m.add_box(Vec3::splat(-1.0), Vec3::ONE);
        let plain = encode_mesh(4, 3, &m);
        m.openness = (0..m.triangle_count()).map(|k| k as f32 / 12.0).collect();
        let open = encode_mesh(4, 3, &m);
        assert_ne!(open, plain);
        let (_, back) = decode_mesh(&open).unwrap();
        assert_eq!(back, m);
        assert_eq!(back.openness_of(6), 0.5);
        let mut bad = m.clone();
        bad.openness.pop();
        let e = decode_mesh(&encode_mesh(4, 3, &bad))
            .unwrap_err()
            .to_string();
        assert!(e.contains("openness is not one per triangle"), "{e}");
        for x in [-0.1, 1.5, f32::NAN] {
            let mut bad = m.clone();
            bad.openness[3] = x;
            let e = decode_mesh(&encode_mesh(4, 3, &bad))
                .unwrap_err()
                .to_string();
            assert!(e.contains("openness outside [0, 1]"), "{x}: {e}");
        }
    }

    #[test]
    fn a_mesh_keeps_its_portals_which_must_be_rectangles() {
        let mut m = TriMesh::default();
        m.add_box(Vec3::splat(-1.0), Vec3::ONE);
        let plain = encode_mesh(4, 3, &m);
        m.portals = vec![
            Portal {
                corner: Vec3::new(-0.5, 0.2, 1.0),
                u: Vec3::new(1.0, 0.0, 0.0),
                v: Vec3::new(0.0, 0.5, 0.0),
            },
            Portal {
                corner: Vec3::new(1.0, 0.0, 0.5),
                u: Vec3::new(0.0, 0.0, -1.0),
                v: Vec3::new(0.0, 0.7, 0.0),
            },
        ];
        let with = encode_mesh(4, 3, &m);
        assert_ne!(with, plain);
        let (_, back) = decode_mesh(&with).unwrap();
        assert_eq!(back, m);
        let mut skew = m.clone();
        skew.portals[1].v = Vec3::new(0.0, 0.7, 0.7);
        let e = decode_mesh(&encode_mesh(4, 3, &skew))
            .unwrap_err()
            .to_string();
        assert!(e.contains("portal 1 is not a rectangle"), "{e}");
    }
}
