//! `nerfjit data check`: what a data set holds (its camera files, views, image sizes and formats,
//! intrinsics, where the cameras are), or precisely what is wrong with it, before any training. Reads
//! Blender and course camera files, nerfstudio / instant-ngp `transforms.json`, COLMAP model folders,
//! LLFF scenes (`poses_bounds.npy`) and DTU scans (`cameras_sphere.npz`); a folder holding several of
//! these is read as the most specific, or as `--format` names, and the report says which it holds.

use std::path::{Path, PathBuf};

use image::ImageDecoder;
use nerfjit_runtime::{
    choose_layout, default_images_folder, dtu_cameras_file, is_nerfstudio, load_blender_cameras,
    load_box_cameras, load_colmap, load_dtu, load_llff, load_nerfstudio, CameraFormat, CameraSet, Capture,
    Layout,
};

use crate::failure::{Failure, Result};

/// The camera files looked for in a folder, in this order.
const CAMERA_FILES: &[&str] = &[
    "transforms_train.json",
    "transforms_val.json",
    "transforms_test.json",
    "transforms.json",
    "box_cameras.json",
];

/// Checks `path`, a camera file or a data folder, read as `format` when given, else by the most specific
/// layout it holds (and says so when it holds several); a report, or what is wrong.
pub fn run(path: &Path, format: Option<Layout>) -> Result<String> {
    if !path.exists() {
        return Err(Failure::Message(format!("'{}' does not exist", path.display())));
    }
    let chosen = choose_layout(path, format)?;
    let note = chosen.as_ref().and_then(|c| c.note(path)).map(|n| n + "\n");
    let report = match chosen.map(|c| (c.found.layout, c.found.source)) {
        Some((Layout::Dtu, folder)) => check_dtu(&folder),
        Some((Layout::Llff, folder)) => check_llff(&folder),
        Some((Layout::Colmap, model)) => check_colmap(&model),
        Some((Layout::Nerfstudio, file)) => check_file(&file),
        _ => check_camera_files(path),
    }?;
    Ok(note.unwrap_or_default() + &report)
}

/// Checks a camera file, or every camera file of a folder (Blender's splits, the course's).
fn check_camera_files(path: &Path) -> Result<String> {
    let files: Vec<PathBuf> = if path.is_dir() {
        let mut found: Vec<PathBuf> = CAMERA_FILES
            .iter()
            .map(|f| path.join(f))
            .filter(|f| f.is_file())
            .collect();
        if found.is_empty() {
            found = other_camera_files(path)?;
        }
        if found.is_empty() {
            return Err(Failure::Message(format!(
                "'{}' holds no camera file: looked for {} and other .json files with frames or cameras",
                path.display(),
                CAMERA_FILES.join(", ")
            )));
        }
        found
    } else {
        vec![path.to_path_buf()]
    };
    let reports = files.iter().map(|f| check_file(f)).collect::<Result<Vec<_>>>()?;
    Ok(reports.concat())
}

/// The `.json` files of `folder` that look like camera files, by name.
fn other_camera_files(folder: &Path) -> Result<Vec<PathBuf>> {
    let entries = std::fs::read_dir(folder)
        .map_err(|e| Failure::Message(format!("cannot list '{}': {e}", folder.display())))?;
    let mut files: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "json") && format_of(p).is_ok())
        .collect();
    files.sort();
    Ok(files)
}

fn format_of(file: &Path) -> Result<CameraFormat> {
    let text = nerfjit_runtime::input::read_text_capped(file)
        .map_err(|e| Failure::Message(format!("cannot read '{}': {e}", file.display())))?;
    CameraFormat::of_text(&text).ok_or_else(|| {
        Failure::Message(format!(
            "'{}' is neither a Blender transforms file (camera_angle_x, frames) nor a course camera file \
             (image_size, cameras)",
            file.display()
        ))
    })
}

/// One camera file: its report, or the first problem found.
fn check_file(file: &Path) -> Result<String> {
    let text = nerfjit_runtime::input::read_text_capped(file)
        .map_err(|e| Failure::Message(format!("cannot read '{}': {e}", file.display())))?;
    if is_nerfstudio(&text) {
        let capture = load_nerfstudio(file)?;
        return check_capture(file, "nerfstudio / instant-ngp", capture, true);
    }
    let format = format_of(file)?;
    let set = match format {
        CameraFormat::Blender => load_blender_cameras(file)?,
        CameraFormat::Box => load_box_cameras(file)?,
    };
    let n = set.cameras.len();
    let mut out = format!(
        "{}: {} cameras\n",
        file.display(),
        match format {
            CameraFormat::Blender => "Blender (NeRF-synthetic)",
            CameraFormat::Box => "course (PyTorch3D look-at)",
        }
    );
    let (images, (width, _)) = image_summary(&set)?;
    out += &format!("  {n} view{}, {images}\n", if n == 1 { "" } else { "s" });
    if format == CameraFormat::Blender {
        let scale = set.cameras[0].ndc_scale().pixels(width, width);
        let focal = set.cameras[0].focal().x * 0.5 * scale;
        out += &format!(
            "  focal {focal:.1} px for {width} px wide images ({:.1}° horizontal field of view)\n",
            2.0 * (0.5 * width as f32 / focal).atan().to_degrees()
        );
    }
    let centers: Vec<glam::Vec3> = set.cameras.iter().map(|c| c.position()).collect();
    let distances: Vec<f32> = centers.iter().map(|c| c.length()).collect();
    let (near, far) = (
        distances.iter().copied().fold(f32::INFINITY, f32::min),
        distances.iter().copied().fold(0.0, f32::max),
    );
    let lo = centers.iter().fold(glam::Vec3::INFINITY, |a, c| a.min(*c));
    let hi = centers.iter().fold(glam::Vec3::NEG_INFINITY, |a, c| a.max(*c));
    out += &format!(
        "  camera centers {near:.2} to {far:.2} from the origin, within [{:.2}, {:.2}, {:.2}] to [{:.2}, {:.2}, {:.2}]\n",
        lo.x, lo.y, lo.z, hi.x, hi.y, hi.z
    );
    Ok(out)
}

/// Whether every image exists and all have one size: e.g. "images 800×800 PNG (RGBA), all present", and
/// that (width, height).
fn image_summary(set: &CameraSet) -> Result<(String, (u32, u32))> {
    let missing: Vec<&PathBuf> = set.images.iter().filter(|p| !p.is_file()).collect();
    if !missing.is_empty() {
        let shown: Vec<String> = missing
            .iter()
            .take(3)
            .map(|p| format!("'{}'", p.display()))
            .collect();
        return Err(Failure::Message(format!(
            "{} of the {} images are missing: {}{}",
            missing.len(),
            set.images.len(),
            shown.join(", "),
            if missing.len() > 3 { ", ..." } else { "" }
        )));
    }
    let mut kinds: Vec<(u32, u32, String)> = Vec::new();
    for path in &set.images {
        let kind = image_kind(path)?;
        if let Some((w, h)) = set.image_size {
            if (kind.0, kind.1) != (w, h) {
                return Err(Failure::Message(format!(
                    "'{}' is {}×{}, but the camera file says the images are {w}×{h}",
                    path.display(),
                    kind.0,
                    kind.1
                )));
            }
        }
        if !kinds.contains(&kind) {
            kinds.push(kind);
        }
    }
    let sizes: Vec<(u32, u32)> = kinds.iter().map(|k| (k.0, k.1)).collect();
    if sizes.iter().any(|s| *s != sizes[0]) {
        return Err(Failure::Message(format!(
            "the images differ in size ({}): nerfjit trains on images of one size",
            kinds
                .iter()
                .map(|(w, h, what)| format!("{w}×{h} {what}"))
                .collect::<Vec<_>>()
                .join(", ")
        )));
    }
    let formats: Vec<&str> = kinds.iter().map(|k| k.2.as_str()).collect();
    let (w, h) = sizes[0];
    Ok((
        format!("images {w}×{h} {}, all present", formats.join(" and ")),
        (w, h),
    ))
}

/// Width, height and format of an image, read from its header only (`.npy` images: from their shape).
fn image_kind(path: &Path) -> Result<(u32, u32, String)> {
    let bad =
        |e: &dyn std::fmt::Display| Failure::Message(format!("cannot read image '{}': {e}", path.display()));
    if path.extension().is_some_and(|e| e == "npy") {
        let image = nerfjit_runtime::read_npy_rgb(path)?;
        return Ok((image.width, image.height, "NumPy RGB".into()));
    }
    let reader = image::ImageReader::open(path)
        .map_err(|e| bad(&e))?
        .with_guessed_format()
        .map_err(|e| bad(&e))?;
    let format = reader
        .format()
        .map_or("unknown format".to_string(), |f| format!("{f:?}").to_uppercase());
    let decoder = reader.into_decoder().map_err(|e| bad(&e))?;
    let (w, h) = decoder.dimensions();
    Ok((w, h, format!("{format} ({:?})", decoder.color_type())))
}

/// A COLMAP model folder with its images beside it.
fn check_colmap(folder: &Path) -> Result<String> {
    let images = default_images_folder(folder).ok_or_else(|| {
        Failure::Message(format!(
            "'{}' is a COLMAP model, but there is no 'images' folder beside it or its parent",
            folder.display()
        ))
    })?;
    let capture = load_colmap(folder, &images)?;
    check_capture(
        folder,
        &format!("COLMAP (images in {})", images.display()),
        capture,
        true,
    )
}

/// An LLFF scene: its smallest image folder's views (every folder of images is listed), and its depth
/// bounds.
fn check_llff(folder: &Path) -> Result<String> {
    let folders = nerfjit_runtime::data::llff::image_scales(folder);
    let downscale = folders.last().copied().unwrap_or(1);
    let scene = load_llff(folder, downscale)?;
    let listed: Vec<String> = folders
        .iter()
        .map(|k| match k {
            1 => "images".to_string(),
            k => format!("images_{k}"),
        })
        .collect();
    let mut out = check_capture(
        folder,
        &format!(
            "LLFF (poses_bounds.npy; image folders {}; checked: {})",
            listed.join(", "),
            scene.images.display()
        ),
        scene.capture,
        true,
    )?;
    out += &format!(
        "  train with data: llff(\"{}\", downscale: {downscale}) and LLFF's split, val: holdout(every: 8)\n",
        folder.display()
    );
    Ok(out)
}

/// A DTU scan, with its masks when it has them.
fn check_dtu(folder: &Path) -> Result<String> {
    let masks = folder.join("mask").is_dir();
    let capture = load_dtu(folder, masks)?;
    let distances: Vec<f32> = capture
        .frames
        .iter()
        .map(|f| f.camera.c2w.w_axis.truncate().length())
        .collect();
    let (near, far) = (
        distances.iter().copied().fold(f32::INFINITY, f32::min),
        distances.iter().copied().fold(0.0, f32::max),
    );
    let masked = if masks {
        let missing = capture
            .frames
            .iter()
            .filter_map(|f| f.mask.as_ref())
            .find(|m| image_kind(m).is_err());
        if let Some(mask) = missing {
            image_kind(mask)?;
        }
        format!("{} masks", capture.frames.len())
    } else {
        "no masks".to_string()
    };
    let camera_file = dtu_cameras_file(folder).expect("checked by the caller");
    let mut out = check_capture(
        folder,
        &format!("DTU / IDR / NeuS ({}, {masked})", camera_file.display()),
        capture,
        false,
    )?;
    out += &format!(
        "  in the scan's frame (the default, normalize: false), the object inside the unit sphere: camera centers \
         {near:.2} to {far:.2} from the origin\n"
    );
    Ok(out)
}

/// A capture's report: views, image sizes (from the headers, checked against the cameras), intrinsics,
/// sparse points, and where normalization puts the cameras.
fn check_capture(source: &Path, kind: &str, mut capture: Capture, normalized: bool) -> Result<String> {
    let n = capture.frames.len();
    let mut out = format!("{}: {kind} cameras\n", source.display());
    let set = CameraSet {
        cameras: Vec::new(),
        images: capture.frames.iter().map(|f| f.image.clone()).collect(),
        image_size: None,
    };
    // The images all have one size (or image_summary said otherwise): each camera must state it.
    let (images, (w, h)) = image_summary(&set)?;
    for frame in &capture.frames {
        if (w, h) != (frame.camera.width, frame.camera.height) {
            return Err(Failure::Message(format!(
                "'{}' is {w}×{h}, but its camera says {}×{}",
                frame.image.display(),
                frame.camera.width,
                frame.camera.height
            )));
        }
    }
    out += &format!("  {n} view{}, {images}\n", if n == 1 { "" } else { "s" });
    let focal: Vec<f32> = capture.frames.iter().map(|f| f.camera.intrinsics.fx).collect();
    let (lo, hi) = (
        focal.iter().copied().fold(f32::INFINITY, f32::min),
        focal.iter().copied().fold(0.0, f32::max),
    );
    let distorted = capture
        .frames
        .iter()
        .filter(|f| !f.camera.distortion.is_none())
        .count();
    out += &format!(
        "  focal {lo:.1} to {hi:.1} px; {distorted} of {n} views with lens distortion (undistorted on load)\n"
    );
    if !capture.points.is_empty() {
        out += &format!("  {} sparse points\n", capture.points.len());
    }
    if let Some(scale) = capture.aabb_scale {
        out += &format!("  aabb_scale {scale}\n");
    }
    if let Some((near, far)) = capture.depth_bounds {
        out += &format!("  depth bounds {near:.3} to {far:.3} in the capture's units\n");
    }
    let normalization = capture.normalize()?;
    let c = normalization.center;
    out += &format!(
        "  normalized ({}): z up, centered on what the cameras look at, scaled by {:.4} so the cameras \
         are 4 units away on average (center [{:.3}, {:.3}, {:.3}] in the rotated capture)\n",
        if normalized {
            "the default"
        } else {
            "with normalize: true"
        },
        normalization.scale,
        c.x,
        c.y,
        c.z
    );
    if let Some((near, far)) = capture.depth_bounds {
        out += &format!("  depth bounds normalized: {near:.3} to {far:.3}\n");
    }
    if let Some(extent) = capture.aabb_extent(Some(&normalization)) {
        out += &format!(
            "  aabb_scale's box normalized: within ±{extent:.2} (an occupancy grid outside contracted space needs \
             bounds at least that)\n"
        );
    }
    Ok(out)
}
