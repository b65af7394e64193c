//! `matflow-bench`: benchmarks that print numbers (never timed tests).
//!
//! A program of its own, not part of the `matflow` users run: each suite
//! drives the `matflow` binary as a child process (found beside this one,
//! or at `$MATFLOW_BIN`), reports medians of several runs, and runs the
//! side programs under `scripts/` (Mitsuba 3, Embree, the validation
//! scenes) when they are installed. See `docs/results/` for the tables
//! and the commands that made them.

#[macro_use]
extern crate matflow_cli;

mod harness;
mod suites;

use anyhow::Result;
use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "matflow-bench",
    version,
    about = "matflow's benchmarks: run time against error, medians of several runs"
)]
struct Cli {
    #[command(subcommand)]
    suite: Suite,
}

#[derive(Subcommand)]
enum Suite {
    /// BVH build time, ray throughput and wall time of a full render.
    Render(suites::render::BenchRenderArgs),
    /// The renderer's BRDF kernel written with matflow's lanes, `wide`
    /// and `pulp`: time per evaluation, same bits.
    Lanes(suites::lanes::BenchLanesArgs),
    /// Inverse rendering: wall time against rerender error per budget,
    /// route and skip.
    Invert(suites::invert::BenchInvertArgs),
    /// Inverse rendering on procedural scenes with known truth: envmap,
    /// material and relighting errors per budget and route.
    Synthetic(suites::synthetic::BenchSyntheticArgs),
    /// The pipeline engine: first run, re-edit of one material and a
    /// no-change re-run, over the binary.
    Pipeline(suites::pipeline::BenchPipelineArgs),
    /// Glass against Mitsuba 3's dielectric and roughdielectric.
    Glass(suites::glass::BenchGlassArgs),
    /// Object insertion: render time with and without objects, re-edits
    /// of an inserted object's material, their error.
    Insert(suites::insert::BenchInsertArgs),
    /// Dataset jobs: samples/s per generator, scaling from 1 to 2 shard
    /// processes.
    Dataset(suites::dataset::BenchDatasetArgs),
    /// The refraction-length network: inference time per 512² image on
    /// each backend, held-out error next to the baselines.
    Refraction(suites::dataset::BenchRefractionArgs),
    /// The prediction stage: inference time and peak memory per photo on
    /// each backend, accuracy on held-out rooms and against the official
    /// MatNet's predictions, end-to-end re-render PSNR.
    Matnet(suites::matnet::BenchMatnetArgs),
    /// A `rooms` dataset's scenes written for Mitsuba 3 beside their
    /// bundles (`scripts/mitsuba_rooms.py` photographs them): the
    /// prediction network scored on two renderers' photos of one scene.
    ExportRooms(suites::export_rooms::ExportRoomsArgs),
    /// One click's selection on a bundle's predictions, with its normals
    /// and with normals from its depth: pixels taken, overlays to look at.
    Select(suites::select::BenchSelectArgs),
    /// The studio over its API: a material change's first preview and
    /// converged result, memory, idle CPU, the export reproduced.
    Studio(suites::studio::BenchStudioArgs),
}

fn run(s: Suite) -> Result<()> {
    match s {
        Suite::Render(a) => suites::render::bench_render(a),
        Suite::Lanes(a) => suites::lanes::bench_lanes(a),
        Suite::Invert(a) => suites::invert::bench_invert(a),
        Suite::Synthetic(a) => suites::synthetic::bench_synthetic(a),
        Suite::Pipeline(a) => suites::pipeline::bench_pipeline(a),
        Suite::Glass(a) => suites::glass::bench_glass(a),
        Suite::Insert(a) => suites::insert::bench_insert(a),
        Suite::Dataset(a) => suites::dataset::bench_dataset(a),
        Suite::Refraction(a) => suites::dataset::bench_refraction(a),
        Suite::Matnet(a) => suites::matnet::bench_matnet(a),
        Suite::ExportRooms(a) => suites::export_rooms::export_rooms(a),
        Suite::Studio(a) => suites::studio::bench_studio(a),
        Suite::Select(a) => suites::select::bench_select(a),
    }
}

fn main() {
    matflow_cli::init_logging();
    if let Err(e) = run(Cli::parse().suite) {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

#[cfg(test)]
mod tests {
    /// `docs/reference/bench.md` is this program's help, generated
    /// (`MATFLOW_BLESS=1` rewrites it when stale).
    #[test]
    fn reference_of_the_benchmarks_is_current() {
        use clap::CommandFactory;
        let want = matflow_cli::reference::command_page(
            "`matflow-bench` command line",
            "Every suite and option of the benchmark program, as `matflow-bench … --help` \
             prints them. The tables they print, with the commands that made them: \
             [Results](../results/README.md).",
            super::Cli::command(),
        );
        let path =
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../docs/reference/bench.md");
        let have = std::fs::read_to_string(&path).unwrap_or_default();
        if have != want {
            if std::env::var_os("MATFLOW_BLESS").is_some() {
                std::fs::write(&path, want).unwrap();
            } else {
                panic!(
                    "docs/reference/bench.md is stale: regenerate it with `MATFLOW_BLESS=1 \
                     cargo test --release --workspace -- reference`"
                );
            }
        }
    }
}
