//! Files the page asks for: an orbit video around the current view and a mesh of the scene, made with the
//! same renderer and mesher as the CLI commands the page shows beside them.

use std::path::PathBuf;

use glam::{Quat, Vec3};
use image::RgbImage;

use super::scene::{Layer, Scene, ViewCamera};
use crate::failure::{Failure, Result};
use crate::mesh::{extract_and_write, MeshArgs};

/// What to export.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Export {
    /// An MP4 (H.264) orbit around the view's target.
    Video,
    /// A PLY mesh of the scene's surface (or of a density level).
    Mesh,
}

impl Export {
    /// The export named `name` (`video` or `mesh`).
    pub fn parse(name: &str) -> Option<Export> {
        match name {
            "video" => Some(Export::Video),
            "mesh" => Some(Export::Mesh),
            _ => None,
        }
    }
}

/// Frames of an orbit video.
pub const ORBIT_FRAMES: usize = 60;

/// An exported file.
pub struct File {
    /// The name the page saves it under.
    pub name: String,
    /// Its MIME type.
    pub mime: &'static str,
    /// Its contents.
    pub bytes: Vec<u8>,
}

/// Makes `what` for `scene` from `view`; `stem` names the file.
pub fn export(what: Export, scene: &Scene, view: &ViewCamera, stem: &str) -> Result<File> {
    match what {
        Export::Video => video(scene, view, stem),
        Export::Mesh => mesh(scene, stem),
    }
}

/// A scratch file for an export, removed when dropped.
struct Scratch(PathBuf);

impl Scratch {
    fn new(extension: &str) -> Scratch {
        static NEXT: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
        let n = NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        Scratch(std::env::temp_dir().join(format!("nerfjit-view-{}-{n}.{extension}", std::process::id())))
    }

    fn read(&self) -> Result<Vec<u8>> {
        std::fs::read(&self.0)
            .map_err(|e| Failure::Message(format!("cannot read back '{}': {e}", self.0.display())))
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.0);
    }
}

/// The cameras of a full turn of `view` about its target and up direction.
pub fn orbit(view: &ViewCamera, frames: usize) -> Vec<ViewCamera> {
    let axis = view.up.normalize_or(Vec3::Y);
    (0..frames)
        .map(|i| {
            let turn = Quat::from_axis_angle(axis, std::f32::consts::TAU * i as f32 / frames as f32);
            ViewCamera {
                eye: view.target + turn * (view.eye - view.target),
                ..*view
            }
        })
        .collect()
}

fn video(scene: &Scene, view: &ViewCamera, stem: &str) -> Result<File> {
    // Volume fields render slowly: smaller frames keep the wait reasonable.
    let side = if scene.kind() == "surface" { 256 } else { 128 };
    let frames = orbit(view, ORBIT_FRAMES)
        .iter()
        .map(|camera| scene.render(camera, side, side, Layer::Color))
        .collect::<Result<Vec<RgbImage>>>()?;
    let scratch = Scratch::new("mp4");
    nerfjit_runtime::video::save_mp4(&scratch.0, &frames, 40)?;
    Ok(File {
        name: format!("{stem}-orbit.mp4"),
        mime: "video/mp4",
        bytes: scratch.read()?,
    })
}

fn mesh(scene: &Scene, stem: &str) -> Result<File> {
    let (function, level, radius) = scene.mesh_settings();
    let scratch = Scratch::new("ply");
    let args = MeshArgs {
        function,
        resolution: 160,
        bounds: ([-radius; 3], [radius; 3]),
        level,
        out: &scratch.0,
        gif: None,
        prune: true,
        color: None,
    };
    extract_and_write(scene.program(), scene.params(), &args)?;
    Ok(File {
        name: format!("{stem}.ply"),
        mime: "application/octet-stream",
        bytes: scratch.read()?,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    #[test]
    fn an_orbit_turns_about_the_up_axis_at_a_constant_distance() {
        let view = ViewCamera {
            eye: Vec3::new(3.0, 1.0, 0.0),
            target: Vec3::new(0.0, 1.0, 0.0),
            up: Vec3::Y,
            focal: 1.0,
        };
        let cameras = orbit(&view, 4);
        assert_eq!(cameras[0], view);
        assert!(
            (cameras[1].eye - Vec3::new(0.0, 1.0, -3.0)).length() < 1e-5,
            "{}",
            cameras[1].eye
        );
        assert!((cameras[2].eye - Vec3::new(-3.0, 1.0, 0.0)).length() < 1e-5);
        assert!(cameras.iter().all(|c| c.target == view.target && c.focal == 1.0));
    }

    #[test]
    fn a_mesh_and_a_video_of_a_sphere() {
        let program = nerfjit_dsl::compile("ball.sdf", "fn sdf(p: vec3) -> f32 = length(p) - 1").unwrap();
        let params = program.param_values.clone();
        let scene = Scene::compile(program, &params, Path::new(".")).unwrap();
        let mesh = export(Export::Mesh, &scene, &ViewCamera::default(), "ball").unwrap();
        assert_eq!(mesh.name, "ball.ply");
        assert!(mesh.bytes.starts_with(b"ply\n"));
        let view = ViewCamera {
            eye: Vec3::new(0.0, 0.0, -4.0),
            ..ViewCamera::default()
        };
        let video = export(Export::Video, &scene, &view, "ball").unwrap();
        assert_eq!(&video.bytes[4..8], b"ftyp", "an MP4 file");
    }
}
