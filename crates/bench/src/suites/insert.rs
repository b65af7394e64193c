//! `matflow-bench insert`: what inserting objects costs and how exact a
//! re-edit from kept paths is.
//!
//! 1. Render time with the insert pipeline's objects (a glass jug and a
//!    diffuse torus) against the same render without them, in process, on
//!    the procedural room with its true materials and sky (interleaved
//!    runs, medians).
//! 2. `pipelines/insert.yaml` at the chosen size, over the binary: the
//!    first run, then re-edits of the jug's glass (its tint) served from
//!    the `trace` stage's kept paths (medians).
//! 3. The re-edited render with objects (kept paths) and a full path trace
//!    at the same spp, each against a high-spp full render of the edited
//!    scene (sRGB PSNR).

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result};
use clap::Args;
use matflow_geom::mesh_for_view;
use matflow_render::{render, EnvMap, RenderOptions, RenderScene};
use matflow_scene::metrics::psnr_gamma;

use crate::harness::{median, run_child, with_outputs};

#[derive(Args)]
pub struct BenchInsertArgs {
    /// Image side (the pipeline's anchors are scaled from its 256²).
    #[arg(long, default_value_t = 512)]
    pub size: usize,
    #[arg(long, default_value_t = 64)]
    pub spp: u32,
    /// Repetitions; medians are reported.
    #[arg(long, default_value_t = 3)]
    pub runs: usize,
    /// Samples per pixel of the reference render of the edited scene.
    #[arg(long, default_value_t = 1024)]
    pub reference_spp: u32,
    #[arg(long, default_value = "pipelines/insert.yaml")]
    pub pipeline: PathBuf,
    #[arg(long, default_value = "/tmp/matflow-bench-insert")]
    pub work: PathBuf,
}

/// The insert pipeline's objects at `size`, meshes under `meshes`, the
/// jug's material `jug`.
fn objects_yaml(size: usize, meshes: &Path, jug: &str) -> String {
    let k = size as f64 / 256.0;
    format!(
        "[{{mesh: {}, anchor: [{}, {}], scale: 0.9, rotate: [0, 20, 0], material: {jug}}}, \
         {{mesh: {}, anchor: [{}, {}], scale: 0.7, material: {{type: diffuse, albedo: [0.2, 0.4, 0.8]}}}}]",
        meshes.join("jug.obj").display(),
        (200.0 * k).round(),
        (236.0 * k).round(),
        meshes.join("torus.obj").display(),
        (40.0 * k).round(),
        (236.0 * k).round(),
    )
}

const GLASS: &str = "{type: glass, ior: 1.5}";

pub fn bench_insert(a: BenchInsertArgs) -> Result<()> {
    let exe = crate::harness::matflow_exe()?;
    if a.work.exists() {
        std::fs::remove_dir_all(&a.work)?;
    }
    std::fs::create_dir_all(&a.work)?;
    let meshes =
        std::fs::canonicalize(a.pipeline.parent().unwrap_or(Path::new(".")).join("meshes"))
            .context("the pipeline's meshes/ folder")?;
    let n = a.size;
    let runs = a.runs.max(1);
    outln!(
        "bench insert: {} at {n}², {} spp, {} thread(s)",
        a.pipeline.display(),
        a.spp,
        rayon::current_num_threads()
    );

    // 1. Render time with and without the objects.
    let s = matflow_procgen::synthetic::generate(1, n, n);
    let (cam, dm) = mesh_for_view(&s.depth, &matflow_geom::MeshParams::default())?;
    let v = matflow_engine::value::parse_override(&objects_yaml(n, &meshes, GLASS))
        .map_err(anyhow::Error::msg)?;
    let mut reads = Vec::new();
    let norm = matflow_engine::spec::normalize_fields(
        &matflow_nodes::objects::OBJECTS,
        &v,
        None,
        Path::new("."),
        "bench",
        &mut reads,
    )
    .map_err(|(_, m)| anyhow::anyhow!("objects{m}"))?;
    let specs = matflow_nodes::objects::specs(&norm)?;
    let objs = matflow_nodes::objects::place(&specs, &cam, &dm.mesh)?;
    let env = EnvMap::new(&s.envmap)?;
    let with = RenderScene::with_objects(cam, dm.mesh.clone(), &s.maps, env.clone(), &objs)?;
    let without = RenderScene::new(cam, dm.mesh.clone(), &s.maps, env)?;
    let opts = RenderOptions {
        spp: a.spp,
        ..Default::default()
    };
    let (mut tw, mut to) = (Vec::new(), Vec::new());
    for _ in 0..runs {
        let t = Instant::now();
        render(&without, &opts, &|_, _| {});
        to.push(t.elapsed().as_secs_f64());
        let t = Instant::now();
        render(&with, &opts, &|_, _| {});
        tw.push(t.elapsed().as_secs_f64());
    }
    let (tw, to) = (median(tw), median(to));
    outln!(
        "| render, procedural room {n}², {} spp, depth 4 | without objects | with the jug (glass) and torus | ratio |\n|---|---|---|---|\n| median of {runs} | {to:.2} s | {tw:.2} s | {:.2} |",
        a.spp,
        tw / to
    );

    // 2. The pipeline over the binary: first run, then re-edits.
    let cache = a.work.join("cache");
    let base_sets = [
        format!("scene.size={n}"),
        format!("base.spp={}", a.spp),
        format!("base.objects={}", objects_yaml(n, &meshes, GLASS)),
        format!("inserted.output={}", a.work.join("inserted.exr").display()),
        format!("full.output={}", a.work.join("full.exr").display()),
    ];
    let run_file = |file: &Path, extra: &[String]| run_child(&exe, file, &cache, &base_sets, extra);
    let (first, summary) = run_file(&a.pipeline, &[])?;
    outln!("first run (empty cache): {first:.2} s   [{summary}]");
    let tints = [
        "[1, 0.6, 0.3]",
        "[0.5, 0.8, 1]",
        "[0.7, 1, 0.7]",
        "[1, 0.9, 0.5]",
    ];
    let mut edits = Vec::new();
    for k in 0..runs {
        let jug = format!(
            "{{type: glass, ior: 1.5, tint: {}}}",
            tints[k % tints.len()]
        );
        let set = format!("inserted.objects={}", objects_yaml(n, &meshes, &jug));
        let (t, s) = run_file(&a.pipeline, &[set])?;
        outln!("re-edit {} (the jug's tint): {t:.2} s   [{s}]", k + 1);
        edits.push(t);
    }
    outln!(
        "| pipeline | size | spp | first run | re-edit of the jug's glass (median of {runs}) |\n|---|---|---|---|---|\n| {} | {n}² | {} | {first:.2} s | {:.2} s |",
        a.pipeline.display(),
        a.spp,
        median(edits)
    );

    // 3. Errors against a high-spp render of the edited scene.
    if a.reference_spp > 0 {
        let jug = format!("{{type: glass, ior: 1.5, tint: {}}}", tints[0]);
        let edited = objects_yaml(n, &meshes, &jug);
        let mut t = with_outputs(&a.pipeline, "[kept, fresh, reference]")?;
        let work = std::fs::canonicalize(&a.work)?;
        t.push_str(&format!(
            "  kept:\n    kind: insert\n    mesh: mesh\n    materials: recovered\n    paths: base\n    \
             composite: full\n    objects: {edited}\n    output: {}\n",
            work.join("kept.exr").display()
        ));
        for (name, spp, seed) in [("fresh", a.spp, 0), ("reference", a.reference_spp, 99)] {
            t.push_str(&format!(
                "  {name}:\n    kind: insert\n    mesh: mesh\n    materials: recovered\n    \
                 envmap: recovered.envmap\n    composite: full\n    filter: box\n    spp: {spp}\n    \
                 seed: {seed}\n    objects: {edited}\n    output: {}\n",
                work.join(format!("{name}.exr")).display()
            ));
        }
        crate::harness::run_beside(&a.pipeline, ".bench-insert-check.yaml", &t, |f| {
            run_file(f, &[])
        })?;
        let load = |n: &str| matflow_scene::io::read_exr_rgb(&a.work.join(format!("{n}.exr")));
        let (k, f, r) = (load("kept")?, load("fresh")?, load("reference")?);
        outln!(
            "the re-edited render with objects against a {} spp reference (sRGB PSNR): from kept paths {:.2} dB, full path trace at {} spp {:.2} dB",
            a.reference_spp,
            psnr_gamma(&k, &r),
            a.spp,
            psnr_gamma(&f, &r)
        );
    }
    glass_region(&a, &exe)
}

/// 4. `pipelines/glass.yaml` at the same size: the first run, then
///    re-edits of the transparent box's T served from kept paths, and the
///    re-edited render against a high-spp full render of the edited scene.
fn glass_region(a: &BenchInsertArgs, exe: &Path) -> Result<()> {
    let n = a.size;
    let runs = a.runs.max(1);
    let file = a
        .pipeline
        .parent()
        .unwrap_or(Path::new("."))
        .join("glass.yaml");
    let cache = a.work.join("glass-cache");
    let k = n as f64 / 256.0;
    let sets = [
        format!("scene.size={n}"),
        format!("base.spp={}", a.spp),
        format!(
            "glassy.mask_flood=[{}, {}]",
            (205.0 * k).round(),
            (185.0 * k).round()
        ),
        format!("glass.output={}", a.work.join("glass.exr").display()),
    ];
    let run = |file: &Path, extra: &[String]| run_child(exe, file, &cache, &sets, extra);
    let (first, s) = run(&file, &[])?;
    outln!("glass: first run (empty cache): {first:.2} s   [{s}]");
    let ts = [0.6, 0.3, 0.8, 0.45];
    let mut edits = Vec::new();
    for k in 0..runs {
        let set = format!("glassy.transmission={}", ts[k % ts.len()]);
        let (t, s) = run(&file, &[set])?;
        outln!("re-edit {} (the box's T): {t:.2} s   [{s}]", k + 1);
        edits.push(t);
    }
    outln!(
        "| pipeline | size | spp | first run | re-edit of the region's T (median of {runs}) |\n|---|---|---|---|---|\n| {} | {n}² | {} | {first:.2} s | {:.2} s |",
        file.display(),
        a.spp,
        median(edits)
    );
    if a.reference_spp > 0 {
        let mut t = with_outputs(&file, "[glass, fresh, reference]")?;
        let work = std::fs::canonicalize(&a.work)?;
        for (name, spp, seed) in [("fresh", a.spp, 0), ("reference", a.reference_spp, 99)] {
            t.push_str(&format!(
                "  {name}:\n    kind: render\n    mesh: mesh\n    materials: glassy\n    \
                 envmap: recovered.envmap\n    filter: box\n    spp: {spp}\n    seed: {seed}\n    \
                 output: {}\n",
                work.join(format!("glass-{name}.exr")).display()
            ));
        }
        let check = file.with_file_name(".bench-glass-check.yaml");
        std::fs::write(&check, t)?;
        let r = run(&check, &[format!("glassy.transmission={}", ts[0])]);
        let _ = std::fs::remove_file(&check);
        r?;
        let load = |n: &str| matflow_scene::io::read_exr_rgb(&a.work.join(n));
        let (g, f, r) = (
            load("glass.exr")?,
            load("glass-fresh.exr")?,
            load("glass-reference.exr")?,
        );
        outln!(
            "the re-edited transparent region against a {} spp reference (sRGB PSNR): from kept paths {:.2} dB, full path trace at {} spp {:.2} dB",
            a.reference_spp,
            psnr_gamma(&g, &r),
            a.spp,
            psnr_gamma(&f, &r)
        );
    }
    Ok(())
}
