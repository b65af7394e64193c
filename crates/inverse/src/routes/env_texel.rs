//! Envmap route `texel`: every texel (and channel) a free parameter in log
//! space, Adam on the frozen linear transport ([`fit_texels`]).

use glam::Vec3;

use super::{
    Entry, EnvFitter, EnvRoute, EnvStage, EnvStart, OptionKind, PlanInputs, RouteOption, Settings,
};
use crate::envfit::{fit_texels, EnvFitOptions, EnvTransport, FitTrace};
use crate::loss::Target;

pub const ROUTE: Entry<dyn EnvRoute> = Entry {
    name: "texel",
    doc: "free log-space texels, Adam on the frozen transport (fast)",
    options: OPTIONS,
    build: |s| Box::new(Texel::from_settings(s)),
};

const OPTIONS: &[RouteOption] = &[
    RouteOption {
        name: "smooth",
        kind: OptionKind::Float {
            min: 0.0,
            max: 100.0,
        },
        default: None,
        doc: "weight of the smoothness prior on log texels (mean squared log difference of \
              neighbouring texels); default 0.01 with trusted R/M, 0 for photos",
    },
    RouteOption {
        name: "lr",
        kind: OptionKind::Float {
            min: 1e-6,
            max: 10.0,
        },
        default: Some("0.05"),
        doc: "Adam learning rate on log radiance",
    },
];

/// The smoothness weight with trusted R/M (synthetic data), measured at
/// budget 60 (2-core machine; synthetic: means over seeds 1 and 2):
///
/// | setting | texel smoothing | loops | synthetic rerender / relight / envmap SSIM | indoor | jinjya |
/// |---|---|---|---|---|---|
/// | both off | 0 | 5–7 | 38.51 / 25.64 / 0.058 | 30.34 | 34.14 |
/// | smoothing | 0.01 | 5–7 | 38.98 / 25.73 / 0.182 | 29.40 | 34.16 |
/// | smoothing, 2 loops | 0.01 | 2 | 40.29 / 27.14 / 0.239 | — | — |
///
/// With photos the indoor "envmap" stands in for sharp interior lights
/// that smoothing blurs, so it is off there.
pub const SYNTHETIC_SMOOTH: f32 = 0.01;

/// One envmap stage per pixel (it stops early after a few dozen steps);
/// the orchestration's fixed cost includes two such stages. 1.7e-6
/// before each pixel's terms were merged per texel: its stages took
/// 0.76× on jinjya (30 cached paths) and 1.02× on indoor (12), 0.88× as
/// their geometric mean (median stage times, old and new binaries
/// alternated three times at 20 s).
pub const STAGE_PER_PIXEL: f64 = 1.5e-6;

pub struct Texel {
    smooth: Option<f32>,
    lr: f32,
}

impl Texel {
    fn from_settings(s: &Settings) -> Texel {
        Texel {
            smooth: s.get("smooth").map(|v| v as f32),
            lr: s.f32_or(OPTIONS, "lr", 0.05),
        }
    }
}

impl EnvRoute for Texel {
    fn steps(&self, p: &PlanInputs) -> usize {
        p.steps
    }
    fn stage_seconds(&self, p: &PlanInputs, _steps: usize) -> f64 {
        STAGE_PER_PIXEL * p.pixels
    }
    fn takes_start_envmap(&self) -> bool {
        true
    }
    fn fits_lamps(&self) -> bool {
        true
    }
    fn start(&self, s: &EnvStart) -> Box<dyn EnvFitter> {
        let smooth = self
            .smooth
            .unwrap_or(if s.trust_rm { SYNTHETIC_SMOOTH } else { 0.0 });
        Box::new(TexelFit {
            smooth,
            lr: self.lr,
        })
    }
}

struct TexelFit {
    smooth: f32,
    lr: f32,
}

impl EnvFitter for TexelFit {
    fn fit(
        &mut self,
        tr: &EnvTransport,
        target: &Target,
        current: &[Vec3],
        stage: &EnvStage,
        progress: &(dyn Fn(usize, f64) + Sync),
    ) -> (Vec<Vec3>, FitTrace) {
        fit_texels(
            tr,
            target,
            current,
            &EnvFitOptions {
                steps: stage.steps,
                lr: self.lr,
                early_stop: stage.early_stop,
                smooth: self.smooth,
                lamp_sparsity: stage.lamp_sparsity,
            },
            progress,
        )
    }
}
