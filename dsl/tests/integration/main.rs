//! The front end's integration tests: parsing and type errors, derivatives against finite differences,
//! MLPs, nearest-primitive gradients.
//!
//! One test binary per crate (`cargo test -p CRATE --test integration MODULE::`): each module was its own
//! binary, each linked on its own.

mod derivatives;
mod frontend;
mod mlp;
mod nearest;
