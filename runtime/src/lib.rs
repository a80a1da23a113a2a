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
#![warn(missing_docs)]

pub mod camera;
pub mod camera_files;
pub mod error;
pub mod field;
pub mod image_out;
mod json;
pub mod npy;
pub mod paths;
pub mod rays;
pub mod rng;
pub mod sphere_trace;
pub mod viz;

pub use camera::{Camera, NdcScale};
pub use camera_files::{load_blender_cameras, load_box_cameras, CameraSet};
pub use error::{Error, Result};
pub use field::{BatchFn, ClosureFn};
pub use image_out::{depth_image, normal_image, rgb_image, save_gif, save_png, Quantize};
pub use npy::{read_npy_rgb, write_npy_rgb, ImageF32};
pub use paths::{orbit, surround, Up};
pub use rays::RayBatch;
pub use rng::Rng;
pub use sphere_trace::{render_frames, sphere_trace, Frame, Shading, TraceSettings};
