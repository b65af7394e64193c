//! What the path tracer needs: camera, mesh + BVH, screen-space materials
//! and the environment map.

use glam::{Vec2, Vec3};
use matflow_geom::{mesh_for_view, vertex_normals, Bvh, DepthMesh, MeshStats, TriMesh};
use matflow_scene::{Camera, GrayImage, MaterialMaps};

use crate::bsdf::Material;
use crate::envmap::EnvMap;
use crate::fmath;
use crate::RenderError;

/// Per-pixel materials of the maps (row-major), sanitised.
pub fn materials_from_maps(maps: &MaterialMaps) -> Vec<Material> {
    (0..maps.albedo.data.len())
        .map(|k| {
            Material {
                albedo: maps.albedo.data[k],
                roughness: maps.roughness.data[k],
                metallic: maps.metallic.data[k],
            }
            .sanitized()
        })
        .collect()
}

/// The scene of a depth map (camera-space z, 0 for sky) seen by the
/// default camera of its size: the mesh cut at depth discontinuities
/// (`mesh_angle_deg`, the reference's angle test), its BVH, the
/// screen-space materials and the envmap. The one way the CLI and the
/// pipeline nodes turn a bundle's depth into something to render; the
/// mesh's statistics come back too.
pub fn scene_from_depth(
    depth: &GrayImage,
    maps: &MaterialMaps,
    env: EnvMap,
    mesh_angle_deg: f64,
) -> Result<(RenderScene, MeshStats), RenderError> {
    let (cam, DepthMesh { mesh, stats, .. }) = mesh_for_view(depth, mesh_angle_deg)?;
    Ok((RenderScene::new(cam, mesh, maps, env)?, stats))
}

pub struct RenderScene {
    pub camera: Camera,
    pub mesh: TriMesh,
    pub bvh: Bvh,
    pub face_normals: Vec<Vec3>,
    /// Angle-weighted vertex normals (used only by the reference-compatible
    /// sampling frame).
    pub vertex_normals: Vec<Vec3>,
    /// Screen-space materials, row-major, sanitised.
    pub materials: Vec<Material>,
    pub env: EnvMap,
    focal: f32,
    principal: Vec2,
}

impl RenderScene {
    pub fn new(
        camera: Camera,
        mesh: TriMesh,
        maps: &MaterialMaps,
        env: EnvMap,
    ) -> Result<RenderScene, RenderError> {
        if maps.width() != camera.width || maps.height() != camera.height {
            return Err(RenderError::MaterialSize {
                maps_width: maps.width(),
                maps_height: maps.height(),
                width: camera.width,
                height: camera.height,
            });
        }
        let bvh = Bvh::build(&mesh);
        let face_normals = (0..mesh.triangle_count())
            .map(|i| mesh.face_normal(i))
            .collect();
        let vertex_normals = vertex_normals(&mesh);
        let materials = materials_from_maps(maps);
        Ok(RenderScene {
            focal: camera.focal(),
            principal: camera.principal_point(),
            camera,
            mesh,
            bvh,
            face_normals,
            vertex_normals,
            materials,
            env,
        })
    }

    /// Index of the pixel a camera-space point projects into (nearest, as
    /// the reference looks materials up at every bounce); `None` for points
    /// at or behind the camera plane.
    #[inline]
    pub fn material_index(&self, p: Vec3) -> Option<usize> {
        // Camera::project_to_pixel with the focal length precomputed.
        let depth = -p.z;
        if !(depth > 1e-8) {
            return None;
        }
        let fx = self.focal * p.x / depth + self.principal.x + 0.5;
        let fy = -self.focal * p.y / depth + self.principal.y + 0.5;
        let w = self.camera.width;
        let h = self.camera.height;
        // NaN clamps to 0 through the saturating cast.
        let x = (fmath::floor(fx).clamp(0.0, w as f32 - 1.0)) as usize;
        let y = (fmath::floor(fy).clamp(0.0, h as f32 - 1.0)) as usize;
        Some(y * w + x)
    }

    /// Interpolated vertex normal at a hit.
    #[inline]
    pub fn shading_normal(&self, prim: u32, u: f32, v: f32) -> Vec3 {
        let t = self.mesh.indices[prim as usize];
        let n = self.vertex_normals[t[0] as usize] * (1.0 - u - v)
            + self.vertex_normals[t[1] as usize] * u
            + self.vertex_normals[t[2] as usize] * v;
        n.normalize_or(self.face_normals[prim as usize])
    }

    /// Film position of the camera ray through `film`.
    #[inline]
    pub fn camera_ray(&self, film: Vec2) -> Vec3 {
        Vec3::new(
            (film.x - 0.5 - self.principal.x) / self.focal,
            -(film.y - 0.5 - self.principal.y) / self.focal,
            -1.0,
        )
        .normalize()
    }
}
