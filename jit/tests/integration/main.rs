//! The JIT's integration tests: kernels against the f64 interpreter and finite differences, the tape,
//! the interval extension, the sphere tracer, the math approximations.
//!
//! One test binary per crate (`cargo test -p CRATE --test integration MODULE::`): each module was its own
//! binary, each linked on its own.

mod common;
mod conformance;
mod dense;
mod grid;
mod interval;
mod march;
mod math_accuracy;
mod nearest_gradient;
mod random_programs;
mod tape;
