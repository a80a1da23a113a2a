//! nerfstudio's keyframed camera paths (`camera_path.json`, as its viewer's render panel writes them):
//! one camera per frame, already interpolated.
//!
//! Each entry of `camera_path` has `camera_to_world` (a 4×4 or 3×4 matrix, flattened row-major, in
//! the OpenGL convention), `fov` (the vertical field of view in degrees) and optionally `aspect`
//! (width / height); `render_width` and `render_height` give the frame size and `fps` the frame rate.
//! The poses are in the scene's own coordinates: they line up with a field trained in the same frame
//! (a Blender scene, or a capture nerfstudio did not reorient).

use std::path::Path;

use glam::{Mat4, Vec4};

use crate::cameras::camera::{Camera, PixelIntrinsics};
use crate::error::{Error, Result};
use crate::json::{self, Node};

/// The cameras of a camera path and the frame size and rate it asks for.
#[derive(Debug, Clone)]
pub struct CameraPath {
    /// One camera per frame.
    pub cameras: Vec<Camera>,
    /// Frame width in pixels.
    pub width: u32,
    /// Frame height in pixels.
    pub height: u32,
    /// Frames per second, if stated.
    pub fps: Option<f32>,
}

/// Whether a camera file's text is a nerfstudio camera path.
pub fn is_camera_path(text: &str) -> bool {
    text.contains("\"camera_path\"") && text.contains("\"camera_to_world\"")
}

/// Reads a nerfstudio `camera_path.json` (see the [module docs](self)).
pub fn load_camera_path(path: &Path) -> Result<CameraPath> {
    let doc = json::read(path)?;
    let root = Node::root(path, &doc);
    let side = |key: &str| -> Result<u32> {
        let node = root.get(key)?;
        match node.u32()? {
            n @ 1..=16384 => Ok(n),
            n => Err(node.invalid(Error::Invalid(format!("{n} pixels is outside 1 to 16384")))),
        }
    };
    let (width, height) = (side("render_width")?, side("render_height")?);
    let fps = root.opt("fps")?.map(|n| n.f32()).transpose()?;
    let frames = root.get("camera_path")?.items()?;
    if frames.is_empty() {
        return Err(Error::format(path, "camera_path: the list is empty"));
    }
    let cameras = frames
        .iter()
        .map(|frame| {
            let c2w = matrix(&frame.get("camera_to_world")?)?;
            let fov_node = frame.get("fov")?;
            let fov = fov_node.f32()?;
            if !(fov > 0.0 && fov < 180.0) {
                return Err(fov_node.invalid(Error::Invalid(format!(
                    "fov {fov} must be a vertical field of view in (0, 180) degrees"
                ))));
            }
            let fy = 0.5 * height as f32 / (0.5 * fov.to_radians()).tan();
            let intrinsics = PixelIntrinsics {
                fx: fy,
                fy,
                cx: 0.5 * width as f32,
                cy: 0.5 * height as f32,
            };
            Camera::from_pixels(c2w, intrinsics, width, height).map_err(|e| frame.invalid(e))
        })
        .collect::<Result<Vec<_>>>()?;
    Ok(CameraPath {
        cameras,
        width,
        height,
        fps,
    })
}

/// A camera-to-world matrix flattened row-major: 16 numbers, or 12 (the last row is 0 0 0 1).
fn matrix(node: &Node) -> Result<Mat4> {
    let values: Vec<f32> = node.items()?.iter().map(|n| n.f32()).collect::<Result<_>>()?;
    let row = |r: usize| {
        Vec4::new(
            values[4 * r],
            values[4 * r + 1],
            values[4 * r + 2],
            values[4 * r + 3],
        )
    };
    match values.len() {
        12 | 16 => Ok(Mat4::from_cols(row(0), row(1), row(2), Vec4::W).transpose()),
        n => Err(node.invalid(Error::Invalid(format!(
            "expected 16 (or 12) numbers of a row-major matrix, found {n}"
        )))),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    fn temp_file(name: &str, text: &str) -> std::path::PathBuf {
        let dir = std::env::temp_dir().join(format!("nerfjit-camera-path-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join(name);
        std::fs::write(&path, text).unwrap();
        path
    }

    #[test]
    fn a_camera_path_gives_one_camera_per_frame() {
        // A camera at (0, 0, 4) looking down −z (OpenGL), then one moved 1 along x.
        let text = r#"{"camera_type": "perspective", "render_height": 48, "render_width": 64, "fps": 24,
            "camera_path": [
              {"camera_to_world": [1,0,0,0, 0,1,0,0, 0,0,1,4, 0,0,0,1], "fov": 60, "aspect": 1.333},
              {"camera_to_world": [1,0,0,1, 0,1,0,0, 0,0,1,4], "fov": 60}
            ]}"#;
        assert!(is_camera_path(text));
        let path = load_camera_path(&temp_file("camera_path.json", text)).unwrap();
        assert_eq!(
            (path.cameras.len(), path.width, path.height, path.fps),
            (2, 64, 48, Some(24.0))
        );
        assert_eq!(path.cameras[1].position(), Vec3::new(1.0, 0.0, 4.0));
        // The origin is at the center of the first frame; a point at the top edge of the vertical
        // field of view is on the top edge of the image.
        let (row, col) = path.cameras[0].project(Vec3::ZERO, 64, 48).unwrap();
        assert!((row - 24.0).abs() < 1e-4 && (col - 32.0).abs() < 1e-4);
        let top = Vec3::new(0.0, 4.0 * 30f32.to_radians().tan(), 0.0);
        let (row, _) = path.cameras[0].project(top, 64, 48).unwrap();
        assert!(row.abs() < 1e-3, "{row}");
    }

    #[test]
    fn bad_camera_paths_name_the_problem() {
        let cases = [
            (
                r#"{"render_height": 48, "render_width": 64, "camera_path": []}"#,
                "the list is empty",
            ),
            (
                r#"{"render_height": 48, "render_width": 64, "camera_path": [{"camera_to_world": [1,0,0], "fov": 60}]}"#,
                "camera_path[0].camera_to_world: expected 16 (or 12) numbers",
            ),
            (
                r#"{"render_height": 48, "render_width": 64, "camera_path": [{"camera_to_world": [1,0,0,0,0,1,0,0,0,0,1,4], "fov": 0}]}"#,
                "camera_path[0].fov: fov 0 must be",
            ),
            (
                r#"{"render_height": 0, "render_width": 64, "camera_path": []}"#,
                "render_height: 0 pixels",
            ),
        ];
        for (text, want) in cases {
            let e = load_camera_path(&temp_file("bad_path.json", text))
                .unwrap_err()
                .to_string();
            assert!(e.contains(want), "{e}\nwanted: {want}");
        }
    }
}
