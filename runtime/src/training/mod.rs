//! What every training loop uses: the Adam optimizer and learning-rate schedules ([`optim`]), image
//! quality measures ([`metrics`]) and flushing subnormal floats ([`denormals`]).

pub mod denormals;
pub mod metrics;
pub mod optim;
