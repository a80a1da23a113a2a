//! Surfaces: sphere tracing of SDFs ([`mod@sphere_trace`], marching whole rays through the fused tracer
//! compiled kernels offer, and skipping empty space proven by interval bounds in `empty_space`), marching
//! cubes ([`marching`], pruned by bounds over boxes in [`prune`], with fields specialized to regions of the
//! grid in [`regions`]), triangle meshes and their files ([`mesh`], and glTF binary files in [`glb`], with texture atlases from [`atlas`]), distances between points and meshes
//! ([`mesh_metrics`]) and a software rasterizer for previews ([`raster`]).

pub mod atlas;
mod bvh;
mod empty_space;
pub mod glb;
pub mod marching;
pub mod mesh;
pub mod mesh_metrics;
pub mod prune;
pub mod raster;
pub mod regions;
pub mod sphere_trace;
