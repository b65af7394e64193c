//! `matflow-bench select`: one click's selection on a bundle's
//! predictions (`matflow_scene::select`), with the bundle's own normals,
//! with normals estimated from its depth, and with the bundle's normals
//! within the photo's own edges (the `edit` stage's `mask_object`), at
//! two colour tolerances:
//! the pixels taken per click, and an overlay per click written beside
//! for a person to judge (the photo, the region tinted blue, the click
//! red). Real photos have no ground truth here: the images are the check.

use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use clap::Args;
use matflow_scene::select::{grow_object_within_edges, Grow};
use matflow_scene::{io, Bundle, Camera, MaterialSource};

#[derive(Args)]
pub struct BenchSelectArgs {
    /// A bundle folder (its predicted depth, albedo, normals and photo).
    pub bundle: PathBuf,
    /// Clicks, each `x,y` in the bundle's pixels.
    #[arg(required = true)]
    pub clicks: Vec<String>,
    /// Colour tolerances to try.
    #[arg(long, value_delimiter = ',', default_values_t = [0.1, 0.2])]
    pub tolerances: Vec<f32>,
    /// The photo's step that stops a region in the last column (the
    /// `edit` stage's `object_edges`; its default).
    #[arg(long, default_value_t = 0.03)]
    pub edges: f32,
    /// Where the overlays go.
    #[arg(long, default_value = "/tmp/matflow-bench-select")]
    pub out: PathBuf,
}

pub fn bench_select(a: BenchSelectArgs) -> Result<()> {
    let b = Bundle::open(&a.bundle).with_context(|| a.bundle.display().to_string())?;
    let depth = b.load_depth()?;
    let maps = b.load_materials(MaterialSource::Pred)?;
    let photo = b.load_gt_image()?;
    let (w, h) = (depth.width, depth.height);
    let cam = Camera::new(w, h);
    std::fs::create_dir_all(&a.out)?;
    outln!("{} ({w}x{h}): pixels one click selects", a.bundle.display());
    outln!();
    outln!("| click | tolerance | bundle's normals | normals from depth | bundle's normals, within the photo's edges (the edit's rule) | normals from depth, within the photo's edges (the edit with object_normals: depth) |");
    outln!("|---|---|---|---|---|---|");
    for click in &a.clicks {
        let v: Vec<usize> = click
            .split(',')
            .map(|x| x.trim().parse())
            .collect::<Result<_, _>>()
            .with_context(|| format!("click {click:?}: x,y"))?;
        if v.len() != 2 || v[0] >= w || v[1] >= h {
            bail!("click {click:?}: x,y inside the {w}x{h} image");
        }
        for &tol in &a.tolerances {
            let g = Grow {
                albedo_tol: tol,
                ..Grow::default()
            };
            let mut counts = Vec::new();
            let (given, seed) = (maps.normal.as_ref(), (v[0], v[1]));
            for (tag, n, edges) in [
                ("given", given, None),
                ("depth", None, None),
                ("edges", given, Some(a.edges)),
                ("depth_edges", None, Some(a.edges)),
            ] {
                let edges = edges.map(|step| (&photo, step));
                let m = grow_object_within_edges(&maps.albedo, &depth, n, edges, &cam, seed, &g);
                counts.push(m.data.iter().filter(|&&s| s).count());
                let shown = matflow_scene::Image::from_fn(w, h, |x, y| {
                    let near = x.abs_diff(v[0]) < 3 && y.abs_diff(v[1]) < 3;
                    let c = photo.get(x, y);
                    if near {
                        glam::Vec3::new(1.0, 0.0, 0.0)
                    } else if m.get(x, y) {
                        c * 0.5 + glam::Vec3::new(0.0, 0.05, 0.25)
                    } else {
                        c
                    }
                });
                let file = a.out.join(format!("{}_{}_{tol}_{tag}.png", v[0], v[1]));
                io::write_png_gamma(&file, &shown)?;
            }
            outln!(
                "| {click} | {tol} | {} px | {} px | {} px | {} px |",
                counts[0],
                counts[1],
                counts[2],
                counts[3]
            );
        }
    }
    outln!();
    outln!("overlays: {}", a.out.display());
    Ok(())
}
