//! Optimization: the Adam optimizer and learning-rate schedules.

use rayon::prelude::*;

use crate::error::{Error, Result};

/// Adam (Kingma & Ba) with bias correction, as `torch.optim.Adam` without weight decay:
/// m ← β1·m + (1−β1)·g, v ← β2·v + (1−β2)·g², θ ← θ − lr·m̂/(√v̂ + ε) with
/// m̂ = m/(1−β1ᵗ), v̂ = v/(1−β2ᵗ).
#[derive(Debug, Clone, PartialEq)]
pub struct Adam {
    /// Learning rate (set it from a [`Schedule`] before each step if it varies).
    pub lr: f32,
    /// Decay of the first moment.
    pub beta1: f32,
    /// Decay of the second moment.
    pub beta2: f32,
    /// Added to √v̂ in the denominator.
    pub eps: f32,
    steps: u32,
    m: Vec<f32>,
    v: Vec<f32>,
}

impl Adam {
    /// Adam for `n_params` parameters with learning rate `lr`, β1 0.9, β2 0.999, ε 1e-8.
    pub fn new(n_params: usize, lr: f32) -> Adam {
        Adam {
            lr,
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
            steps: 0,
            m: vec![0.0; n_params],
            v: vec![0.0; n_params],
        }
    }

    /// Number of steps taken.
    pub fn steps(&self) -> u32 {
        self.steps
    }

    /// Updates `params` by one step along the gradients `grads` (both of length `n_params`).
    pub fn step(&mut self, params: &mut [f32], grads: &[f32]) -> Result<()> {
        if params.len() != self.m.len() || grads.len() != self.m.len() {
            return Err(Error::Invalid(format!(
                "Adam for {} parameters got {} parameters and {} gradients",
                self.m.len(),
                params.len(),
                grads.len()
            )));
        }
        self.steps += 1;
        let t = self.steps as i32;
        let (b1, b2) = (self.beta1, self.beta2);
        let correction1 = 1.0 - b1.powi(t);
        let correction2 = 1.0 - b2.powi(t);
        let lr = self.lr;
        let eps = self.eps;
        // Element by element (the same result on any number of threads), in parallel blocks.
        const BLOCK: usize = 1 << 14;
        params
            .par_chunks_mut(BLOCK)
            .zip(grads.par_chunks(BLOCK))
            .zip(self.m.par_chunks_mut(BLOCK).zip(self.v.par_chunks_mut(BLOCK)))
            .for_each(|((params, grads), (m, v))| {
                for ((p, g), (m, v)) in params.iter_mut().zip(grads).zip(m.iter_mut().zip(v)) {
                    *m = b1 * *m + (1.0 - b1) * g;
                    *v = b2 * *v + (1.0 - b2) * g * g;
                    let m_hat = *m / correction1;
                    let v_hat = *v / correction2;
                    *p -= lr * m_hat / (v_hat.sqrt() + eps);
                }
            });
        Ok(())
    }

    /// The first and second moments, one of each per parameter.
    pub fn moments(&self) -> (&[f32], &[f32]) {
        (&self.m, &self.v)
    }

    /// An optimizer with learning rate `lr` (and the default β1, β2, ε) that has taken `steps` steps and
    /// holds the moments `m` and `v` (as [`Adam::moments`] gives them; of equal length).
    pub fn from_moments(lr: f32, steps: u32, m: Vec<f32>, v: Vec<f32>) -> Result<Adam> {
        if m.len() != v.len() {
            return Err(Error::Invalid(format!(
                "Adam moments of unequal lengths ({} and {})",
                m.len(),
                v.len()
            )));
        }
        Ok(Adam {
            steps,
            m,
            v,
            ..Adam::new(0, lr)
        })
    }

    /// The state for a checkpoint: `[steps, m…, v…]` (steps exact up to 2²⁴).
    pub fn state(&self) -> Vec<f32> {
        let mut state = Vec::with_capacity(1 + 2 * self.m.len());
        state.push(self.steps as f32);
        state.extend_from_slice(&self.m);
        state.extend_from_slice(&self.v);
        state
    }

    /// Restores the state written by [`Adam::state`] into an optimizer for `n_params`
    /// parameters with learning rate `lr` (and the default β1, β2, ε).
    pub fn from_state(n_params: usize, lr: f32, state: &[f32]) -> Result<Adam> {
        let steps = state.first().copied().unwrap_or(f32::NAN);
        let valid_steps = steps >= 0.0 && steps <= (1u32 << 24) as f32 && steps.fract() == 0.0;
        if state.len() != 1 + 2 * n_params || !valid_steps {
            return Err(Error::Invalid(format!(
                "Adam state of {} values does not hold a step count and 2×{n_params} moments",
                state.len()
            )));
        }
        Ok(Adam {
            steps: steps as u32,
            m: state[1..1 + n_params].to_vec(),
            v: state[1 + n_params..].to_vec(),
            ..Adam::new(n_params, lr)
        })
    }
}

/// A learning rate as a function of the step number (from 0).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Schedule {
    /// Always `lr`.
    Constant {
        /// The learning rate.
        lr: f32,
    },
    /// `lr·gamma^(step / steps_per_decay)`, decaying smoothly.
    Exponential {
        /// The learning rate at step 0.
        lr: f32,
        /// Factor per `steps_per_decay` steps.
        gamma: f32,
        /// Steps over which the rate is multiplied by `gamma` (> 0).
        steps_per_decay: u32,
    },
    /// `lr·factor^⌊step / every⌋`, in steps.
    Step {
        /// The learning rate at step 0.
        lr: f32,
        /// Factor applied every `every` steps.
        factor: f32,
        /// Steps between changes (> 0).
        every: u32,
    },
}

impl Schedule {
    /// Checks that the rates and factors are finite and positive and the periods non-zero.
    pub fn check(&self) -> Result<()> {
        let (lr, factor, period) = match *self {
            Schedule::Constant { lr } => (lr, 1.0, 1),
            Schedule::Exponential {
                lr,
                gamma,
                steps_per_decay,
            } => (lr, gamma, steps_per_decay),
            Schedule::Step { lr, factor, every } => (lr, factor, every),
        };
        let positive = |x: f32| x.is_finite() && x > 0.0;
        if !(positive(lr) && positive(factor) && period > 0) {
            return Err(Error::Invalid(format!(
                "learning-rate schedule {self:?} needs a finite positive rate and factor and a non-zero period"
            )));
        }
        Ok(())
    }

    /// The learning rate at `step`.
    pub fn lr(&self, step: u32) -> f32 {
        match *self {
            Schedule::Constant { lr } => lr,
            Schedule::Exponential {
                lr,
                gamma,
                steps_per_decay,
            } => lr * gamma.powf(step as f32 / steps_per_decay as f32),
            Schedule::Step { lr, factor, every } => lr * factor.powi((step / every.max(1)) as i32),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn first_step_moves_each_parameter_by_lr() {
        // With bias correction, m̂ = g and v̂ = g², so the first step is lr·sign(g).
        let mut adam = Adam::new(3, 0.1);
        let mut p = [1.0, 2.0, 3.0];
        adam.step(&mut p, &[0.5, -20.0, 0.0]).unwrap();
        assert!(
            (p[0] - 0.9).abs() < 1e-6 && (p[1] - 2.1).abs() < 1e-6 && p[2] == 3.0,
            "{p:?}"
        );
        assert_eq!(adam.steps(), 1);
    }

    #[test]
    fn adam_minimizes_an_ill_conditioned_quadratic() {
        // f(p) = Σ cᵢ(pᵢ − tᵢ)² with curvatures spanning 4 orders of magnitude.
        let (c, t) = ([100.0, 1.0, 0.01], [1.0, -2.0, 0.5]);
        let mut p = [0.0f32; 3];
        let mut adam = Adam::new(3, 0.05);
        let schedule = Schedule::Exponential {
            lr: 0.05,
            gamma: 0.1,
            steps_per_decay: 2000,
        };
        for step in 0..3000 {
            let g: Vec<f32> = (0..3).map(|i| 2.0 * c[i] * (p[i] - t[i])).collect();
            adam.lr = schedule.lr(step);
            adam.step(&mut p, &g).unwrap();
        }
        for i in 0..3 {
            assert!((p[i] - t[i]).abs() < 1e-2, "{p:?}");
        }
    }

    #[test]
    fn state_round_trips_and_continues_identically() {
        let mut a = Adam::new(2, 0.01);
        let mut p = [0.3, -0.7];
        for k in 0..5 {
            a.step(&mut p, &[k as f32, 1.0 - k as f32]).unwrap();
        }
        let state = a.state();
        assert_eq!(state.len(), 5);
        assert_eq!(state[0], 5.0);
        let mut b = Adam::from_state(2, 0.01, &state).unwrap();
        assert_eq!(a, b);
        let mut q = p;
        a.step(&mut p, &[0.2, 0.1]).unwrap();
        b.step(&mut q, &[0.2, 0.1]).unwrap();
        assert_eq!(p, q);
        assert!(Adam::from_state(3, 0.01, &state).is_err());
        assert!(Adam::from_state(2, 0.01, &[0.5, 0.0, 0.0, 0.0, 0.0]).is_err());
        assert!(Adam::from_state(0, 0.01, &[]).is_err());
        assert!(a.step(&mut [0.0; 3], &[0.0; 3]).is_err());
    }

    #[test]
    fn schedules_give_their_rates() {
        let close = |a: f32, b: f32| (a - b).abs() <= 1e-6 * b.abs();
        let c = Schedule::Constant { lr: 5e-4 };
        assert_eq!((c.lr(0), c.lr(100_000)), (5e-4, 5e-4));
        let e = Schedule::Exponential {
            lr: 0.1,
            gamma: 0.5,
            steps_per_decay: 100,
        };
        assert!(close(e.lr(0), 0.1) && close(e.lr(100), 0.05) && close(e.lr(300), 0.0125));
        assert!(close(e.lr(50), 0.1 * 0.5f32.sqrt()));
        let s = Schedule::Step {
            lr: 1.0,
            factor: 0.1,
            every: 10,
        };
        assert_eq!((s.lr(0), s.lr(9)), (1.0, 1.0));
        assert!(close(s.lr(10), 0.1) && close(s.lr(19), 0.1) && close(s.lr(25), 0.01));
        for good in [c, e, s] {
            assert!(good.check().is_ok());
        }
        let bad = [
            Schedule::Constant { lr: -1.0 },
            Schedule::Step {
                lr: 1.0,
                factor: 0.5,
                every: 0,
            },
            Schedule::Exponential {
                lr: 1.0,
                gamma: f32::NAN,
                steps_per_decay: 5,
            },
        ];
        for b in bad {
            assert!(b.check().is_err(), "{b:?}");
        }
    }
}
