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
//! nerfjit::run::run("examples/torus.sdf", &overrides, Some(&out), false, None)?;
//! assert!(std::fs::metadata(out.join("torus.gif"))?.len() > 0);
//! # std::fs::remove_dir_all(&out)?;
//! # Ok(())
//! # }
//! ```
//!
//! A [`session::Session`] keeps a checked script, its params and one kernel cache between calls: its
//! blocks run one at a time, and the params a `train` block learned can be read, changed and rendered
//! with (a field trained and then rendered or meshed is compiled once); its documentation trains the
//! course's box from Rust. Both kinds of training run [`training_loop::train`], each block an
//! [`training_loop::Objective`]. The other modules are the commands' work (one function per command or
//! block kind).

pub mod block;
pub mod camera_setting;
pub mod check;
pub mod checkpoint;
pub mod compare;
#[cfg(test)]
mod conformance;
pub mod data_check;
pub mod data_source;
pub mod eval;
pub mod failure;
pub mod import;
pub mod interrupt;
pub mod ir_dump;
pub mod jit_field;
pub mod large_model;
pub mod mesh_command;
pub mod metrics_log;
pub mod nonfinite;
pub mod observe;
pub mod output;
pub mod points;
pub mod regularizers;
pub mod run;
pub mod schema;
pub mod script;
pub mod session;
pub mod setting_values;
pub mod settings;
pub mod sphere_trace_block;
pub mod steepness;
pub mod tensorboard;
pub mod train_block;
pub mod train_sdf_block;
pub mod training_loop;
pub mod transmittance_command;
pub mod validation;
pub mod views;
pub mod viz_block;
pub mod volume_block;

/// The stack of the thread that does the work: deep (but limited) expressions make the compiler's
/// passes recurse deeply; the pages are only committed as they are used.
pub const WORK_STACK_BYTES: usize = 1 << 30;

/// Writes command output to standard output; a closed pipe (`nerfjit ir ... | head`) ends the output
/// quietly instead of panicking.
pub fn emit(text: &str) {
    use std::io::Write;
    let _ = std::io::stdout().lock().write_all(text.as_bytes());
}
