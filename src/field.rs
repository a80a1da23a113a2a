//! Compiled script functions as the runtime sees them: [`BatchFn`]s backed by JIT kernels.

use std::sync::Arc;

use nerfjit_dsl::{kernels, Program, Type};
use nerfjit_jit::{Kernel, KernelCache, Options};
use nerfjit_runtime::BatchFn;

use crate::failure::{Failure, Result};

/// A JIT kernel with the params it reads: evaluates per-point outputs (no reductions).
pub struct JitFn {
    kernel: Arc<Kernel>,
    params: Arc<[f32]>,
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
}

/// What to compile of a function.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Kind {
    /// Its value.
    Value,
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
        Kind::Value => kernels::value(&lowered),
        Kind::Gradient => kernels::with_gradient(&lowered),
    };
    Ok(JitFn {
        kernel: cache.get(&graph, Options::default())?,
        params: program.param_values.clone().into(),
    })
}
