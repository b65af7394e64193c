//! `matflow`: single-image inverse rendering and physically based editing.
//! The commands live in the library (`lib.rs`); this is only the entry.

use clap::Parser;

fn main() {
    matflow_cli::init_logging();
    if let Err(e) = matflow_cli::run_cli(matflow_cli::Cli::parse()) {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}
