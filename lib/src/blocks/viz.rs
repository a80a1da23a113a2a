//! `viz { ... }`: the teaching images of cameras and rays — the pixel grid in NDC, the ray directions, and
//! stratified sample points along rays seen from a second camera.

use std::path::PathBuf;

use nerfjit_dsl::Diagnostic;
use nerfjit_runtime::output::viz::{
    pixel_grid_image, ray_directions_image, sample_points_image, SamplePoints,
};
use nerfjit_runtime::{save_png, Camera};

use crate::failure::Result;
use crate::settings::block::Block;
use crate::settings::typed::typed_settings;

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

typed_settings! {
    /// The settings of a `viz` block, as read.
    pub struct VizSettings for crate::settings::schema::VIZ {
        camera: required,
        view: value,
        size: size,
        near: number,
        far: number,
        samples: whole,
        rays: whole,
        grid: output,
        directions: output,
        points: output,
    }
}

impl VizPlan {
    /// Reads and checks a `viz` block.
    pub fn new(mut b: Block) -> Result<VizPlan> {
        let s = VizSettings::read(&mut b)?;
        let camera = b.cameras_of(&s.camera)?.remove(0);
        let view = match &s.view {
            Some(v) => Some(b.cameras_of(v)?.remove(0)),
            None => None,
        };
        let size = s.size;
        let (near, far) = b.interval(s.near, s.far)?;
        let (samples, rays) = (s.samples as usize, s.rays as usize);
        let (grid, directions, points_out) = (s.grid, s.directions, s.points);
        if grid.is_none() && directions.is_none() && points_out.is_none() {
            return Err(b.error(
                Diagnostic::new(b.span(), "this viz block draws nothing: it names no output image")
                    .with_hint("add grid: \"grid.png\", directions: \"dirs.png\" or points: \"points.png\""),
            ));
        }
        if points_out.is_some() && view.is_none() {
            return Err(b.error(
                Diagnostic::new(b.span(), "drawing sample points needs a second camera 'view'")
                    .with_hint("add e.g. view: look_at(eye: [4, 2, -4], at: [0, 0, 0], up: [0, 1, 0])"),
            ));
        }
        b.finish()?;
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
