//! A bundle folder as a render scene: its depth meshed (and completed),
//! its materials and envmap, and its maps' lamps.

use std::path::Path;
use std::time::Instant;

use matflow_engine::NodeError;
use matflow_geom::MeshParams;
use matflow_render::{scene_from_depth, EnvMap, RenderScene};
use matflow_scene::{io, Bundle, MaterialSource};

use crate::Context;

/// A bundle's scene, ready to render.
pub struct LoadedScene {
    pub scene: RenderScene,
    pub maps: matflow_scene::MaterialMaps,
    pub env: EnvMap,
    /// Building mesh and BVH.
    pub seconds: f64,
}

/// Builds mesh, BVH, materials and envmap for a bundle; with `lamps`,
/// the lamps of the maps' folder light them too (`FOLDER/lamps.json`:
/// those `matflow invert` fitted with its `best_results/` maps, the true
/// ones with `ground_truth/`), the sun among them only under the envmap
/// it came with (a new `envmap` is a new sky, which brings its own sun).
pub fn load_scene(
    bundle_dir: &Path,
    materials: MaterialSource,
    envmap: Option<&Path>,
    mesh: MeshParams,
    reference_compat: bool,
    complete: Option<matflow_geom::CompleteParams>,
    lamps: bool,
) -> Result<LoadedScene, NodeError> {
    let bundle = Bundle::open(bundle_dir).node_err()?;
    let depth = bundle.load_depth().node_err()?;
    let maps = bundle.load_materials(materials).node_err()?;
    let env_path = match envmap {
        Some(p) => p.to_path_buf(),
        None => bundle.envmap_path().context(|| {
            format!(
                "{}: no best_results/envmap.hdr or ground_truth/envmap.hdr; pass --envmap FILE.hdr (or .exr)",
                bundle_dir.display()
            )
        })?,
    };
    let mut env_img = io::read_envmap(&env_path).node_err()?;
    if reference_compat {
        env_img = matflow_render::envmap::merge_seam_columns(&env_img);
    }
    let env = EnvMap::new(&env_img).context(|| format!("{}", env_path.display()))?;
    let t0 = Instant::now();
    let mut scene = scene_from_depth(&depth, &maps, env.clone(), mesh, complete.as_ref())
        .context(|| format!("{}: building the scene", bundle_dir.display()))?
        .0;
    if let Some(folder) = materials.folder().filter(|_| lamps) {
        if let Some(mut l) = matflow_scene::lamps::bundle_lamps(bundle_dir, folder).node_err()? {
            if envmap.is_some() {
                l.retain(|l| !l.is_distant());
            }
            scene.set_lamps(l).node_err()?;
        }
    }
    Ok(LoadedScene {
        scene,
        maps,
        env,
        seconds: t0.elapsed().as_secs_f64(),
    })
}

/// What a render says of its light sampling.
pub fn light_guide_note(scene: &RenderScene) -> String {
    match &scene.light_visibility {
        Some(v) => format!(
            "light guided by visibility in {} of {} regions (the scene sees {:.0} % of the sky)",
            scene.env.guided_clusters(),
            v.clusters(),
            100.0 * v.open_fraction()
        ),
        None => "light sampled by radiance".into(),
    }
}

/// Under this PSNR on its own photo a result is reported as not
/// explaining it (`render`, `invert`).
pub const EXPLAINS_PHOTO_DB: f64 = 20.0;

/// How well `psnr` on the photo explains it, in words: the line, and a
/// warning under [`EXPLAINS_PHOTO_DB`].
pub fn photo_psnr_lines(what: &str, psnr: f64) -> Vec<String> {
    let mut lines = vec![format!(
        "{what} explains the photo at {psnr:.2} dB (sRGB, gamma 2.2)"
    )];
    if psnr < EXPLAINS_PHOTO_DB {
        lines.push(format!(
            "warning: {what} explains the photo at only {psnr:.2} dB (under {EXPLAINS_PHOTO_DB} dB): \
             the geometry or the light does not explain the photo"
        ));
    }
    lines
}
