//! Fuzz target for the front end: any byte string must give a program or diagnostics, never a panic, and
//! a program must lower every one of its functions (and their gradients) without panicking. Programs with
//! networks of more than `MAX_DENSE_PARAMS` weights are only compiled, not lowered: differentiating a
//! course-size network takes seconds under the sanitizer and tests nothing a small one does not.
#![no_main]

use libfuzzer_sys::fuzz_target;
use nerfjit_dsl::{Program, Type};

/// Most weights (params outside grid tables) of a program whose functions are lowered.
const MAX_DENSE_PARAMS: usize = 20_000;

/// The params of `program` outside grid encodings' tables.
fn dense_params(program: &Program) -> usize {
    let grid = |ty: &Type| matches!(ty, Type::Grid(_));
    program
        .params
        .iter()
        .filter(|p| !grid(&p.ty))
        .map(|p| p.ty.scalars())
        .sum()
}

fuzz_target!(|data: &[u8]| {
    let Ok(source) = std::str::from_utf8(data) else {
        return;
    };
    match nerfjit_dsl::compile("fuzz.sdf", source) {
        Ok(program) if dense_params(&program) > MAX_DENSE_PARAMS => {}
        Ok(program) => {
            for sig in program.functions() {
                if let Ok(f) = program.lower(&sig.name) {
                    let _ = nerfjit_dsl::kernels::with_gradient(&f);
                }
            }
        }
        Err(report) => {
            assert!(!report.diagnostics.is_empty());
            let _ = report.to_string();
        }
    }
});
