//! `nerfjit ir`: the IR of a function's kernel of any kind and the Cranelift IR of its code.

use nerfjit_dsl::kernel_graphs::{self, SdfLoss};
use nerfjit_dsl::Type;
use nerfjit_jit::{Kernel, Options};

use crate::failure::{Failure, Result};
use crate::script;

/// Which kernel of a function to show.
#[derive(Clone, Copy, Debug)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum KernelKind {
    /// The function's values.
    Value,
    /// Values and the gradient of each output with respect to the inputs.
    Grad,
    /// The vector-Jacobian product: input gradients per point, param gradients reduced.
    Vjp,
    /// The param gradient of c_f·f + c_g·∇ₓf (for the eikonal loss; scalar functions only).
    SecondOrder,
    /// Interval bounds of the values over boxes of inputs (low corners, then high corners).
    Bounds,
    /// The SDF regularizers' loss kernel (scalar functions of a point): the near-surface term
    /// exp(−100·|f|) and the eikonal term (|∇ₓf| − 1)² per point, unit weights, and their param gradient.
    Regularizers,
}

/// Prints the IR and node statistics, then (unless `graph_only`) the Cranelift IR.
pub fn run(path: &str, function: &str, kind: KernelKind, graph_only: bool) -> Result<String> {
    let program = script::load(path)?;
    let lowered = program.lower(function)?;
    let n_params = program.n_params();
    let (graph, what) = match kind {
        KernelKind::Value => (kernel_graphs::value(&lowered), "values"),
        KernelKind::Grad => (
            kernel_graphs::with_gradient(&lowered),
            "values and input gradients",
        ),
        KernelKind::Vjp => (kernel_graphs::vjp(&lowered, n_params), "vector-Jacobian product"),
        KernelKind::Bounds => (kernel_graphs::interval(&lowered), "interval bounds over boxes"),
        KernelKind::SecondOrder => {
            if lowered.graph.outputs.len() != 1 {
                return Err(Failure::Message(format!(
                    "the second-order kernel is for scalar functions; '{function}' has {} outputs",
                    lowered.graph.outputs.len()
                )));
            }
            (
                kernel_graphs::second_order(&lowered, n_params),
                "second-order param gradient",
            )
        }
        KernelKind::Regularizers => {
            nerfjit_field::check_signature(&program, function, &[&[Type::Vec(3)]], &Type::F32)?;
            let loss = SdfLoss::Regularizers {
                near: 1.0,
                sharpness: 100.0,
                eikonal: 1.0,
            };
            (
                kernel_graphs::sdf_loss(&lowered, n_params, loss),
                "near-surface and eikonal terms and their param gradient",
            )
        }
    };
    let stats: Vec<String> = graph.stats().iter().map(|(op, n)| format!("{op} {n}")).collect();
    let text = format!(
        "; {}: {what}\n; {} nodes: {}\n{graph}\n",
        lowered.signature,
        graph.len(),
        stats.join(", ")
    );
    if graph_only {
        return Ok(text);
    }
    let kernel = Kernel::compile(
        &graph,
        Options {
            keep_clif: true,
            ..Options::default()
        },
    )?;
    Ok(format!(
        "{text}; Cranelift IR ({} bytes of machine code, compiled in {:.1} ms)\n{}",
        kernel.stats().code_bytes,
        kernel.stats().seconds * 1e3,
        kernel.stats().clif.as_deref().unwrap_or("")
    ))
}
