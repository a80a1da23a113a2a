//! instant-ngp's running occupancy for training: per cell a decaying maximum of the density seen at
//! random points in it, refreshed every few steps, so that the grid follows the field as it trains
//! without probing every cell each time.
//!
//! The state starts as the field's density at one random point in every cell, as instant-ngp's first
//! updates sample every cell ([`DensityEma::sampled`], for training), or as [`OccupancyGrid::build`]'s
//! probe peaks ([`DensityEma::probe`], 27 points a cell, for a grid rendered once). Each
//! [`DensityEma::update`] multiplies every cell's value by `decay` and raises each of a random
//! `fraction` of the cells (drawn with replacement) to the field's first output at a uniform random
//! point inside it (NaN counts as +∞).
//! [`DensityEma::grid`] marks the cells whose value is above the threshold, or above the mean value
//! where that is lower (a faint field keeps its larger values occupied); unlike a rebuilt grid it is
//! not dilated: a cell empties only after no random point in it has been dense for many updates.

use rayon::prelude::*;

use super::build::{cell_peaks, check_grid, check_threshold, mean};
use super::OccupancyGrid;
use crate::error::{Error, Result};
use crate::field::BatchFn;
use crate::rng::Rng;
use crate::volume::composite::Mode;

/// Points per field call in an update.
const UPDATE_BATCH: usize = 8192;

/// The running per-cell density of a `resolution`³ grid over a box.
#[derive(Debug, Clone)]
pub struct DensityEma {
    bounds: ([f32; 3], [f32; 3]),
    resolution: usize,
    /// Cell x + y·res + z·res² at that index.
    values: Vec<f32>,
}

impl DensityEma {
    /// The first state: each cell's peak over the probes [`OccupancyGrid::build`] takes.
    pub fn probe(field: &dyn BatchFn, bounds: ([f32; 3], [f32; 3]), resolution: usize) -> Result<DensityEma> {
        Ok(DensityEma {
            bounds,
            resolution,
            values: cell_peaks(field, bounds, resolution)?,
        })
    }

    /// The first state from one uniform random point in every cell: 27 times cheaper than
    /// [`DensityEma::probe`], and what the updates refresh anyway.
    pub fn sampled(
        field: &dyn BatchFn,
        bounds: ([f32; 3], [f32; 3]),
        resolution: usize,
        rng: &mut Rng,
    ) -> Result<DensityEma> {
        check_grid(field, bounds, resolution)?;
        let n_cells = resolution.pow(3);
        let mut state = DensityEma {
            bounds,
            resolution,
            values: vec![0.0; n_cells],
        };
        state.raise(field, (0..n_cells).collect(), rng);
        Ok(state)
    }

    /// One update: every value decays by `decay` (in [0, 1]), then ⌈`fraction` · cells⌉ random cells
    /// (`fraction` in (0, 1]) take the maximum with `field` at a random point inside them.
    pub fn update(&mut self, field: &dyn BatchFn, decay: f32, fraction: f32, rng: &mut Rng) -> Result<()> {
        if !((0.0..=1.0).contains(&decay) && fraction > 0.0 && fraction <= 1.0) {
            return Err(Error::Invalid(format!(
                "an occupancy update needs a decay in [0, 1] and a fraction in (0, 1], got {decay} and {fraction}"
            )));
        }
        let n_cells = self.values.len();
        let n = ((fraction as f64 * n_cells as f64).ceil() as usize).min(n_cells);
        let mut cells: Vec<usize> = (0..n).map(|_| rng.below(n_cells as u64) as usize).collect();
        // In the grid's order, so that the points of a field call lie in a slab of cells and share the
        // encoding's table entries and cache lines (the maximum does not depend on the order).
        cells.sort_unstable();
        self.values.par_iter_mut().for_each(|v| *v *= decay);
        self.raise(field, cells, rng);
        Ok(())
    }

    /// Raises each of `cells` to the maximum of its value and `field` at a uniform random point in it.
    fn raise(&mut self, field: &dyn BatchFn, cells: Vec<usize>, rng: &mut Rng) {
        let res = self.resolution;
        let n = cells.len();
        let (lo, hi) = self.bounds;
        let size = [0, 1, 2].map(|a| (hi[a] - lo[a]) / res as f32);
        let mut points: [Vec<f32>; 3] = Default::default();
        for &cell in &cells {
            let at = [cell % res, cell / res % res, cell / (res * res)];
            for (a, column) in points.iter_mut().enumerate() {
                column.push(lo[a] + (at[a] as f32 + rng.next_f32()) * size[a]);
            }
        }
        let n_inputs = field.n_inputs();
        let mut seen = vec![0.0f32; n];
        seen.par_chunks_mut(UPDATE_BATCH)
            .enumerate()
            .for_each(|(c, seen)| {
                let span = c * UPDATE_BATCH..c * UPDATE_BATCH + seen.len();
                let mut inputs: Vec<&[f32]> = points.iter().map(|p| &p[span.clone()]).collect();
                // A field that takes a view direction is probed along +z, as in a rebuild.
                let (zeros, ones) = (vec![0.0f32; seen.len()], vec![1.0f32; seen.len()]);
                if n_inputs == 6 {
                    inputs.extend([&zeros[..], &zeros[..], &ones[..]]);
                }
                let mut outputs = vec![vec![0.0f32; seen.len()]; field.n_outputs()];
                let mut outs: Vec<&mut [f32]> = outputs.iter_mut().map(|v| &mut v[..]).collect();
                field.eval(seen.len(), &inputs, &mut outs);
                for (s, &v) in seen.iter_mut().zip(&outputs[0]) {
                    *s = if v.is_nan() { f32::INFINITY } else { v };
                }
            });
        for (&cell, &v) in cells.iter().zip(&seen) {
            self.values[cell] = self.values[cell].max(v);
        }
    }

    /// The grid of the cells whose value exceeds `threshold`, or the mean value where that is lower.
    pub fn grid(&self, mode: Mode, threshold: f32) -> Result<OccupancyGrid> {
        check_threshold(mode, threshold)?;
        let threshold = threshold.min(mean(&self.values));
        Ok(OccupancyGrid::from_cells(self.bounds, self.resolution, |i| {
            self.values[i] > threshold
        }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::ClosureFn;

    const UNIT: ([f32; 3], [f32; 3]) = ([-1.0; 3], [1.0; 3]);

    /// Density 10 inside a ball of `radius` around the origin, 0 outside.
    fn ball(radius: f32) -> ClosureFn<impl Fn(&[f32], &mut [f32]) + Sync> {
        ClosureFn::new(3, 1, move |p, out| {
            out[0] = if p[0] * p[0] + p[1] * p[1] + p[2] * p[2] < radius * radius {
                10.0
            } else {
                0.0
            }
        })
    }

    #[test]
    fn the_first_state_is_the_rebuilt_grid_without_dilation() {
        let field = ball(0.5);
        let ema = DensityEma::probe(&field, UNIT, 16).unwrap();
        let grid = ema.grid(Mode::Density, 1.0).unwrap();
        let rebuilt = OccupancyGrid::build(&field, UNIT, 16, Mode::Density, 1.0).unwrap();
        assert!(grid.occupied([0.0; 3]) && !grid.occupied([0.9, 0.9, 0.9]));
        // Every cell the EMA keeps, the dilated rebuild keeps too; the dilation adds a shell.
        let cells = |g: &OccupancyGrid| {
            (0..16 * 16 * 16)
                .filter(|&i| g.cell(i % 16, i / 16 % 16, i / 256))
                .collect::<Vec<_>>()
        };
        let (kept, dilated) = (cells(&grid), cells(&rebuilt));
        assert!(kept.iter().all(|c| dilated.contains(c)));
        assert!(kept.len() < dilated.len(), "{} vs {}", kept.len(), dilated.len());
    }

    #[test]
    fn a_sampled_first_state_keeps_the_cells_inside_and_drops_those_outside() {
        let field = ball(0.5);
        let ema = DensityEma::sampled(&field, UNIT, 16, &mut Rng::new(5)).unwrap();
        let grid = ema.grid(Mode::Density, 1.0).unwrap();
        let probed = DensityEma::probe(&field, UNIT, 16).unwrap();
        let probed = probed.grid(Mode::Density, 1.0).unwrap();
        let h = 1.0 / 16.0;
        for i in 0..16 * 16 * 16 {
            let at = [i % 16, i / 16 % 16, i / 256];
            let center = at.map(|c| -1.0 + (2 * c + 1) as f32 * h);
            // The cell's nearest and farthest distances from the origin.
            let near = center.map(|c| (c.abs() - h).max(0.0));
            let far = center.map(|c| c.abs() + h);
            let length = |v: [f32; 3]| v.iter().map(|x| x * x).sum::<f32>().sqrt();
            let sampled = grid.cell(at[0], at[1], at[2]);
            if length(far) < 0.5 {
                assert!(sampled, "cell {at:?} lies inside the ball");
            }
            if length(near) > 0.5 {
                assert!(!sampled, "cell {at:?} lies outside the ball");
            }
            // Where one point finds density, the 27 probes' peak does too.
            assert!(!sampled || probed.cell(at[0], at[1], at[2]), "cell {at:?}");
        }
        assert!(DensityEma::sampled(&field, UNIT, 0, &mut Rng::new(5)).is_err());
    }

    #[test]
    fn cells_empty_after_the_field_shrinks_and_fill_when_it_grows() {
        let mut rng = Rng::new(3);
        let mut ema = DensityEma::probe(&ball(0.8), UNIT, 8).unwrap();
        let grid = ema.grid(Mode::Density, 1.0).unwrap();
        // A point in the shell between radius 0.4 and 0.8.
        let shell = [0.6, 0.0, 0.0];
        assert!(grid.occupied(shell));
        // The field shrinks to radius 0.3: the shell's cells decay below the threshold (and below the
        // mean value, which the few dense cells keep near 0.2).
        for _ in 0..150 {
            ema.update(&ball(0.3), 0.95, 0.25, &mut rng).unwrap();
        }
        let grid = ema.grid(Mode::Density, 1.0).unwrap();
        assert!(!grid.occupied(shell) && grid.occupied([0.0; 3]));
        // It grows back: random points in the shell find the density again.
        for _ in 0..20 {
            ema.update(&ball(0.8), 0.95, 0.25, &mut rng).unwrap();
        }
        assert!(ema.grid(Mode::Density, 1.0).unwrap().occupied(shell));
    }

    #[test]
    fn bad_arguments_are_errors() {
        let field = ball(0.5);
        let mut ema = DensityEma::probe(&field, UNIT, 4).unwrap();
        let mut rng = Rng::new(1);
        assert!(ema.update(&field, 1.5, 0.5, &mut rng).is_err());
        assert!(ema.update(&field, 0.9, 0.0, &mut rng).is_err());
        assert!(ema.update(&field, 0.9, f32::NAN, &mut rng).is_err());
        assert!(ema.grid(Mode::Density, f32::NAN).is_err());
        assert!(DensityEma::probe(&field, UNIT, 0).is_err());
    }
}
