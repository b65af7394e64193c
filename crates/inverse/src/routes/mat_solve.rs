//! Material route `solve`: per pixel, the exact minimiser of its loss on
//! the tables, A, R and M jointly ([`solve_pixels`]).

use matflow_render::Material;

use super::{
    Entry, MatFitter, MatRoute, MatStage, MatStart, OptionKind, PlanInputs, RouteOption, Settings,
};
use crate::loss::Target;
use crate::matfit::{MatFit, Parts};
use crate::solve::{solve_pixels, SolveOptions};
use crate::tables::PixelTable;

pub const ROUTE: Entry<dyn MatRoute> = Entry {
    name: "solve",
    doc: "per-pixel exact solves on the tables (fast)",
    options: OPTIONS,
    build: |s| Box::new(Solve::from_settings(s)),
};

const OPTIONS: &[RouteOption] = &[RouteOption {
    name: "rounds",
    kind: OptionKind::Int { min: 1, max: 64 },
    default: None,
    doc: "rounds of the per-pixel solve per material stage; default from the budget \
          (1 below 12 s, 2 below 30 s, else 3)",
}];

/// One round per pixel from a grid over (R, M): 3.6e-6 before pixels
/// were solved two at a time in one vector, which took a cold round
/// 0.80× and a warm one 0.89× (geometric means over jinjya and indoor at
/// 20 s of the trace log's round times, old and new binaries alternated
/// three times: jinjya 0.74× / 0.85×, indoor 0.87× / 0.94×).
pub const COLD_ROUND: f64 = 2.9e-6;
/// One round per pixel from the previous answer (compass search only):
/// 1.6e-6 before, see [`COLD_ROUND`].
pub const WARM_ROUND: f64 = 1.42e-6;

pub struct Solve {
    rounds: Option<usize>,
}

impl Solve {
    fn from_settings(s: &Settings) -> Solve {
        Solve {
            rounds: s.get("rounds").map(|v| v as usize),
        }
    }

    /// The route with rounds from the budget.
    pub fn budgeted() -> Solve {
        Solve { rounds: None }
    }

    /// Rounds per stage: set, or from the budget.
    pub fn rounds(&self, budget_seconds: f64) -> usize {
        let b = budget_seconds.max(1.0);
        self.rounds.unwrap_or(if b >= 30.0 {
            3
        } else if b >= 12.0 {
            2
        } else {
            1
        })
    }

    /// Seconds of one loop: the tables and the solve of every surface
    /// pixel.
    pub fn loop_seconds(&self, p: &PlanInputs, tables: f64, warm: bool) -> f64 {
        let rounds = self.rounds(p.budget_seconds);
        let per_pixel = if warm {
            WARM_ROUND * rounds as f64
        } else {
            COLD_ROUND + WARM_ROUND * (rounds - 1) as f64
        };
        tables + per_pixel * p.surface_fraction * p.pixels
    }
}

impl MatRoute for Solve {
    /// The solve searches A, R and M jointly.
    fn stages(&self) -> &'static [Parts] {
        &[Parts::ARM]
    }
    fn steps(&self, p: &PlanInputs) -> usize {
        p.steps
    }
    fn loop_seconds(&self, p: &PlanInputs, tables: f64, _steps: usize, warm: bool) -> f64 {
        Solve::loop_seconds(self, p, tables, warm)
    }
    fn start(&self, s: &MatStart) -> Box<dyn MatFitter> {
        Box::new(SolveFit {
            rounds: self.rounds(s.budget_seconds),
            min_roughness: resolvable_roughness(s.env_width, s.env_height),
        })
    }
}

/// The roughness whose reflection lobe (solid angle ≈ 4π·α², α = R²)
/// covers one average envmap texel (4π / (W·H)): R = (W·H)^(-1/4), 0.21
/// at 32×16. Sharper lobes see detail the envmap does not have, and their
/// per-pixel estimates rest on a few frozen directions, so the solve does
/// not go below it unless the prediction does.
pub fn resolvable_roughness(env_width: usize, env_height: usize) -> f32 {
    ((env_width * env_height).max(1) as f32).powf(-0.25)
}

struct SolveFit {
    rounds: usize,
    min_roughness: f32,
}

impl MatFitter for SolveFit {
    fn fit(
        &mut self,
        tables: &[PixelTable],
        target: &Target,
        pred: &[Material],
        current: &[Material],
        stage: &MatStage,
        progress: &(dyn Fn(usize, f64) + Sync),
    ) -> MatFit {
        solve_pixels(
            tables,
            target,
            pred,
            current,
            &SolveOptions {
                delta: stage.delta,
                zeta: stage.zeta,
                parts: stage.parts,
                rounds: self.rounds,
                rescale: stage.rescale,
                reference_weighting: true,
                min_roughness: self.min_roughness,
                warm: stage.loop_index > 0,
            },
            progress,
        )
    }
}
