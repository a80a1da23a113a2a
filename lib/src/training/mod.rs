//! Training: the one loop every objective runs, the data it fits, the per-view colour transforms, the regularizers, validation on
//! held-out views, and the logs it writes (metrics JSON lines, TensorBoard events).

pub mod appearance;
pub mod clearance;
pub mod data_source;
pub mod metrics_log;
pub mod regularizers;
pub mod tensorboard;
pub mod train_loop;
pub mod validation;
