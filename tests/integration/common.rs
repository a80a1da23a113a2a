//! What the integration tests share: running nerfjit in a folder, a small training scene (four views of a
//! box rendered by the CLI, and a script that recovers the box from them), and reading a textured glTF file.

use std::ops::Deref;
use std::path::Path;
use std::process::Command;

/// A test's own empty folder in the system's temporary folder, removed with everything in it when the
/// test ends (also when it fails), so that test runs leave nothing behind.
pub struct Scratch(tempfile::TempDir);

impl Deref for Scratch {
    type Target = Path;

    fn deref(&self) -> &Path {
        self.0.path()
    }
}

impl AsRef<Path> for Scratch {
    fn as_ref(&self) -> &Path {
        self.0.path()
    }
}

/// A fresh [`Scratch`] folder whose name starts `nerfjit-{kind}-{name}-`.
pub fn scratch(kind: &str, name: &str) -> Scratch {
    let dir = tempfile::Builder::new()
        .prefix(&format!("nerfjit-{kind}-{name}-"))
        .tempdir();
    Scratch(dir.expect("a temporary folder"))
}

/// Runs nerfjit with `args` in `dir`: success, standard output and standard error.
pub fn run(dir: &Path, args: &[&str]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_nerfjit"))
        .args(args)
        .current_dir(dir)
        .output()
        .expect("runs");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

pub const CAMERAS: &str = r#"{
  "image_size": [40, 40],
  "cameras": [
    {"image": "view_000.png", "focal": 1.0, "principal_point": [0, 0], "eye": [-2.5, 0.3, 0.0], "scene_center": [0, 0, 0], "up": [0, 1, 0]},
    {"image": "view_001.png", "focal": 1.0, "principal_point": [0, 0], "eye": [-1.0, 0.5, -2.2], "scene_center": [0, 0, 0], "up": [0, 1, 0]},
    {"image": "view_002.png", "focal": 1.0, "principal_point": [0, 0], "eye": [0.0, -0.4, -2.5], "scene_center": [0, 0, 0], "up": [0, 1, 0]},
    {"image": "view_003.png", "focal": 1.0, "principal_point": [0, 0], "eye": [1.8, 0.8, -1.6], "scene_center": [0, 0, 0], "up": [0, 1, 0]}
  ]
}"#;

pub const FIELD: &str =
    "fn opacity(p: vec3) -> f32 = opacity_laplace(box(p - center, sides), alpha: 1.0, beta: 0.05)\n\
                     fn color(p: vec3) -> vec3 = clamp(abs(p - center), 0.02, 0.98)\n";

/// Renders the four views of the true box into `dir` (cams.json, view_000.png, ...).
pub fn make_views(dir: &Path) {
    std::fs::write(dir.join("cams.json"), CAMERAS).unwrap();
    let truth = format!(
        "const center = [0.2, -0.1, 0.1]\nconst sides = [1.2, 0.8, 1.0]\n{FIELD}\
         render volume {{ camera: cameras(\"cams.json\"), size: 40, near: 0, far: 5, samples: 48, out: \"view.png\" }}\n"
    );
    std::fs::write(dir.join("truth.sdf"), truth).unwrap();
    let (ok, _, err) = run(dir, &["run", "truth.sdf"]);
    assert!(ok, "{err}");
    assert!(dir.join("view_003.png").exists());
}

/// A script that trains the box's center and sides for `steps` steps, with `extra` settings (the checkpoint
/// is the default `train.ckpt.safetensors` unless they name one).
pub fn trainer_with(steps: u32, extra: &str) -> String {
    format!(
        "param center: vec3 = [0, 0, 0]\nparam sides: vec3 = [1.0, 1.0, 1.0]\n{FIELD}\
         train {{ data: views(\"cams.json\"), near: 0, far: 5, samples: 48, steps: {steps}, batch: 800, lr: 0.01, \
         schedule: exponential(gamma: 0.1, every: 400), checkpoint_every: 50, summary: \"summary.json\" {extra}}}\n"
    )
}

/// A textured glTF binary as the `gltf` crate reads it: its one primitive's positions, normals, UVs and
/// triangles' corners, and its base color texture.
pub struct TexturedGlb {
    pub positions: Vec<glam::Vec3>,
    pub normals: Vec<glam::Vec3>,
    pub uvs: Vec<glam::Vec2>,
    pub indices: Vec<usize>,
    pub texture: image::RgbImage,
}

/// Reads the textured glTF binary at `path` (panics if it is not one).
pub fn read_textured_glb(path: &Path) -> TexturedGlb {
    let gltf = gltf::Gltf::open(path).unwrap();
    let blob = gltf.blob.as_deref().unwrap();
    let primitive = gltf.meshes().next().unwrap().primitives().next().unwrap();
    let reader = primitive.reader(|_| Some(blob));
    let positions = reader.read_positions().unwrap().map(glam::Vec3::from).collect();
    let normals = reader.read_normals().unwrap().map(glam::Vec3::from).collect();
    let uvs = reader
        .read_tex_coords(0)
        .unwrap()
        .into_f32()
        .map(glam::Vec2::from)
        .collect();
    let Some(gltf::mesh::util::ReadIndices::U32(indices)) = reader.read_indices() else {
        panic!("u32 indices")
    };
    let info = primitive
        .material()
        .pbr_metallic_roughness()
        .base_color_texture()
        .unwrap();
    let gltf::image::Source::View { view, .. } = info.texture().source().source() else {
        panic!("an embedded image")
    };
    let png = &blob[view.offset()..view.offset() + view.length()];
    TexturedGlb {
        positions,
        normals,
        uvs,
        indices: indices.map(|i| i as usize).collect(),
        texture: image::load_from_memory(png).unwrap().to_rgb8(),
    }
}
