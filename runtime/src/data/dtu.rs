//! DTU scans in the IDR / NeuS / VolSDF layout as a [`Capture`].
//!
//! A scan's folder holds `cameras_sphere.npz` (NeuS; IDR and VolSDF name it `cameras.npz`), the images
//! in `image/` or `images/`, and optionally the object masks in `mask/`, paired by the sorted order of
//! their names. For each view i the archive holds `world_mat_i`, the 4×4 projection P = K·[R | t] from
//! world to pixels (OpenCV convention: pixel centers at whole coordinates, the camera looks down +Z with
//! +Y down), and `scale_mat_i`, a similarity mapping the unit sphere onto the region of interest. The
//! capture is in the coordinates of P·S, where the object lies inside the unit sphere, as every surface
//! paper works with it: K, R and the camera center come from an RQ decomposition of P·S's left 3×3 block.

use std::path::{Path, PathBuf};

use glam::{DMat3, DVec3, Mat4};

use crate::cameras::camera::PixelIntrinsics;
use crate::data::capture::{Capture, Distortion, Frame, FrameCamera};
use crate::data::llff::image_files;
use crate::data::npy;
use crate::error::{Error, Result};
use crate::input::read_stream_capped;

/// The camera archives looked for in a scan's folder, in this order.
pub const CAMERA_FILES: &[&str] = &["cameras_sphere.npz", "cameras.npz"];

/// The camera archive of the scan in `folder`, if it has one.
pub fn dtu_cameras_file(folder: &Path) -> Option<PathBuf> {
    CAMERA_FILES
        .iter()
        .map(|name| folder.join(name))
        .find(|path| path.is_file())
}

/// Reads the DTU scan in `folder` (see the [module docs](self)), with its masks when `masks` is set
/// (an error if it has none).
pub fn load_dtu(folder: &Path, masks: bool) -> Result<Capture> {
    let cameras = dtu_cameras_file(folder).ok_or_else(|| {
        Error::format(
            folder,
            format!("holds no camera archive ({})", CAMERA_FILES.join(" or ")),
        )
    })?;
    let images_folder = ["image", "images"]
        .iter()
        .map(|name| folder.join(name))
        .find(|path| path.is_dir())
        .ok_or_else(|| Error::format(folder, "holds no 'image' or 'images' folder"))?;
    let images = image_files(&images_folder)?;
    let mask_files = if masks {
        let mask_folder = folder.join("mask");
        if !mask_folder.is_dir() {
            return Err(Error::format(
                folder,
                "holds no 'mask' folder (train without masks: masks: false)",
            ));
        }
        let files = image_files(&mask_folder)?;
        if files.len() != images.len() {
            return Err(Error::format(
                &mask_folder,
                format!("{} masks for {} images", files.len(), images.len()),
            ));
        }
        files.into_iter().map(Some).collect()
    } else {
        vec![None; images.len()]
    };
    let matrices = read_matrices(&cameras, images.len())?;
    let (width, height) = match images.first() {
        Some(first) => {
            image::image_dimensions(first).map_err(|e| Error::format(first, format!("invalid image: {e}")))?
        }
        None => return Err(Error::format(&images_folder, "holds no PNG or JPEG images")),
    };
    let frames = matrices
        .into_iter()
        .zip(images.into_iter().zip(mask_files))
        .enumerate()
        .map(|(k, ((world, scale), (image, mask)))| {
            let (c2w, intrinsics) = decompose(world * scale)
                .map_err(|e| Error::format(&cameras, format!("world_mat_{k} · scale_mat_{k}: {e}")))?;
            let camera = FrameCamera {
                c2w,
                intrinsics,
                distortion: Distortion::default(),
                width,
                height,
            };
            camera
                .camera(width, height)
                .map_err(|e| Error::format(&cameras, format!("view {k}: {e}")))?;
            Ok(Frame { camera, image, mask })
        })
        .collect::<Result<Vec<_>>>()?;
    Ok(Capture {
        frames,
        points: Vec::new(),
        aabb_scale: None,
        depth_bounds: None,
    })
}

/// `world_mat_i` and `scale_mat_i` (the identity where an archive has none) for views 0 to `n` − 1.
fn read_matrices(path: &Path, n: usize) -> Result<Vec<(ProjectionMatrix, ProjectionMatrix)>> {
    let file = std::fs::File::open(path).map_err(|e| Error::read(path, e))?;
    let mut archive = zip::ZipArchive::new(std::io::BufReader::new(file))
        .map_err(|e| Error::format(path, format!("not a .npz (zip) archive: {e}")))?;
    let views = archive
        .file_names()
        .filter_map(|name| name.ok())
        .filter(|name| {
            name.strip_prefix("world_mat_")
                .and_then(|rest| rest.strip_suffix(".npy"))
                .is_some_and(|k| k.parse::<usize>().is_ok())
        })
        .count();
    if views != n {
        return Err(Error::format(
            path,
            format!("{views} world_mat_i entries for {n} images: one camera per image"),
        ));
    }
    let mut read = |name: String, required: bool| -> Result<Option<ProjectionMatrix>> {
        let entry = match archive.by_name(&name) {
            Ok(entry) => entry,
            Err(zip::result::ZipError::FileNotFound) if !required => return Ok(None),
            Err(e) => return Err(Error::format(path, format!("{name}: {e}"))),
        };
        let bytes = read_stream_capped(entry).map_err(|e| Error::format(path, format!("{name}: {e}")))?;
        let array = npy::parse(&bytes).map_err(|e| Error::format(path, format!("{name}: {e}")))?;
        if !matches!(array.shape[..], [3, 4] | [4, 4]) {
            return Err(Error::format(
                path,
                format!("{name}: shape is {:?}, expected (4, 4) or (3, 4)", array.shape),
            ));
        }
        let values = array.to_f64();
        let at = |r: usize, c: usize| {
            if array.fortran_order {
                values[c * array.shape[0] + r]
            } else {
                values[r * 4 + c]
            }
        };
        let mut rows = [[0.0, 0.0, 0.0, 0.0], [0.0; 4], [0.0; 4], [0.0, 0.0, 0.0, 1.0]];
        for (r, row) in rows.iter_mut().enumerate().take(array.shape[0]) {
            *row = std::array::from_fn(|c| at(r, c));
        }
        if rows.iter().flatten().any(|v| !v.is_finite()) {
            return Err(Error::format(
                path,
                format!("{name}: holds values that are not finite"),
            ));
        }
        Ok(Some(ProjectionMatrix(rows)))
    };
    (0..n)
        .map(|k| {
            let world = read(format!("world_mat_{k}.npy"), true)?.expect("required");
            let scale = read(format!("scale_mat_{k}.npy"), false)?.unwrap_or(ProjectionMatrix::IDENTITY);
            Ok((world, scale))
        })
        .collect()
}

/// A 4×4 matrix in float64 (rows first), as the archives store them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProjectionMatrix(pub [[f64; 4]; 4]);

impl ProjectionMatrix {
    /// The identity.
    pub const IDENTITY: ProjectionMatrix = ProjectionMatrix([
        [1.0, 0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ]);
}

impl std::ops::Mul for ProjectionMatrix {
    type Output = ProjectionMatrix;

    fn mul(self, other: ProjectionMatrix) -> ProjectionMatrix {
        let (a, b) = (self.0, other.0);
        ProjectionMatrix(std::array::from_fn(|r| {
            std::array::from_fn(|c| (0..4).map(|k| a[r][k] * b[k][c]).sum())
        }))
    }
}

/// The camera-to-world pose (OpenGL convention) and pixel intrinsics (pixel centers at +0.5, as
/// nerfjit's cameras have them) of the projection `p` = K·[R | t] (OpenCV convention), by an RQ
/// decomposition of its left 3×3 block with a positive diagonal in K. Refuses a singular block and a
/// skewed K (skew beyond 10⁻³ of the focal length), which a pinhole camera cannot represent.
pub fn decompose(p: ProjectionMatrix) -> std::result::Result<(Mat4, PixelIntrinsics), String> {
    let p = p.0;
    let row = |r: usize| DVec3::new(p[r][0], p[r][1], p[r][2]);
    let (mut m1, mut m2, mut m3) = (row(0), row(1), row(2));
    let mut p4 = DVec3::new(p[0][3], p[1][3], p[2][3]);
    let block = DMat3::from_cols(m1, m2, m3).transpose();
    let det = block.determinant();
    let scale = m1.length() * m2.length() * m3.length();
    if det.is_nan() || det.abs() <= 1e-12 * scale {
        return Err("the projection's 3×3 block is singular".into());
    }
    // P is defined up to scale: with a negative determinant, −P has a rotation (det R = +1).
    if det < 0.0 {
        (m1, m2, m3, p4) = (-m1, -m2, -m3, -p4);
    }
    // Gram–Schmidt from the last row: M = K·R with K upper triangular.
    let k33 = m3.length();
    let r3 = m3 / k33;
    let k23 = m2.dot(r3);
    let u2 = m2 - k23 * r3;
    let k22 = u2.length();
    let r2 = u2 / k22;
    let (k13, k12) = (m1.dot(r3), m1.dot(r2));
    let u1 = m1 - k12 * r2 - k13 * r3;
    let k11 = u1.length();
    let r1 = u1 / k11;
    if k12.abs() > 1e-3 * k11 {
        return Err(format!(
            "the intrinsics have a skew of {:.4} px (focal {:.1} px): not a pinhole camera",
            k12 / k33,
            k11 / k33
        ));
    }
    let world_to_camera = DMat3::from_cols(r1, r2, r3).transpose();
    let center = -(DMat3::from_cols(m1, m2, m3).transpose().inverse() * p4);
    // Camera axes in world space: OpenCV's x right, y down, z forward; OpenGL's y up and z backwards.
    let camera_to_world = world_to_camera.transpose();
    let axis = |v: DVec3| v.as_vec3().extend(0.0);
    let c2w = Mat4::from_cols(
        axis(camera_to_world.x_axis),
        axis(-camera_to_world.y_axis),
        axis(-camera_to_world.z_axis),
        center.as_vec3().extend(1.0),
    );
    let intrinsics = PixelIntrinsics {
        fx: (k11 / k33) as f32,
        fy: (k22 / k33) as f32,
        cx: (k13 / k33 + 0.5) as f32,
        cy: (k23 / k33 + 0.5) as f32,
    };
    Ok((c2w, intrinsics))
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DQuat;
    use proptest::prelude::*;

    proptest! {
        /// A projection built from intrinsics, a rotation and a center (OpenCV conventions), scaled by
        /// any nonzero factor, decomposes into the same camera.
        #[test]
        fn decomposition_recovers_the_camera(
            fx in 100.0f64..5000.0, aspect in 0.8f64..1.25, cx in 0.0f64..2000.0, cy in 0.0f64..2000.0,
            axis in prop::array::uniform3(-1.0f64..1.0), angle in 0.0f64..std::f64::consts::TAU,
            center in prop::array::uniform3(-50.0f64..50.0),
            factor in prop_oneof![-1e3f64..-1e-3, 1e-3f64..1e3],
        ) {
            let axis = DVec3::from(axis);
            prop_assume!(axis.length() > 0.1);
            let w2c = DMat3::from_quat(DQuat::from_axis_angle(axis.normalize(), angle));
            let center = DVec3::from(center);
            let k = DMat3::from_cols(
                DVec3::new(fx, 0.0, 0.0),
                DVec3::new(0.0, fx * aspect, 0.0),
                DVec3::new(cx, cy, 1.0),
            );
            let (m, p4) = (k * w2c, -(k * w2c * center));
            let p = ProjectionMatrix(std::array::from_fn(|r| {
                if r == 3 {
                    [0.0, 0.0, 0.0, 1.0]
                } else {
                    [m.col(0)[r] * factor, m.col(1)[r] * factor, m.col(2)[r] * factor, p4[r] * factor]
                }
            }));
            let (c2w, intrinsics) = decompose(p).unwrap();
            let close = |a: f32, b: f64, tolerance: f64| (f64::from(a) - b).abs() <= tolerance * (1.0 + b.abs());
            prop_assert!(close(intrinsics.fx, fx, 1e-4) && close(intrinsics.fy, fx * aspect, 1e-4));
            prop_assert!(close(intrinsics.cx, cx + 0.5, 1e-4) && close(intrinsics.cy, cy + 0.5, 1e-4));
            for i in 0..3 {
                prop_assert!(close(c2w.w_axis[i], center[i], 1e-4), "{c2w} {center}");
            }
            // OpenGL axes: −Z is the OpenCV camera's forward (+Z), +Y its up (−Y).
            let forward = w2c.row(2).as_vec3();
            let down = w2c.row(1).as_vec3();
            prop_assert!((-c2w.z_axis.truncate() - forward).length() < 1e-4);
            prop_assert!((c2w.y_axis.truncate() + down).length() < 1e-4);
        }
    }

    #[test]
    fn singular_and_skewed_projections_are_refused() {
        let mut singular = ProjectionMatrix::IDENTITY;
        singular.0[2] = [1.0, 0.0, 0.0, 0.0];
        assert!(decompose(singular).unwrap_err().contains("singular"));
        let mut skewed = ProjectionMatrix::IDENTITY;
        skewed.0[0][1] = 0.2;
        assert!(decompose(skewed).unwrap_err().contains("skew"));
    }
}
