//! Optimization: the Adam optimizer and learning-rate schedules.

use std::ops::Range;

use rayon::prelude::*;

use crate::error::{Error, Result};

/// Adam (Kingma & Ba) with bias correction, as `torch.optim.Adam` without weight decay:
/// m ← β1·m + (1−β1)·g, v ← β2·v + (1−β2)·g², θ ← θ − lr·m̂/(√v̂ + ε) with
/// m̂ = m/(1−β1ᵗ), v̂ = v/(1−β2ᵗ).
///
/// Params in the [`Adam::sparse`] ranges (grid tables) are updated as `torch.optim.SparseAdam` updates
/// them: an entry whose gradient is exactly 0 in a step keeps its moments and its value (the step count
/// t of the bias correction is the optimizer's, as in PyTorch); instant-ngp's optimizer also leaves
/// untouched table entries alone.
///
/// An element whose gradient or updated value is not finite keeps its value and moments, and
/// [`Adam::step`] counts it: training checks the step's outcome in the update's own pass over the params
/// rather than in passes of its own.
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
    /// Disjoint ranges of params updated only where their gradient is non-zero (empty: none).
    pub sparse: Vec<Range<usize>>,
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
            sparse: Vec::new(),
            steps: 0,
            m: vec![0.0; n_params],
            v: vec![0.0; n_params],
        }
    }

    /// Number of steps taken.
    pub fn steps(&self) -> u32 {
        self.steps
    }

    /// Updates `params` by one step along the gradients `grads` (both of length `n_params`); returns the
    /// number of elements left as they were because their gradient or updated value is not finite.
    pub fn step(&mut self, params: &mut [f32], grads: &[f32]) -> Result<usize> {
        if params.len() != self.m.len() || grads.len() != self.m.len() {
            return Err(Error::Invalid(format!(
                "Adam for {} parameters got {} parameters and {} gradients",
                self.m.len(),
                params.len(),
                grads.len()
            )));
        }
        let mut sparse = self.sparse.clone();
        sparse.sort_by_key(|r| r.start);
        let disjoint = sparse.windows(2).all(|w| w[0].end <= w[1].start);
        if !disjoint || sparse.iter().any(|r| r.start > r.end || r.end > params.len()) {
            return Err(Error::Invalid(format!(
                "Adam's sparse ranges {:?} are not disjoint ranges of its {} parameters",
                self.sparse,
                params.len()
            )));
        }
        self.steps += 1;
        let t = self.steps as i32;
        let update = Update {
            b1: self.beta1,
            b2: self.beta2,
            correction1: 1.0 - self.beta1.powi(t),
            correction2: 1.0 - self.beta2.powi(t),
            lr: self.lr,
            eps: self.eps,
        };
        // Each stretch of dense params before a sparse range, then that range; the empty range at the end
        // closes the last dense stretch.
        let (mut start, mut rejected) = (0, 0);
        for range in sparse
            .iter()
            .cloned()
            .chain(std::iter::once(params.len()..params.len()))
        {
            let dense = start..range.start;
            rejected += update.run(params, grads, &mut self.m, &mut self.v, dense, false);
            start = range.end;
            rejected += update.run(params, grads, &mut self.m, &mut self.v, range, true);
        }
        Ok(rejected)
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

/// The coefficients of one Adam step.
#[derive(Clone, Copy)]
struct Update {
    b1: f32,
    b2: f32,
    correction1: f32,
    correction2: f32,
    lr: f32,
    eps: f32,
}

impl Update {
    /// Updates the params in `range`, leaving those whose gradient is 0 as they are if `sparse`, and those
    /// whose gradient or updated value is not finite (returns their count). Element by element (the same
    /// result on any number of threads), in parallel blocks; without branches and with the coefficients
    /// copied into the closure, so that the loop vectorizes (a table of millions of entries is updated
    /// every step).
    fn run(
        &self,
        params: &mut [f32],
        grads: &[f32],
        m: &mut [f32],
        v: &mut [f32],
        range: Range<usize>,
        sparse: bool,
    ) -> usize {
        const BLOCK: usize = 1 << 14;
        let Update {
            b1,
            b2,
            correction1,
            correction2,
            lr,
            eps,
        } = *self;
        let r = range;
        params[r.clone()]
            .par_chunks_mut(BLOCK)
            .zip(grads[r.clone()].par_chunks(BLOCK))
            .zip(m[r.clone()].par_chunks_mut(BLOCK).zip(v[r].par_chunks_mut(BLOCK)))
            .map(move |((params, grads), (m, v))| {
                let mut rejected = 0u32;
                // The results of a stretch go to buffers of their own and are copied back after it: a
                // loop that stores `if keep { old } else { new }` over the old value compiles to masked
                // stores (`vmaskmovps`), which AMD's Zen cores run microcoded (on a Zen 3 on 2026-12-03,
                // Adam's time a sample in W8 halved without them).
                const STRETCH: usize = 64;
                let mut out = [[0.0f32; STRETCH]; 3];
                for ((params, grads), (m, v)) in params
                    .chunks_mut(STRETCH)
                    .zip(grads.chunks(STRETCH))
                    .zip(m.chunks_mut(STRETCH).zip(v.chunks_mut(STRETCH)))
                {
                    let [out_p, out_m, out_v] = &mut out;
                    let outs = out_p.iter_mut().zip(out_m.iter_mut().zip(out_v.iter_mut()));
                    let ins = params.iter().zip(grads).zip(m.iter().zip(v.iter()));
                    for (((&p, &g), (&m, &v)), (out_p, (out_m, out_v))) in ins.zip(outs) {
                        let m_new = b1 * m + (1.0 - b1) * g;
                        let v_new = b2 * v + (1.0 - b2) * g * g;
                        let m_hat = m_new / correction1;
                        let v_hat = v_new / correction2;
                        let p_new = p - lr * m_hat / (v_hat.sqrt() + eps);
                        let bad = !(g.is_finite() & p_new.is_finite());
                        rejected += u32::from(bad);
                        let keep = (sparse & (g == 0.0)) | bad;
                        *out_m = if keep { m } else { m_new };
                        *out_v = if keep { v } else { v_new };
                        *out_p = if keep { p } else { p_new };
                    }
                    let n = params.len();
                    params.copy_from_slice(&out[0][..n]);
                    m.copy_from_slice(&out[1][..n]);
                    v.copy_from_slice(&out[2][..n]);
                }
                rejected as usize
            })
            .sum()
    }
}

/// A learning rate as a function of the step number (from 0) or of the fraction of the run done.
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
    /// `lr·gamma^f`, `f` the fraction of the run done (0 at its start, 1 at its end): the rate reaches
    /// `lr·gamma` as the run ends, however many steps the machine takes in a time limit.
    ExponentialOverRun {
        /// The learning rate at the run's start.
        lr: f32,
        /// Factor over the whole run.
        gamma: f32,
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
            Schedule::ExponentialOverRun { lr, gamma } => (lr, gamma, 1),
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

    /// The learning rate at `step`, `fraction` of the run being done (clamped to [0, 1]; only
    /// [`Schedule::ExponentialOverRun`] reads it).
    pub fn lr(&self, step: u32, fraction: f64) -> f32 {
        match *self {
            Schedule::Constant { lr } => lr,
            Schedule::Exponential {
                lr,
                gamma,
                steps_per_decay,
            } => lr * gamma.powf(step as f32 / steps_per_decay as f32),
            Schedule::ExponentialOverRun { lr, gamma } => lr * gamma.powf(fraction.clamp(0.0, 1.0) as f32),
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

    /// Gradients of 6 params over 4 steps, some exactly 0 (and one -0).
    fn gradients(k: usize) -> [f32; 6] {
        let g = [0.5, 0.0, -1.5, 0.25, -0.0, 2.0];
        std::array::from_fn(|i| {
            if (i + k).is_multiple_of(3) {
                0.0
            } else {
                g[i] * (k as f32 + 1.0)
            }
        })
    }

    #[test]
    fn sparse_ranges_leave_untouched_entries_and_update_the_rest_as_dense_adam() {
        let mut dense = Adam::new(6, 0.1);
        let mut sparse = Adam {
            sparse: vec![4..6, 1..3],
            ..Adam::new(6, 0.1)
        };
        let (mut p_dense, mut p_sparse) = ([1.0f32; 6], [1.0f32; 6]);
        for k in 0..4 {
            let g = gradients(k);
            let (before, moments) = (p_sparse, (sparse.m.clone(), sparse.v.clone()));
            dense.step(&mut p_dense, &g).unwrap();
            sparse.step(&mut p_sparse, &g).unwrap();
            for i in 0..6 {
                let in_sparse = (1..3).contains(&i) || (4..6).contains(&i);
                if in_sparse && g[i] == 0.0 {
                    assert_eq!(p_sparse[i].to_bits(), before[i].to_bits(), "step {k}, param {i}");
                    assert_eq!((sparse.m[i], sparse.v[i]), (moments.0[i], moments.1[i]));
                } else if !in_sparse {
                    // Outside the sparse ranges: exactly dense Adam, zeros included.
                    assert_eq!(p_sparse[i].to_bits(), p_dense[i].to_bits(), "step {k}, param {i}");
                } else {
                    assert_ne!(p_sparse[i], before[i], "step {k}, param {i} moves");
                }
            }
        }
        // Param 2 (sparse, its gradient 0 at step 1 only) ends elsewhere than dense Adam takes it.
        assert_ne!(p_sparse[2].to_bits(), p_dense[2].to_bits());
    }

    #[test]
    fn sparse_ranges_without_zero_gradients_give_dense_adam_bit_for_bit() {
        let mut dense = Adam::new(5, 0.01);
        let mut sparse = Adam {
            sparse: vec![0..2, 3..5],
            ..Adam::new(5, 0.01)
        };
        let (mut a, mut b) = ([0.1f32, 0.2, 0.3, 0.4, 0.5], [0.1f32, 0.2, 0.3, 0.4, 0.5]);
        for k in 1..20 {
            let g: Vec<f32> = (0..5)
                .map(|i| (i as f32 + 1.0) * (k as f32).sin() + 0.01)
                .collect();
            dense.step(&mut a, &g).unwrap();
            sparse.step(&mut b, &g).unwrap();
        }
        assert_eq!(a.map(f32::to_bits), b.map(f32::to_bits));
    }

    #[test]
    fn overlapping_or_outside_sparse_ranges_are_refused() {
        for ranges in [
            vec![0..3, 2..4],
            vec![0..1, 3..7],
            vec![0..1, Range { start: 3, end: 2 }],
        ] {
            let mut adam = Adam {
                sparse: ranges.clone(),
                ..Adam::new(5, 0.01)
            };
            let mut p = [0.0f32; 5];
            let err = adam.step(&mut p, &[1.0; 5]).unwrap_err().to_string();
            assert!(err.contains("sparse ranges"), "{ranges:?}: {err}");
            assert_eq!(adam.steps(), 0);
        }
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
            adam.lr = schedule.lr(step, 0.0);
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
    fn elements_whose_gradient_or_new_value_is_not_finite_keep_their_state_and_are_counted() {
        for sparse in [false, true] {
            // A huge rate makes element 3's step overflow; elements 1 and 2 have non-finite gradients.
            let mut adam = Adam::new(5, 1e38);
            if sparse {
                adam.sparse = std::iter::once(0..5).collect();
            }
            adam.step(&mut [0.0; 5], &[1.0, 1.0, 1.0, 0.0, 1.0]).unwrap();
            let (m, v) = (adam.m.clone(), adam.v.clone());
            let mut p = [1.0, 2.0, 3.0, -3e38, 5.0];
            let before = p;
            let rejected = adam
                .step(&mut p, &[1e-30, f32::NAN, f32::INFINITY, 1.0, 0.0])
                .unwrap();
            assert_eq!(rejected, 3, "sparse {sparse}");
            assert!(p.iter().all(|x| x.is_finite()), "{p:?}");
            assert_eq!(&p[1..4], &before[1..4]);
            assert_eq!((&adam.m[1..4], &adam.v[1..4]), (&m[1..4], &v[1..4]));
            // The finite elements did step: element 0 on its gradient, element 4 on its moments unless
            // sparse (a zero gradient there keeps it).
            assert_ne!(p[0], before[0]);
            assert_eq!(p[4] == before[4], sparse);
        }
    }

    #[test]
    fn schedules_give_their_rates() {
        let close = |a: f32, b: f32| (a - b).abs() <= 1e-6 * b.abs();
        let c = Schedule::Constant { lr: 5e-4 };
        assert_eq!((c.lr(0, 0.0), c.lr(100_000, 1.0)), (5e-4, 5e-4));
        let e = Schedule::Exponential {
            lr: 0.1,
            gamma: 0.5,
            steps_per_decay: 100,
        };
        assert!(close(e.lr(0, 0.5), 0.1) && close(e.lr(100, 0.0), 0.05) && close(e.lr(300, 1.0), 0.0125));
        assert!(close(e.lr(50, 0.9), 0.1 * 0.5f32.sqrt()));
        let r = Schedule::ExponentialOverRun { lr: 0.1, gamma: 0.01 };
        assert!(close(r.lr(7, 0.0), 0.1) && close(r.lr(0, 0.5), 0.01) && close(r.lr(0, 1.0), 0.001));
        assert!(
            close(r.lr(0, -3.0), 0.1) && close(r.lr(0, 7.0), 0.001),
            "clamped to the run"
        );
        let s = Schedule::Step {
            lr: 1.0,
            factor: 0.1,
            every: 10,
        };
        assert_eq!((s.lr(0, 0.0), s.lr(9, 0.0)), (1.0, 1.0));
        assert!(close(s.lr(10, 0.0), 0.1) && close(s.lr(19, 0.0), 0.1) && close(s.lr(25, 0.0), 0.01));
        for good in [c, e, r, s] {
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
