//! The kernels of a script's functions and how they run on many points: in chunks over every core, reading
//! numpy's memory where it holds columns, writing their outputs in place.

use std::ops::Range;

use nerfjit_jit::Kernel;
use rayon::prelude::*;

/// What a kernel of a function computes.
#[derive(Clone, Copy, Debug, Hash, PartialEq, Eq)]
pub(crate) enum Kind {
    /// The values.
    Value,
    /// The values, then each output's gradient with respect to the inputs.
    Gradient,
    /// Inputs and one cotangent per output → the values, the inputs' cotangents; the params' as reductions.
    Vjp,
    /// Inputs, one cotangent per output and one per input gradient of `Vjp` → that gradient's backward pass
    /// in the inputs and the cotangents; the params' as reductions.
    VjpBackward,
}

/// A compiled kernel of one function and its shape.
pub(crate) struct Compiled {
    pub(crate) kernel: Kernel,
    /// Scalars the function reads per point.
    pub(crate) inputs: usize,
    /// Scalars it returns per point.
    pub(crate) outputs: usize,
    /// Whether it returns one scalar (`f32`), not a vector.
    pub(crate) scalar: bool,
}

/// What fills the input columns of points start..end (`fill(start, end, columns)`).
pub(crate) type FillColumns<'a> = dyn Fn(usize, usize, &mut [Vec<f32>]) + Sync + 'a;

/// Where a kernel's input columns come from: numpy's memory itself (column-major points), or copies that
/// each chunk makes of its rows.
pub(crate) enum Inputs<'a> {
    Columns(Vec<&'a [f32]>),
    Filled(&'a FillColumns<'a>),
}

/// Points per call of a kernel; the calls run on every core.
const CHUNK: usize = 4096;

impl Compiled {
    /// Runs the kernel on n points over every core, reading its input columns from `inputs`: for each of
    /// `ranges` (of output indices) a column-major (n, range) array of those outputs, which the kernel writes
    /// in place, and the reductions summed over the points.
    pub(crate) fn run(
        &self,
        n: usize,
        inputs: &Inputs,
        params: &[f32],
        ranges: &[Range<usize>],
    ) -> (Vec<Vec<f32>>, Vec<f32>) {
        let k = &self.kernel;
        let chunks = n.div_ceil(CHUNK);
        let mut results: Vec<Vec<f32>> = ranges.iter().map(|r| vec![0.0f32; n * r.len()]).collect();
        // Each chunk's part of each output column that a result holds, by output index.
        let mut parts: Vec<Vec<Option<&mut [f32]>>> = (0..chunks)
            .map(|_| (0..k.n_outputs).map(|_| None).collect())
            .collect();
        for (result, range) in results.iter_mut().zip(ranges) {
            for (column, output) in result.chunks_mut(n.max(1)).zip(range.clone()) {
                for (c, part) in column.chunks_mut(CHUNK).enumerate() {
                    parts[c][output] = Some(part);
                }
            }
        }
        let chunk = |(c, mut columns): (usize, Vec<Option<&mut [f32]>>)| -> Vec<f32> {
            let (start, end) = (c * CHUNK, ((c + 1) * CHUNK).min(n));
            let len = end - start;
            let filled: Vec<Vec<f32>>;
            let ins: Vec<&[f32]> = match inputs {
                Inputs::Columns(columns) => columns.iter().map(|col| &col[start..end]).collect(),
                Inputs::Filled(fill) => {
                    let mut columns = vec![vec![0.0f32; len]; k.n_inputs];
                    fill(start, end, &mut columns);
                    filled = columns;
                    filled.iter().map(Vec::as_slice).collect()
                }
            };
            // Outputs no result holds go to scratch columns.
            let mut scratch = vec![vec![0.0f32; len]; columns.iter().filter(|c| c.is_none()).count()];
            let mut spare = scratch.iter_mut();
            let mut outs: Vec<&mut [f32]> = columns
                .iter_mut()
                .map(|c| match c.take() {
                    Some(part) => part,
                    None => spare.next().expect("a scratch column").as_mut_slice(),
                })
                .collect();
            let mut reductions = vec![0.0f32; k.n_reductions];
            k.eval(len, &ins, &mut outs, params, &mut reductions);
            reductions
        };
        // One chunk runs on the calling thread: a call on a few points costs no thread hand-off.
        let sums: Vec<Vec<f32>> = match parts.len() {
            0 | 1 => parts.into_iter().enumerate().map(chunk).collect(),
            _ => parts.into_par_iter().enumerate().map(chunk).collect(),
        };
        let mut reductions = vec![0.0f32; k.n_reductions];
        for part in sums {
            for (total, x) in reductions.iter_mut().zip(part) {
                *total += x;
            }
        }
        (results, reductions)
    }
}
