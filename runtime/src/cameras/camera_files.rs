//! Loading lists of cameras from the course's `box_cameras.json` and from Blender /
//! NeRF-synthetic `transforms_*.json` files.

use std::path::{Path, PathBuf};

use glam::Vec2;

use crate::cameras::camera::{check_field_of_view, Camera};
use crate::error::{Error, Result};
use crate::json::{self, Node};

/// Cameras read from a file, each with the image it took.
#[derive(Debug, Clone)]
pub struct CameraSet {
    /// The cameras, in file order.
    pub cameras: Vec<Camera>,
    /// The image of each camera, resolved against the folder of the JSON file.
    pub images: Vec<PathBuf>,
    /// (width, height) of the images when the file states it.
    pub image_size: Option<(u32, u32)>,
}

/// The camera file formats read here.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CameraFormat {
    /// Blender / NeRF-synthetic `transforms_*.json` (`camera_angle_x`, `frames`).
    Blender,
    /// The course's `box_cameras.json` (`image_size`, `cameras`).
    Box,
}

impl CameraFormat {
    /// The format of a camera file's text: Blender if it has `frames`, the course's if it has `cameras`.
    pub fn of_text(text: &str) -> Option<CameraFormat> {
        if text.contains("\"frames\"") {
            Some(CameraFormat::Blender)
        } else if text.contains("\"cameras\"") {
            Some(CameraFormat::Box)
        } else {
            None
        }
    }
}

/// `path` relative to the folder of `file` (a leading `./` is dropped).
fn beside(file: &Path, path: &str) -> PathBuf {
    let path = path.strip_prefix("./").unwrap_or(path);
    file.parent().unwrap_or(Path::new("")).join(path)
}

/// A transforms file's `file_path` beside the file; without an extension it gets `.png`, as in the
/// original NeRF loader.
pub(crate) fn frame_image(file: &Path, path: &str) -> PathBuf {
    let mut image = beside(file, path);
    if image.extension().is_none() {
        image.set_extension("png");
    }
    image
}

/// Reads the course format (`box_cameras.json`): `image_size` [H, W] and a list `cameras` of
/// `{image, focal, principal_point, eye, scene_center, up}` PyTorch3D look-at cameras
/// (`focal` is a number or [fx, fy], in NDC).
pub fn load_box_cameras(path: &Path) -> Result<CameraSet> {
    let doc = json::read(path)?;
    let root = Node::root(path, &doc);
    let size = root.get("image_size")?;
    let [height, width] = match size.items()?.as_slice() {
        [h, w] => [h.u32()?, w.u32()?],
        _ => return Err(size.invalid(Error::Invalid("expected [height, width]".into()))),
    };
    let entries = root.get("cameras")?.items()?;
    if entries.is_empty() {
        return Err(Error::format(path, "cameras: the list is empty"));
    }
    let mut set = CameraSet {
        cameras: Vec::with_capacity(entries.len()),
        images: Vec::with_capacity(entries.len()),
        image_size: Some((width, height)),
    };
    for entry in &entries {
        let focal_node = entry.get("focal")?;
        let focal = match focal_node.f32() {
            Ok(f) => Vec2::splat(f),
            Err(_) => focal_node.vec2()?,
        };
        let camera = Camera::look_at(
            entry.get("eye")?.vec3()?,
            entry.get("scene_center")?.vec3()?,
            entry.get("up")?.vec3()?,
            focal,
            entry.get("principal_point")?.vec2()?,
        )
        .map_err(|e| entry.invalid(e))?;
        set.cameras.push(camera);
        set.images.push(beside(path, entry.get("image")?.str()?));
    }
    Ok(set)
}

/// Reads a Blender / NeRF-synthetic `transforms_*.json`: `camera_angle_x` and a list `frames`
/// of `{file_path, transform_matrix}`. A `file_path` without extension gets `.png`, as in the
/// original NeRF loader. The file states no image size.
pub fn load_blender_cameras(path: &Path) -> Result<CameraSet> {
    let doc = json::read(path)?;
    let root = Node::root(path, &doc);
    let angle_node = root.get("camera_angle_x")?;
    let camera_angle_x = angle_node.f32()?;
    check_field_of_view(camera_angle_x).map_err(|e| angle_node.invalid(e))?;
    let frames = root.get("frames")?.items()?;
    if frames.is_empty() {
        return Err(Error::format(path, "frames: the list is empty"));
    }
    let mut set = CameraSet {
        cameras: Vec::with_capacity(frames.len()),
        images: Vec::with_capacity(frames.len()),
        image_size: None,
    };
    for frame in &frames {
        let matrix = frame.get("transform_matrix")?;
        let camera =
            Camera::from_blender(matrix.mat4_rows()?, camera_angle_x).map_err(|e| matrix.invalid(e))?;
        let image = frame_image(path, frame.get("file_path")?.str()?);
        set.cameras.push(camera);
        set.images.push(image);
    }
    Ok(set)
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    const DATA: &str = "/work/shared/data";

    fn temp_file(name: &str, text: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("nerfjit-camfiles-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join(name);
        std::fs::write(&path, text).unwrap();
        path
    }

    const BOX: &str = r#"{"image_size": [32, 48], "cameras": [
        {"image": "a.npy", "focal": 1.0, "principal_point": [0.0, 0.0],
         "eye": [-2.5, 0.0, 0.0], "scene_center": [0.0, 0.0, 0.0], "up": [0.0, 1.0, 0.0]},
        {"image": "b.npy", "focal": [2.0, 2.0], "principal_point": [0.0, 0.0],
         "eye": [0.0, 0.0, -2.5], "scene_center": [0.0, 0.0, 0.0], "up": [0.0, 1.0, 0.0]}]}"#;

    #[test]
    fn box_format_is_read() {
        let path = temp_file("box.json", BOX);
        let set = load_box_cameras(&path).unwrap();
        assert_eq!(set.image_size, Some((48, 32)));
        assert_eq!(set.cameras.len(), 2);
        assert_eq!(set.images[1], path.parent().unwrap().join("b.npy"));
        assert_eq!(set.cameras[0].position(), Vec3::new(-2.5, 0.0, 0.0));
        // Focal 2 doubles the NDC offset of a point off the axis.
        let (_, col) = set.cameras[1].project(Vec3::new(0.25, 0.0, 0.0), 32, 32).unwrap();
        assert!((col - 0.5 * (32.0 - 2.0 * 0.1 * 32.0)).abs() < 1e-3, "{col}");
    }

    #[test]
    fn course_box_cameras_load_when_present() {
        let path = Path::new(DATA).join("assignment3/box_cameras.json");
        if !path.exists() {
            eprintln!("note: {} not found, skipping", path.display());
            return;
        }
        let set = load_box_cameras(&path).unwrap();
        assert_eq!(set.cameras.len(), 4);
        assert_eq!(set.image_size, Some((256, 256)));
        assert!(set.images[0].ends_with("box_0.npy"));
        for cam in &set.cameras {
            let (row, col) = cam.project(Vec3::ZERO, 256, 256).unwrap();
            assert!((row - 128.0).abs() < 1e-3 && (col - 128.0).abs() < 1e-3);
        }
    }

    #[test]
    fn lego_transforms_load_when_present() {
        let path = Path::new(DATA).join("lego/transforms_train.json");
        if !path.exists() {
            eprintln!("note: {} not found, skipping", path.display());
            return;
        }
        let set = load_blender_cameras(&path).unwrap();
        assert_eq!(set.cameras.len(), set.images.len());
        assert!(set.images[0].ends_with("train/r_1.png"), "{:?}", set.images[0]);
        assert!(set.images[0].exists());
        // The lego cameras orbit the scene looking roughly at the origin.
        let (row, col) = set.cameras[0].project(Vec3::ZERO, 800, 800).unwrap();
        assert!((row - 400.0).abs() < 80.0 && (col - 400.0).abs() < 80.0);
    }

    #[test]
    fn bad_files_give_errors_naming_file_and_problem() {
        let missing = Path::new("/nonexistent/cams.json");
        let e = load_box_cameras(missing).unwrap_err().to_string();
        assert_eq!(e, "cannot read /nonexistent/cams.json: file not found");

        let path = temp_file("bad.json", "{ not json");
        let e = load_box_cameras(&path).unwrap_err().to_string();
        assert!(e.starts_with(&format!("{}: invalid JSON", path.display())), "{e}");

        let path = temp_file("noeye.json", &BOX.replace("\"eye\": [0.0, 0.0, -2.5],", ""));
        let e = load_box_cameras(&path).unwrap_err().to_string();
        assert!(e.ends_with("cameras[1]: missing key 'eye'"), "{e}");

        let path = temp_file("badangle.json", r#"{"camera_angle_x": "wide", "frames": []}"#);
        let e = load_blender_cameras(&path).unwrap_err().to_string();
        assert!(
            e.ends_with("camera_angle_x: expected a number, found a string"),
            "{e}"
        );

        let path = temp_file(
            "badmatrix.json",
            r#"{"camera_angle_x": 0.7, "frames": [{"file_path": "x", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0]]}]}"#,
        );
        let e = load_blender_cameras(&path).unwrap_err().to_string();
        assert!(
            e.ends_with("frames[0].transform_matrix: expected 4 rows, found 3"),
            "{e}"
        );
    }
}
