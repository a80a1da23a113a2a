//! Helpers shared by the JIT tests: compiling a graph and running it next to the interpreter.

use nerfjit_dsl::interp;
use nerfjit_dsl::ir::Graph;
use nerfjit_jit::{Kernel, Options};

/// Runs `g` through the JIT on `points[i][k]` (point i, input k); returns outputs per point and reductions.
pub fn jit_eval(
    g: &Graph,
    points: &[Vec<f64>],
    params: &[f64],
    options: Options,
) -> (Vec<Vec<f32>>, Vec<f32>) {
    let k = Kernel::compile(g, options).expect("compiles");
    let n = points.len();
    let cols: Vec<Vec<f32>> = (0..g.n_inputs as usize)
        .map(|c| points.iter().map(|p| p[c] as f32).collect())
        .collect();
    let ins: Vec<&[f32]> = cols.iter().map(Vec::as_slice).collect();
    let mut outs = vec![vec![0.0f32; n]; g.outputs.len()];
    let mut out_refs: Vec<&mut [f32]> = outs.iter_mut().map(Vec::as_mut_slice).collect();
    let params32: Vec<f32> = params.iter().map(|&x| x as f32).collect();
    let mut red = vec![0.0f32; g.reductions.len()];
    k.eval(n, &ins, &mut out_refs, &params32, &mut red);
    let per_point = (0..n).map(|i| outs.iter().map(|o| o[i]).collect()).collect();
    (per_point, red)
}

/// The interpreter's outputs per point (inputs rounded to f32 first, as the JIT sees them).
pub fn interp_eval(g: &Graph, points: &[Vec<f64>], params: &[f64]) -> (Vec<Vec<f64>>, Vec<f64>) {
    let round = |v: &[f64]| v.iter().map(|&x| f64::from(x as f32)).collect::<Vec<_>>();
    let params = round(params);
    let mut sums = vec![0.0; g.reductions.len()];
    let outs = points
        .iter()
        .map(|p| {
            let e = interp::eval_point(g, &round(p), &params);
            for (s, r) in sums.iter_mut().zip(&e.reductions) {
                *s += r;
            }
            e.outputs
        })
        .collect();
    (outs, sums)
}

/// Whether an f32 result matches an f64 reference within `tol` relative to `scale` (NaN matches NaN,
/// infinities must match exactly).
pub fn close(got: f32, want: f64, tol: f64, scale: f64) -> bool {
    let got = f64::from(got);
    if want.is_nan() || got.is_nan() {
        return want.is_nan() && got.is_nan();
    }
    if want.is_infinite() || got.is_infinite() {
        return want == got || (got - want).abs() <= tol * want.abs();
    }
    (got - want).abs() <= tol * (scale + want.abs())
}
