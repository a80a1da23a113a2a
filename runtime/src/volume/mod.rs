//! Volume rendering: depths along rays ([`sampler`], [`importance`]), occupancy grids for skipping empty
//! space ([`occupancy`], [`occupancy_ema`]), the compositor and its backward pass ([`composite`]), and its
//! three callers: rendering ([`render`]), hierarchical rendering ([`hierarchical`]) and the training step
//! ([`train`]); plus [`transmittance`] through piecewise-constant media, the course's first exercise.

pub mod composite;
pub mod hierarchical;
pub mod importance;
pub mod occupancy;
pub mod occupancy_ema;
pub mod render;
pub mod sampler;
pub mod train;
pub mod transmittance;
