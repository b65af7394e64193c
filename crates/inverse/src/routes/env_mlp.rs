//! Envmap route `mlp`: the paper's positional-encoding MLP with a Softplus
//! head ([`EnvMlp`]), Adam on the frozen transport.

use glam::Vec3;

use super::{
    network_options, Entry, EnvFitter, EnvRoute, EnvStage, EnvStart, Network, PlanInputs,
    RouteOption, Settings,
};
use crate::envfit::{EnvFitOptions, EnvMlp, EnvMlpOptions, EnvTransport, FitTrace};
use crate::loss::Target;

pub const ROUTE: Entry<dyn EnvRoute> = Entry {
    name: "mlp",
    doc: "the paper's positional-encoding MLP with a Softplus head",
    options: OPTIONS,
    build: |s| Box::new(Mlp::from_settings(s)),
};

const OPTIONS: &[RouteOption] = &network_options(
    "64",
    "hidden width (the reference: 256)",
    "0.001",
    "Adam learning rate, ×0.8 every 100 steps (the reference: 1e-3)",
);

/// One step of the network, per pixel the envmap stage sees; a stage
/// takes about half its steps before its stopping rule.
pub const STEP_PER_PIXEL: f64 = 2.4e-7;

pub struct Mlp {
    net: EnvMlpOptions,
}

impl Mlp {
    fn from_settings(s: &Settings) -> Mlp {
        let n = Network::of(s, OPTIONS);
        Mlp {
            net: EnvMlpOptions {
                lr: n.lr,
                width: n.width,
                depth: n.depth,
                multires: n.octaves,
                ..EnvMlpOptions::default()
            },
        }
    }
}

impl EnvRoute for Mlp {
    /// The budget's steps, fewer when the stages would take more than a
    /// tenth of the budget (the reference's thousands do not fit a CPU
    /// minute).
    fn steps(&self, p: &PlanInputs) -> usize {
        p.steps
            .min((0.1 * p.available / (0.5 * STEP_PER_PIXEL * p.env_pixels)) as usize)
            .max(20)
    }
    fn stage_seconds(&self, p: &PlanInputs, steps: usize) -> f64 {
        0.5 * STEP_PER_PIXEL * p.env_pixels * steps as f64
    }
    fn takes_start_envmap(&self) -> bool {
        false
    }
    fn start(&self, s: &EnvStart) -> Box<dyn EnvFitter> {
        Box::new(MlpFit {
            net: EnvMlp::new(
                s.width,
                s.height,
                s.exposure,
                &EnvMlpOptions {
                    seed: s.seed,
                    ..self.net
                },
            ),
            lr: self.net.lr,
        })
    }
}

struct MlpFit {
    net: EnvMlp,
    lr: f32,
}

impl EnvFitter for MlpFit {
    fn fit(
        &mut self,
        tr: &EnvTransport,
        target: &Target,
        _current: &[Vec3],
        stage: &EnvStage,
        progress: &(dyn Fn(usize, f64) + Sync),
    ) -> (Vec<Vec3>, FitTrace) {
        self.net.fit(
            tr,
            target,
            &EnvFitOptions {
                steps: stage.steps,
                lr: self.lr,
                early_stop: stage.early_stop,
                smooth: 0.0,
                lamp_sparsity: 0.0,
            },
            progress,
        )
    }
    fn rescale(&mut self, s: Vec3) {
        self.net.scale *= s;
    }
}
