//! The artifacts kinds exchange (scene, image, materials, envmap, mesh,
//! kept paths) and the helpers that read them into numeric types.

use std::path::Path;

use glam::{Vec2, Vec3};
use matflow_engine::{NodeError, ParamSpec, ParamType};
use matflow_geom::{mesh_for_view, TriMesh};
use matflow_inverse::paths::{PathCache, PathWords};
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
    a.encode()
}

pub fn decode_mesh(b: &[u8]) -> Result<(Camera, TriMesh), NodeError> {
    let a = Artifact::decode(b, "mesh")?;
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
    Ok((
        Camera::new(cam[0] as usize, cam[1] as usize),
        TriMesh {
            positions,
            indices,
            film,
        },
    ))
}

/// A renderable scene from a mesh artifact, materials and an envmap.
pub fn render_scene(
    mesh: &[u8],
    maps: &MaterialMaps,
    env: &RgbImage,
) -> Result<RenderScene, NodeError> {
    let (cam, tri) = decode_mesh(mesh)?;
    if maps.width() != cam.width || maps.height() != cam.height {
        return Err(err(format!(
            "materials are {}x{} but the mesh's camera is {}x{}",
            maps.width(),
            maps.height(),
            cam.width,
            cam.height
        )));
    }
    RenderScene::new(cam, tri, maps, EnvMap::new(env).map_err(err)?).map_err(err)
}

pub(crate) fn mesh_of(depth: &GrayImage, angle: f64) -> Result<TriMesh, NodeError> {
    Ok(mesh_for_view(depth, angle)
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
    pub cache: PathCache,
    /// Samples per pixel and seed of the base render (box filter, the
    /// cache's max_depth).
    pub spp: u32,
    pub seed: u64,
    pub materials: MaterialMaps,
    pub envmap: RgbImage,
    pub image: RgbImage,
}

impl Kept {
    /// Options of the base render (re-used for re-traced pixels).
    pub fn render_options(&self) -> RenderOptions {
        RenderOptions {
            spp: self.spp,
            max_depth: self.cache.max_depth,
            seed: self.seed,
            filter: PixelFilter::Box,
            ..Default::default()
        }
    }

    pub fn encode(&self) -> Vec<u8> {
        let w = self.cache.to_words();
        let mut meta = w.meta.to_vec();
        meta.extend([self.spp, self.seed as u32, (self.seed >> 32) as u32]);
        let mut a = Artifact::new("paths");
        a.put_u32("meta", 9, 1, meta);
        let n = |v: &[u32], k: usize| (v.len() / k) as u32;
        let (vs, rs) = (w.vert_start.into_owned(), w.rec_start.into_owned());
        let (counts, verts) = (w.row_counts.into_owned(), w.vertices.into_owned());
        let recs = w.records.into_owned();
        a.put_u32("vert_start", n(&vs, 1), 1, vs);
        a.put_u32("rec_start", n(&rs, 1), 1, rs);
        a.put_u32("row_counts", n(&counts, 2), 2, counts);
        a.put_u32("vertices", n(&verts, 2), 2, verts);
        a.put_u32("records", n(&recs, 5), 5, recs);
        a.put_materials("base_", &self.materials);
        a.put_rgb("envmap", &self.envmap);
        a.put_rgb("image", &self.image);
        a.encode()
    }

    pub fn decode(b: &[u8]) -> Result<Kept, NodeError> {
        let a = Artifact::decode(b, "paths")?;
        let meta = a.u32_list("meta", 1)?;
        let [w, h, spp, depth, ew, eh, base_spp, seed_lo, seed_hi] = meta[..] else {
            return Err(err("paths artifact: the meta section is not 9 words"));
        };
        let cache = PathCache::from_words(&PathWords {
            meta: [w, h, spp, depth, ew, eh],
            vert_start: a.u32_list("vert_start", 1)?.into(),
            rec_start: a.u32_list("rec_start", 1)?.into(),
            row_counts: a.u32_list("row_counts", 2)?.into(),
            vertices: a.u32_list("vertices", 2)?.into(),
            records: a.u32_list("records", 5)?.into(),
        })
        .map_err(failed)?;
        Ok(Kept {
            cache,
            spp: base_spp,
            seed: seed_lo as u64 | (seed_hi as u64) << 32,
            materials: a.materials("base_")?,
            envmap: a.rgb("envmap")?,
            image: a.rgb("image")?,
        })
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
