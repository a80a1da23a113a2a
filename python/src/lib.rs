//! nerfjit from Python: the extension module `nerfjit._nerfjit`, which the package `nerfjit` re-exports.
//!
//! Conversions only, one module each: `script` (a compiled program with its params, whose functions run
//! as JIT kernels — `kernels` — on numpy arrays), `field` (trained fields rendered into numpy images), `bake`
//! (fields baked into splats, drawn into numpy images),
//! `data` (data sets as numpy arrays) and `runs` (a script's blocks run as `nerfjit run` does, their
//! training followed step by step). Kernels run with the GIL released, over the machine's cores;
//! compilation and runs happen on threads with the command line's deep stack.

mod bake;
mod data;
mod field;
mod kernels;
mod runs;
mod script;

use nerfjit::failure::Failure;
use pyo3::create_exception;
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;

create_exception!(
    nerfjit,
    ScriptError,
    PyValueError,
    "A script that does not compile; the message is the diagnostic: line, column, caret and hint."
);
create_exception!(
    nerfjit,
    NerfjitError,
    PyRuntimeError,
    "Anything else nerfjit refuses or fails at: a missing file, a bad argument, a run that failed."
);

/// The Python exception for `failure`.
pub(crate) fn to_py(failure: Failure) -> PyErr {
    match failure {
        Failure::Script(report) => ScriptError::new_err(report.to_string()),
        other => NerfjitError::new_err(other.to_string()),
    }
}

/// Runs `work` on a thread with the command line's stack (deep expressions recurse deeply in the
/// compiler's passes).
pub(crate) fn on_work_stack<T: Send>(work: impl FnOnce() -> T + Send) -> T {
    std::thread::scope(|scope| {
        let thread = std::thread::Builder::new()
            .stack_size(nerfjit::WORK_STACK_BYTES)
            .spawn_scoped(scope, work)
            .expect("a thread for the work");
        thread
            .join()
            .unwrap_or_else(|panic| std::panic::resume_unwind(panic))
    })
}

/// The extension module: `Script`, `Field`, `Bake`, `Trainer`, `run`, `load`, `bake`, `load_views` and the
/// exceptions.
#[pymodule]
fn _nerfjit(module: &Bound<'_, PyModule>) -> PyResult<()> {
    module.add_class::<script::Script>()?;
    module.add_class::<field::Field>()?;
    module.add_class::<bake::Bake>()?;
    module.add_class::<runs::Trainer>()?;
    module.add_class::<runs::Steps>()?;
    module.add_function(wrap_pyfunction!(runs::run, module)?)?;
    module.add_function(wrap_pyfunction!(field::load, module)?)?;
    module.add_function(wrap_pyfunction!(bake::bake, module)?)?;
    module.add_function(wrap_pyfunction!(data::load_views, module)?)?;
    module.add("ScriptError", module.py().get_type::<ScriptError>())?;
    module.add("NerfjitError", module.py().get_type::<NerfjitError>())?;
    Ok(())
}
