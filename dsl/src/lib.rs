//! The `.sdf` language of nerfjit: source text to typed, differentiable IR.
//!
//! The pipeline, one module per stage: [`lexer`] → [`parser`] (to the [`ast`]) → [`program`] (names,
//! params and their initial values) → [`elaborate`] (type checking and lowering, with [`builtins`] and the
//! prelude) → [`ir`] graphs → [`autodiff`] and [`kernels`] (graph transforms) → [`interp`], the f64
//! reference interpreter. Errors are [`diag::Diagnostic`]s with spans, printed with a caret.
//!
//! ```
//! let program = nerfjit_dsl::compile("torus.sdf", "fn sdf(p: vec3) -> f32 = torus(p, 1.0, 0.25)").unwrap();
//! let f = program.lower("sdf").unwrap();
//! let d = nerfjit_dsl::interp::eval_point(&f.graph, &[1.0, 0.0, 0.0], &program.param_values_f64());
//! assert!((d.outputs[0] + 0.25).abs() < 1e-12);
//! ```
#![warn(missing_docs)]

pub mod ast;
pub mod autodiff;
pub mod budget;
pub mod builtins;
pub mod config;
pub mod diag;
pub mod elaborate;
pub mod grid;
pub mod init;
pub mod interp;
pub mod interval;
pub mod ir;
pub mod kernels;
pub mod lexer;
pub mod overrides;
pub mod parser;
pub mod program;
pub mod types;
mod validate;
pub mod value;

pub use diag::{Diagnostic, Report, Span};
pub use program::{compile, compile_with, Lowered, Program, Signature, PRELUDE};
pub use types::Type;

impl Program {
    /// The initial param values in f64, as the interpreter takes them.
    pub fn param_values_f64(&self) -> Vec<f64> {
        self.param_values.iter().map(|&x| f64::from(x)).collect()
    }
}
