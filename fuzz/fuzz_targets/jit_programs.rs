//! Fuzz target for the JIT: a script that compiles gives kernels for each of its functions (value and
//! gradient) that Cranelift compiles and that run on a few points, in buffers of exactly the sizes the
//! kernels declare (AddressSanitizer catches a read or write outside them), without panicking. Programs
//! with large networks are skipped (see `size`).
#![no_main]

mod size;

use libfuzzer_sys::fuzz_target;
use nerfjit_dsl::kernel_graphs;
use nerfjit_jit::{Kernel, Options};

/// Points per evaluation: one full group of four and an unaligned tail.
const POINTS: usize = 7;

fuzz_target!(|data: &[u8]| {
    let Ok(source) = std::str::from_utf8(data) else {
        return;
    };
    let Ok(program) = nerfjit_dsl::compile("fuzz.sdf", source) else {
        return;
    };
    if !size::small_enough(&program) {
        return;
    }
    let params = program.param_values.clone();
    for sig in program.functions() {
        let Ok(f) = program.lower(&sig.name) else {
            continue;
        };
        for graph in [kernel_graphs::value(&f), kernel_graphs::with_gradient(&f)] {
            if graph.len() > 20_000 {
                continue;
            }
            let Ok(kernel) = Kernel::compile(&graph, Options::default()) else {
                continue;
            };
            run(&kernel, &params);
        }
    }
});

/// Evaluates `kernel` at `POINTS` points spread over [-2, 2] in buffers of exactly the sizes it declares.
fn run(kernel: &Kernel, params: &[f32]) {
    if params.len() < kernel.n_params {
        return;
    }
    let inputs: Vec<Vec<f32>> = (0..kernel.n_inputs)
        .map(|i| {
            (0..POINTS)
                .map(|p| ((p * 7 + i * 3) % 9) as f32 * 0.5 - 2.0)
                .collect()
        })
        .collect();
    let mut outputs = vec![vec![0.0f32; POINTS]; kernel.n_outputs];
    let mut reductions = vec![0.0f32; kernel.n_reductions];
    let ins: Vec<&[f32]> = inputs.iter().map(Vec::as_slice).collect();
    let mut outs: Vec<&mut [f32]> = outputs.iter_mut().map(Vec::as_mut_slice).collect();
    kernel.eval(
        POINTS,
        &ins,
        &mut outs,
        &params[..kernel.n_params],
        &mut reductions,
    );
}
