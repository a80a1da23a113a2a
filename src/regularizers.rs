//! The SDF regularizers on uniform random points, shared by `train sdf` and (for VolSDF-style fields)
//! `train`: a near-surface penalty w_near · mean exp(−α|d|) and the eikonal term
//! w_eik · mean (|∇ₓd| − 1)², whose param gradient comes from the JIT's second-order kernel.

use nerfjit_dsl::{kernels, Program, Type};
use nerfjit_jit::{Kernel, Options};
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

/// The compiled kernels of an SDF for the regularizers: d and ∇d, and the second-order param gradient.
pub struct RegularizerKernels {
    gradient: Kernel,
    second_order: Kernel,
}

impl RegularizerKernels {
    /// Compiles the kernels of `fn name(p: vec3) -> f32`.
    pub fn compile(program: &Program, name: &str) -> Result<RegularizerKernels> {
        crate::field::check_signature(program, name, &[&[Type::Vec(3)]], &Type::F32)?;
        let lowered = program.lower(name)?;
        let n = program.n_params();
        Ok(RegularizerKernels {
            gradient: Kernel::compile(&kernels::with_gradient(&lowered), Options::default())?,
            second_order: Kernel::compile(&kernels::second_order(&lowered, n), Options::default())?,
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

impl Regularizers {
    /// Adds the regularizers' param gradient to `grads`; returns the (weighted) near and eikonal terms.
    pub fn add(
        &self,
        k: &RegularizerKernels,
        params: &[f32],
        grads: &mut [f32],
        rng: &mut Rng,
        threads: usize,
    ) -> [f32; 2] {
        let m = self.points;
        let ys = uniform_points(rng, m, self.bound);
        let ins: Vec<&[f32]> = ys.iter().map(Vec::as_slice).collect();
        let mut out = vec![vec![0.0f32; m]; 4];
        {
            let mut refs: Vec<&mut [f32]> = out.iter_mut().map(Vec::as_mut_slice).collect();
            k.gradient
                .eval_parallel(m, &ins, &mut refs, params, &mut [], threads);
        }
        let (alpha, w_near, w_eik) = (self.near_sharpness, self.near_weight, self.eikonal_weight);
        let mut cots = vec![vec![0.0f32; m]; 4];
        let (mut near, mut eik) = (0.0f64, 0.0f64);
        for j in 0..m {
            let dj = out[0][j];
            let e = (-alpha * dj.abs()).exp();
            near += f64::from(e);
            cots[0][j] = if dj == 0.0 {
                0.0
            } else {
                -w_near * alpha * dj.signum() * e / m as f32
            };
            let g = [out[1][j], out[2][j], out[3][j]];
            let norm = (g[0] * g[0] + g[1] * g[1] + g[2] * g[2]).sqrt();
            eik += f64::from((norm - 1.0) * (norm - 1.0));
            if norm > 0.0 {
                for c in 0..3 {
                    cots[1 + c][j] = w_eik * 2.0 * (norm - 1.0) * g[c] / norm / m as f32;
                }
            }
        }
        let with_cots: Vec<&[f32]> = ins
            .iter()
            .copied()
            .chain(cots.iter().map(Vec::as_slice))
            .collect();
        let mut scratch = vec![vec![0.0f32; m]; 4];
        let mut refs: Vec<&mut [f32]> = scratch.iter_mut().map(Vec::as_mut_slice).collect();
        k.second_order
            .eval_parallel(m, &with_cots, &mut refs, params, grads, threads);
        [w_near * (near / m as f64) as f32, w_eik * (eik / m as f64) as f32]
    }
}
