//! Adam over splats' parameters ([`SplatTuner`]): centers and colors as they are, opacities through their
//! logit, scales through their logarithm and rotations as quaternions renormalized after each step, as 3D
//! Gaussian splatting optimizes them. Colors are kept in [0, 1].

use rayon::prelude::*;

use super::gradients::SplatGradients;
use super::Splats;
use crate::error::{Error, Result};

/// Parameters a splat has, as optimized: center 3, color 3, opacity logit 1, log scales 3, rotation 4.
const PER_SPLAT: usize = 14;

/// Opacities are kept this far inside (0, 1), where their logit is finite.
const OPACITY_MARGIN: f32 = 1e-6;

/// Learning rates of each kind of parameter (Adam's step sizes).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TuneRates {
    /// Centers, in scene units.
    pub position: f32,
    /// Colors.
    pub color: f32,
    /// Opacities' logits.
    pub opacity: f32,
    /// Scales' logarithms.
    pub scale: f32,
    /// Quaternions' components.
    pub rotation: f32,
}

/// Adam's moments for every parameter of a set of splats.
pub struct SplatTuner {
    /// The step sizes at a rate factor of 1.
    pub rates: TuneRates,
    first: Vec<f32>,
    second: Vec<f32>,
    steps: i32,
}

impl SplatTuner {
    /// A tuner for `count` splats.
    pub fn new(count: usize, rates: TuneRates) -> SplatTuner {
        SplatTuner {
            rates,
            first: vec![0.0; count * PER_SPLAT],
            second: vec![0.0; count * PER_SPLAT],
            steps: 0,
        }
    }

    /// One Adam step of `splats` down `gradients` (with respect to the splats' own parameters, as
    /// [`splat_loss_gradients`](super::splat_loss_gradients) gives them), every rate times `factor`.
    pub fn step(&mut self, splats: &mut Splats, gradients: &SplatGradients, factor: f32) -> Result<()> {
        let n = splats.len();
        if self.first.len() != n * PER_SPLAT || gradients.positions.len() != n {
            return Err(Error::Invalid(format!(
                "the tuner holds {} splats, the scene {n}, the gradients {}",
                self.first.len() / PER_SPLAT,
                gradients.positions.len()
            )));
        }
        self.steps += 1;
        let (beta1, beta2, epsilon) = (0.9f32, 0.999f32, 1e-15f32);
        let correct1 = 1.0 - beta1.powi(self.steps);
        let correct2 = 1.0 - beta2.powi(self.steps);
        let r = self.rates;
        let rates: [f32; PER_SPLAT] = std::array::from_fn(|k| {
            factor
                * match k {
                    0..=2 => r.position,
                    3..=5 => r.color,
                    6 => r.opacity,
                    7..=9 => r.scale,
                    _ => r.rotation,
                }
        });
        let Splats {
            positions,
            colors,
            opacities,
            scales,
            rotations,
        } = splats;
        positions
            .par_iter_mut()
            .zip(colors.par_iter_mut())
            .zip(opacities.par_iter_mut())
            .zip(scales.par_iter_mut())
            .zip(rotations.par_iter_mut())
            .zip(self.first.par_chunks_mut(PER_SPLAT))
            .zip(self.second.par_chunks_mut(PER_SPLAT))
            .enumerate()
            .for_each(
                |(i, ((((((position, color), opacity), scale), rotation), m), v))| {
                    let o = opacity.clamp(OPACITY_MARGIN, 1.0 - OPACITY_MARGIN);
                    let mut params = [0.0f32; PER_SPLAT];
                    let mut grads = [0.0f32; PER_SPLAT];
                    params[0..3].copy_from_slice(position);
                    grads[0..3].copy_from_slice(&gradients.positions[i]);
                    params[3..6].copy_from_slice(color);
                    grads[3..6].copy_from_slice(&gradients.colors[i]);
                    params[6] = (o / (1.0 - o)).ln();
                    grads[6] = gradients.opacities[i] * o * (1.0 - o);
                    for k in 0..3 {
                        params[7 + k] = scale[k].ln();
                        grads[7 + k] = gradients.scales[i][k] * scale[k];
                    }
                    params[10..14].copy_from_slice(rotation);
                    grads[10..14].copy_from_slice(&gradients.rotations[i]);
                    for k in 0..PER_SPLAT {
                        let g = if grads[k].is_finite() { grads[k] } else { 0.0 };
                        m[k] = beta1 * m[k] + (1.0 - beta1) * g;
                        v[k] = beta2 * v[k] + (1.0 - beta2) * g * g;
                        let step = (m[k] / correct1) / ((v[k] / correct2).sqrt() + epsilon);
                        params[k] -= rates[k] * step;
                    }
                    position.copy_from_slice(&params[0..3]);
                    *color = std::array::from_fn(|k| params[3 + k].clamp(0.0, 1.0));
                    *opacity = (1.0 / (1.0 + (-params[6]).exp())).clamp(0.0, 1.0);
                    *scale = std::array::from_fn(|k| params[7 + k].exp().max(f32::MIN_POSITIVE));
                    let q = glam::Vec4::from_slice(&params[10..14]);
                    let length = q.length();
                    *rotation = match length.is_finite() && length > 0.0 {
                        true => (q / length).to_array(),
                        false => [1.0, 0.0, 0.0, 0.0],
                    };
                },
            );
        Ok(())
    }
}
