//! Fuzz target for the front end: any byte string must give a program or diagnostics, never a panic, and
//! a program must lower every one of its functions (and their gradients) without panicking. Programs with
//! large networks are only compiled, not lowered (see `size`).
#![no_main]

mod size;

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(source) = std::str::from_utf8(data) else {
        return;
    };
    match nerfjit_dsl::compile("fuzz.sdf", source) {
        Ok(program) if !size::small_enough(&program) => {}
        Ok(program) => {
            for sig in program.functions() {
                if let Ok(f) = program.lower(&sig.name) {
                    let _ = nerfjit_dsl::kernel_graphs::with_gradient(&f);
                }
            }
        }
        Err(report) => {
            assert!(!report.diagnostics.is_empty());
            let _ = report.to_string();
        }
    }
});
