//! Material route `mlp`: the paper's positional-encoding MLP ([`MatMlp`]),
//! AdamW on stratified minibatches of the tables, R+M then A.

use matflow_render::Material;

use super::{
    network_options, Entry, MatFitter, MatRoute, MatStage, MatStart, Network, PlanInputs,
    RouteOption, Settings,
};
use crate::loss::Target;
use crate::matfit::{MatFit, MatFitOptions, MatMlp, MatMlpOptions, Parts};
use crate::tables::PixelTable;

pub const ROUTE: Entry<dyn MatRoute> = Entry {
    name: "mlp",
    doc: "the paper's positional-encoding MLP (minibatched AdamW)",
    options: OPTIONS,
    build: |s| Box::new(Mlp::from_settings(s)),
};

const OPTIONS: &[RouteOption] = &network_options(
    "32",
    "hidden width (the reference: 256; a step costs ∝ width² per pixel on the CPU)",
    "0.001",
    "AdamW learning rate, ×0.8 every 100 steps (the reference: 3e-4)",
);

/// One step (forward, reverse, AdamW) per pixel. A loop's two stages
/// take about `steps` steps together (the R+M stage stops early, the
/// albedo stage rarely).
pub const STEP_PER_PIXEL: f64 = 1.9e-7;

pub struct Mlp {
    net: MatMlpOptions,
}

impl Mlp {
    fn from_settings(s: &Settings) -> Mlp {
        let n = Network::of(s, OPTIONS);
        Mlp {
            net: MatMlpOptions {
                lr: n.lr,
                width: n.width,
                depth: n.depth,
                multires: n.octaves,
                ..MatMlpOptions::default()
            },
        }
    }
}

impl MatRoute for Mlp {
    fn stages(&self) -> &'static [Parts] {
        &[Parts::RM, Parts::A]
    }
    /// The budget's steps, fewer when a loop would take more than half the
    /// budget (the reference's thousands do not fit a CPU minute).
    fn steps(&self, p: &PlanInputs) -> usize {
        p.steps
            .min((0.5 * p.available / (STEP_PER_PIXEL * p.pixels)) as usize)
            .max(20)
    }
    fn loop_seconds(&self, p: &PlanInputs, tables: f64, steps: usize, _warm: bool) -> f64 {
        tables + STEP_PER_PIXEL * p.pixels * steps as f64
    }
    fn start(&self, s: &MatStart) -> Box<dyn MatFitter> {
        let net = MatMlpOptions {
            seed: s.seed,
            ..self.net
        };
        Box::new(MlpFit {
            mlp: MatMlp::new(s.width, s.height, s.pred, &net),
            net,
        })
    }
}

struct MlpFit {
    mlp: MatMlp,
    net: MatMlpOptions,
}

impl MatFitter for MlpFit {
    fn fit(
        &mut self,
        tables: &[PixelTable],
        target: &Target,
        pred: &[Material],
        current: &[Material],
        stage: &MatStage,
        progress: &(dyn Fn(usize, f64) + Sync),
    ) -> MatFit {
        self.mlp.fit(
            tables,
            target,
            pred,
            current,
            &MatFitOptions {
                steps: stage.steps,
                lr: self.net.lr,
                delta: stage.delta,
                zeta: stage.zeta,
                parts: stage.parts,
                early_stop: stage.early_stop,
                rescale: stage.rescale,
            },
            &self.net,
            progress,
        )
    }
}
