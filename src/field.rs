//! Compiled script functions as the runtime sees them: [`BatchFn`]s backed by JIT kernels.

use std::sync::Arc;

use nerfjit_dsl::{kernels, Program, Type};
use nerfjit_jit::{Kernel, KernelCache, Marcher, Options, Rays, Stop};
use nerfjit_runtime::march::{MarchRays, RayMarcher};
use nerfjit_runtime::BatchFn;

use crate::failure::{Failure, Result};

/// A JIT kernel with the params it reads: evaluates per-point outputs (no reductions); an SDF also carries
/// its fused sphere tracer.
pub struct JitFn {
    kernel: Arc<Kernel>,
    marcher: Option<Marcher>,
    params: Arc<[f32]>,
}

impl RayMarcher for JitFn {
    fn march(&self, n: usize, rays: &MarchRays, eps: f32, max_steps: u32, t: &mut [f32], hit: &mut [f32]) {
        let marcher = self
            .marcher
            .as_ref()
            .expect("as_marcher returns Some only with a marcher");
        let rays = Rays {
            origin: rays.origin,
            direction: rays.direction,
            t0: rays.t0,
            t1: rays.t1,
        };
        marcher.march(n, &rays, &self.params, Stop { eps, max_steps }, t, hit);
    }
}

impl BatchFn for JitFn {
    fn n_inputs(&self) -> usize {
        self.kernel.n_inputs
    }

    fn n_outputs(&self) -> usize {
        self.kernel.n_outputs
    }

    fn eval(&self, n: usize, inputs: &[&[f32]], outputs: &mut [&mut [f32]]) {
        self.kernel.eval(n, inputs, outputs, &self.params, &mut []);
    }

    fn as_marcher(&self) -> Option<&dyn RayMarcher> {
        self.marcher.as_ref().map(|_| self as &dyn RayMarcher)
    }
}

/// What to compile of a function.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Kind {
    /// Its value.
    Value,
    /// Its value, and a fused sphere tracer (for an SDF).
    Sdf,
    /// Its value and the gradient of each output with respect to the inputs.
    Gradient,
}

/// Compiles function `name` of `program` after checking its signature against `inputs` → `output`.
pub fn compile(
    program: &Program,
    cache: &KernelCache,
    name: &str,
    inputs: &[Type],
    output: &Type,
    kind: Kind,
) -> Result<JitFn> {
    let lowered = program.lower(name)?;
    let sig = &lowered.signature;
    let got: Vec<&Type> = sig.inputs.iter().map(|(_, t)| t).collect();
    if got != inputs.iter().collect::<Vec<_>>() || !sig.output.coerces_to(output) {
        let want: Vec<String> = inputs.iter().map(Type::to_string).collect();
        return Err(Failure::Message(format!(
            "'{name}' must have the signature fn {name}({}) -> {output}, but the script has {sig}",
            want.join(", ")
        )));
    }
    let graph = match kind {
        Kind::Value | Kind::Sdf => kernels::value(&lowered),
        Kind::Gradient => kernels::with_gradient(&lowered),
    };
    let marcher = match kind {
        Kind::Sdf => Some(Marcher::compile(&graph)?),
        _ => None,
    };
    Ok(JitFn {
        kernel: cache.get(&graph, Options::default())?,
        marcher,
        params: program.param_values.clone().into(),
    })
}
