//! `nerfjit ir`: the IR of a function (optionally its gradient graph) and the Cranelift IR of its kernel.

use nerfjit_dsl::kernels;
use nerfjit_jit::{Kernel, Options};

use crate::failure::Result;
use crate::script;

/// Prints the IR, node statistics and the Cranelift IR.
pub fn run(path: &str, function: &str, grad: bool) -> Result<String> {
    let program = script::load(path)?;
    let lowered = program.lower(function)?;
    let graph = if grad {
        kernels::with_gradient(&lowered)
    } else {
        kernels::value(&lowered)
    };
    let kernel = Kernel::compile(&graph, Options { keep_clif: true })?;
    let stats: Vec<String> = graph.stats().iter().map(|(op, n)| format!("{op} {n}")).collect();
    Ok(format!(
        "; {}{}\n; {} nodes: {}\n{graph}\n; Cranelift IR ({} bytes of machine code, compiled in {:.1} ms)\n{}",
        lowered.signature,
        if grad { ", with the gradient of each output" } else { "" },
        graph.len(),
        stats.join(", "),
        kernel.stats().code_bytes,
        kernel.stats().seconds * 1e3,
        kernel.stats().clif.as_deref().unwrap_or("")
    ))
}
