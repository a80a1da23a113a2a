//! Fine-tuning splats ([`SplatTuner`]): the runtime's [`Adam`] over each kind of parameter, as 3D Gaussian
//! splatting optimizes them — centers and colors as they are, opacities through their logit, scales through
//! their logarithm, rotations as quaternions renormalized after each step, spherical harmonics (where the
//! splats have them) as they are. Colors are kept in [0, 1].

use rayon::prelude::*;

use super::gradients::SplatGradients;
use super::Splats;
use crate::error::{Error, Result};
use crate::training::optim::Adam;

/// Opacities are kept this far inside (0, 1), where their logit is finite.
const OPACITY_MARGIN: f32 = 1e-6;

/// Adam's ε: the splats' gradients are means over a frame's pixels, as small as 1e-12 for a splat few
/// pixels see, which the default (1e-8) would hold still (3D Gaussian splatting uses 1e-15 too).
const EPSILON: f32 = 1e-15;

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
    /// Degree-one spherical harmonics' coefficients.
    pub sh: f32,
}

/// Adam's state for every parameter of a set of splats, one optimizer per kind.
pub struct SplatTuner {
    /// The step sizes at a rate factor of 1.
    pub rates: TuneRates,
    positions: Adam,
    colors: Adam,
    opacities: Adam,
    scales: Adam,
    rotations: Adam,
    sh: Adam,
}

impl SplatTuner {
    /// A tuner for `count` splats.
    pub fn new(count: usize, rates: TuneRates) -> SplatTuner {
        let adam = |per_splat: usize| {
            let mut adam = Adam::new(count * per_splat, 0.0);
            adam.eps = EPSILON;
            adam
        };
        SplatTuner {
            rates,
            positions: adam(3),
            colors: adam(3),
            opacities: adam(1),
            scales: adam(3),
            rotations: adam(4),
            sh: adam(9),
        }
    }

    /// Keeps the state of splat `i` where `keep[i]`, as [`Splats::retain`] keeps the splats (so that
    /// tuning goes on where it was for those left).
    pub fn retain(&mut self, keep: &[bool]) -> Result<()> {
        for (adam, per_splat) in [
            (&mut self.positions, 3),
            (&mut self.colors, 3),
            (&mut self.opacities, 1),
            (&mut self.scales, 3),
            (&mut self.rotations, 4),
            (&mut self.sh, 9),
        ] {
            let (m, v) = adam.moments();
            let kept = |values: &[f32]| -> Vec<f32> {
                values
                    .chunks(per_splat)
                    .zip(keep.iter().chain(std::iter::repeat(&true)))
                    .filter(|(_, &keep)| keep)
                    .flat_map(|(chunk, _)| chunk.iter().copied())
                    .collect()
            };
            let (m, v) = (kept(m), kept(v));
            let mut kept = Adam::from_moments(adam.lr, adam.steps(), m, v)?;
            kept.eps = adam.eps;
            *adam = kept;
        }
        Ok(())
    }

    /// One Adam step of `splats` down `gradients` (with respect to the splats' own parameters, as
    /// [`splat_loss_gradients`](super::splat_loss_gradients) gives them), every rate times `factor`.
    pub fn step(&mut self, splats: &mut Splats, gradients: &SplatGradients, factor: f32) -> Result<()> {
        let n = splats.len();
        if self.opacities.moments().0.len() != n || gradients.positions.len() != n {
            return Err(Error::Invalid(format!(
                "the tuner holds {} splats, the scene {n}, the gradients {}",
                self.opacities.moments().0.len(),
                gradients.positions.len()
            )));
        }
        let r = self.rates;
        let same = |x: [f32; 3]| x;
        step_kind(
            &mut self.positions,
            r.position * factor,
            &mut splats.positions,
            &gradients.positions,
            Raw {
                raw: same,
                gradient: |_, g| g,
                back: same,
            },
        )?;
        step_kind(
            &mut self.colors,
            r.color * factor,
            &mut splats.colors,
            &gradients.colors,
            Raw {
                raw: same,
                gradient: |_, g| g,
                back: |c: [f32; 3]| c.map(|x| x.clamp(0.0, 1.0)),
            },
        )?;
        step_kind(
            &mut self.scales,
            r.scale * factor,
            &mut splats.scales,
            &gradients.scales,
            Raw {
                raw: |s: [f32; 3]| s.map(f32::ln),
                gradient: |s: [f32; 3], g: [f32; 3]| std::array::from_fn(|k| g[k] * s[k]),
                back: |l: [f32; 3]| l.map(|x| x.exp().max(f32::MIN_POSITIVE)),
            },
        )?;
        step_kind(
            &mut self.rotations,
            r.rotation * factor,
            &mut splats.rotations,
            &gradients.rotations,
            Raw {
                raw: |q: [f32; 4]| q,
                gradient: |_, g| g,
                back: |q: [f32; 4]| {
                    let length = glam::Vec4::from(q).length();
                    match length.is_finite() && length > 0.0 {
                        true => q.map(|x| x / length),
                        false => [1.0, 0.0, 0.0, 0.0],
                    }
                },
            },
        )?;
        if !splats.sh.is_empty() {
            if gradients.sh.len() != n {
                return Err(Error::Invalid(format!(
                    "{n} splats with spherical harmonics but {} gradients of them",
                    gradients.sh.len()
                )));
            }
            // Moved as they are: Adam on their numbers in place.
            self.sh.lr = r.sh * factor;
            self.sh.step(
                splats.sh.as_flattened_mut().as_flattened_mut(),
                gradients.sh.as_flattened().as_flattened(),
            )?;
        }
        let mut opacities: Vec<[f32; 1]> = splats.opacities.iter().map(|&o| [o]).collect();
        let opacity_gradients: Vec<[f32; 1]> = gradients.opacities.iter().map(|&g| [g]).collect();
        let inside = |o: f32| o.clamp(OPACITY_MARGIN, 1.0 - OPACITY_MARGIN);
        step_kind(
            &mut self.opacities,
            r.opacity * factor,
            &mut opacities,
            &opacity_gradients,
            Raw {
                raw: |[o]: [f32; 1]| [(inside(o) / (1.0 - inside(o))).ln()],
                gradient: |[o]: [f32; 1], [g]: [f32; 1]| [g * inside(o) * (1.0 - inside(o))],
                back: |[l]: [f32; 1]| [(1.0 / (1.0 + (-l).exp())).clamp(0.0, 1.0)],
            },
        )?;
        for (o, [new]) in splats.opacities.iter_mut().zip(opacities) {
            *o = new;
        }
        Ok(())
    }
}

/// How a kind of parameter is optimized: the value Adam moves (`raw`), the gradient with respect to it given
/// the value and the gradient with respect to the value (`gradient`), and the value it stands for (`back`).
struct Raw<R, G, B> {
    raw: R,
    gradient: G,
    back: B,
}

/// One step of `adam` at rate `lr` over `values` (`K` numbers a splat) down `gradients`, as `how` says.
fn step_kind<const K: usize, R, G, B>(
    adam: &mut Adam,
    lr: f32,
    values: &mut [[f32; K]],
    gradients: &[[f32; K]],
    how: Raw<R, G, B>,
) -> Result<()>
where
    R: Fn([f32; K]) -> [f32; K] + Sync,
    G: Fn([f32; K], [f32; K]) -> [f32; K] + Sync,
    B: Fn([f32; K]) -> [f32; K] + Sync,
{
    let mut raw: Vec<f32> = values.par_iter().flat_map_iter(|&v| (how.raw)(v)).collect();
    let raw_gradients: Vec<f32> = values
        .par_iter()
        .zip(gradients)
        .flat_map_iter(|(&v, &g)| (how.gradient)(v, g))
        .collect();
    adam.lr = lr;
    adam.step(&mut raw, &raw_gradients)?;
    values
        .par_iter_mut()
        .zip(raw.par_chunks_exact(K))
        .for_each(|(v, new)| *v = (how.back)(std::array::from_fn(|k| new[k])));
    Ok(())
}
