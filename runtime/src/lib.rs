//! The rendering runtime of nerfjit: everything between compiled scene kernels and image files.
//!
//! - [`field`]: [`BatchFn`], the only interface to compiled kernels (batches of points in
//!   structure-of-arrays layout), and [`ClosureFn`] for analytic functions.
//! - [`camera`]: [`Camera`], perspective cameras in the PyTorch3D NDC and Blender / NeRF
//!   conventions; [`paths`] makes turntable paths of them and [`camera_files`] loads them
//!   from the course's JSON files.
//! - [`rays`]: [`RayBatch`], rays of a full image or of random pixels.
//! - [`mod@sphere_trace`]: the tiled, parallel sphere tracer producing [`Frame`]s.
//! - [`image_out`] and [`npy`]: PNG, GIF and `.npy` files; [`viz`]: teaching images.
//! - Volume rendering: [`transmittance`] through piecewise-constant media, [`sampler`] for
//!   depths along rays, [`composite`] (the compositor and its backward pass) and [`volume`]
//!   ([`render_volume`], producing [`VolumeFrame`]s).
//! - [`occupancy`]: [`OccupancyGrid`], for empty-space skipping with [`render_volume_with`].
//! - [`occupancy_ema`]: [`DensityEma`], instant-ngp's running occupancy for training.
//! - Training: [`BatchVjp`] (a kernel's backward pass), [`train`] ([`volume_step`]),
//!   [`optim`] (Adam, learning-rate schedules), [`metrics`] (PSNR, SSIM) and [`dataset`]
//!   (the course's views).
#![warn(missing_docs)]

pub mod blender;
mod bvh;
pub mod camera;
pub mod camera_files;
pub mod camera_path;
pub mod capture;
pub mod colmap;
pub mod composite;
pub mod dataset;
pub mod denormals;
pub mod error;
pub mod field;
pub mod hierarchical;
pub mod image_out;
pub mod importance;
pub mod input;
mod json;
pub mod label;
pub mod march;
pub mod marching;
pub mod mesh;
pub mod mesh_metrics;
pub mod metrics;
pub mod nerfstudio;
pub mod npy;
pub mod occupancy;
pub mod occupancy_ema;
pub mod optim;
pub mod paths;
mod ply;
pub mod pointcloud;
pub mod prune;
pub mod raster;
pub mod rays;
pub mod rng;
pub mod sampler;
pub mod sphere_trace;
pub mod train;
pub mod transmittance;
pub mod video;
pub mod viz;
pub mod volume;

pub use blender::load_blender_views;
pub use camera::{Camera, NdcScale, PixelIntrinsics};
pub use camera_files::{load_blender_cameras, load_box_cameras, CameraFormat, CameraSet};
pub use camera_path::{is_camera_path, load_camera_path, CameraPath};
pub use capture::{Capture, CaptureRequest, Normalization};
pub use colmap::{default_images_folder, is_colmap_model, load_colmap};
pub use composite::{Compositor, Mode, RayOutput, SampleGrads, Samples};
pub use dataset::{load_box_views, read_rgb_image, Views};
pub use denormals::flush_denormals;
pub use error::{Error, Result};
pub use field::{BatchFn, BatchVjp, ClosureFn, ClosureVjp};
pub use image_out::{depth_image, normal_image, rgb_image, save_gif, save_png, Quantize};
pub use mesh::Mesh;
pub use mesh_metrics::{chamfer_report, point_to_mesh_distances, ChamferReport};
pub use metrics::{mse, psnr, ssim};
pub use nerfstudio::{is_nerfstudio, load_nerfstudio};
pub use npy::{read_npy_rgb, write_npy_f32, write_npy_rgb, ImageF32};
pub use occupancy::OccupancyGrid;
pub use occupancy_ema::DensityEma;
pub use optim::{Adam, Schedule};
pub use paths::{orbit, surround, Up};
pub use pointcloud::{bounding_box, mean_center, read_points};
pub use raster::{render_mesh, render_points};
pub use rays::RayBatch;
pub use rng::Rng;
pub use sampler::{sample_depths, sample_points, DepthRange, DepthSpacing, Spacing};
pub use sphere_trace::{render_frames, sphere_trace, sphere_trace_into, Frame, Shading, TraceSettings};
pub use train::{volume_step, volume_step_with, FinePass, StepOptions, StepResult};
pub use transmittance::{Medium, Segment, Transmittance};
pub use video::save_mp4;
pub use volume::render_volume_with;
pub use volume::{render_volume, VolumeFrame, VolumeSettings};
