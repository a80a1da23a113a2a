//! The per-view colour transforms of a `train` block with `appearance: true` (issue 52): one affine map
//! of colours per training view ([`nerfjit_runtime::volume::appearance`]), learnt beside the field with
//! Adam at the block's learning rate, so that photos of one capture may differ in exposure and white
//! balance. A step trains the transform of its view only; each view's Adam counts its own steps.
//!
//! The field's colours and the transforms can trade a common factor (a field twice as bright under
//! transforms that halve): a weak pull toward the identity ([`PULL`]) settles that, so that held-out
//! views, renders and scores, which use no transform, see colours on the training views' average look.

use nerfjit_runtime::volume::appearance::{ColorTransform, TRANSFORM_VALUES};
use nerfjit_runtime::Adam;

use crate::checkpoint::VIEW_STATE;
use crate::failure::{Failure, Result};
use crate::settings::values::AdamSettings;

/// The weight λ of the pull toward the identity, λ·‖values − identity‖² added to a step's loss for its
/// view's transform.
pub const PULL: f32 = 1e-3;

/// Every training view's colour transform and its optimizer.
pub struct Appearance {
    transforms: Vec<ColorTransform>,
    optimizers: Vec<Adam>,
}

impl Appearance {
    /// The identity for each of `views` views, optimized with the decay rates and ε of `settings`.
    pub fn new(views: usize, settings: AdamSettings) -> Appearance {
        let adam = configured(Adam::new(TRANSFORM_VALUES, 0.0), settings);
        Appearance {
            transforms: vec![ColorTransform::IDENTITY; views],
            optimizers: vec![adam; views],
        }
    }

    /// View `view`'s transform.
    pub fn of(&self, view: usize) -> ColorTransform {
        self.transforms[view]
    }

    /// One Adam step of view `view`'s transform at learning rate `lr` along `grads` (∂loss/∂values), plus
    /// the pull toward the identity; a transform that would become non-finite stops the run.
    pub fn step(&mut self, view: usize, grads: [f32; TRANSFORM_VALUES], lr: f32) -> Result<()> {
        let values = &mut self.transforms[view].0;
        let identity = ColorTransform::IDENTITY.0;
        let pulled: Vec<f32> = (0..TRANSFORM_VALUES)
            .map(|k| grads[k] + 2.0 * PULL * (values[k] - identity[k]))
            .collect();
        let adam = &mut self.optimizers[view];
        adam.lr = lr;
        match adam.step(values, &pulled) {
            Ok(0) => Ok(()),
            Ok(_) => Err(Failure::Message(format!(
                "training diverged: the colour transform of training view {view} would become non-finite"
            ))),
            Err(e) => Err(Failure::Message(e.to_string())),
        }
    }

    /// The state of every view for a checkpoint: [`VIEW_STATE`] floats a view, in the views' order.
    pub fn state(&self) -> Vec<f32> {
        let mut state = Vec::with_capacity(self.transforms.len() * VIEW_STATE);
        for (t, adam) in self.transforms.iter().zip(&self.optimizers) {
            state.extend_from_slice(&t.0);
            state.extend(adam.state());
        }
        state
    }

    /// Restores the state written by [`Appearance::state`] for `views` views.
    pub fn from_state(views: usize, state: &[f32], settings: AdamSettings) -> Result<Appearance> {
        if state.len() != views * VIEW_STATE {
            return Err(Failure::Message(format!(
                "the checkpoint's colour transforms hold {} floats, not {VIEW_STATE} for each of the {views} \
                 training views: it was written for other training data",
                state.len()
            )));
        }
        let mut appearance = Appearance::new(views, settings);
        for (view, saved) in state.chunks_exact(VIEW_STATE).enumerate() {
            let (values, adam) = saved.split_at(TRANSFORM_VALUES);
            appearance.transforms[view].0.copy_from_slice(values);
            let restored =
                Adam::from_state(TRANSFORM_VALUES, 0.0, adam).map_err(|e| Failure::Message(e.to_string()))?;
            appearance.optimizers[view] = configured(restored, settings);
        }
        Ok(appearance)
    }

    /// The transforms, for the run's summary: one list of 12 values (`A` row-major, then `b`) a view.
    pub fn summary(&self) -> serde_json::Value {
        self.transforms.iter().map(|t| t.0.to_vec()).collect()
    }
}

/// `adam` with the decay rates and ε of `settings`.
fn configured(mut adam: Adam, settings: AdamSettings) -> Adam {
    adam.beta1 = settings.beta1;
    adam.beta2 = settings.beta2;
    adam.eps = settings.eps;
    adam
}

#[cfg(test)]
mod tests {
    use super::*;

    fn settings() -> AdamSettings {
        AdamSettings {
            beta1: 0.9,
            beta2: 0.99,
            eps: 1e-15,
            sparse: false,
        }
    }

    #[test]
    fn a_view_learns_its_gain_and_the_others_stay_the_identity() {
        let mut a = Appearance::new(3, settings());
        // The loss ‖A·c − 0.5·c‖² of a grey c = (1, 1, 1): view 1's photos are half as bright.
        for _ in 0..2000 {
            let t = a.of(1).0;
            let mut grads = [0.0; TRANSFORM_VALUES];
            for i in 0..3 {
                let error = t[3 * i] + t[3 * i + 1] + t[3 * i + 2] + t[9 + i] - 0.5;
                for j in 0..3 {
                    grads[3 * i + j] = 2.0 * error;
                }
                grads[9 + i] = 2.0 * error;
            }
            a.step(1, grads, 1e-3).unwrap();
        }
        let t = a.of(1).0;
        for i in 0..3 {
            let gain = t[3 * i] + t[3 * i + 1] + t[3 * i + 2] + t[9 + i];
            assert!((gain - 0.5).abs() < 0.01, "row {i}: {gain}");
        }
        assert_eq!(
            (a.of(0), a.of(2)),
            (ColorTransform::IDENTITY, ColorTransform::IDENTITY)
        );
        // A checkpoint's state gives the same transforms and the same next step.
        let mut b = Appearance::from_state(3, &a.state(), settings()).unwrap();
        assert_eq!(b.state(), a.state());
        let g = [0.1; TRANSFORM_VALUES];
        a.step(1, g, 1e-3).unwrap();
        b.step(1, g, 1e-3).unwrap();
        assert_eq!(a.of(1), b.of(1));
        assert!(Appearance::from_state(4, &a.state(), settings()).is_err());
    }
}
