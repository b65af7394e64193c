//! The `matflow` command line as a library: each subcommand's arguments
//! and its action, so that the binary (`main.rs`) stays a dispatcher and
//! `matflow-bench` can reuse what users run (scene loading, routes' flags,
//! peak memory) without re-declaring it.

/// `println!` for the command's output: a closed pipe (`matflow cache ls
/// | head`) ends the process quietly with status 0 instead of a panic.
#[macro_export]
macro_rules! outln {
    () => {
        $crate::write_out(format_args!(""), true)
    };
    ($($t:tt)*) => {
        $crate::write_out(format_args!($($t)*), true)
    };
}

/// `print!` with the same handling of a closed pipe.
#[macro_export]
macro_rules! out {
    ($($t:tt)*) => {
        $crate::write_out(format_args!($($t)*), false)
    };
}

/// Writes to stdout; exits quietly when the reader has gone, with an
/// error for any other write failure (a full disk behind a redirect).
pub fn write_out(args: std::fmt::Arguments, newline: bool) {
    use std::io::Write;
    let mut o = std::io::stdout().lock();
    let r = o
        .write_fmt(args)
        .and_then(|_| if newline { o.write_all(b"\n") } else { Ok(()) });
    if let Err(e) = r {
        if e.kind() == std::io::ErrorKind::BrokenPipe {
            std::process::exit(0);
        }
        eprintln!("error: writing the output: {e}");
        std::process::exit(1);
    }
}

/// Logs to stderr, filtered by `$MATFLOW_LOG` (default: warnings), for
/// `matflow` and `matflow-bench` alike.
pub fn init_logging() {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_env("MATFLOW_LOG")
                .unwrap_or_else(|_| "warn".into()),
        )
        .with_writer(std::io::stderr)
        .init();
}

pub mod cluster;
pub mod commands;
pub mod dataset;
pub mod invert;
pub mod predict;
pub mod reference;
pub mod routes;
pub mod run;
pub mod stage_flags;
pub mod studio;

use anyhow::Result;
use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "matflow",
    version,
    about = "Turn one photograph into an editable, physically based scene"
)]
pub struct Cli {
    #[command(subcommand)]
    pub cmd: Cmd,
}

#[derive(Subcommand)]
pub enum Cmd {
    /// Path-trace a bundle (geometry from its depth) and write EXR + PNG.
    Render(commands::RenderArgs),
    /// Build the mesh from a bundle's depth and write it as binary PLY.
    Mesh(commands::MeshArgs),
    /// Write matflow's procedural meshes for insertion (jug, torus,
    /// sphere, cube) as OBJ files.
    Shapes(commands::ShapesArgs),
    /// Generate a procedural scene bundle (room, objects, known materials)
    /// and render its input image.
    Synth(commands::SynthArgs),
    /// Recover the envmap and materials from a bundle's image and
    /// predictions; writes best_results/ and summary.json.
    Invert(invert::InvertArgs),
    /// Predict a bundle from a photo (MatNet's stage: depth, albedo,
    /// roughness, metallic, normals) with the bundled model or another
    /// ONNX model under MatNet's contract.
    Predict(predict::PredictArgs),
    /// Run a pipeline file: only what its outputs need, cached stages
    /// served from the content-addressed store.
    Run(run::RunArgs),
    /// Generate a dataset's WebDataset shards from a spec (`dataset:`
    /// section), all or one process's share; `dataset merge DIR` checks
    /// and indexes them.
    Dataset(dataset::DatasetArgs),
    /// Print the node kinds a pipeline may use: parameters (type, default,
    /// unit) and outputs, as markdown.
    Kinds,
    /// Inspect and clean the content-addressed cache.
    #[command(subcommand)]
    Cache(run::CacheCmd),
    /// Serve every node kind over gRPC for `matflow run --workers`.
    Worker(cluster::WorkerArgs),
    /// Open a photo, a bundle or a pipeline in the browser: the session's
    /// pipeline run on the engine, its photo and maps shown, the pipeline
    /// exported.
    Studio(studio::StudioArgs),
}

/// Carries out one parsed command line.
pub fn run_cli(cli: Cli) -> Result<()> {
    match cli.cmd {
        Cmd::Render(a) => commands::render(a),
        Cmd::Mesh(a) => commands::mesh(a),
        Cmd::Shapes(a) => commands::shapes(a),
        Cmd::Synth(a) => commands::synth(a),
        Cmd::Invert(a) => invert::invert_cmd(a),
        Cmd::Predict(a) => predict::predict(a),
        Cmd::Run(a) => run::run(a),
        Cmd::Dataset(a) => dataset::dataset(a),
        Cmd::Cache(c) => run::cache(c),
        Cmd::Kinds => {
            out!("{}", matflow_nodes::reference_markdown());
            Ok(())
        }
        Cmd::Worker(w) => {
            let dir = run::cache_dir(w.cache.as_deref());
            cluster::worker(w, dir)
        }
        Cmd::Studio(a) => studio::studio(a),
    }
}
