//! Volume rendering: depths along rays ([`sampler`], [`importance`]), occupancy grids for skipping empty
//! space ([`occupancy`]: their spaces, building, the walk along a ray, instant-ngp's running grid), the
//! compositor and its backward pass ([`composite`]), the volume pass of a tile of rays with depths of their
//! own (`pass`) that the training step ([`train`]) and hierarchical rendering ([`hierarchical`]) run, with
//! per-view colour transforms ([`appearance`]), and rendering with depths shared by all rays ([`render`]);
//! [`model`] chooses between plain and hierarchical rendering and training; plus [`transmittance`] through
//! piecewise-constant media, the course's first exercise.

pub mod appearance;
pub mod composite;
pub mod hierarchical;
pub mod importance;
pub mod model;
pub mod occupancy;
pub(crate) mod pass;
pub mod render;
pub mod sampler;
pub mod settings;
pub mod train;
pub mod transmittance;
