//! The work of the command line's commands that are not a block of a script: one module per command
//! (`nerfjit run` runs a script's blocks as a [`crate::session::Session`]).

pub mod bake;
pub mod check;
pub mod compare;
pub mod data_check;
pub mod eval;
pub mod export;
pub mod import;
pub mod ir_dump;
pub mod point_cloud;
pub mod render_views;
pub mod run;
pub mod sweep;
pub mod transmittance;
