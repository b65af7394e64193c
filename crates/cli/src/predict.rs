//! `matflow predict PHOTO --out BUNDLE`: the `matnet` kind on its own, as
//! a one-stage pipeline (so it is cached like any stage, and its report
//! names the backend and the model's digest). Its flags are the kind's
//! parameters; the photo is the positional argument.

use anyhow::Result;
use clap::Args;

use crate::stage_flags::{StageFlags, StageKind, StageRun};

/// `matflow predict`: the `matnet` kind.
pub struct PredictCmd;

impl StageKind for PredictCmd {
    const KIND: &'static str = "matnet";
    const POSITIONAL: &'static [&'static str] = &["photo"];
    /// The command writes a bundle: `--out` is needed.
    fn adjust(cmd: clap::Command) -> clap::Command {
        cmd.mut_arg("output", |a| a.required(true))
    }
}

#[derive(Args)]
pub struct PredictArgs {
    #[command(flatten)]
    pub stage: StageFlags<PredictCmd>,
    #[command(flatten)]
    pub run: StageRun,
}

pub fn predict(a: PredictArgs) -> Result<()> {
    crate::stage_flags::run_stage(PredictCmd::KIND, &a.stage.0, &a.run).map(|_| ())
}
