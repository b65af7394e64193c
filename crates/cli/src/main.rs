//! `matflow`: single-image inverse rendering and physically based editing.

mod bench;
mod bench_compare;
mod bench_distributed;
mod bench_invert;
mod bench_pipeline;
mod bench_synthetic;
mod cluster;
mod commands;
mod invert;
mod routes;
mod run;

use anyhow::Result;
use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "matflow",
    version,
    about = "Turn one photograph into an editable, physically based scene"
)]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Path-trace a bundle (geometry from its depth) and write EXR + PNG.
    Render(commands::RenderArgs),
    /// Build the mesh from a bundle's depth and write it as binary PLY.
    Mesh(commands::MeshArgs),
    /// Generate a procedural scene bundle (room, objects, known materials)
    /// and render its input image.
    Synth(commands::SynthArgs),
    /// Recover the envmap and materials from a bundle's image and
    /// predictions; writes best_results/ and summary.json.
    Invert(invert::InvertArgs),
    /// Run a pipeline file: only what its outputs need, cached stages
    /// served from the content-addressed store.
    Run(run::RunArgs),
    /// Print the node kinds a pipeline may use: parameters (type, default,
    /// unit) and outputs, as markdown.
    Kinds,
    /// Inspect and clean the content-addressed cache.
    #[command(subcommand)]
    Cache(run::CacheCmd),
    /// Serve every node kind over gRPC for `matflow run --workers`.
    Worker(cluster::WorkerArgs),
    /// Benchmarks that print numbers.
    #[command(subcommand)]
    Bench(bench::BenchCmd),
}

fn main() {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_env("MATFLOW_LOG")
                .unwrap_or_else(|_| "warn".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    let cli = Cli::parse();
    let res: Result<()> = match cli.cmd {
        Cmd::Render(a) => commands::render(a),
        Cmd::Mesh(a) => commands::mesh(a),
        Cmd::Synth(a) => commands::synth(a),
        Cmd::Invert(a) => invert::invert_cmd(a),
        Cmd::Run(a) => run::run(a),
        Cmd::Cache(c) => run::cache(c),
        Cmd::Kinds => {
            print!("{}", matflow_nodes::reference_markdown());
            Ok(())
        }
        Cmd::Bench(b) => bench::run(b),
        Cmd::Worker(w) => {
            let dir = run::cache_dir(w.cache.as_deref());
            cluster::worker(w, dir)
        }
    };
    if let Err(e) = res {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}
