//! COLMAP sparse models (`cameras`, `images`, `points3D`, as `.txt` or `.bin`) as a [`Capture`].
//!
//! COLMAP stores world-to-camera poses (a unit quaternion `qw qx qy qz` and a translation) in
//! OpenCV's camera convention (+X right, +Y down, +Z forward); they become OpenGL
//! camera-to-world poses here. Camera models: `SIMPLE_PINHOLE`, `PINHOLE`, `SIMPLE_RADIAL`,
//! `RADIAL` and `OPENCV`; the fisheye and other models are refused. Frames are sorted by image
//! name. Counts that a binary file declares are checked against the file's size before they are
//! trusted. The scene's depth bounds come from the sparse points
//! ([`Capture::depth_bounds_from_points`]).

use std::path::{Path, PathBuf};

use glam::{DMat3, DQuat, DVec3, Mat4, Vec3, Vec4};

use crate::cameras::camera::PixelIntrinsics;
use crate::data::capture::{Capture, Distortion, Frame, FrameCamera};
use crate::error::{Error, Result};

/// COLMAP's camera models by id: name and number of parameters.
const MODELS: &[(&str, usize)] = &[
    ("SIMPLE_PINHOLE", 3),
    ("PINHOLE", 4),
    ("SIMPLE_RADIAL", 4),
    ("RADIAL", 5),
    ("OPENCV", 8),
    ("OPENCV_FISHEYE", 8),
    ("FULL_OPENCV", 12),
    ("FOV", 5),
    ("SIMPLE_RADIAL_FISHEYE", 4),
    ("RADIAL_FISHEYE", 5),
    ("THIN_PRISM_FISHEYE", 12),
];

/// The models nerfjit reads (the first five of [`MODELS`]).
const SUPPORTED: usize = 5;

/// One COLMAP camera: its model's intrinsics, distortion and image size.
#[derive(Debug, Clone, Copy)]
struct ModelCamera {
    id: u32,
    intrinsics: PixelIntrinsics,
    distortion: Distortion,
    width: u32,
    height: u32,
}

/// One registered image: its pose (world to camera) and camera.
#[derive(Debug, Clone)]
struct ModelImage {
    rotation: DQuat,
    translation: DVec3,
    camera: u32,
    name: String,
}

/// Whether `folder` holds a COLMAP model (`cameras.txt` or `cameras.bin`).
pub fn is_colmap_model(folder: &Path) -> bool {
    folder.join("cameras.txt").is_file() || folder.join("cameras.bin").is_file()
}

/// Reads the COLMAP model in `folder` (text or binary) with its images in `images`.
pub fn load_colmap(folder: &Path, images: &Path) -> Result<Capture> {
    let binary = folder.join("cameras.bin").is_file();
    let (cameras, model_images, points) = if binary {
        (
            binary_cameras(&folder.join("cameras.bin"))?,
            binary_images(&folder.join("images.bin"))?,
            binary_points(&folder.join("points3D.bin"))?,
        )
    } else if folder.join("cameras.txt").is_file() {
        (
            text_cameras(&folder.join("cameras.txt"))?,
            text_images(&folder.join("images.txt"))?,
            text_points(&folder.join("points3D.txt"))?,
        )
    } else {
        return Err(Error::read(
            folder,
            "no COLMAP model here: expected cameras, images and points3D as .txt or .bin",
        ));
    };
    let mut sorted = model_images;
    sorted.sort_by(|a, b| a.name.cmp(&b.name));
    if sorted.is_empty() {
        return Err(Error::format(
            &folder.join("images"),
            "the model has no registered images",
        ));
    }
    let frames = sorted
        .iter()
        .map(|image| {
            let camera = cameras.iter().find(|c| c.id == image.camera).ok_or_else(|| {
                Error::format(
                    folder,
                    format!(
                        "image '{}' names camera {}, which the model lacks",
                        image.name, image.camera
                    ),
                )
            })?;
            Ok(Frame {
                camera: FrameCamera {
                    c2w: camera_to_world(image),
                    intrinsics: camera.intrinsics,
                    distortion: camera.distortion,
                    width: camera.width,
                    height: camera.height,
                },
                image: images.join(&image.name),
                mask: None,
            })
        })
        .collect::<Result<Vec<_>>>()?;
    let mut capture = Capture {
        frames,
        points,
        aabb_scale: None,
        depth_bounds: None,
    };
    // The scene's depth range from the sparse points, as LLFF's `imgs2poses` finds it: a forward-facing
    // capture is then normalized as LLFF's scenes are.
    capture.depth_bounds = capture.depth_bounds_from_points();
    Ok(capture)
}

/// The OpenGL camera-to-world matrix of a COLMAP world-to-camera pose.
fn camera_to_world(image: &ModelImage) -> Mat4 {
    let r = DMat3::from_quat(image.rotation.normalize());
    let center = -(r.transpose() * image.translation);
    let c2w = r.transpose();
    // OpenCV axes (right, down, forward) → OpenGL (right, up, back).
    let column = |v: DVec3| Vec4::new(v.x as f32, v.y as f32, v.z as f32, 0.0);
    Mat4::from_cols(
        column(c2w.x_axis),
        column(-c2w.y_axis),
        column(-c2w.z_axis),
        center.as_vec3().extend(1.0),
    )
}

/// A camera of `model` (an index into [`MODELS`]) from its parameters.
fn model_camera(
    file: &Path,
    id: u32,
    model: usize,
    (width, height): (u64, u64),
    params: &[f64],
) -> Result<ModelCamera> {
    let name = MODELS.get(model).map_or("an unknown model", |m| m.0);
    if model >= SUPPORTED {
        let names: Vec<&str> = MODELS[..SUPPORTED].iter().map(|m| m.0).collect();
        return Err(Error::format(
            file,
            format!(
                "camera {id} uses {name}; nerfjit reads {} (undistort other models first with COLMAP's \
                 image_undistorter)",
                names.join(", ")
            ),
        ));
    }
    let p: Vec<f32> = params.iter().map(|&x| x as f32).collect();
    let (fx, fy, cx, cy, d) = match (model, p.as_slice()) {
        (0, &[f, cx, cy]) => (f, f, cx, cy, Distortion::default()),
        (1, &[fx, fy, cx, cy]) => (fx, fy, cx, cy, Distortion::default()),
        (2, &[f, cx, cy, k1]) => (
            f,
            f,
            cx,
            cy,
            Distortion {
                k1,
                ..Default::default()
            },
        ),
        (3, &[f, cx, cy, k1, k2]) => (
            f,
            f,
            cx,
            cy,
            Distortion {
                k1,
                k2,
                ..Default::default()
            },
        ),
        (4, &[fx, fy, cx, cy, k1, k2, p1, p2]) => (
            fx,
            fy,
            cx,
            cy,
            Distortion {
                k1,
                k2,
                k3: 0.0,
                p1,
                p2,
            },
        ),
        _ => {
            return Err(Error::format(
                file,
                format!(
                    "camera {id} ({name}) has {} parameters, expected {}",
                    p.len(),
                    MODELS[model].1
                ),
            ))
        }
    };
    let side = |n: u64| u32::try_from(n).ok().filter(|&n| (1..=1_000_000).contains(&n));
    let (Some(width), Some(height)) = (side(width), side(height)) else {
        return Err(Error::format(
            file,
            format!("camera {id} has an impossible image size {width}×{height}"),
        ));
    };
    let finite = p.iter().all(|x| x.is_finite()) && fx > 0.0 && fy > 0.0;
    if !finite {
        return Err(Error::format(
            file,
            format!(
                "camera {id} has non-finite parameters or a focal length that is not positive: {params:?}"
            ),
        ));
    }
    Ok(ModelCamera {
        id,
        intrinsics: PixelIntrinsics { fx, fy, cx, cy },
        distortion: d,
        width,
        height,
    })
}

/// The lines of a COLMAP text file without its `#` comments, with their 1-based line numbers.
fn text_lines(file: &Path) -> Result<Vec<(usize, String)>> {
    let text = crate::input::read_text_capped(file).map_err(|e| Error::reading(file, e))?;
    Ok(text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.starts_with('#'))
        .map(|(i, l)| (i + 1, l.trim().to_string()))
        .collect())
}

/// The non-empty lines of a COLMAP text file split into words, each with at least `least` words (the
/// `expected` fields), with their line numbers.
fn records(file: &Path, least: usize, expected: &str) -> Result<Vec<(usize, Vec<String>)>> {
    let mut records = Vec::new();
    for (line, text) in text_lines(file)? {
        let words: Vec<String> = text.split_whitespace().map(str::to_string).collect();
        if words.is_empty() {
            continue;
        }
        if words.len() < least {
            return Err(Error::format(file, format!("line {line}: expected {expected}")));
        }
        records.push((line, words));
    }
    Ok(records)
}

/// The fields of a text line parsed as numbers of type `T`.
fn fields<T: std::str::FromStr>(file: &Path, line: usize, words: &[&str]) -> Result<Vec<T>> {
    words
        .iter()
        .map(|w| {
            w.parse()
                .map_err(|_| Error::format(file, format!("line {line}: '{w}' is not a valid number here")))
        })
        .collect()
}

fn text_cameras(file: &Path) -> Result<Vec<ModelCamera>> {
    let mut cameras = Vec::new();
    for (line, words) in records(file, 4, "CAMERA_ID MODEL WIDTH HEIGHT PARAMS")? {
        let words: Vec<&str> = words.iter().map(String::as_str).collect();
        let model = MODELS.iter().position(|m| m.0 == words[1]).ok_or_else(|| {
            Error::format(file, format!("line {line}: unknown camera model '{}'", words[1]))
        })?;
        let numbers: Vec<u64> = fields(file, line, &[words[0], words[2], words[3]])?;
        let id = u32::try_from(numbers[0]).map_err(|_| {
            Error::format(
                file,
                format!("line {line}: camera id {} is too large", numbers[0]),
            )
        })?;
        let params: Vec<f64> = fields(file, line, &words[4..])?;
        let camera = model_camera(file, id, model, (numbers[1], numbers[2]), &params)
            .map_err(|e| Error::format(file, format!("line {line}: {}", reason(e))))?;
        cameras.push(camera);
    }
    Ok(cameras)
}

/// An error's reason without the file name it already carries.
fn reason(e: Error) -> String {
    match e {
        Error::Format { reason, .. } => reason,
        other => other.to_string(),
    }
}

fn text_images(file: &Path) -> Result<Vec<ModelImage>> {
    let lines = text_lines(file)?;
    let mut images = Vec::new();
    // Each image takes two lines: its pose, then its 2D points (possibly empty).
    let mut rest = lines.iter();
    while let Some((line, text)) = rest.next() {
        if text.is_empty() {
            continue;
        }
        let words: Vec<&str> = text.split_whitespace().collect();
        if words.len() < 10 {
            return Err(Error::format(
                file,
                format!("line {line}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME"),
            ));
        }
        let pose: Vec<f64> = fields(file, *line, &words[1..8])?;
        let camera: Vec<u32> = fields(file, *line, &words[8..9])?;
        images.push(image(
            file,
            &format!("line {line}"),
            &pose,
            camera[0],
            words[9..].join(" "),
        )?);
        rest.next();
    }
    Ok(images)
}

/// A registered image from its pose numbers `qw qx qy qz tx ty tz`.
fn image(file: &Path, at: &str, pose: &[f64], camera: u32, name: String) -> Result<ModelImage> {
    let rotation = DQuat::from_xyzw(pose[1], pose[2], pose[3], pose[0]);
    let translation = DVec3::new(pose[4], pose[5], pose[6]);
    if !(rotation.is_finite() && translation.is_finite() && rotation.length() > 1e-6) {
        return Err(Error::format(
            file,
            format!("{at}: the pose {pose:?} needs a finite, non-zero quaternion and translation"),
        ));
    }
    if name.is_empty() || Path::new(&name).is_absolute() || name.split(['/', '\\']).any(|p| p == "..") {
        return Err(Error::format(
            file,
            format!("{at}: name '{name}' must be a relative path inside the image folder"),
        ));
    }
    Ok(ModelImage {
        rotation,
        translation,
        camera,
        name,
    })
}

fn text_points(file: &Path) -> Result<Vec<Vec3>> {
    if !file.is_file() {
        return Ok(Vec::new());
    }
    let mut points = Vec::new();
    for (line, words) in records(file, 4, "POINT3D_ID X Y Z ...")? {
        let words: Vec<&str> = words.iter().map(String::as_str).collect();
        let xyz: Vec<f32> = fields(file, line, &words[1..4])?;
        points.push(Vec3::new(xyz[0], xyz[1], xyz[2]));
    }
    Ok(points)
}

/// A little-endian reader over a binary COLMAP file whose errors name the file.
struct Reader<'a> {
    file: &'a Path,
    bytes: &'a [u8],
    at: usize,
}

impl<'a> Reader<'a> {
    fn new(file: &'a Path, bytes: &'a [u8]) -> Reader<'a> {
        Reader { file, bytes, at: 0 }
    }

    fn take(&mut self, n: usize) -> Result<&[u8]> {
        let end = self
            .at
            .checked_add(n)
            .filter(|&e| e <= self.bytes.len())
            .ok_or_else(|| {
                Error::format(
                    self.file,
                    format!("truncated: needs {n} more bytes at offset {}", self.at),
                )
            })?;
        let slice = &self.bytes[self.at..end];
        self.at = end;
        Ok(slice)
    }

    fn u64(&mut self) -> Result<u64> {
        Ok(u64::from_le_bytes(self.take(8)?.try_into().expect("8 bytes")))
    }

    fn u32(&mut self) -> Result<u32> {
        Ok(u32::from_le_bytes(self.take(4)?.try_into().expect("4 bytes")))
    }

    fn f64(&mut self) -> Result<f64> {
        Ok(f64::from_le_bytes(self.take(8)?.try_into().expect("8 bytes")))
    }

    /// A count of records of at least `record` bytes each, checked against the bytes left.
    fn count(&mut self, what: &str, record: usize) -> Result<usize> {
        let n = self.u64()?;
        let left = (self.bytes.len() - self.at) as u64;
        if n.saturating_mul(record as u64) > left {
            return Err(Error::format(
                self.file,
                format!("declares {n} {what}, more than its {left} remaining bytes can hold"),
            ));
        }
        Ok(n as usize)
    }

    /// A NUL-terminated string.
    fn name(&mut self) -> Result<String> {
        let rest = &self.bytes[self.at..];
        let len = rest
            .iter()
            .position(|&b| b == 0)
            .ok_or_else(|| Error::format(self.file, "truncated: an image name has no end"))?;
        let name = String::from_utf8_lossy(&rest[..len]).into_owned();
        self.at += len + 1;
        Ok(name)
    }
}

fn read_binary(file: &Path) -> Result<Vec<u8>> {
    crate::input::read_capped(file).map_err(|e| Error::reading(file, e))
}

fn binary_cameras(file: &Path) -> Result<Vec<ModelCamera>> {
    let bytes = read_binary(file)?;
    let mut r = Reader::new(file, &bytes);
    let n = r.count("cameras", 24)?;
    let mut cameras = Vec::with_capacity(n);
    for _ in 0..n {
        let id = r.u32()?;
        let model = r.u32()? as usize;
        let size = (r.u64()?, r.u64()?);
        let Some(&(_, count)) = MODELS.get(model) else {
            return Err(Error::format(
                file,
                format!("camera {id} has an unknown model id {model}"),
            ));
        };
        let params = (0..count).map(|_| r.f64()).collect::<Result<Vec<_>>>()?;
        cameras.push(model_camera(file, id, model, size, &params)?);
    }
    Ok(cameras)
}

fn binary_images(file: &Path) -> Result<Vec<ModelImage>> {
    let bytes = read_binary(file)?;
    let mut r = Reader::new(file, &bytes);
    let n = r.count("images", 73)?;
    let mut images = Vec::with_capacity(n);
    for _ in 0..n {
        let id = r.u32()?;
        let pose = (0..7).map(|_| r.f64()).collect::<Result<Vec<_>>>()?;
        let camera = r.u32()?;
        let name = r.name()?;
        let points = r.count("2D points", 24)?;
        r.take(points * 24)?;
        images.push(image(file, &format!("image {id}"), &pose, camera, name)?);
    }
    Ok(images)
}

fn binary_points(file: &Path) -> Result<Vec<Vec3>> {
    if !file.is_file() {
        return Ok(Vec::new());
    }
    let bytes = read_binary(file)?;
    let mut r = Reader::new(file, &bytes);
    let n = r.count("points", 51)?;
    let mut points = Vec::with_capacity(n);
    for _ in 0..n {
        let _id = r.u64()?;
        let xyz = [r.f64()?, r.f64()?, r.f64()?];
        r.take(3 + 8)?; // color and reprojection error
        let track = r.count("track elements", 8)?;
        r.take(track * 8)?;
        points.push(DVec3::from(xyz).as_vec3());
    }
    Ok(points)
}

/// The folder of a model's images when none is named: `images` beside the model's folder or
/// beside its parent (COLMAP's `project/sparse/0` next to `project/images`).
pub fn default_images_folder(model: &Path) -> Option<PathBuf> {
    model
        .ancestors()
        .skip(1)
        .take(2)
        .map(|a| a.join("images"))
        .find(|f| f.is_dir())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data::scratch_folder;

    const CAMERAS: &str =
        "# Camera list\n1 PINHOLE 64 48 70 72 31.5 24.5\n2 OPENCV 64 48 80 80 32 24 -0.1 0.01 0.001 0.002\n";
    // The second image is the first turned 90° about the camera's z axis and moved.
    const IMAGES: &str = "# Image list\n\
        7 1 0 0 0 0 0 4 1 b.png\n\
        1 2 3 4 5 6 7\n\
        3 0.7071067811865476 0 0 0.7071067811865476 1 2 3 2 a.png\n\
        \n";
    const POINTS: &str = "# 3D points\n1 0.5 -0.25 2 255 0 0 0.1 7 0\n";

    fn write_text(dir: &Path) {
        std::fs::write(dir.join("cameras.txt"), CAMERAS).unwrap();
        std::fs::write(dir.join("images.txt"), IMAGES).unwrap();
        std::fs::write(dir.join("points3D.txt"), POINTS).unwrap();
    }

    /// The same model in COLMAP's binary format.
    fn write_binary(dir: &Path) {
        let mut cameras = 2u64.to_le_bytes().to_vec();
        for (id, model, params) in [
            (1u32, 1u32, vec![70.0, 72.0, 31.5, 24.5]),
            (2, 4, vec![80.0, 80.0, 32.0, 24.0, -0.1, 0.01, 0.001, 0.002]),
        ] {
            cameras.extend(id.to_le_bytes());
            cameras.extend(model.to_le_bytes());
            cameras.extend(64u64.to_le_bytes());
            cameras.extend(48u64.to_le_bytes());
            params.iter().for_each(|p: &f64| cameras.extend(p.to_le_bytes()));
        }
        std::fs::write(dir.join("cameras.bin"), cameras).unwrap();
        let mut images = 2u64.to_le_bytes().to_vec();
        let s = std::f64::consts::FRAC_1_SQRT_2;
        for (id, pose, camera, name, points) in [
            (7u32, [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 4.0], 1u32, "b.png", 1u64),
            (3, [s, 0.0, 0.0, s, 1.0, 2.0, 3.0], 2, "a.png", 0),
        ] {
            images.extend(id.to_le_bytes());
            pose.iter().for_each(|p| images.extend(p.to_le_bytes()));
            images.extend(camera.to_le_bytes());
            images.extend(name.as_bytes());
            images.push(0);
            images.extend(points.to_le_bytes());
            for _ in 0..points {
                images.extend(1.5f64.to_le_bytes());
                images.extend(2.5f64.to_le_bytes());
                images.extend(1i64.to_le_bytes());
            }
        }
        std::fs::write(dir.join("images.bin"), images).unwrap();
        let mut points = 1u64.to_le_bytes().to_vec();
        points.extend(1u64.to_le_bytes());
        [0.5, -0.25, 2.0, 0.1]
            .iter()
            .enumerate()
            .for_each(|(i, p): (usize, &f64)| {
                if i == 3 {
                    points.extend([255, 0, 0]);
                }
                points.extend(p.to_le_bytes());
            });
        points.extend(1u64.to_le_bytes());
        points.extend(7u32.to_le_bytes());
        points.extend(0u32.to_le_bytes());
        std::fs::write(dir.join("points3D.bin"), points).unwrap();
    }

    fn check(capture: &Capture, images: &Path) {
        let [a, b] = capture.frames.as_slice() else {
            panic!("{capture:?}")
        };
        assert_eq!(
            (a.image.clone(), b.image.clone()),
            (images.join("a.png"), images.join("b.png"))
        );
        assert_eq!(
            b.camera.intrinsics,
            PixelIntrinsics {
                fx: 70.0,
                fy: 72.0,
                cx: 31.5,
                cy: 24.5
            }
        );
        assert!(b.camera.distortion.is_none());
        assert_eq!(a.camera.distortion.k1, -0.1);
        assert_eq!((a.camera.width, a.camera.height), (64, 48));
        // Identity rotation, t = (0, 0, 4): the camera sits at z = −4 looking down +z (OpenCV),
        // so its OpenGL back axis is −z.
        let c2w = b.camera.c2w;
        assert!(c2w.w_axis.truncate().abs_diff_eq(Vec3::new(0.0, 0.0, -4.0), 1e-6));
        assert!(c2w.z_axis.truncate().abs_diff_eq(-Vec3::Z, 1e-6));
        assert!(c2w.y_axis.truncate().abs_diff_eq(-Vec3::Y, 1e-6));
        // A world point projects where OpenCV's formula puts it, for the rotated camera too.
        let camera = a.camera.camera(64, 48).unwrap();
        let world = Vec3::new(0.3, -0.2, 1.5);
        let r = DMat3::from_quat(DQuat::from_xyzw(
            0.0,
            0.0,
            std::f64::consts::FRAC_1_SQRT_2,
            std::f64::consts::FRAC_1_SQRT_2,
        ));
        let x = r * world.as_dvec3() + DVec3::new(1.0, 2.0, 3.0);
        let (u, v) = (80.0 * x.x / x.z + 32.0, 80.0 * x.y / x.z + 24.0);
        let (row, col) = camera.project(world, 64, 48).unwrap();
        assert!(
            (f64::from(col) - u).abs() < 1e-3 && (f64::from(row) - v).abs() < 1e-3,
            "{row},{col} vs {v},{u}"
        );
        assert_eq!(capture.points, vec![Vec3::new(0.5, -0.25, 2.0)]);
    }

    #[test]
    fn text_and_binary_models_read_the_same() {
        let text_scratch = scratch_folder("colmap-text");
        let text = text_scratch.path();
        write_text(text);
        check(
            &load_colmap(text, &text.join("imgs")).unwrap(),
            &text.join("imgs"),
        );
        let binary_scratch = scratch_folder("colmap-binary");
        let binary = binary_scratch.path();
        write_binary(binary);
        check(
            &load_colmap(binary, &binary.join("imgs")).unwrap(),
            &binary.join("imgs"),
        );
    }

    #[test]
    fn bad_models_name_the_file_and_the_problem() {
        let dir_scratch = scratch_folder("colmap-bad");
        let dir = dir_scratch.path();
        write_text(dir);
        let fisheye = CAMERAS.replace(
            "1 PINHOLE 64 48 70 72 31.5 24.5",
            "1 OPENCV_FISHEYE 64 48 70 72 31.5 24.5 0 0 0 0",
        );
        std::fs::write(dir.join("cameras.txt"), fisheye).unwrap();
        let e = load_colmap(dir, dir).unwrap_err().to_string();
        assert!(
            e.contains("cameras.txt: line 2: camera 1 uses OPENCV_FISHEYE; nerfjit reads"),
            "{e}"
        );
        std::fs::write(dir.join("cameras.txt"), CAMERAS).unwrap();
        std::fs::write(dir.join("images.txt"), IMAGES.replace("2 a.png", "9 a.png")).unwrap();
        let e = load_colmap(dir, dir).unwrap_err().to_string();
        assert!(e.contains("image 'a.png' names camera 9"), "{e}");
        std::fs::write(dir.join("images.txt"), IMAGES.replace("2 a.png", "2 ../a.png")).unwrap();
        let e = load_colmap(dir, dir).unwrap_err().to_string();
        assert!(
            e.contains("must be a relative path inside the image folder"),
            "{e}"
        );
        std::fs::write(
            dir.join("images.txt"),
            IMAGES.replace("0.7071067811865476 1 2", "x 1 2"),
        )
        .unwrap();
        let e = load_colmap(dir, dir).unwrap_err().to_string();
        assert!(e.contains("images.txt: line 4: 'x' is not a valid number"), "{e}");

        let bin_scratch = scratch_folder("colmap-badbin");
        let bin = bin_scratch.path();
        write_binary(bin);
        let mut bytes = std::fs::read(bin.join("images.bin")).unwrap();
        bytes[..8].copy_from_slice(&u64::MAX.to_le_bytes());
        std::fs::write(bin.join("images.bin"), &bytes).unwrap();
        let e = load_colmap(bin, bin).unwrap_err().to_string();
        assert!(
            e.contains("images.bin: declares 18446744073709551615 images"),
            "{e}"
        );
        bytes[..8].copy_from_slice(&2u64.to_le_bytes());
        std::fs::write(bin.join("images.bin"), &bytes[..bytes.len() - 5]).unwrap();
        let e = load_colmap(bin, bin).unwrap_err().to_string();
        assert!(e.contains("images.bin: truncated"), "{e}");
        let empty_scratch = scratch_folder("colmap-empty");
        let empty = empty_scratch.path();
        let e = load_colmap(empty, empty).unwrap_err().to_string();
        assert!(e.contains("no COLMAP model here"), "{e}");
    }
}
