//! nerfstudio / instant-ngp `transforms.json` files as a [`Capture`].
//!
//! The intrinsics `fl_x`, `fl_y`, `cx`, `cy`, `w`, `h`, the distortion `k1`, `k2`, `k3`, `p1`,
//! `p2` and `camera_model` may be given once at the top level or per frame (a frame's value wins).
//! Missing values follow nerfstudio and instant-ngp: `fl_x` from `camera_angle_x`, `fl_y` from
//! `camera_angle_y` or `fl_x`, the principal point at the image center, `w` and `h` from the
//! image's header. Camera models: `PINHOLE`, `SIMPLE_PINHOLE` and `OPENCV` (the default when
//! unnamed); fisheye and equirectangular cameras are refused. `transform_matrix` is
//! camera-to-world in the OpenGL convention; `aabb_scale` is kept for reports.

use std::path::Path;

use crate::cameras::camera::PixelIntrinsics;
use crate::cameras::camera_files::frame_image;
use crate::data::capture::{Capture, Distortion, Frame, FrameCamera};
use crate::error::{Error, Result};
use crate::json::{self, Node};

/// The camera models read; the others are refused with this list.
const MODELS: &[&str] = &["PINHOLE", "SIMPLE_PINHOLE", "OPENCV"];

/// Whether a camera file's text looks like a nerfstudio / instant-ngp file (pixel intrinsics)
/// rather than a Blender one.
pub fn is_nerfstudio(text: &str) -> bool {
    text.contains("\"frames\"") && (text.contains("\"fl_x\"") || text.contains("\"camera_model\""))
}

/// Reads a `transforms.json` (see the [module docs](self)). Image paths are relative to the file's
/// folder; a path without extension gets `.png`.
pub fn load_nerfstudio(path: &Path) -> Result<Capture> {
    let doc = json::read(path)?;
    let root = Node::root(path, &doc);
    let entries = root.get("frames")?.items()?;
    if entries.is_empty() {
        return Err(Error::format(path, "frames: the list is empty"));
    }
    let frames = entries
        .iter()
        .map(|entry| read_frame(path, &root, entry))
        .collect::<Result<Vec<_>>>()?;
    let aabb_scale = root.opt("aabb_scale")?.map(|n| n.f32()).transpose()?;
    Ok(Capture {
        frames,
        points: Vec::new(),
        aabb_scale,
        depth_bounds: None,
    })
}

/// A frame's value of `key`, else the top level's, as a number.
fn number(root: &Node, frame: &Node, key: &str) -> Result<Option<f32>> {
    match frame.opt(key)? {
        Some(n) => n.f32().map(Some),
        None => root.opt(key)?.map(|n| n.f32()).transpose(),
    }
}

fn read_frame(path: &Path, root: &Node, frame: &Node) -> Result<Frame> {
    let image = frame_image(path, frame.get("file_path")?.str()?);
    let model = match frame.opt("camera_model")? {
        Some(n) => Some(n),
        None => root.opt("camera_model")?,
    };
    if let Some(node) = model {
        let name = node.str()?;
        if !MODELS.contains(&name) {
            return Err(node.invalid(Error::Invalid(format!(
                "camera model '{name}' is not supported: nerfjit reads {} (undistort other captures first, \
                 e.g. with COLMAP's image_undistorter)",
                MODELS.join(", ")
            ))));
        }
    }
    let (width, height) = match (number(root, frame, "w")?, number(root, frame, "h")?) {
        (Some(w), Some(h)) => (pixels(frame, "w", w)?, pixels(frame, "h", h)?),
        _ => header_size(&image)?,
    };
    let (w, h) = (width as f32, height as f32);
    let angle = |key: &str, side: f32| -> Result<Option<f32>> {
        Ok(number(root, frame, key)?.map(|a| 0.5 * side / (0.5 * a).tan()))
    };
    let fx = match number(root, frame, "fl_x")? {
        Some(f) => f,
        None => angle("camera_angle_x", w)?.ok_or_else(|| {
            frame.invalid(Error::Invalid("neither fl_x nor camera_angle_x is given".into()))
        })?,
    };
    let fy = match number(root, frame, "fl_y")? {
        Some(f) => f,
        None => angle("camera_angle_y", h)?.unwrap_or(fx),
    };
    let intrinsics = PixelIntrinsics {
        fx,
        fy,
        cx: number(root, frame, "cx")?.unwrap_or(0.5 * w),
        cy: number(root, frame, "cy")?.unwrap_or(0.5 * h),
    };
    let coefficient = |key: &str| number(root, frame, key).map(|k| k.unwrap_or(0.0));
    let distortion = Distortion {
        k1: coefficient("k1")?,
        k2: coefficient("k2")?,
        k3: coefficient("k3")?,
        p1: coefficient("p1")?,
        p2: coefficient("p2")?,
    };
    let matrix = frame.get("transform_matrix")?;
    let camera = FrameCamera {
        c2w: matrix.mat4_rows()?,
        intrinsics,
        distortion,
        width,
        height,
    };
    // Builds the camera once to check the pose and intrinsics, with an error naming the frame.
    camera.camera(width, height).map_err(|e| frame.invalid(e))?;
    Ok(Frame {
        camera,
        image,
        mask: None,
    })
}

/// A width or height given as a number: a whole number of pixels from 1.
fn pixels(frame: &Node, key: &str, value: f32) -> Result<u32> {
    if value >= 1.0 && value.fract() == 0.0 && value <= 1e6 {
        Ok(value as u32)
    } else {
        Err(frame.invalid(Error::Invalid(format!(
            "{key} is {value}: image sides are whole numbers of pixels from 1"
        ))))
    }
}

/// The size an image's header states (the image is not decoded).
fn header_size(image: &Path) -> Result<(u32, u32)> {
    image::image_dimensions(image).map_err(|e| match e {
        image::ImageError::IoError(e) if e.kind() == std::io::ErrorKind::NotFound => Error::read(
            image,
            "file not found (the camera file states no w and h, so nerfjit reads them from the image)",
        ),
        e => Error::format(image, format!("invalid image: {e}")),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;
    use std::path::PathBuf;

    fn temp_file(name: &str, text: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("nerfjit-nerfstudio-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join(name);
        std::fs::write(&path, text).unwrap();
        path
    }

    const IDENTITY: &str = "[[1,0,0,0],[0,1,0,0],[0,0,1,4],[0,0,0,1]]";

    #[test]
    fn global_and_per_frame_intrinsics_are_read() {
        let text = format!(
            r#"{{"camera_model": "OPENCV", "fl_x": 100, "fl_y": 90, "cx": 40, "cy": 30, "w": 80, "h": 60,
                "k1": -0.1, "aabb_scale": 4,
                "frames": [
                  {{"file_path": "images/a.jpg", "transform_matrix": {IDENTITY}}},
                  {{"file_path": "./images/b", "fl_x": 120, "cx": 41.5, "k1": 0, "transform_matrix": {IDENTITY}}}
                ]}}"#
        );
        let path = temp_file("transforms.json", &text);
        let capture = load_nerfstudio(&path).unwrap();
        assert_eq!(capture.aabb_scale, Some(4.0));
        let [a, b] = capture.frames.as_slice() else {
            panic!()
        };
        assert!(a.image.ends_with("images/a.jpg") && b.image.ends_with("images/b.png"));
        assert_eq!((a.camera.width, a.camera.height), (80, 60));
        let k = PixelIntrinsics {
            fx: 100.0,
            fy: 90.0,
            cx: 40.0,
            cy: 30.0,
        };
        assert_eq!(a.camera.intrinsics, k);
        assert_eq!(a.camera.distortion.k1, -0.1);
        assert_eq!(
            b.camera.intrinsics,
            PixelIntrinsics {
                fx: 120.0,
                cx: 41.5,
                ..k
            }
        );
        assert!(b.camera.distortion.is_none());
        assert_eq!(b.camera.c2w.w_axis.truncate(), Vec3::new(0.0, 0.0, 4.0));
    }

    #[test]
    fn instant_ngp_angles_give_the_focal_lengths() {
        let text = format!(
            r#"{{"camera_angle_x": 1.0, "camera_angle_y": 0.8, "w": 64, "h": 48,
                "frames": [{{"file_path": "a.png", "transform_matrix": {IDENTITY}}}]}}"#
        );
        let capture = load_nerfstudio(&temp_file("ngp.json", &text)).unwrap();
        let k = capture.frames[0].camera.intrinsics;
        assert!((k.fx - 32.0 / 0.5f32.tan()).abs() < 1e-3);
        assert!((k.fy - 24.0 / 0.4f32.tan()).abs() < 1e-3);
        assert_eq!((k.cx, k.cy), (32.0, 24.0));
    }

    #[test]
    fn bad_files_name_the_frame_and_the_problem() {
        let cases = [
            (
                format!(r#"{{"camera_model": "OPENCV_FISHEYE", "fl_x": 1, "w": 8, "h": 8, "frames": [{{"file_path": "a.png", "transform_matrix": {IDENTITY}}}]}}"#),
                "camera_model: camera model 'OPENCV_FISHEYE' is not supported",
            ),
            (
                format!(r#"{{"w": 8, "h": 8, "frames": [{{"file_path": "a.png", "transform_matrix": {IDENTITY}}}]}}"#),
                "frames[0]: neither fl_x nor camera_angle_x is given",
            ),
            (
                format!(r#"{{"fl_x": 10, "w": 8.5, "h": 8, "frames": [{{"file_path": "a.png", "transform_matrix": {IDENTITY}}}]}}"#),
                "frames[0]: w is 8.5",
            ),
            (
                format!(r#"{{"fl_x": -10, "w": 8, "h": 8, "frames": [{{"file_path": "a.png", "transform_matrix": {IDENTITY}}}]}}"#),
                "frames[0]: focal lengths (-10, -10) px must be positive",
            ),
            (
                r#"{"fl_x": 10, "w": 8, "h": 8, "frames": [{"file_path": "a.png", "transform_matrix": [[2,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}"#.to_string(),
                "must be finite with a rotation",
            ),
            (
                r#"{"fl_x": 10, "frames": [{"file_path": "missing.png", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}"#.to_string(),
                "missing.png: file not found (the camera file states no w and h",
            ),
        ];
        for (text, want) in cases {
            let path = temp_file("bad.json", &text);
            let e = load_nerfstudio(&path).unwrap_err().to_string();
            assert!(e.contains(want), "{e}\nwanted: {want}");
            assert!(e.contains("bad.json") || e.contains("missing.png"), "{e}");
        }
    }
}
