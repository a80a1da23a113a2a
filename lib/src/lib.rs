//! nerfjit: neural volume and surface rendering on the CPU, driven by `.sdf` scene scripts. This crate is
//! the library the `nerfjit` command line (`nerfjit-cli`) drives: running a script's blocks (training,
//! rendering, meshing), checkpoints, and the commands' work; the compiler, JIT and runtime are the
//! `nerfjit-dsl`, `nerfjit-jit` and `nerfjit-runtime` crates, the live viewer `nerfjit-viewer` (a
//! [`observe::TrainingObserver`]) and the benchmark workloads `nerfjit-bench`. It has no web server and
//! no terminal UI: progress bars and Ctrl-C are the command line's ([`observe`], [`interrupt`]).
//!
//! Running a script from Rust as `nerfjit run` does (here a shipped example, smaller, into a folder):
//!
//! ```
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! let out = std::env::temp_dir().join(format!("nerfjit-doctest-{}", std::process::id()));
//! let overrides = ["render.size=32".to_string()];
//! nerfjit::commands::run::run("examples/torus.sdf", &overrides, Some(&out), false, None)?;
//! assert!(std::fs::metadata(out.join("torus.gif"))?.len() > 0);
//! # std::fs::remove_dir_all(&out)?;
//! # Ok(())
//! # }
//! ```
//!
//! A [`session::Session`] keeps a checked script, its params and one kernel cache between calls: its
//! blocks run one at a time, and the params a `train` block learned can be read, changed and rendered
//! with (a field trained and then rendered or meshed is compiled once); its documentation trains the
//! course's box from Rust. Its modules, from the bottom up (each uses only those before it, as
//! `.ci/check_cycles.py` checks): [`failure`] and [`cluster`] (errors and the MPI job), [`console`],
//! [`interrupt`] and [`observe`] (what the program says, Ctrl-C, progress), [`script`], [`settings`] (the
//! schema of every block setting and their parsers), [`frame_files`], [`diagnostics`], [`folder_lock`]
//! (one run or render a folder) and [`bake_file`] (a baked scene's file), [`checkpoint`],
//! [`training`] (both kinds of training run [`training::train_loop::train`], each block an
//! [`training::train_loop::Objective`]; validation; logs), [`blocks`] (what each kind of block does),
//! [`session`] and [`commands`] (the work of the other commands). The JIT's kernels reach the runtime as
//! fields through the `nerfjit-field` crate.
pub mod bake_file;
pub mod bake_view;
pub mod blocks;
pub mod checkpoint;
pub mod city_model;
pub mod cluster;
pub mod commands;
#[cfg(test)]
mod conformance;
pub mod console;
pub mod diagnostics;
pub mod failure;
pub mod folder_lock;
pub mod frame_files;
pub mod interrupt;

pub mod observe;
pub mod script;
pub mod session;
pub mod settings;
pub mod training;

/// The stack of the thread that does the work: deep (but limited) expressions make the compiler's
/// passes recurse deeply; the pages are only committed as they are used.
pub const WORK_STACK_BYTES: usize = 1 << 30;

pub use console::{emit, note};
