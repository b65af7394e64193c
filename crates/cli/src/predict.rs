//! `matflow predict PHOTO --out BUNDLE`: the `matnet` stage on its own, as
//! a one-stage pipeline (so it is cached like any stage, and its report
//! names the backend and the model's digest).

use std::path::{Path, PathBuf};

use anyhow::{bail, Result};
use clap::Args;
use matflow_engine::spec::{self, Override};
use matflow_engine::Value;

#[derive(Args)]
pub struct PredictArgs {
    /// The photo: PNG or JPEG (8 or 16 bits, grey or colour) or a linear
    /// EXR, any size and aspect (centre-cropped to a square).
    pub photo: PathBuf,
    /// The bundle folder to write (gt_image, albedoPred, normalPred,
    /// roughnessPred, metallicPred, depth.exr or depthPred.exr,
    /// prediction.json).
    #[arg(long)]
    pub out: PathBuf,
    /// An ONNX model under MatNet's contract (default: the bundled one).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// tract (built in) or onnxruntime (ORT_DYLIB_PATH or the Python
    /// wheel's library).
    #[arg(long, default_value = "tract")]
    pub backend: String,
    /// Cache folder (as for `run`).
    #[arg(long)]
    pub cache: Option<PathBuf>,
    /// Write the run's JSON report here.
    #[arg(long)]
    pub report: Option<PathBuf>,
    /// No progress bars.
    #[arg(long)]
    pub quiet: bool,
}

const PIPELINE: &str =
    "pipeline: predict\noutputs: [matnet]\nstages:\n  matnet:\n    kind: matnet\n";

fn set(name: &str, v: &Path) -> Override {
    Override {
        stage: "matnet".into(),
        param: name.into(),
        value: Value::Str(v.display().to_string()),
        text: format!("matnet.{name}={}", v.display()),
    }
}

pub fn predict(a: PredictArgs) -> Result<()> {
    let reg = matflow_nodes::registry();
    let mut o = vec![set("photo", &a.photo), set("output", &a.out)];
    if let Some(m) = &a.model {
        o.push(set("model", m));
    }
    o.push(Override {
        stage: "matnet".into(),
        param: "backend".into(),
        value: Value::Str(a.backend.clone()),
        text: format!("matnet.backend={}", a.backend),
    });
    // Relative paths resolve against the current folder.
    let here = Path::new("(matflow predict)");
    let p = match spec::parse(PIPELINE, here, &reg, &o) {
        Ok(p) => p,
        Err(e) => bail!("{}", e.message),
    };
    crate::run::execute(
        &p,
        reg,
        &crate::run::Execution {
            cache: a.cache.as_deref(),
            remote: &crate::cluster::RemoteArgs::default(),
            parallel: 1,
            quiet: a.quiet,
            report: a.report.as_deref(),
            label: &a.photo.display().to_string(),
        },
    )
    .map(|_| ())
}
