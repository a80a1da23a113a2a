//! The SDF regularizers on uniform random points, shared by `train sdf` and (for VolSDF-style fields)
//! `train`: a near-surface penalty w_near · mean exp(−α|d|) and the eikonal term
//! w_eik · mean (|∇ₓd| − 1)², whose param gradient comes from the JIT's second-order kernel.

use std::sync::Arc;

use nerfjit_dsl::kernel_graphs::{self, SdfLoss};
use nerfjit_dsl::{Program, Type};
use nerfjit_jit::{Kernel, KernelCache, Options, Precision};
use nerfjit_runtime::volume::occupancy::OccupancyGrid;
use nerfjit_runtime::Rng;

use crate::failure::Result;

/// The weights and sampling of the regularizers.
#[derive(Clone, Copy, Debug)]
pub struct Regularizers {
    /// Uniform points per step.
    pub points: usize,
    /// The points lie in [−bound, bound]³.
    pub bound: f32,
    /// w_near.
    pub near_weight: f32,
    /// α.
    pub near_sharpness: f32,
    /// w_eik.
    pub eikonal_weight: f32,
}

/// The compiled loss kernel of an SDF for the regularizers: the weighted near-surface and eikonal terms
/// per point and their param gradient (second order for the eikonal term), in one pass.
pub struct RegularizerKernels {
    loss: Arc<Kernel>,
}

impl RegularizerKernels {
    /// The kernel of `fn name(p: vec3) -> f32` for the weights and point count of `reg`, from `cache`,
    /// its dense products in `products`.
    pub fn compile(
        program: &Program,
        name: &str,
        reg: &Regularizers,
        cache: &KernelCache,
        products: Precision,
    ) -> Result<RegularizerKernels> {
        nerfjit_field::check_signature(program, name, &[&[Type::Vec(3)]], &Type::F32)?;
        let lowered = program.lower(name)?;
        let m = reg.points as f64;
        let loss = SdfLoss::Regularizers {
            near: f64::from(reg.near_weight) / m,
            sharpness: f64::from(reg.near_sharpness),
            eikonal: f64::from(reg.eikonal_weight) / m,
        };
        let graph = kernel_graphs::sdf_loss(&lowered, program.n_params(), loss);
        Ok(RegularizerKernels {
            loss: cache.get(
                &graph,
                Options {
                    products,
                    ..Options::default()
                },
            )?,
        })
    }
}

/// `points` uniform random points in [−bound, bound]³, as columns.
pub fn uniform_points(rng: &mut Rng, points: usize, bound: f32) -> [Vec<f32>; 3] {
    let mut cols = [
        Vec::with_capacity(points),
        Vec::with_capacity(points),
        Vec::with_capacity(points),
    ];
    for _ in 0..points {
        for c in &mut cols {
            c.push((rng.next_f32() * 2.0 - 1.0) * bound);
        }
    }
    cols
}

/// `points` random points in [−bound, bound]³ inside the cells `grid` marks occupied, as columns: each
/// drawn uniformly until it lands in an occupied cell, at most [`OCCUPIED_TRIES`] times (a point that
/// finds none keeps its last draw, so an empty grid gives uniform points).
pub fn occupied_points(rng: &mut Rng, points: usize, bound: f32, grid: &OccupancyGrid) -> [Vec<f32>; 3] {
    let mut cols = [
        Vec::with_capacity(points),
        Vec::with_capacity(points),
        Vec::with_capacity(points),
    ];
    for _ in 0..points {
        let mut p = [0.0; 3];
        for _ in 0..OCCUPIED_TRIES {
            p = [0; 3].map(|_| (rng.next_f32() * 2.0 - 1.0) * bound);
            if grid.occupied(p) {
                break;
            }
        }
        for (c, x) in cols.iter_mut().zip(p) {
            c.push(x);
        }
    }
    cols
}

/// Draws per point of [`occupied_points`] before it gives up on finding an occupied cell.
pub const OCCUPIED_TRIES: usize = 256;

impl Regularizers {
    /// Adds the regularizers' param gradient to `grads` (the kernels were compiled for these settings);
    /// returns the (weighted) near and eikonal terms.
    pub fn add(
        &self,
        k: &RegularizerKernels,
        params: &[f32],
        grads: &mut [f32],
        rng: &mut Rng,
        threads: usize,
    ) -> [f32; 2] {
        let ys = uniform_points(rng, self.points, self.bound);
        self.add_at(k, &ys, params, grads, threads)
    }

    /// As [`Regularizers::add`], at the given `points` (columns of `self.points` values) instead of
    /// uniform ones.
    pub fn add_at(
        &self,
        k: &RegularizerKernels,
        points: &[Vec<f32>; 3],
        params: &[f32],
        grads: &mut [f32],
        threads: usize,
    ) -> [f32; 2] {
        let m = self.points;
        let ins: Vec<&[f32]> = points.iter().map(Vec::as_slice).collect();
        let mut terms = vec![vec![0.0f32; m]; 2];
        let mut refs: Vec<&mut [f32]> = terms.iter_mut().map(Vec::as_mut_slice).collect();
        k.loss.eval_parallel(m, &ins, &mut refs, params, grads, threads);
        let sum = |c: &[f32]| c.iter().map(|&x| f64::from(x)).sum::<f64>() as f32;
        [sum(&terms[0]), sum(&terms[1])]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn points_of(cols: &[Vec<f32>; 3]) -> Vec<[f32; 3]> {
        (0..cols[0].len())
            .map(|i| [cols[0][i], cols[1][i], cols[2][i]])
            .collect()
    }

    #[test]
    fn occupied_points_lie_in_occupied_cells() {
        // The 3 × 3 × 3 cells of 8³ over [-1, 1]³ about (0.3, -0.6, 0.1): 27/512 of the box, so a point
        // misses them all 256 draws with probability (1 − 27/512)^256 ≈ 1e-6, and uniform points would
        // land there one time in 19.
        let bounds = ([-1.0; 3], [1.0; 3]);
        let grid = OccupancyGrid::from_points(bounds, 8, &[[0.3, -0.6, 0.1]], 1).unwrap();
        assert_eq!(grid.occupied_cells(), 27);
        let mut rng = Rng::new(7);
        let points = points_of(&occupied_points(&mut rng, 500, 1.0, &grid));
        assert_eq!(points.len(), 500);
        let cell = |x: f32| ((x + 1.0) * 4.0).floor();
        for p in &points {
            assert!(grid.occupied(*p), "{p:?} is in an empty cell");
            let offset = [0, 1, 2].map(|i| cell(p[i]) - cell([0.3f32, -0.6, 0.1][i]));
            assert!(offset.iter().all(|o| o.abs() <= 1.0), "{p:?}");
        }
        // Spread over the block, not stuck in one cell.
        let cells: std::collections::HashSet<[i32; 3]> =
            points.iter().map(|p| p.map(|x| cell(x) as i32)).collect();
        assert_eq!(cells.len(), 27);
    }

    #[test]
    fn occupied_points_of_an_empty_grid_are_uniform_in_the_bounds() {
        let grid = OccupancyGrid::from_points(([-1.0; 3], [1.0; 3]), 8, &[], 0).unwrap();
        let mut rng = Rng::new(3);
        let points = points_of(&occupied_points(&mut rng, 1000, 0.5, &grid));
        assert!(points.iter().flatten().all(|x| x.abs() <= 0.5));
        let mean = points.iter().map(|p| p[0]).sum::<f32>() / 1000.0;
        assert!(mean.abs() < 0.05, "mean x {mean}");
        assert!(points.iter().any(|p| p[0] > 0.4) && points.iter().any(|p| p[0] < -0.4));
    }
}
