//! The `.sdf` language of nerfjit: source text to typed, differentiable IR.
//!
//! The facade: [`compile`] (or [`compile_with`], with `--set` overrides) turns a script into a
//! [`Program`] whose functions lower to [`ir`] graphs; [`autodiff`] and [`kernel_graphs`] transform the graphs
//! (gradients, VJPs, second order, interval bounds); [`interp`] is the f64 reference interpreter and
//! [`interval`] its interval counterpart; [`simplify`] restricts a graph to a box of inputs; [`nearest`]
//! differentiates unions through their nearest primitive of each shape. Errors are
//! [`Diagnostic`]s with spans, printed with a caret. Block settings stay as written ([`ast::ConfigBlock`],
//! read through [`config`]). The stages behind
//! `compile` (lexer, parser, elaboration with the builtins, `--set` overrides) are private.
//!
//! ```
//! let program = nerfjit_dsl::compile("torus.sdf", "fn sdf(p: vec3) -> f32 = torus(p, 1.0, 0.25)").unwrap();
//! let f = program.lower("sdf").unwrap();
//! let d = nerfjit_dsl::interp::eval_point(&f.graph, &[1.0, 0.0, 0.0], &program.param_values_f64());
//! assert!((d.outputs[0] + 0.25).abs() < 1e-12);
//! ```

pub mod ast;
pub mod autodiff;
pub mod budget;
pub mod config;
pub mod diag;
mod elaborate;
pub mod grid;
pub mod init;
pub mod interp;
pub mod interval;
pub mod ir;
pub mod kernel_graphs;
mod lexer;
pub mod march_rays;
pub mod nearest;
mod overrides;
mod parser;
pub mod program;
pub mod simplify;
pub mod types;
mod validate;
pub mod value;

pub use diag::{Diagnostic, Report, Span};
pub use parser::MAX_SOURCE_BYTES;
pub use program::{compile, compile_with, Lowered, Program, Signature, PRELUDE};
pub use types::Type;

impl Program {
    /// The initial param values in f64, as the interpreter takes them.
    pub fn param_values_f64(&self) -> Vec<f64> {
        self.param_values.iter().map(|&x| f64::from(x)).collect()
    }
}
