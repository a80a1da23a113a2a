//! The end-to-end tests: the CLI, golden images, hostile input, captures and data formats, training,
//! the viewer.
//!
//! One test binary per crate (`cargo test -p CRATE --test integration MODULE::`): each module was its own
//! binary, each linked on its own.

mod bake;
mod captures;
mod cli;
mod common;
mod golden;
mod hostile;
mod training;
mod viewer;
