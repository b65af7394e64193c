//! `refraction_render`: the object photographed, and the view without it.

use super::*;

pub struct RefractionRenderNode;

pub(crate) const RENDER_INFO: NodeInfo = NodeInfo {
    kind: "refraction_render",
    version: 2,
    doc: "One sample's photographs for the refraction-length network: the object (opaque, its \
         material given) on an optional ground under an environment map, and the same view \
         without the object, path-traced and exposed alike (`matflow dataset` makes these).",
    params: &RENDER_PARAMS,
    outputs: &[
        OutputSpec {
            name: "image.png",
            ty: "file",
            doc: "8-bit sRGB: the object in its surroundings",
        },
        OutputSpec {
            name: "background.png",
            ty: "file",
            doc: "8-bit sRGB: the same view without the object",
        },
        OutputSpec {
            name: "render.json",
            ty: "file",
            doc: "the exposure applied (linear scale) and the samples taken",
        },
    ],
};

impl RefractionRenderNode {
    fn envmap(p: &Params) -> Result<RgbImage, NodeError> {
        let env = if let Some(path) = p.path("envmap") {
            io::read_envmap(&path).map_err(failed)?
        } else {
            let kind = EnvKind::from_name(p.str("envmap_kind"))
                .ok_or_else(|| err("`envmap_kind` is sky or room"))?;
            let w = p.i64("envmap_width") as usize;
            procedural_envmap(kind, p.i64("envmap_seed") as u64, w, (w / 2).max(2))
        };
        Ok(rotate_and_expose(&env, p.f64("envmap_rotation"), 0.0))
    }
}

/// A checkerboard texture of two squares per side, `contrast` apart (16
/// texels a square, so bilinear lookups keep the edges sharp).
fn checker(contrast: f32) -> RgbImage {
    Image::from_fn(32, 32, |x, y| {
        Vec3::splat(if (x / 16 + y / 16) % 2 == 0 {
            1.0
        } else {
            1.0 - contrast
        })
    })
}

impl Node for RefractionRenderNode {
    fn info(&self) -> &'static NodeInfo {
        &RENDER_INFO
    }
    fn check(&self, p: &Params) -> Result<(), String> {
        check_object(p)?;
        match (p.is_set("envmap"), p.is_set("envmap_kind")) {
            (true, true) => Err("give `envmap` or `envmap_kind`, not both".into()),
            (false, false) => Err("give `envmap` (a file) or `envmap_kind` (sky or room)".into()),
            _ => Ok(()),
        }
    }
    /// Only the envmap's format here: a dataset has thousands of these
    /// stages sharing a few files, which its generator reads once each;
    /// a damaged file fails its stage with the file's name.
    fn preflight(&self, p: &Params) -> Result<(), String> {
        if let Some(path) = p.path("envmap") {
            let ext = path
                .extension()
                .map(|e| e.to_string_lossy().to_lowercase())
                .unwrap_or_default();
            if ext != "hdr" && ext != "exr" {
                return Err(format!(
                    "{}: an environment map must be Radiance HDR (.hdr) or linear OpenEXR (.exr)",
                    path.display()
                ));
            }
        }
        Ok(())
    }
    fn film_size(&self, p: &Params) -> Option<(usize, usize)> {
        let n = p.i64("size") as usize;
        Some((n, n))
    }
    fn estimate_seconds(&self, p: &Params, film: Option<(usize, usize)>) -> f64 {
        2.0 * crate::data::render_seconds(film, p.i64("spp"), 4)
    }
    fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
        let p = ctx.params;
        let v = view(p)?;
        let env_world = Self::envmap(p)?;
        let env = EnvMap::new(&rotated(&env_world, v.to_world)).map_err(failed)?;
        let (w, h) = (v.camera.width, v.camera.height);
        let rgb = |name: &str| -> Vec3 {
            let f = p.floats(name).unwrap_or_else(|| vec![0.5; 3]);
            Vec3::new(f[0] as f32, f[1] as f32, f[2] as f32)
        };
        let maps = MaterialMaps::uniform(w, h, Vec3::splat(0.5), 0.5, 0.0);
        let mut objects = Vec::new();
        if let Some((g, uvs)) = &v.ground {
            let tile = p.f32("ground_tile");
            let contrast = p.f32("ground_checker");
            objects.push(SceneObject {
                mesh: g.clone(),
                normals: Vec::new(),
                surface: Surface::Principled(Material {
                    albedo: rgb("ground_albedo"),
                    roughness: p.f32("ground_roughness"),
                    metallic: 0.0,
                }),
                // Two texels per square: u = x / (2·tile).
                uvs: uvs.iter().map(|uv| *uv / (2.0 * tile)).collect(),
                texture: (contrast > 0.0).then(|| std::sync::Arc::new(checker(contrast))),
            });
        }
        let object = SceneObject {
            mesh: v.object.clone(),
            normals: v.normals.clone(),
            surface: Surface::Principled(Material {
                albedo: rgb("albedo"),
                roughness: p.f32("roughness"),
                metallic: p.f32("metallic"),
            }),
            uvs: Vec::new(),
            texture: None,
        };
        let opts = RenderOptions {
            spp: p.i64("spp") as u32,
            seed: ctx.seed,
            ..RenderOptions::default()
        };
        let draw = |objs: &[SceneObject], half: usize| -> Result<RgbImage, NodeError> {
            let scene =
                RenderScene::with_objects(v.camera, TriMesh::default(), &maps, env.clone(), objs)
                    .map_err(failed)?;
            let total = 2 * w * h;
            Ok(render(&scene, &opts, &|d, _| {
                (ctx.progress)((half * w * h + d) as u64, total as u64)
            })
            .image)
        };
        let background = draw(&objects, 0)?;
        objects.push(object);
        let image = draw(&objects, 1)?;
        // Exposure: the background's log-average luminance to 0.18.
        let scale =
            matflow_scene::color::exposure_to_key(&background, 0.18) * 2f64.powf(p.f64("exposure"));
        let expose = |img: &RgbImage| img.map(|c| c * scale as f32);
        let mut out = BTreeMap::new();
        out.insert(
            "image.png".into(),
            io::png_srgb_bytes(&expose(&image)).map_err(failed)?,
        );
        out.insert(
            "background.png".into(),
            io::png_srgb_bytes(&expose(&background)).map_err(failed)?,
        );
        let json = serde_json::json!({
            "exposure_scale": scale,
            "spp": opts.spp,
        });
        out.insert("render.json".into(), json.to_string().into_bytes());
        Ok(out)
    }
}
