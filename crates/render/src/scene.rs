//! What the path tracer needs: camera, mesh + BVH, screen-space materials
//! and the environment map.

use glam::{Vec2, Vec3};
use matflow_geom::{
    complete_beyond_frame, mesh_for_view, vertex_normals, Bvh, CompleteParams, Completion,
    DepthMesh, MeshParams, MeshStats, Portal, TriMesh,
};
use matflow_scene::{Camera, GrayImage, MaterialMaps};

use crate::bsdf::Material;
use crate::dielectric::Dielectric;
use crate::envmap::EnvMap;
use crate::fmath::{self, ONE_BELOW};
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
/// (`mesh_params`: the angle test and the silhouettes), its BVH, the
/// screen-space materials and the envmap. The one way the CLI and the
/// pipeline nodes turn a bundle's depth into something to render; the
/// mesh's statistics come back too. With `complete`, the geometry is
/// completed past the frame ([`matflow_geom::complete_beyond_frame`]: the
/// room's planes extended and, if asked, the room closed), the added
/// triangles taking the materials of the pixels they continue; what the
/// completion did comes back too (the default without one).
pub fn scene_from_depth(
    depth: &GrayImage,
    maps: &MaterialMaps,
    env: EnvMap,
    mesh_params: MeshParams,
    complete: Option<&CompleteParams>,
) -> Result<(RenderScene, MeshStats, Completion), RenderError> {
    scene_from_depth_guided(depth, maps, env, mesh_params, complete, true)
}

/// As [`scene_from_depth`], the light guide built or not
/// ([`RenderScene::new_guided`]).
pub fn scene_from_depth_guided(
    depth: &GrayImage,
    maps: &MaterialMaps,
    env: EnvMap,
    mesh_params: MeshParams,
    complete: Option<&CompleteParams>,
    guided: bool,
) -> Result<(RenderScene, MeshStats, Completion), RenderError> {
    let (
        cam,
        DepthMesh {
            mut mesh, stats, ..
        },
    ) = mesh_for_view(depth, &mesh_params)?;
    let completion = complete
        .map(|p| complete_beyond_frame(&mut mesh, depth, &cam, p))
        .unwrap_or_default();
    Ok((
        RenderScene::new_guided(cam, mesh, maps, env, guided)?,
        stats,
        completion,
    ))
}

/// The material of an inserted object's surface. Unlike the screen-space
/// materials of the depth mesh, opaque object surfaces are two-sided (the
/// normal is turned towards the viewer), since meshes from files are not
/// always closed or consistently wound; glass uses the outward normal to
/// tell inside from outside.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Surface {
    /// matflow's BRDF (the paper's eqs. 5–11), as the depth mesh uses.
    Principled(Material),
    /// Lambertian: albedo/π.
    Diffuse(Vec3),
    /// A dielectric interface ([`crate::dielectric`]).
    Glass(Dielectric),
}

impl Surface {
    /// Clamps parameters into their valid ranges.
    pub fn sanitized(self) -> Surface {
        match self {
            Surface::Principled(m) => Surface::Principled(m.sanitized()),
            Surface::Diffuse(a) => {
                let fin = |x: f32| {
                    if x.is_finite() {
                        x.clamp(0.0, 1.0)
                    } else {
                        0.0
                    }
                };
                Surface::Diffuse(Vec3::new(fin(a.x), fin(a.y), fin(a.z)))
            }
            Surface::Glass(g) => Surface::Glass(g.sanitized()),
        }
    }

    #[inline]
    pub fn is_glass(&self) -> bool {
        matches!(self, Surface::Glass(_))
    }
}

/// An object placed in the scene: a triangle mesh in camera space, its
/// per-vertex shading normals (empty: smooth normals computed from the
/// mesh), its surface and, optionally, a colour texture (linear RGB)
/// with per-vertex texture coordinates that multiplies the albedo of a
/// diffuse or principled surface.
#[derive(Clone, Debug)]
pub struct SceneObject {
    pub mesh: TriMesh,
    pub normals: Vec<Vec3>,
    pub surface: Surface,
    pub uvs: Vec<Vec2>,
    pub texture: Option<std::sync::Arc<matflow_scene::RgbImage>>,
}

/// A texture lookup: bilinear, wrapping, v = 0 at the bottom row (OBJ).
pub fn texture_at(t: &matflow_scene::RgbImage, uv: Vec2) -> Vec3 {
    let (w, h) = (t.width, t.height);
    if w == 0 || h == 0 || !uv.is_finite() {
        return Vec3::ONE;
    }
    let x = (uv.x - uv.x.floor()) * w as f32 - 0.5;
    let y = (1.0 - (uv.y - uv.y.floor())) * h as f32 - 0.5;
    let (x0, y0) = (x.floor(), y.floor());
    let (fx, fy) = (x - x0, y - y0);
    let wrap = |i: f32, n: usize| (i as i64).rem_euclid(n as i64) as usize;
    let px = |i: f32, j: f32| t.data[wrap(j, h) * w + wrap(i, w)];
    let top = px(x0, y0) * (1.0 - fx) + px(x0 + 1.0, y0) * fx;
    let bottom = px(x0, y0 + 1.0) * (1.0 - fx) + px(x0 + 1.0, y0 + 1.0) * fx;
    let c = top * (1.0 - fy) + bottom * fy;
    if c.is_finite() {
        c.clamp(Vec3::ZERO, Vec3::ONE)
    } else {
        Vec3::ONE
    }
}

impl Surface {
    /// The surface with its albedo multiplied by `tex` (glass unchanged).
    #[inline]
    pub fn textured(self, tex: Vec3) -> Surface {
        match self {
            Surface::Diffuse(a) => Surface::Diffuse(a * tex),
            Surface::Principled(m) => Surface::Principled(Material {
                albedo: m.albedo * tex,
                ..m
            }),
            g => g,
        }
    }
}

/// One pixel of a transparent region: its glass interface and refraction
/// distances (scene units; see `matflow_scene::transparency`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GlassPixel {
    pub interface: Dielectric,
    pub d1: f32,
    pub d2: f32,
}

/// Transparent regions of the depth mesh (the paper's single-view
/// transparency) and what shows through them.
#[derive(Clone)]
pub struct ScreenGlass {
    /// Per pixel, its glass inside a region.
    pub glass: Vec<Option<GlassPixel>>,
    /// Per pixel, the background's material (inpainted inside the regions,
    /// the ordinary one elsewhere), sanitised.
    pub background: Vec<Material>,
    /// Per pixel, the depth mesh's surface seen through the pixel's centre:
    /// point and triangle ([`NO_SURFACE`]: sky).
    pub surface: Vec<(Vec3, u32)>,
}

/// What share of each ray's light arrives through `bvh`'s triangles when
/// triangle `k` lets `openness[k]` through ([`TriMesh::openness`]):
/// partly open surfaces bound the scene, so the nearest hit decides (1 for
/// a miss, the hit triangle's openness otherwise). `hits` is scratch.
pub(crate) fn transmittance_stream(
    bvh: &Bvh,
    openness: &[f32],
    rays: &[(Vec3, Vec3)],
    hits: &mut Vec<Option<matflow_geom::Hit>>,
    out: &mut Vec<f32>,
) {
    hits.clear();
    hits.resize(rays.len(), None);
    bvh.intersect_stream(rays, 0.0, f32::INFINITY, hits);
    out.clear();
    out.extend(hits.iter().map(|h| {
        h.map_or(1.0, |h| {
            openness.get(h.prim as usize).copied().unwrap_or(0.0)
        })
    }));
}

/// [`ScreenGlass::surface`] of a pixel that sees the sky.
pub const NO_SURFACE: u32 = u32::MAX;

pub use matflow_scene::lamps::{Lamp, LampAt};

/// Where a scene's ray-tracing hierarchy comes from.
enum Hierarchy<'a> {
    /// Built over the whole mesh.
    Build,
    /// This one (built over the mesh without its objects), the objects'
    /// triangles added.
    Over(&'a Bvh),
    /// Given: built over this mesh before and stored.
    Given(Bvh),
}

#[derive(Clone)]
pub struct RenderScene {
    pub camera: Camera,
    /// The depth mesh's triangles first, then each object's.
    pub mesh: TriMesh,
    /// Shared between the copies of a scene (its materials or envmap
    /// changed, the geometry not).
    pub bvh: std::sync::Arc<Bvh>,
    pub face_normals: Vec<Vec3>,
    /// Angle-weighted vertex normals (on the depth mesh used only by the
    /// reference-compatible sampling frame; the shading normals of objects).
    pub vertex_normals: Vec<Vec3>,
    /// The depth mesh came with shading normals ([`TriMesh::normals`]):
    /// its surfaces shade with the interpolated vertex normals instead of
    /// the flat triangle normals.
    pub given_normals: bool,
    /// Screen-space materials, row-major, sanitised.
    pub materials: Vec<Material>,
    /// Triangles of the depth mesh (screen-space materials); triangle
    /// `screen_prims + k` belongs to object `prim_object[k]`.
    pub screen_prims: usize,
    pub prim_object: Vec<u32>,
    /// Surfaces of the objects, sanitised. A vertex on object `k` uses
    /// material index `width·height + k`.
    pub objects: Vec<Surface>,
    /// Per object, its texture, and the texture coordinates of every
    /// vertex from `object_vertices` on (objects without one: zeros).
    pub textures: Vec<Option<std::sync::Arc<matflow_scene::RgbImage>>>,
    pub uvs: Vec<Vec2>,
    pub object_vertices: usize,
    /// Transparent regions, when the materials have any. A vertex on the
    /// background seen through pixel `p` uses material index
    /// `width·height + objects + p`.
    pub screen_glass: Option<ScreenGlass>,
    /// The envmap lit by; guided by [`RenderScene::light_visibility`] when
    /// the scene has one (set it with [`RenderScene::set_env`] to keep the
    /// guide).
    pub env: EnvMap,
    /// What each region of the scene sees of the sky, measured once for
    /// the geometry ([`crate::guide`]); `None` samples light by radiance
    /// alone.
    pub light_visibility: Option<std::sync::Arc<crate::guide::Visibility>>,
    /// Lamps inside the scene and the sun ([`Lamp`]; none by default),
    /// set with [`RenderScene::set_lamps`].
    pub lamps: Vec<Lamp>,
    /// Length of a shadow ray towards a distant lamp: past everything in
    /// the scene (set with the lamps).
    pub(crate) lamp_far: f32,
    /// The openings light samples aim at besides the envmap's density
    /// ([`crate::portal`]): the mesh's [`TriMesh::portals`], or those of
    /// [`RenderScene::set_portals`].
    pub portals: crate::portal::Portals,
    /// Where a vertex sees a portal, the share of its light samples aimed
    /// at the portals (the rest follow the envmap's density):
    /// [`crate::portal::PORTAL_SHARE`] by default.
    pub portal_share: f32,
    focal: f32,
    principal: Vec2,
}

/// `portals` prepared for sampling, or the error naming the first bad one
/// or too many.
fn checked_portals(portals: &[Portal]) -> Result<crate::portal::Portals, RenderError> {
    if let Some(index) = portals.iter().position(|p| !p.is_valid()) {
        return Err(RenderError::Portal { index });
    }
    if portals.len() > crate::portal::MAX_PORTALS {
        return Err(RenderError::TooManyPortals {
            count: portals.len(),
            max: crate::portal::MAX_PORTALS,
        });
    }
    Ok(crate::portal::Portals::new(portals))
}

impl RenderScene {
    pub fn new(
        camera: Camera,
        mesh: TriMesh,
        maps: &MaterialMaps,
        env: EnvMap,
    ) -> Result<RenderScene, RenderError> {
        RenderScene::with_objects(camera, mesh, maps, env, &[])
    }

    /// As [`RenderScene::new`], the light guide built or not (a scene
    /// rendered once at a few samples may not repay it).
    pub fn new_guided(
        camera: Camera,
        mesh: TriMesh,
        maps: &MaterialMaps,
        env: EnvMap,
        guided: bool,
    ) -> Result<RenderScene, RenderError> {
        RenderScene::build(camera, mesh, maps, env, &[], guided, Hierarchy::Build)
    }

    /// The scene with objects added to the depth mesh.
    pub fn with_objects(
        camera: Camera,
        mesh: TriMesh,
        maps: &MaterialMaps,
        env: EnvMap,
        objects: &[SceneObject],
    ) -> Result<RenderScene, RenderError> {
        RenderScene::build(camera, mesh, maps, env, objects, true, Hierarchy::Build)
    }

    /// [`RenderScene::new`] with the mesh's hierarchy given (one built by
    /// [`Bvh::build`] on this mesh and stored) instead of built.
    pub fn with_bvh(
        camera: Camera,
        mesh: TriMesh,
        maps: &MaterialMaps,
        env: EnvMap,
        bvh: Bvh,
    ) -> Result<RenderScene, RenderError> {
        RenderScene::build(camera, mesh, maps, env, &[], true, Hierarchy::Given(bvh))
    }

    /// [`RenderScene::with_objects`] on `plain`'s mesh and camera (a scene
    /// built without objects), its hierarchy kept and the objects'
    /// triangles added to it ([`Bvh::with_added`]) instead of one built
    /// over everything: moving an object in a large scene rebuilds only
    /// the object's. Renders as the scene built whole does (the same hits
    /// up to [`matflow_geom::bvh`]'s rounding effect on coincident faces).
    pub fn with_objects_over(
        plain: &RenderScene,
        maps: &MaterialMaps,
        env: EnvMap,
        objects: &[SceneObject],
    ) -> Result<RenderScene, RenderError> {
        let mut mesh = plain.mesh.clone();
        mesh.indices.truncate(plain.screen_prims);
        mesh.positions.truncate(plain.object_vertices);
        mesh.film.truncate(plain.object_vertices);
        let bvh = (!plain.prim_object.is_empty()).then(|| Bvh::build(&mesh));
        let over = bvh.as_ref().unwrap_or(&plain.bvh);
        RenderScene::build(
            plain.camera,
            mesh,
            maps,
            env,
            objects,
            true,
            Hierarchy::Over(over),
        )
    }

    fn build(
        camera: Camera,
        mut mesh: TriMesh,
        maps: &MaterialMaps,
        env: EnvMap,
        objects: &[SceneObject],
        guided: bool,
        over: Hierarchy<'_>,
    ) -> Result<RenderScene, RenderError> {
        if maps.width() != camera.width || maps.height() != camera.height {
            return Err(RenderError::MaterialSize {
                maps_width: maps.width(),
                maps_height: maps.height(),
                width: camera.width,
                height: camera.height,
            });
        }
        let screen_prims = mesh.triangle_count();
        let screen_vertices = mesh.vertex_count();
        let npix = (camera.width * camera.height) as u32;
        if mesh
            .material_pixel
            .iter()
            .any(|&q| q != matflow_geom::PROJECTED && q >= npix)
        {
            return Err(RenderError::MaterialPixel {
                pixels: npix as usize,
            });
        }
        let portals = checked_portals(&mesh.portals)?;
        mesh.material_pixel.truncate(screen_prims);
        mesh.openness.truncate(screen_prims);
        for o in &mut mesh.openness {
            // NaN clamps to 0 (solid).
            *o = if *o > 0.0 { o.min(1.0) } else { 0.0 };
        }
        if mesh.openness.iter().all(|&o| o == 0.0) {
            mesh.openness.clear();
        }
        let mut prim_object = Vec::new();
        for (k, o) in objects.iter().enumerate() {
            let base = mesh.positions.len() as u32;
            mesh.positions.extend_from_slice(&o.mesh.positions);
            mesh.indices
                .extend(o.mesh.indices.iter().map(|t| t.map(|i| base + i)));
            prim_object.extend(std::iter::repeat_n(k as u32, o.mesh.indices.len()));
        }
        if !mesh.film.is_empty() {
            mesh.film.resize(mesh.positions.len(), Vec2::ZERO);
        }
        let bvh = std::sync::Arc::new(match over {
            Hierarchy::Over(b) => b.clone().with_added(&mesh, screen_prims),
            Hierarchy::Given(b) => b,
            Hierarchy::Build => Bvh::build(&mesh),
        });
        let face_normals = matflow_geom::huge::huge(
            (0..mesh.triangle_count())
                .map(|i| mesh.face_normal(i))
                .collect(),
        );
        let mut vertex_normals = vertex_normals(&mesh);
        let given_normals = !mesh.normals.is_empty();
        // Given shading normals (a predicted normal map laid on the depth
        // mesh) replace the averaged ones where they face the same side.
        for (d, s) in vertex_normals
            .iter_mut()
            .zip(&mesh.normals)
            .take(screen_vertices)
        {
            let n = s.normalize_or_zero();
            if n.dot(*d) > 0.0 {
                *d = n;
            }
        }
        let mut at = screen_vertices;
        for o in objects {
            let n = o.mesh.vertex_count();
            if o.normals.len() == n {
                for (d, s) in vertex_normals[at..at + n].iter_mut().zip(&o.normals) {
                    *d = s.normalize_or(*d);
                }
            }
            at += n;
        }
        let materials = matflow_geom::huge::huge(materials_from_maps(maps));
        let mut uvs = Vec::new();
        for o in objects {
            let n = o.mesh.vertex_count();
            if o.texture.is_some() && o.uvs.len() == n {
                uvs.extend_from_slice(&o.uvs);
            } else {
                uvs.extend(std::iter::repeat_n(Vec2::ZERO, n));
            }
        }
        let screen_glass = maps
            .transparency
            .as_ref()
            .map(|t| screen_glass(&camera, &bvh, screen_prims, maps, t));
        let mut scene = RenderScene {
            textures: objects
                .iter()
                .map(|o| {
                    o.texture
                        .clone()
                        .filter(|_| o.uvs.len() == o.mesh.vertex_count())
                })
                .collect(),
            uvs,
            object_vertices: screen_vertices,
            screen_glass,
            screen_prims,
            prim_object,
            objects: objects.iter().map(|o| o.surface.sanitized()).collect(),
            focal: camera.focal(),
            principal: camera.principal_point(),
            camera,
            mesh,
            bvh,
            face_normals,
            vertex_normals,
            given_normals,
            materials,
            env,
            light_visibility: None,
            lamps: Vec::new(),
            lamp_far: 1.0,
            portals,
            portal_share: crate::portal::PORTAL_SHARE,
        };
        if guided {
            scene.set_light_guide(Some(&crate::guide::GuideParams::default()));
        }
        Ok(scene)
    }

    /// Measures what each region of the scene sees of the sky and, if the
    /// scene is enclosed enough to gain from it
    /// ([`crate::guide::GuideParams::enclosed_below`]), guides the
    /// envmap's light samples by it from now on ([`crate::guide`]; every
    /// scene starts with the default parameters). `None` returns to
    /// sampling by radiance alone. Returns whether the scene is guided.
    pub fn set_light_guide(&mut self, params: Option<&crate::guide::GuideParams>) -> bool {
        self.light_visibility = params.and_then(|p| {
            // A coarse probe first (a fraction of the rays): open scenes
            // stop here.
            let probe = crate::guide::GuideParams {
                points: 2,
                walks: p.walks / 4,
                dir_width: 16,
                dir_height: 8,
                ..*p
            };
            let build = |q: &crate::guide::GuideParams| {
                crate::guide::Visibility::build(
                    &self.face_normals,
                    self.screen_prims,
                    &self.bvh,
                    &self.mesh.openness,
                    &self.primary_grid(q.walks),
                    q,
                )
            };
            if !(build(&probe).open_fraction() < p.enclosed_below) {
                return None;
            }
            Some(std::sync::Arc::new(build(p)))
        });
        let env = self.env.clone();
        self.set_env(env);
        self.light_visibility.is_some()
    }

    /// Camera ray directions through a grid of about `n` points spread
    /// evenly over the film.
    fn primary_grid(&self, n: usize) -> Vec<Vec3> {
        let (w, h) = (self.camera.width as f64, self.camera.height as f64);
        let gw = ((n as f64 * w / h).sqrt().round() as usize).max(1);
        let gh = (n / gw).max(1);
        (0..gh)
            .flat_map(|j| {
                (0..gw).map(move |i| {
                    let film = Vec2::new(
                        ((i as f64 + 0.5) / gw as f64 * w) as f32,
                        ((j as f64 + 0.5) / gh as f64 * h) as f32,
                    );
                    self.camera_ray(film)
                })
            })
            .collect()
    }

    /// A length past everything in the scene from any point in it: four
    /// times the farthest vertex from the camera, and one more (a ray that
    /// long towards a distant light leaves the scene).
    pub fn beyond(&self) -> f32 {
        let r = self
            .mesh
            .positions
            .iter()
            .map(|p| p.length())
            .filter(|r| r.is_finite())
            .fold(0.0f32, f32::max);
        4.0 * r + 1.0
    }

    /// Lights the scene with `lamps` besides its envmap (replacing any it
    /// had). Each must be [`Lamp::is_valid`].
    pub fn set_lamps(&mut self, lamps: Vec<Lamp>) -> Result<(), RenderError> {
        if let Some(k) = lamps.iter().position(|l| !l.is_valid()) {
            return Err(RenderError::Lamp { index: k });
        }
        if lamps.iter().any(Lamp::is_distant) {
            self.lamp_far = self.beyond();
        }
        self.lamps = lamps;
        Ok(())
    }

    /// Aims light samples at `portals` (replacing the mesh's; none turns
    /// portal sampling off). Each must be [`Portal::is_valid`], and at
    /// most [`crate::portal::MAX_PORTALS`].
    pub fn set_portals(&mut self, portals: &[Portal]) -> Result<(), RenderError> {
        self.portals = checked_portals(portals)?;
        Ok(())
    }

    /// The portals' weights from `o` when light samples there aim at
    /// them (the scene has portals, a positive share, and `o` sees one).
    #[inline]
    fn portals_seen(&self, o: Vec3) -> Option<crate::portal::PortalWeights> {
        if self.portals.is_empty() || !(self.portal_share > 0.0) {
            return None;
        }
        Some(self.portals.weights(o)).filter(|w| w.total > 0.0)
    }

    /// A light sample for a vertex at `o` in the envmap's sampling
    /// cluster `cluster`: (direction, radiance, pdf). Where a portal is
    /// seen, `u1` chooses between the portals
    /// ([`RenderScene::portal_share`]) and the envmap's density, and the
    /// pdf is the mixture's.
    #[inline]
    pub(crate) fn sample_sky(
        &self,
        o: Vec3,
        cluster: u32,
        u1: f32,
        u2: f32,
    ) -> Option<(Vec3, Vec3, f32)> {
        let Some(w) = self.portals_seen(o) else {
            return self.env.sample_in(cluster, u1, u2);
        };
        let a = self.portal_share;
        let (d, le, pdf_e, pdf_p) = if u1 < a {
            let (d, pdf_p) = self.portals.sample(o, &w, (u1 / a).min(ONE_BELOW), u2)?;
            let (le, pdf_e) = self.env.eval_pdf_in(cluster, d);
            (d, le, pdf_e, pdf_p)
        } else {
            let u = ((u1 - a) / (1.0 - a)).clamp(0.0, ONE_BELOW);
            let (d, le, pdf_e) = self.env.sample_in(cluster, u, u2)?;
            (d, le, pdf_e, self.portals.pdf(o, &w, d))
        };
        let pdf = a * pdf_p + (1.0 - a) * pdf_e;
        (pdf > 0.0 && pdf.is_finite()).then_some((d, le, pdf))
    }

    /// The radiance from direction `d` and the density
    /// [`RenderScene::sample_sky`] draws it with from `o`.
    #[inline]
    pub(crate) fn sky_eval_pdf(&self, o: Vec3, cluster: u32, d: Vec3) -> (Vec3, f32) {
        let (le, pdf_e) = self.env.eval_pdf_in(cluster, d);
        match self.portals_seen(o) {
            Some(w) => {
                let a = self.portal_share;
                (le, a * self.portals.pdf(o, &w, d) + (1.0 - a) * pdf_e)
            }
            None => (le, pdf_e),
        }
    }

    /// Lights the scene with `env`, guided by the scene's visibility when
    /// it has one.
    pub fn set_env(&mut self, env: EnvMap) {
        self.env = match &self.light_visibility {
            Some(v) => env.guided(v.clone()),
            None => env.unguided(),
        };
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

    /// The share of light that passes through triangle `prim` (0: solid;
    /// objects are solid): see [`TriMesh::openness`].
    #[inline]
    pub fn openness(&self, prim: u32) -> f32 {
        self.mesh.openness_of(prim as usize)
    }

    /// Whether any triangle lets light through.
    #[inline]
    pub fn has_openness(&self) -> bool {
        !self.mesh.openness.is_empty()
    }

    /// The material index of a vertex at `p` on triangle `prim`: the pixel
    /// `p` projects into for the depth mesh ([`Self::material_index`]) —
    /// or the pixel the triangle names, for geometry completed past the
    /// frame ([`TriMesh::material_pixel`]) — and `width·height + k` on
    /// object `k`.
    #[inline]
    pub fn vertex_material(&self, prim: u32, p: Vec3) -> Option<usize> {
        self.material_of(prim, p, self.mesh.material_pixel_of(prim as usize))
    }

    /// [`Self::vertex_material`] for a camera ray's first vertex: whatever
    /// of the view's mesh a camera ray meets is what its pixel shows, so
    /// it takes the material of the pixel it projects into, also on
    /// geometry completed past the frame (a plane filled in behind an
    /// occluder, reached through a crack of the depth mesh at a
    /// silhouette; an extension within half a pixel of the border), whose
    /// named pixel serves every other ray.
    #[inline]
    pub fn camera_vertex_material(&self, prim: u32, p: Vec3) -> Option<usize> {
        self.material_of(prim, p, None)
    }

    /// The material index of a vertex at `p` on `prim`, whose named pixel
    /// (if any) is `named`.
    #[inline]
    fn material_of(&self, prim: u32, p: Vec3, named: Option<u32>) -> Option<usize> {
        let prim = prim as usize;
        if prim < self.screen_prims {
            match named {
                Some(q) => Some(q as usize),
                None => self.material_index(p),
            }
        } else {
            let k = self.prim_object[prim - self.screen_prims] as usize;
            Some(self.camera.width * self.camera.height + k)
        }
    }

    /// The object surface of material index `q`, `None` for pixels.
    #[inline]
    pub fn object_surface(&self, q: usize) -> Option<&Surface> {
        self.objects.get(q.wrapping_sub(self.materials.len()))
    }

    /// The first material index of background vertices.
    #[inline]
    pub fn background_base(&self) -> usize {
        self.materials.len() + self.objects.len()
    }

    /// The glass of pixel `q`, when it lies in a transparent region.
    #[inline]
    pub fn glass_pixel(&self, q: usize) -> Option<&GlassPixel> {
        self.screen_glass.as_ref()?.glass.get(q)?.as_ref()
    }

    /// The screen-space material of index `q`: a pixel's, or the
    /// background's seen through a pixel.
    #[inline]
    pub fn screen_material(&self, q: usize) -> Material {
        match self.materials.get(q) {
            Some(m) => *m,
            None => self
                .screen_glass
                .as_ref()
                .and_then(|g| g.background.get(q - self.background_base()))
                .copied()
                .unwrap_or(Material {
                    albedo: Vec3::ZERO,
                    roughness: 1.0,
                    metallic: 0.0,
                }),
        }
    }

    /// Whether material index `q` is glass (an object's or a transparent
    /// region's).
    #[inline]
    pub fn is_glass(&self, q: usize) -> bool {
        self.object_surface(q).is_some_and(Surface::is_glass) || self.glass_pixel(q).is_some()
    }

    /// Per pixel (row-major), the distance along the ray through the
    /// pixel's centre to the first hit, or infinity where it sees nothing
    /// (the sky).
    pub fn primary_distances(&self) -> Vec<f32> {
        use rayon::prelude::*;
        let (w, h) = (self.camera.width, self.camera.height);
        (0..w * h)
            .into_par_iter()
            .with_min_len(256)
            .map(|k| {
                let film = Vec2::new((k % w) as f32 + 0.5, (k / w) as f32 + 0.5);
                let d = self.camera_ray(film);
                self.bvh
                    .intersect(Vec3::ZERO, d, 0.0, f32::INFINITY)
                    .map_or(f32::INFINITY, |hit| hit.t)
            })
            .collect()
    }

    /// Per pixel (row-major), the fraction of an `n`×`n` grid of camera
    /// rays through the pixel whose first hit is an object: where an
    /// inserted object covers the image (the compositing matte).
    pub fn object_coverage(&self, n: usize) -> Vec<f32> {
        use rayon::prelude::*;
        let (w, h) = (self.camera.width, self.camera.height);
        let n = n.max(1);
        // Only pixels in the film box of the objects' vertices can see
        // them (a camera ray meets a triangle only inside its projection);
        // a vertex at or behind the camera plane leaves the whole film.
        let (mut lo, mut hi) = (Vec2::splat(f32::INFINITY), Vec2::splat(f32::NEG_INFINITY));
        let mut whole = false;
        for p in self
            .mesh
            .positions
            .get(self.object_vertices..)
            .unwrap_or(&[])
        {
            match self.camera.project(*p) {
                Some(f) if f.is_finite() => {
                    lo = lo.min(f);
                    hi = hi.max(f);
                }
                _ => whole = true,
            }
        }
        let (x0, y0, x1, y1) = if whole {
            (0, 0, w, h)
        } else if lo.x > hi.x {
            (0, 0, 0, 0)
        } else {
            let at = |v: f32, max: usize| v.clamp(0.0, max as f32) as usize;
            (
                at(lo.x.floor() - 1.0, w),
                at(lo.y.floor() - 1.0, h),
                at(hi.x.ceil() + 1.0, w),
                at(hi.y.ceil() + 1.0, h),
            )
        };
        (0..w * h)
            .into_par_iter()
            .with_min_len(256)
            .map(|k| {
                let (px, py) = (k % w, k / w);
                if px < x0 || px >= x1 || py < y0 || py >= y1 {
                    return 0.0;
                }
                let (x, y) = (px as f32, py as f32);
                let mut hits = 0u32;
                for j in 0..n {
                    for i in 0..n {
                        let film = Vec2::new(
                            x + (i as f32 + 0.5) / n as f32,
                            y + (j as f32 + 0.5) / n as f32,
                        );
                        let d = self.camera_ray(film);
                        if let Some(hit) = self.bvh.intersect(Vec3::ZERO, d, 0.0, f32::INFINITY) {
                            hits += (hit.prim as usize >= self.screen_prims) as u32;
                        }
                    }
                }
                hits as f32 / (n * n) as f32
            })
            .collect()
    }

    /// The pixel a camera-space point projects into, like
    /// [`Self::material_index`] (nearest, clamped to the film).
    #[inline]
    pub fn pixel_of(&self, p: Vec3) -> Option<usize> {
        self.material_index(p)
    }

    /// The texture colour of object `k` at a hit on triangle `prim`
    /// (barycentrics `u`, `v`); white for untextured objects.
    #[inline]
    pub fn object_texture(&self, k: usize, prim: u32, u: f32, v: f32) -> Vec3 {
        let Some(Some(t)) = self.textures.get(k) else {
            return Vec3::ONE;
        };
        let tri = self.mesh.indices[prim as usize];
        let uv = |i: u32| {
            self.uvs
                .get((i as usize).wrapping_sub(self.object_vertices))
                .copied()
                .unwrap_or(Vec2::ZERO)
        };
        let st = uv(tri[0]) * (1.0 - u - v) + uv(tri[1]) * u + uv(tri[2]) * v;
        texture_at(t, st)
    }

    /// The normal a depth-mesh hit shades with: the triangle's, or with
    /// given shading normals the interpolated one, where it lies on the
    /// triangle's side (by a margin; else the triangle's).
    #[inline]
    pub fn screen_shading_normal(&self, prim: u32, u: f32, v: f32) -> Vec3 {
        let ng = self.face_normals[prim as usize];
        if !self.given_normals {
            return ng;
        }
        let n = self.shading_normal(prim, u, v);
        if n.dot(ng) > 0.1 {
            n
        } else {
            ng
        }
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

/// The transparent regions' per-pixel data: glass, background materials,
/// and the depth mesh's surface through each pixel centre (the first hit
/// on the depth mesh, passing through inserted objects).
fn screen_glass(
    camera: &Camera,
    bvh: &Bvh,
    screen_prims: usize,
    maps: &MaterialMaps,
    t: &matflow_scene::transparency::Transparency,
) -> ScreenGlass {
    use rayon::prelude::*;
    let (w, h) = (camera.width, camera.height);
    let fin = |x: f32| if x.is_finite() { x.max(0.0) } else { 0.0 };
    let glass = (0..w * h)
        .map(|k| {
            t.is_glass(k).then(|| GlassPixel {
                interface: Dielectric {
                    eta: t.ior.data[k],
                    transmission: t.transmission.data[k],
                    tint: t.tint.data[k],
                    roughness: t.roughness.data[k],
                }
                .sanitized(),
                d1: fin(t.d1.data[k]),
                d2: fin(t.d2.data[k]),
            })
        })
        .collect();
    let background = (0..w * h)
        .map(|k| {
            let (albedo, roughness, metallic) = maps.background_at(k);
            Material {
                albedo,
                roughness,
                metallic,
            }
            .sanitized()
        })
        .collect();
    let f = camera.focal();
    let pp = camera.principal_point();
    let surface = (0..w * h)
        .into_par_iter()
        .with_min_len(256)
        .map(|k| {
            let film = Vec2::new((k % w) as f32 + 0.5, (k / w) as f32 + 0.5);
            let d =
                Vec3::new((film.x - 0.5 - pp.x) / f, -(film.y - 0.5 - pp.y) / f, -1.0).normalize();
            let mut tmin = 0.0;
            while let Some(hit) = bvh.intersect(Vec3::ZERO, d, tmin, f32::INFINITY) {
                if (hit.prim as usize) < screen_prims {
                    return (d * hit.t, hit.prim);
                }
                tmin = hit.t * (1.0 + 1e-6) + 1e-6;
            }
            (Vec3::ZERO, NO_SURFACE)
        })
        .collect();
    ScreenGlass {
        glass,
        background,
        surface,
    }
}
