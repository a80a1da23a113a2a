//! The `camera` setting of blocks: the course's orbit, a general orbit, one look-at camera, or a camera
//! file (the course's box_cameras.json, Blender transforms, a nerfstudio transforms.json, a COLMAP model,
//! an LLFF scene or a DTU scan).

use std::path::Path;

use glam::{Vec2, Vec3};
use nerfjit_dsl::config::{Spanned, Value};
use nerfjit_dsl::Diagnostic;
use nerfjit_runtime::{
    choose_layout, default_images_folder, is_camera_path, load_blender_cameras, load_box_cameras,
    load_camera_path, load_colmap, load_dtu, load_llff, load_nerfstudio, orbit, surround, Camera, Layout, Up,
};

use crate::settings::primitives::{triple, CallArgs};

fn up(args: &CallArgs) -> Result<Up, Diagnostic> {
    Ok(Up::named(&args.choice("up", &["y", "z"], "y")?).unwrap_or(Up::Y))
}

/// The cameras a `camera` value describes; a camera file is resolved against `script_dir`. The outer error
/// points into the script; the inner one is the runtime's (a bad file, a degenerate camera).
pub fn cameras(v: &Spanned, script_dir: &Path) -> Result<Result<Vec<Camera>, String>, Diagnostic> {
    let Value::Call(name, _) = &v.value else {
        return Err(Diagnostic::new(v.span, format!("expected a camera path, found {}", v.describe()))
            .with_hint("write surround(radius: 3, frames: 20, up: z, focal: 1), orbit(...) or cameras(\"file.json\")"));
    };
    let result = match name.as_str() {
        "surround" => {
            let a = CallArgs::new(v, &["radius", "frames", "up", "focal"])?;
            let frames = frame_count(&a, 20.0)?;
            surround(
                a.number("radius", None)? as f32,
                frames,
                up(&a)?,
                a.number("focal", Some(1.0))? as f32,
            )
        }
        "orbit" => {
            let a = CallArgs::new(v, &["radius", "elevation", "frames", "up", "focal"])?;
            orbit(
                a.number("radius", None)? as f32,
                a.number("elevation", Some(0.0))? as f32,
                frame_count(&a, 36.0)?,
                up(&a)?,
                a.number("focal", Some(1.0))? as f32,
            )
        }
        "cameras" => {
            let a = CallArgs::new(v, &["file", "normalize"])?;
            let file = script_dir.join(a.string("file")?);
            let normalize = match a.raw("normalize") {
                Some(_) => Some(a.choice("normalize", &["true", "false"], "true")? == "true"),
                None => None,
            };
            camera_file(&file, normalize, None).map(|(cameras, _)| cameras)
        }
        "look_at" => {
            let a = CallArgs::new(v, &["eye", "at", "up", "focal"])?;
            let vec3 = |slot: &str, d: [f32; 3]| -> Result<Vec3, Diagnostic> {
                Ok(Vec3::from_array(match a.raw(slot) {
                    Some(s) => triple(s)?,
                    None => d,
                }))
            };
            let focal = a.number("focal", Some(1.0))? as f32;
            Camera::look_at(
                vec3("eye", [0.0, 0.0, -3.0])?,
                vec3("at", [0.0; 3])?,
                vec3("up", [0.0, 1.0, 0.0])?,
                Vec2::splat(focal),
                Vec2::ZERO,
            )
            .map(|c| vec![c])
        }
        other => {
            return Err(Diagnostic::new(v.span, format!("unknown camera path '{other}'"))
                .with_hint("use surround(...), orbit(...), look_at(...) or cameras(\"file.json\")"))
        }
    };
    Ok(result.map_err(|e| e.to_string()))
}

/// The (width, height) of a camera file's images.
pub type FrameSize = (u32, u32);

/// The cameras of a camera file — the course's, Blender's, a nerfstudio `transforms.json` or
/// `camera_path.json`, a COLMAP model folder, an LLFF scene folder or a DTU scan folder — and the
/// (width, height) of its images when the file says. A folder holding several layouts is read as `layout`
/// when given, else as the most specific ([`choose_layout`], noted). A capture is normalized by its own
/// cameras as training normalizes one when `normalize` is `Some(true)`, kept in its frame when
/// `Some(false)`, and with `None` as training does by default: captures normalized, DTU scans in the
/// scan's frame.
pub fn camera_file(
    file: &Path,
    normalize: Option<bool>,
    layout: Option<Layout>,
) -> nerfjit_runtime::Result<(Vec<Camera>, Option<FrameSize>)> {
    let text = || nerfjit_runtime::input::read_text_capped(file).unwrap_or_default();
    if layout.is_none() && file.is_file() && is_camera_path(&text()) {
        let path = load_camera_path(file)?;
        return Ok((path.cameras, Some((path.width, path.height))));
    }
    let Some(chosen) = choose_layout(file, layout)? else {
        let set = load_box_cameras(file)?;
        return Ok((set.cameras, set.image_size));
    };
    if let Some(note) = chosen.note(file) {
        crate::console::note(&note);
    }
    let source = chosen.found.source.as_path();
    // A DTU scan stays in its own frame (the object inside the unit sphere) unless asked; captures are
    // normalized unless asked not to be.
    let normalize_capture = normalize.unwrap_or(chosen.found.layout != Layout::Dtu);
    let mut capture = match chosen.found.layout {
        Layout::Dtu => load_dtu(source, false)?,
        Layout::Llff => {
            let scales = nerfjit_runtime::data::llff::image_scales(source);
            load_llff(source, scales.last().copied().unwrap_or(1))?.capture
        }
        Layout::Colmap => {
            let images = default_images_folder(source).unwrap_or_else(|| source.to_path_buf());
            load_colmap(source, &images)?
        }
        Layout::Nerfstudio => load_nerfstudio(source)?,
        Layout::Blender if source.is_dir() => {
            return Err(nerfjit_runtime::Error::Invalid(format!(
                "'{}' is a Blender data set ({}): name one of its camera files",
                file.display(),
                chosen.found.evidence
            )))
        }
        Layout::Blender => return Ok((load_blender_cameras(source)?.cameras, None)),
    };
    if normalize_capture {
        capture.normalize()?;
    }
    let size = capture.frames.first().map(|f| (f.camera.width, f.camera.height));
    Ok((capture.cameras(source, 1, None)?, size))
}

/// The most frames a camera path may have.
pub const MAX_FRAMES: usize = 10_000;

/// The `frames` argument of a path: a whole number from 1 to [`MAX_FRAMES`].
fn frame_count(a: &CallArgs, default: f64) -> Result<usize, Diagnostic> {
    let n = a.number("frames", Some(default))?;
    if n.fract() == 0.0 && (1.0..=MAX_FRAMES as f64).contains(&n) {
        Ok(n as usize)
    } else {
        Err(Diagnostic::new(a.span(), format!("{n} frames is out of range"))
            .with_hint(format!("a camera path has 1 to {MAX_FRAMES} frames")))
    }
}

/// 36 cameras circling the box `bounds` about the `up` axis, 25° above its center, framing it.
pub fn turntable(bounds: ([f32; 3], [f32; 3]), up: Up) -> nerfjit_runtime::Result<Vec<Camera>> {
    let (lo, hi) = (Vec3::from_array(bounds.0), Vec3::from_array(bounds.1));
    let center = lo.lerp(hi, 0.5);
    let radius = 0.8 * (hi - lo).length();
    let elevation = 25f32.to_radians();
    // Two directions spanning the plane of the circle, right-handed with `up`.
    let (a, b) = match up {
        Up::Y => (Vec3::X, Vec3::NEG_Z),
        Up::Z => (Vec3::X, Vec3::Y),
    };
    (0..36)
        .map(|i| {
            let phi = std::f32::consts::TAU * i as f32 / 36.0 + std::f32::consts::FRAC_PI_2;
            let flat = radius * elevation.cos();
            let eye =
                center + flat * phi.cos() * a + flat * phi.sin() * b + radius * elevation.sin() * up.vector();
            Camera::look_at(eye, center, up.vector(), Vec2::splat(1.2), Vec2::ZERO)
        })
        .collect()
}
