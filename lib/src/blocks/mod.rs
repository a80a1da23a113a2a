//! What each kind of block of a script does, its settings read into a plan (`render sphere_trace`,
//! `render volume`, `train`, `train sdf`, `mesh`, `bake`, `viz`): one module, one plan type and one name per kind.

pub mod bake;
pub mod mesh;
pub mod sphere_trace;
pub mod train;
pub mod train_sdf;
pub mod viz;
pub mod volume;
