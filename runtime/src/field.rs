//! The one interface between renderers and compiled kernels: [`BatchFn`].

use crate::error::{Error, Result};

/// A function evaluated on batches of points in structure-of-arrays layout (one slice per
/// scalar input/output).
///
/// Renderers call [`BatchFn::eval`] from several threads at once, each with its own buffers.
pub trait BatchFn: Sync {
    /// Number of scalar inputs per point (3 for a function of a position).
    fn n_inputs(&self) -> usize;
    /// Number of scalar outputs per point.
    fn n_outputs(&self) -> usize;
    /// Evaluates points 0..n. `inputs[i]` and `outputs[o]` each have length >= n.
    fn eval(&self, n: usize, inputs: &[&[f32]], outputs: &mut [&mut [f32]]);
}

/// Checks that `f` has the arity a renderer expects; `role` names the function in the error.
pub(crate) fn check_arity(f: &dyn BatchFn, role: &str, inputs: usize, outputs: usize) -> Result<()> {
    if f.n_inputs() != inputs || f.n_outputs() != outputs {
        return Err(Error::Invalid(format!(
            "{role} must map {inputs} inputs to {outputs} outputs, but it maps {} to {}",
            f.n_inputs(),
            f.n_outputs()
        )));
    }
    Ok(())
}

/// A [`BatchFn`] made from a Rust closure evaluated one point at a time, e.g. an analytic SDF
/// for tests: `ClosureFn::new(3, 1, |p, out| out[0] = (p[0]*p[0] + p[1]*p[1] + p[2]*p[2]).sqrt() - 1.0)`.
pub struct ClosureFn<F> {
    n_inputs: usize,
    n_outputs: usize,
    f: F,
}

impl<F: Fn(&[f32], &mut [f32]) + Sync> ClosureFn<F> {
    /// Wraps `f`, which reads `n_inputs` scalars of one point and writes its `n_outputs` scalars.
    pub fn new(n_inputs: usize, n_outputs: usize, f: F) -> Self {
        ClosureFn {
            n_inputs,
            n_outputs,
            f,
        }
    }
}

impl<F: Fn(&[f32], &mut [f32]) + Sync> BatchFn for ClosureFn<F> {
    fn n_inputs(&self) -> usize {
        self.n_inputs
    }

    fn n_outputs(&self) -> usize {
        self.n_outputs
    }

    fn eval(&self, n: usize, inputs: &[&[f32]], outputs: &mut [&mut [f32]]) {
        let mut point = vec![0.0; self.n_inputs];
        let mut values = vec![0.0; self.n_outputs];
        for k in 0..n {
            for (x, column) in point.iter_mut().zip(inputs) {
                *x = column[k];
            }
            (self.f)(&point, &mut values);
            for (column, v) in outputs.iter_mut().zip(&values) {
                column[k] = *v;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn closure_fn_evaluates_every_point_in_soa_layout() {
        let f = ClosureFn::new(2, 2, |p, out| {
            out[0] = p[0] + p[1];
            out[1] = p[0] * p[1];
        });
        assert_eq!((f.n_inputs(), f.n_outputs()), (2, 2));
        let (a, b) = ([1.0, 2.0, 3.0], [4.0, 5.0, 6.0]);
        let (mut sum, mut prod) = ([0.0; 3], [0.0; 3]);
        f.eval(2, &[&a, &b], &mut [&mut sum, &mut prod]);
        assert_eq!(sum, [5.0, 7.0, 0.0]);
        assert_eq!(prod, [4.0, 10.0, 0.0]);
    }

    #[test]
    fn arity_mismatch_is_an_error() {
        let f = ClosureFn::new(3, 1, |_, out| out[0] = 0.0);
        assert!(check_arity(&f, "sdf", 3, 1).is_ok());
        let e = check_arity(&f, "color", 3, 3).unwrap_err().to_string();
        assert!(e.contains("color") && e.contains("3 to 1"), "{e}");
    }
}
