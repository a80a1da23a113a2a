//! Files the page asks for: an orbit video around the current view and a mesh of the scene, made with the
//! same renderer and mesher as the CLI commands the page shows beside them, and a checkpoint of the params
//! shown with the script as edited. A bake's video shows its splats; its mesh and checkpoint are those of
//! the field it was baked from.

use std::path::PathBuf;

use glam::{Quat, Vec3};
use image::RgbImage;

use super::scene::{Layer, Scene, ViewCamera};
use nerfjit::blocks::mesh::{extract_and_write, MeshArgs};
use nerfjit::failure::{Failure, Result};

/// What to export.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Export {
    /// An MP4 (H.264) orbit around the view's target.
    Video,
    /// A PLY mesh of the scene's surface (or of a density level).
    Mesh,
    /// A checkpoint (safetensors) of the params shown, holding the script as edited, that `render`,
    /// `mesh`, `eval-views` and `view` read. It has no optimizer state: Adam starts afresh if a run
    /// resumes from it.
    Checkpoint,
}

impl Export {
    /// The export named `name` (`video`, `mesh` or `checkpoint`).
    pub fn parse(name: &str) -> Option<Export> {
        match name {
            "video" => Some(Export::Video),
            "mesh" => Some(Export::Mesh),
            "checkpoint" => Some(Export::Checkpoint),
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

/// Makes `what` for `scene` from `view`; `stem` names the file and `step` is the training step of the
/// params shown (0 outside a training run).
pub fn export(what: Export, scene: &Scene, view: &ViewCamera, stem: &str, step: u32) -> Result<File> {
    match what {
        Export::Video => video(scene, view, stem),
        Export::Mesh => mesh(scene, stem),
        Export::Checkpoint => checkpoint(scene, stem, step),
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
    let side = if scene.kind() == "volume" { 128 } else { 256 };
    let frames = orbit(view, ORBIT_FRAMES)
        .iter()
        .map(|camera| scene.render(camera, side, side, Layer::Color))
        .collect::<Result<Vec<RgbImage>>>()?;
    let scratch = Scratch::new("mp4");
    nerfjit_runtime::output::video::save_mp4(&scratch.0, &frames, 40)?;
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
        up: nerfjit_runtime::Up::Y,
        prune: true,
        color: None,
        texels: None,
        frame: None,
    };
    // The viewer is served by one rank of an MPI job: it meshes alone.
    nerfjit::cluster::alone(|| {
        extract_and_write(
            scene.program(),
            scene.params(),
            &args,
            &nerfjit_jit::KernelCache::new(),
        )
    })?;
    Ok(File {
        name: format!("{stem}.ply"),
        mime: "application/octet-stream",
        bytes: scratch.read()?,
    })
}

fn checkpoint(scene: &Scene, stem: &str, step: u32) -> Result<File> {
    let scratch = Scratch::new("ckpt.safetensors");
    let params = scene.params();
    let fresh = nerfjit_runtime::Adam::new(params.len(), 0.0);
    nerfjit::checkpoint::write(
        &scratch.0,
        scene.program(),
        step,
        params,
        &fresh,
        Default::default(),
    )?;
    Ok(File {
        name: format!("{stem}.ckpt.safetensors"),
        mime: "application/octet-stream",
        bytes: scratch.read()?,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nerfjit::checkpoint::Script;
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
        let mesh = export(Export::Mesh, &scene, &ViewCamera::default(), "ball", 0).unwrap();
        assert_eq!(mesh.name, "ball.ply");
        assert!(mesh.bytes.starts_with(b"ply\n"));
        let view = ViewCamera {
            eye: Vec3::new(0.0, 0.0, -4.0),
            ..ViewCamera::default()
        };
        let video = export(Export::Video, &scene, &view, "ball", 0).unwrap();
        assert_eq!(&video.bytes[4..8], b"ftyp", "an MP4 file");
    }

    #[test]
    fn a_checkpoint_holds_the_edited_script_and_the_params_shown() {
        let text = "param r: f32 = 1\nconst k = 2\nfn sdf(p: vec3) -> f32 = length(p) - r * k";
        let program = nerfjit_dsl::compile("ball.sdf", text).unwrap();
        let scene = Scene::compile(program, &[0.75], Path::new(".")).unwrap();
        let file = export(Export::Checkpoint, &scene, &ViewCamera::default(), "ball", 120).unwrap();
        assert_eq!(file.name, "ball.ckpt.safetensors");
        let dir = std::env::temp_dir().join(format!("nerfjit-export-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join(&file.name);
        std::fs::write(&path, &file.bytes).unwrap();
        let (program, params) = nerfjit::checkpoint::load_trained(&path).unwrap();
        std::fs::remove_dir_all(&dir).unwrap();
        assert_eq!(params, [0.75]);
        assert_eq!(Script::of(&program).source, text);
    }
}
