//! Optimisers and stopping rules shared by the envmap and material stages.

use rayon::prelude::*;

/// Adam (Kingma & Ba) on a flat parameter vector. Element-wise, so the
/// result does not depend on how the work is split across threads.
#[derive(Clone, Debug)]
pub struct Adam {
    pub lr: f32,
    pub beta1: f32,
    pub beta2: f32,
    pub eps: f32,
    /// Decoupled weight decay (AdamW); 0 for plain Adam.
    pub weight_decay: f32,
    m: Vec<f32>,
    v: Vec<f32>,
    t: i32,
}

impl Adam {
    pub fn new(n: usize, lr: f32) -> Adam {
        Adam {
            lr,
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
            weight_decay: 0.0,
            m: vec![0.0; n],
            v: vec![0.0; n],
            t: 0,
        }
    }

    /// One update; non-finite gradient entries are treated as zero.
    pub fn step(&mut self, params: &mut [f32], grad: &[f32]) {
        assert_eq!(params.len(), grad.len());
        assert_eq!(params.len(), self.m.len());
        self.t += 1;
        let (b1, b2) = (self.beta1, self.beta2);
        let c1 = 1.0 / (1.0 - b1.powi(self.t));
        let c2 = 1.0 / (1.0 - b2.powi(self.t));
        let (lr, eps, wd) = (self.lr, self.eps, self.weight_decay);
        params
            .par_chunks_mut(8192)
            .zip(grad.par_chunks(8192))
            .zip(self.m.par_chunks_mut(8192).zip(self.v.par_chunks_mut(8192)))
            .for_each(|((p, g), (m, v))| {
                for i in 0..p.len() {
                    let gi = if g[i].is_finite() { g[i] } else { 0.0 };
                    m[i] = b1 * m[i] + (1.0 - b1) * gi;
                    v[i] = b2 * v[i] + (1.0 - b2) * gi * gi;
                    let mh = m[i] * c1;
                    let vh = v[i] * c2;
                    p[i] -= lr * (mh / (vh.sqrt() + eps) + wd * p[i]);
                }
            });
    }
}

/// The paper's early-stopping rule: stop once the loss has fallen by less
/// than `min_drop` (5 %) over the last `window` (20) steps.
#[derive(Clone, Debug)]
pub struct EarlyStop {
    pub window: usize,
    pub min_drop: f64,
    history: Vec<f64>,
}

impl EarlyStop {
    pub fn paper() -> EarlyStop {
        EarlyStop {
            window: 20,
            min_drop: 0.05,
            history: Vec::new(),
        }
    }

    /// Records a loss; true when optimisation should stop.
    pub fn update(&mut self, loss: f64) -> bool {
        self.history.push(loss);
        let n = self.history.len();
        if n <= self.window {
            return false;
        }
        let old = self.history[n - 1 - self.window];
        !(loss < old * (1.0 - self.min_drop))
    }
}

/// The reference's `EarlyStopping`: stop after `patience` steps without a
/// relative improvement of `min_delta` over the best loss so far.
#[derive(Clone, Debug)]
pub struct Patience {
    pub patience: usize,
    pub min_delta: f64,
    best: f64,
    counter: usize,
}

impl Patience {
    pub fn new(patience: usize, min_delta: f64) -> Patience {
        Patience {
            patience,
            min_delta,
            best: f64::NAN,
            counter: 0,
        }
    }

    /// Records a loss; true when optimisation should stop. A NaN loss
    /// never counts as an improvement.
    pub fn update(&mut self, loss: f64) -> bool {
        if self.best.is_nan() && loss.is_finite() {
            self.best = loss;
        } else if loss.is_finite() && loss <= self.best * (1.0 - self.min_delta) {
            self.best = loss;
            self.counter = 0;
        } else {
            self.counter += 1;
        }
        self.counter >= self.patience
    }
}

/// StepLR: multiply the learning rate by `gamma` every `step_size` steps.
pub fn step_lr(base: f32, step: usize, step_size: usize, gamma: f32) -> f32 {
    base * gamma.powi((step / step_size.max(1)) as i32)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn adam_minimises_a_quadratic() {
        let mut p = vec![3.0f32, -2.0, 0.5];
        let mut opt = Adam::new(3, 0.1);
        for _ in 0..500 {
            let g: Vec<f32> = p.iter().map(|x| 2.0 * (x - 1.0)).collect();
            opt.step(&mut p, &g);
        }
        for x in p {
            assert!((x - 1.0).abs() < 1e-2, "{x}");
        }
    }

    #[test]
    fn patience_follows_the_reference_rule() {
        let mut p = Patience::new(3, 0.01);
        assert!(!p.update(1.0));
        // 0.995 is not 1 % better than 1.0: counts.
        assert!(!p.update(0.995));
        assert!(!p.update(0.98)); // improvement, resets
        assert!(!p.update(0.975));
        assert!(!p.update(0.975));
        assert!(p.update(0.975));
        let mut p = Patience::new(2, 0.01);
        p.update(1.0);
        assert!(!p.update(f64::NAN));
        assert!(p.update(f64::NAN));
    }

    #[test]
    fn early_stop_follows_the_five_percent_rule() {
        let mut e = EarlyStop::paper();
        // Falling 1 % per step: never stops.
        let mut l = 1.0;
        for _ in 0..100 {
            assert!(!e.update(l));
            l *= 0.99;
        }
        // Flat: stops once 20 flat steps have been seen.
        let mut e = EarlyStop::paper();
        let mut stopped_at = None;
        for i in 0..100 {
            if e.update(1.0) {
                stopped_at = Some(i);
                break;
            }
        }
        assert_eq!(stopped_at, Some(20));
        // NaN stops at once after the window.
        let mut e = EarlyStop::paper();
        for _ in 0..20 {
            e.update(1.0);
        }
        assert!(e.update(f64::NAN));
    }
}
