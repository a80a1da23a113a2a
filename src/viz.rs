//! `viz { ... }`: the teaching images of cameras and rays — the pixel grid in NDC, the ray directions, and
//! stratified sample points along rays seen from a second camera.

use std::path::{Path, PathBuf};

use nerfjit_dsl::config::Settings;
use nerfjit_dsl::{Diagnostic, Program};
use nerfjit_runtime::viz::{pixel_grid_image, ray_directions_image, sample_points_image, SamplePoints};
use nerfjit_runtime::{save_png, Camera};

use crate::failure::{at, Result};
use crate::render::{cameras_setting, output_setting, size_setting};
use crate::settings::{ranged, whole};

const KEYS: &[&str] = &[
    "camera",
    "view",
    "size",
    "near",
    "far",
    "samples",
    "rays",
    "grid",
    "directions",
    "points",
];

/// A checked `viz` block.
pub struct VizPlan {
    camera: Camera,
    view: Option<Camera>,
    size: (u32, u32),
    points: SamplePoints,
    grid: Option<PathBuf>,
    directions: Option<PathBuf>,
    points_out: Option<PathBuf>,
}

impl VizPlan {
    /// Reads and checks a `viz` block.
    pub fn new(
        program: &Program,
        mut s: Settings,
        script_dir: &Path,
        out_dir: Option<&Path>,
    ) -> Result<VizPlan> {
        let err = |d| at(program, d);
        let span = s.span;
        let camera_v = s
            .take("camera")
            .ok_or_else(|| err(Diagnostic::new(span, "the viz block needs 'camera'")))?;
        let camera = cameras_setting(program, &camera_v, script_dir)?.remove(0);
        let view = match s.take("view") {
            Some(v) => Some(cameras_setting(program, &v, script_dir)?.remove(0)),
            None => None,
        };
        let size = size_setting(program, s.take("size"))?;
        let mut num = |key: &str, lo: f64, hi: f64, default: f64| -> Result<f64> {
            Ok(match s.take(key) {
                Some(v) => ranged(&v, lo, hi).map_err(|d| at(program, d))?,
                None => default,
            })
        };
        let (near, far) = (
            num("near", 0.0, 1e6, 0.0)? as f32,
            num("far", 0.0, 1e9, 5.0)? as f32,
        );
        if far <= near {
            return Err(err(Diagnostic::new(
                span,
                format!("far ({far}) must exceed near ({near})"),
            )));
        }
        let mut count = |key: &str, default: u64| -> Result<usize> {
            Ok(match s.take(key) {
                Some(v) => whole(&v, 1, 100_000).map_err(|d| at(program, d))? as usize,
                None => default as usize,
            })
        };
        let samples = count("samples", 16)?;
        let rays = count("rays", 64)?;
        let mut file = |key: &str| {
            s.take(key)
                .map(|v| output_setting(&v, out_dir))
                .transpose()
                .map_err(err)
        };
        let (grid, directions, points_out) = (file("grid")?, file("directions")?, file("points")?);
        if points_out.is_some() && view.is_none() {
            return Err(err(Diagnostic::new(
                span,
                "drawing sample points needs a second camera 'view'",
            )
            .with_hint(
                "add e.g. view: look_at(eye: [4, 2, -4], at: [0, 0, 0], up: [0, 1, 0])",
            )));
        }
        s.finish(KEYS).map_err(err)?;
        Ok(VizPlan {
            camera,
            view,
            size,
            points: SamplePoints {
                rays,
                samples,
                near,
                far,
                seed: 0,
            },
            grid,
            directions,
            points_out,
        })
    }

    /// Writes the requested images; returns a summary line.
    pub fn run(&self) -> Result<String> {
        let (w, h) = self.size;
        let mut written = Vec::new();
        if let Some(path) = &self.grid {
            save_png(path, pixel_grid_image(&self.camera, w, h)?)?;
            written.push(path.display().to_string());
        }
        if let Some(path) = &self.directions {
            save_png(path, ray_directions_image(&self.camera, w, h)?)?;
            written.push(path.display().to_string());
        }
        if let (Some(path), Some(view)) = (&self.points_out, &self.view) {
            save_png(path, sample_points_image(view, &self.camera, w, h, &self.points)?)?;
            written.push(path.display().to_string());
        }
        Ok(format!("wrote {}", written.join(", ")))
    }
}
