//! The interfaces between renderers and compiled kernels: [`BatchFn`] for values and
//! [`BatchVjp`] for their gradients with respect to parameters.

pub use nerfjit_dsl::march_rays::MarchRays;

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

    /// Evaluates every point of `inputs` (one column per input, all of the same length) into new output
    /// columns.
    fn eval_columns(&self, inputs: &[&[f32]]) -> Vec<Vec<f32>> {
        let n = inputs.first().map_or(0, |c| c.len());
        let mut outputs = vec![vec![0.0f32; n]; self.n_outputs()];
        let mut outs: Vec<&mut [f32]> = outputs.iter_mut().map(Vec::as_mut_slice).collect();
        self.eval(n, inputs, &mut outs);
        outputs
    }

    /// A fused sphere tracer of this function, if it is an SDF that offers one; the sphere tracer then
    /// marches whole rays in one call instead of calling [`BatchFn::eval`] once per step.
    fn as_marcher(&self) -> Option<&dyn RayMarcher> {
        None
    }

    /// Interval bounds of this function's first output over boxes of its inputs, if it offers them: a
    /// function of a box's low corner then its high corner (twice the inputs) to a lower and an upper
    /// bound of the output over the box. The sphere tracer uses them to skip the space they prove empty.
    fn interval_bounds(&self) -> Option<&dyn BatchFn> {
        None
    }
}

/// A function with the interval bounds ([`BatchFn::interval_bounds`]) of its first output, given
/// separately (e.g. a compiled SDF and its compiled interval kernel).
pub struct WithBounds<'a> {
    /// The function.
    pub function: &'a dyn BatchFn,
    /// Its bounds over boxes, if any.
    pub bounds: Option<&'a dyn BatchFn>,
}

impl BatchFn for WithBounds<'_> {
    fn n_inputs(&self) -> usize {
        self.function.n_inputs()
    }

    fn n_outputs(&self) -> usize {
        self.function.n_outputs()
    }

    fn eval(&self, n: usize, inputs: &[&[f32]], outputs: &mut [&mut [f32]]) {
        self.function.eval(n, inputs, outputs);
    }

    fn as_marcher(&self) -> Option<&dyn RayMarcher> {
        self.function.as_marcher()
    }

    fn interval_bounds(&self) -> Option<&dyn BatchFn> {
        self.bounds
    }
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

/// The vector-Jacobian product of a [`BatchFn`] with respect to its parameters θ: for each
/// point, given cotangents of its outputs, accumulates the gradient of Σ cotangent·output.
///
/// Trainers call [`BatchVjp::vjp`] from several threads at once, each with its own buffers.
pub trait BatchVjp: Sync {
    /// Number of scalar inputs per point, the same as the forward function's.
    fn n_inputs(&self) -> usize;
    /// Number of cotangents per point (the forward function's number of outputs).
    fn n_outputs(&self) -> usize;
    /// Number of parameters.
    fn n_params(&self) -> usize;
    /// Adds Σ_points Σ_k `cotangents[k][p]`·∂out_k(p)/∂θ to `param_grads` (length
    /// `n_params`) for points 0..n. `inputs[i]` and `cotangents[k]` each have length >= n.
    fn vjp(&self, n: usize, inputs: &[&[f32]], cotangents: &[&[f32]], param_grads: &mut [f32]);

    /// The forward pass and this backward pass run separately, the backward pass reading what the forward
    /// pass kept instead of recomputing it, if the field offers them (one per thread of work).
    fn kept_passes(&self) -> Option<Box<dyn KeptPasses + '_>> {
        None
    }
}

/// A field's forward pass that keeps what its backward pass needs, and that backward pass
/// ([`BatchVjp::kept_passes`]): [`KeptPasses::forward`] on batches of points, then
/// [`KeptPasses::backward`] on all of them in order with the cotangents of the outputs, as often as
/// wanted; [`KeptPasses::finish`] adds what the backward passes held back.
pub trait KeptPasses: Send {
    /// Evaluates points 0..n (as [`BatchFn::eval`]) and keeps what the backward pass needs, after what the
    /// forward passes since the last backward pass kept.
    fn forward(&mut self, n: usize, inputs: &[&[f32]], outputs: &mut [&mut [f32]]);
    /// Adds Σ_points Σ_k `cotangents[k][p]`·∂out_k(p)/∂θ over the `n` points of the forward passes since the
    /// last backward pass (in the order they were evaluated) to `param_grads`, some of it now and the rest
    /// at [`KeptPasses::finish`].
    fn backward(&mut self, n: usize, cotangents: &[&[f32]], param_grads: &mut [f32]);
    /// About the memory the forward pass keeps per point, in bytes.
    fn bytes_per_point(&self) -> usize;
    /// Adds what the backward passes held back to `param_grads`, except the scatters of
    /// [`KeptPasses::hold_scatters`].
    fn finish(&mut self, param_grads: &mut [f32]);

    /// From now on, the backward passes hold their grid scatters (the gradients of hash-grid tables)
    /// back from `param_grads`, for [`KeptPasses::take_scatters`], if the field can; returns whether they
    /// are held. Their params are then left alone by the backward passes and by `finish`.
    fn hold_scatters(&mut self) -> bool {
        false
    }

    /// The scatters held since [`KeptPasses::hold_scatters`], which holds them no more.
    fn take_scatters(&mut self) -> Option<Box<dyn HeldScatters + '_>> {
        None
    }
}

/// Grid scatters held back by a field's backward passes ([`KeptPasses::hold_scatters`]), in parts
/// whose params are disjoint (a level of a grid each): a caller adds the parts of the scatters of several
/// passes into one gradient, a part on each thread, and the sums do not depend on how the parts are shared
/// out.
pub trait HeldScatters: Send + Sync {
    /// The params of each part, sorted and disjoint.
    fn parts(&self) -> &[std::ops::Range<usize>];
    /// Adds part `part`'s scatters to `grads`, the gradients of that part's params alone.
    fn add(&self, part: usize, grads: &mut [f32]);
}

/// A [`KeptPasses`]' forward pass as a [`BatchFn`], for code that evaluates fields through that trait
/// (a volume pass that evaluates every sample in one call).
pub(crate) struct KeptForward<'a, 'b> {
    passes: std::sync::Mutex<&'a mut (dyn KeptPasses + 'b)>,
    n_inputs: usize,
    n_outputs: usize,
}

impl<'a, 'b> KeptForward<'a, 'b> {
    /// The forward pass of `passes`, a field of `n_inputs` inputs and `n_outputs` outputs.
    pub(crate) fn new(passes: &'a mut (dyn KeptPasses + 'b), n_inputs: usize, n_outputs: usize) -> Self {
        KeptForward {
            passes: std::sync::Mutex::new(passes),
            n_inputs,
            n_outputs,
        }
    }

    /// The passes again, for their backward pass.
    pub(crate) fn into_inner(self) -> &'a mut (dyn KeptPasses + 'b) {
        self.passes.into_inner().unwrap_or_else(|e| e.into_inner())
    }
}

impl BatchFn for KeptForward<'_, '_> {
    fn n_inputs(&self) -> usize {
        self.n_inputs
    }

    fn n_outputs(&self) -> usize {
        self.n_outputs
    }

    fn eval(&self, n: usize, inputs: &[&[f32]], outputs: &mut [&mut [f32]]) {
        let mut passes = self.passes.lock().unwrap_or_else(|e| e.into_inner());
        passes.forward(n, inputs, outputs);
    }
}

/// Checks that `vjp` is the backward pass of a function of `inputs` inputs and `outputs`
/// outputs.
pub(crate) fn check_vjp_arity(vjp: &dyn BatchVjp, inputs: usize, outputs: usize) -> Result<()> {
    if vjp.n_inputs() != inputs || vjp.n_outputs() != outputs {
        return Err(Error::Invalid(format!(
            "the gradient function must take {inputs} inputs and {outputs} cotangents like the field, but it takes {} and {}",
            vjp.n_inputs(),
            vjp.n_outputs()
        )));
    }
    Ok(())
}

/// Points per block of [`ClosureFn::eval`].
const CLOSURE_BLOCK: usize = 64;

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
        // Blocks of points are copied to and from point-major buffers in loops of their own:
        // copying each point just before the call would stall reading what was just written.
        let (n_in, n_out) = (self.n_inputs.max(1), self.n_outputs.max(1));
        let mut points = vec![0.0; CLOSURE_BLOCK * n_in];
        let mut values = vec![0.0; CLOSURE_BLOCK * n_out];
        for start in (0..n).step_by(CLOSURE_BLOCK) {
            let end = n.min(start + CLOSURE_BLOCK);
            for (i, column) in inputs.iter().enumerate().take(self.n_inputs) {
                for (k, x) in column[start..end].iter().enumerate() {
                    points[k * n_in + i] = *x;
                }
            }
            let calls = points.chunks_exact(n_in).zip(values.chunks_exact_mut(n_out));
            for (point, values) in calls.take(end - start) {
                (self.f)(&point[..self.n_inputs], &mut values[..self.n_outputs]);
            }
            for (o, column) in outputs.iter_mut().enumerate().take(self.n_outputs) {
                for (k, y) in column[start..end].iter_mut().enumerate() {
                    *y = values[k * n_out + o];
                }
            }
        }
    }
}

/// A [`BatchVjp`] made from a Rust closure evaluated one point at a time:
/// `f(point, cotangent, param_grads)` adds Σ_k `cotangent[k]`·∂out_k/∂θ at `point` to
/// `param_grads`.
pub struct ClosureVjp<F> {
    n_inputs: usize,
    n_outputs: usize,
    n_params: usize,
    f: F,
}

impl<F: Fn(&[f32], &[f32], &mut [f32]) + Sync> ClosureVjp<F> {
    /// Wraps `f`, which reads `n_inputs` scalars of one point and `n_outputs` cotangents and
    /// accumulates into `n_params` gradients.
    pub fn new(n_inputs: usize, n_outputs: usize, n_params: usize, f: F) -> Self {
        ClosureVjp {
            n_inputs,
            n_outputs,
            n_params,
            f,
        }
    }
}

impl<F: Fn(&[f32], &[f32], &mut [f32]) + Sync> BatchVjp for ClosureVjp<F> {
    fn n_inputs(&self) -> usize {
        self.n_inputs
    }

    fn n_outputs(&self) -> usize {
        self.n_outputs
    }

    fn n_params(&self) -> usize {
        self.n_params
    }

    fn vjp(&self, n: usize, inputs: &[&[f32]], cotangents: &[&[f32]], param_grads: &mut [f32]) {
        let mut point = vec![0.0; self.n_inputs];
        let mut cotangent = vec![0.0; self.n_outputs];
        for k in 0..n {
            for (x, column) in point.iter_mut().zip(inputs) {
                *x = column[k];
            }
            for (c, column) in cotangent.iter_mut().zip(cotangents) {
                *c = column[k];
            }
            (self.f)(&point, &cotangent, param_grads);
        }
    }
}

/// Sphere traces rays in one call, with exactly the per-ray semantics of [`crate::surfaces::sphere_trace`] (a fused native loop over whole
/// rays that compiled SDFs offer through [`BatchFn::as_marcher`]): from
/// `t = t0`, up to `max_steps` times, `p = o + t·d`, `dist = sdf(p)`; a hit when `dist < eps`, else
/// `t += dist` and a miss once `t > t1`.
pub trait RayMarcher: Sync {
    /// Marches rays `0..n`; writes the final `t` of each ray and 1.0 where it hit, 0.0 where it missed.
    fn march(&self, n: usize, rays: &MarchRays, eps: f32, max_steps: u32, t: &mut [f32], hit: &mut [f32]);
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
        // Several blocks of points, the last one partial.
        let n = 2 * CLOSURE_BLOCK + 5;
        let (a, b): (Vec<f32>, Vec<f32>) = (0..n + 1).map(|k| (k as f32, 0.5 * k as f32)).unzip();
        let (mut sum, mut prod) = (vec![-1.0; n + 1], vec![-1.0; n + 1]);
        f.eval(n, &[&a, &b], &mut [&mut sum, &mut prod]);
        for k in 0..n {
            assert_eq!((sum[k], prod[k]), (1.5 * k as f32, 0.5 * (k * k) as f32));
        }
        assert_eq!((sum[n], prod[n]), (-1.0, -1.0));
    }

    #[test]
    fn closure_vjp_accumulates_over_points() {
        // out = (θ₀·x, θ₁·x·y): Σ cot·out has gradient (Σ c₀x, Σ c₁xy).
        let vjp = ClosureVjp::new(2, 2, 2, |p, c, g| {
            g[0] += c[0] * p[0];
            g[1] += c[1] * p[0] * p[1];
        });
        assert_eq!((vjp.n_inputs(), vjp.n_outputs(), vjp.n_params()), (2, 2, 2));
        let (x, y) = ([1.0, 2.0, 100.0], [3.0, 4.0, 100.0]);
        let (c0, c1) = ([1.0, -1.0, 100.0], [0.5, 2.0, 100.0]);
        let mut grads = [10.0, 0.0];
        vjp.vjp(2, &[&x, &y], &[&c0, &c1], &mut grads);
        assert_eq!(grads, [10.0 + 1.0 - 2.0, 1.5 + 16.0]);
        assert!(check_vjp_arity(&vjp, 2, 2).is_ok());
        let e = check_vjp_arity(&vjp, 3, 2).unwrap_err().to_string();
        assert!(e.contains("take 3 inputs and 2 cotangents"), "{e}");
    }

    #[test]
    fn arity_mismatch_is_an_error() {
        let f = ClosureFn::new(3, 1, |_, out| out[0] = 0.0);
        assert!(check_arity(&f, "sdf", 3, 1).is_ok());
        let e = check_arity(&f, "color", 3, 3).unwrap_err().to_string();
        assert!(e.contains("color") && e.contains("3 to 1"), "{e}");
    }
}
