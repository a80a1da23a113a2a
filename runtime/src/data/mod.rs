//! Data and file formats read: the course's views ([`dataset`]), Blender / NeRF-synthetic data sets
//! ([`blender`]), captures of real scenes from nerfstudio, COLMAP, LLFF and DTU ([`capture`],
//! [`nerfstudio`], [`colmap`], [`llff`], [`dtu`]), images decoded within the limits ([`decode`]), point
//! clouds ([`pointcloud`]), NumPy files ([`npy`]), and
//! which layout a folder holding several is read as ([`layout`]).

pub mod blender;
pub mod capture;
pub mod colmap;
pub mod dataset;
pub mod decode;
pub mod dtu;
pub mod layout;
pub mod llff;
pub mod nerfstudio;
pub mod npy;
pub(crate) mod ply;
pub mod pointcloud;

/// A fresh, empty folder in the system's temporary folder for one test, named `nerfjit-{name}-…`, removed
/// with everything in it when the returned guard drops (also when the test fails).
#[cfg(test)]
pub(crate) fn scratch_folder(name: &str) -> tempfile::TempDir {
    let prefix = format!("nerfjit-{name}-");
    tempfile::Builder::new().prefix(&prefix).tempdir().unwrap()
}
