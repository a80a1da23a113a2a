//! The rendering runtime of nerfjit: everything between compiled scene kernels and image files, in one
//! folder per subsystem. Each folder below uses only the ones listed before it (`.ci/check_cycles.py`
//! fails on an import that runs up this list):
//!
//! - [`error`], [`rng`], [`input`], [`whole_file`] and `json`: the runtime's [`Error`], its seeded [`Rng`],
//!   size-capped reading of every input file, output files written whole or not at all ([`OutputFile`]),
//!   and typed access to JSON files.
//! - [`cameras`]: [`Camera`], camera files and paths, and [`RayBatch`], rays of a full image or of
//!   random pixels.
//! - [`data`]: the course's [`Views`], Blender data sets, nerfstudio, COLMAP, LLFF and DTU
//!   [`Capture`]s, point clouds and `.npy` files, and the layout a folder is read as.
//! - [`output`]: the surface renderers' [`Frame`]; PNG, GIF and MP4 files, labels and the course's
//!   teaching images.
//! - [`field`]: [`BatchFn`], the only interface to compiled kernels (batches of points in
//!   structure-of-arrays layout), [`BatchVjp`] (a kernel's backward pass), [`ClosureFn`] for analytic
//!   functions, and the fused sphere tracer a compiled SDF may offer.
//! - [`surfaces`]: the tiled, parallel sphere tracer, marching cubes, [`Mesh`]es and their textured glTF
//!   files, point-to-mesh distances and a rasterizer for previews.
//! - [`training`]: [`Adam`] and learning-rate [`Schedule`]s, PSNR and SSIM, denormal flushing.
//! - [`volume`]: sampling along rays, occupancy grids ([`OccupancyGrid`], [`DensityEma`]), the
//!   [`Compositor`], and its callers: [`render_volume`], hierarchical rendering and the training step
//!   [`volume_step`].
//! - [`splats`]: Gaussian [`Splats`](splats::Splats), a baked scene, drawn on the CPU into a volume render's
//!   frame and written in the 3D Gaussian splatting `.ply` layout.

pub mod cameras;
pub mod data;
pub mod error;
pub mod field;
pub mod input;
pub(crate) mod json;
pub mod output;
pub mod rng;
pub mod splats;
pub mod surfaces;
pub mod training;
pub mod volume;
pub mod whole_file;

pub use cameras::camera::{Camera, NdcScale, PixelIntrinsics};
pub use cameras::camera_files::{load_blender_cameras, load_box_cameras, CameraFormat, CameraSet};
pub use cameras::camera_path::{is_camera_path, load_camera_path, CameraPath};
pub use cameras::paths::{orbit, surround, Up};
pub use cameras::rays::RayBatch;
pub use data::blender::load_blender_views;
pub use data::capture::{Capture, CaptureRequest, Normalization};
pub use data::colmap::{default_images_folder, is_colmap_model, load_colmap};
pub use data::dataset::{load_box_views, read_rgb_image, Views};
pub use data::dtu::{dtu_cameras_file, load_dtu};
pub use data::layout::{choose_layout, layouts_at, Chosen, Found, Layout};
pub use data::llff::{is_llff, load_llff, LlffScene};
pub use data::nerfstudio::{is_nerfstudio, load_nerfstudio};
pub use data::npy::{read_npy_rgb, write_npy_f32, write_npy_rgb, ImageF32};
pub use data::pointcloud::{bounding_box, mean_center, read_points, PointFrame};
pub use error::{Error, Result};
pub use field::{BatchFn, BatchVjp, ClosureFn, ClosureVjp, HeldScatters, KeptPasses, WithBounds};
pub use output::frame::Frame;
pub use output::image_out::{depth_image, normal_image, rgb_image, save_gif, save_png, Quantize};
pub use output::video::save_mp4;
pub use rng::Rng;
pub use surfaces::mesh::Mesh;
pub use surfaces::mesh_metrics::{chamfer_report, point_to_mesh_distances, ChamferReport, PointIndex};
pub use surfaces::raster::{render_mesh, render_points};
pub use surfaces::sphere_trace::{
    on_pool, render_frames, sphere_trace, sphere_trace_into, Shading, TraceSettings,
};
pub use training::denormals::flush_denormals;
pub use training::metrics::{masked_mse, mse, psnr, ssim};
pub use training::optim::{Adam, Schedule};
pub use volume::composite::{Compositor, Mode, RayOutput, SampleGrads, Samples};
pub use volume::model::{CoarsePass, TrainableModel, VolumeModel};
pub use volume::occupancy::{
    check_thickness, contract, ndc, uncontract, unndc, CellThickness, DensityEma, GridSpace, OccupancyGrid,
    Unwarped,
};
pub use volume::render::render_volume_with;
pub use volume::render::{render_volume, VolumeFrame, VolumeSettings};
pub use volume::sampler::{sample_depths, sample_points, DepthRange, DepthSpacing, Spacing};
pub use volume::train::{volume_step, volume_step_with, FinePass, StepOptions, StepResult, StepWorkspace};
pub use volume::transmittance::{Medium, Segment, Transmittance};
pub use whole_file::{write_whole, OutputFile};
