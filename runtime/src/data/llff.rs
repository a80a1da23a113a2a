//! LLFF forward-facing scenes (`poses_bounds.npy` beside `images/`, `images_4/`, `images_8/`) as a
//! [`Capture`].
//!
//! `poses_bounds.npy` is a float64 array of shape (N, 17), one row per image in the sorted order of
//! the file names: a 3×5 matrix `[R | t | hwf]` (row-major) and the view's near and far depth bounds.
//! `R` and `t` are camera-to-world with the camera's axes in LLFF's order [down, right, backwards];
//! nerfjit reorders them to OpenGL's [right, up, backwards] as NeRF's loader does. `hwf` holds the
//! full-size images' height, width and focal length in pixels; the focal length scales with the images
//! read (`images_8/` of a 4032-pixel-wide capture: ÷8). The capture's depth bounds are the nearest near
//! and the farthest far over the views.

use std::path::{Path, PathBuf};

use glam::Mat4;

use crate::cameras::camera::PixelIntrinsics;
use crate::data::capture::{Capture, Distortion, Frame, FrameCamera};
use crate::data::npy;
use crate::error::{Error, Result};
use crate::input::read_capped;

/// The name of LLFF's pose file.
pub const POSES_FILE: &str = "poses_bounds.npy";

/// Whether `folder` is an LLFF scene (holds `poses_bounds.npy`).
pub fn is_llff(folder: &Path) -> bool {
    folder.join(POSES_FILE).is_file()
}

/// An LLFF scene read for one image scale.
#[derive(Debug, Clone, PartialEq)]
pub struct LlffScene {
    /// The frames (cameras for the images of [`LlffScene::images`]) and the depth bounds.
    pub capture: Capture,
    /// The folder the images come from: `images_<downscale>` when it exists, else `images`.
    pub images: PathBuf,
    /// The factor still to divide the images by when loading them: 1 when `images_<downscale>` holds
    /// them at that scale, `downscale` when they come from the full-size `images`.
    pub remaining_downscale: u32,
}

/// Reads the LLFF scene in `folder` (see the [module docs](self)) for images divided by `downscale`:
/// from the folder `images_<downscale>` when it exists, else from `images` or from the `images_<k>` of
/// the largest k dividing `downscale`, divided further on load.
pub fn load_llff(folder: &Path, downscale: u32) -> Result<LlffScene> {
    let poses_path = folder.join(POSES_FILE);
    let (rows, values) = read_poses(&poses_path)?;
    let (images, remaining_downscale) = image_folder(folder, downscale.max(1))?;
    let files = image_files(&images)?;
    if files.len() != rows {
        return Err(Error::format(
            &poses_path,
            format!(
                "{rows} poses but {} images in '{}': LLFF pairs them in the sorted order of the names",
                files.len(),
                images.display()
            ),
        ));
    }
    let (width, height) = image::image_dimensions(&files[0])
        .map_err(|e| Error::format(&files[0], format!("invalid image: {e}")))?;
    let mut frames = Vec::with_capacity(rows);
    let (mut near, mut far) = (f32::INFINITY, 0.0f32);
    for (k, (row, file)) in values.chunks_exact(17).zip(files).enumerate() {
        let bad = |what: String| Error::format(&poses_path, format!("view {k}: {what}"));
        if let Some(v) = row.iter().find(|v| !v.is_finite()) {
            return Err(bad(format!("the row holds {v}, not a finite number")));
        }
        let at = |r: usize, c: usize| row[5 * r + c] as f32;
        let (full_height, full_width, focal) = (at(0, 4), at(1, 4), at(2, 4));
        if !(full_height >= 1.0 && full_width >= 1.0 && focal > 0.0) {
            return Err(bad(format!(
                "height, width and focal length {full_height}, {full_width}, {focal} must be positive"
            )));
        }
        let aspect = |w: f32, h: f32| h / w;
        if (aspect(full_width, full_height) - aspect(width as f32, height as f32)).abs() > 0.01 {
            return Err(bad(format!(
                "the poses are for {full_width}×{full_height} images, but '{}' is {width}×{height}: not the same \
                 aspect ratio",
                file.display()
            )));
        }
        let (view_near, view_far) = (row[15] as f32, row[16] as f32);
        if !(view_near > 0.0 && view_far > view_near) {
            return Err(bad(format!(
                "depth bounds {view_near} to {view_far}: need 0 < near < far"
            )));
        }
        near = near.min(view_near);
        far = far.max(view_far);
        let column = |c: usize| glam::Vec3::new(at(0, c), at(1, c), at(2, c));
        // [down, right, back] → [right, up, back].
        let c2w = Mat4::from_cols(
            column(1).extend(0.0),
            (-column(0)).extend(0.0),
            column(2).extend(0.0),
            column(3).extend(1.0),
        );
        let scale = width as f32 / full_width;
        let camera = FrameCamera {
            c2w,
            intrinsics: PixelIntrinsics {
                fx: focal * scale,
                fy: focal * scale,
                cx: 0.5 * width as f32,
                cy: 0.5 * height as f32,
            },
            distortion: Distortion::default(),
            width,
            height,
        };
        camera.camera(width, height).map_err(|e| bad(e.to_string()))?;
        frames.push(Frame {
            camera,
            image: file,
            mask: None,
        });
    }
    Ok(LlffScene {
        capture: Capture {
            frames,
            points: Vec::new(),
            aabb_scale: None,
            depth_bounds: Some((near, far)),
        },
        images,
        remaining_downscale,
    })
}

/// The factors of the image folders of the LLFF scene in `folder`, ascending: 1 for `images`, k for
/// `images_k`.
pub fn image_scales(folder: &Path) -> Vec<u32> {
    let mut scales: Vec<u32> = std::fs::read_dir(folder)
        .map(|entries| {
            entries
                .filter_map(|e| e.ok())
                .filter(|e| e.path().is_dir())
                .filter_map(|e| e.file_name().into_string().ok())
                .filter_map(|name| match name.as_str() {
                    "images" => Some(1),
                    _ => name.strip_prefix("images_")?.parse().ok().filter(|&k| k >= 1),
                })
                .collect()
        })
        .unwrap_or_default();
    scales.sort_unstable();
    scales
}

/// The factor that divides the full-size images of the LLFF scene in `folder` (as its poses state
/// them) to about `width` pixels across: at least 1.
pub fn downscale_for_width(folder: &Path, width: u32) -> Result<u32> {
    let (_, values) = read_poses(&folder.join(POSES_FILE))?;
    let full_width = values[5 + 4];
    Ok((full_width / f64::from(width.max(1))).round().max(1.0) as u32)
}

/// The number of views and the values (17 a view) of a `poses_bounds.npy`.
fn read_poses(path: &Path) -> Result<(usize, Vec<f64>)> {
    let bytes = read_capped(path).map_err(|e| Error::read(path, e))?;
    let array = npy::parse(&bytes).map_err(|e| Error::format(path, e))?;
    match array.shape[..] {
        [n, 17] if n > 0 && !array.fortran_order => Ok((n, array.to_f64())),
        _ => Err(Error::format(
            path,
            format!(
                "shape is {:?}{}, expected (N, 17) in C order: a 3×5 pose and two depth bounds per view",
                array.shape,
                if array.fortran_order {
                    " in Fortran order"
                } else {
                    ""
                }
            ),
        )),
    }
}

/// The folder of the images for `downscale` and the factor left to divide them by.
fn image_folder(folder: &Path, downscale: u32) -> Result<(PathBuf, u32)> {
    let scaled = folder.join(format!("images_{downscale}"));
    if downscale > 1 && scaled.is_dir() {
        return Ok((scaled, 1));
    }
    let full = folder.join("images");
    if full.is_dir() {
        return Ok((full, downscale));
    }
    if let Some(k) = (2..downscale)
        .rev()
        .find(|k| downscale.is_multiple_of(*k) && folder.join(format!("images_{k}")).is_dir())
    {
        return Ok((folder.join(format!("images_{k}")), downscale / k));
    }
    let present: Vec<String> = image_scales(folder)
        .into_iter()
        .map(|k| match k {
            1 => "images".to_string(),
            k => format!("images_{k}"),
        })
        .collect();
    Err(Error::format(
        &folder.join(POSES_FILE),
        format!(
            "no image folder 'images_{downscale}' or 'images' beside it{}",
            if present.is_empty() {
                String::new()
            } else {
                format!(" (found {}: pick downscale to match)", present.join(", "))
            }
        ),
    ))
}

/// The PNG and JPEG files of `folder`, sorted by name.
pub(crate) fn image_files(folder: &Path) -> Result<Vec<PathBuf>> {
    let entries = std::fs::read_dir(folder).map_err(|e| Error::read(folder, e))?;
    let mut files: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.extension()
                .and_then(|e| e.to_str())
                .is_some_and(|e| ["png", "jpg", "jpeg"].contains(&e.to_ascii_lowercase().as_str()))
        })
        .collect();
    files.sort();
    Ok(files)
}
