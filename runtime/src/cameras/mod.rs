//! Cameras and rays: [`camera::Camera`] (perspective, in the PyTorch3D NDC and Blender / NeRF
//! conventions), the course's and Blender's camera files, nerfstudio's keyframed camera paths, turntable
//! paths, and batches of rays through pixels.

pub mod camera;
pub mod camera_files;
pub mod camera_path;
pub mod paths;
pub mod rays;
