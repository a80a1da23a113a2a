//! `render sphere_trace { ... }`: the block's settings, checked before any work, and the render itself.

use std::path::{Path, PathBuf};
use std::time::Instant;

use glam::{Vec2, Vec3};
use nerfjit_dsl::config::{Settings, Spanned, Value};
use nerfjit_dsl::{Diagnostic, Program, Type};
use nerfjit_jit::KernelCache;
use nerfjit_runtime::{
    depth_image, load_blender_cameras, load_box_cameras, normal_image, orbit, render_frames, rgb_image,
    surround, Camera, Frame, Quantize, Shading, TraceSettings, Up,
};

use crate::failure::{at, Failure, Result};
use crate::field::{Compiler, JitFn, Kind};
use crate::output::write_images;
use crate::settings::{name_among, ranged, whole, CallArgs};

const KEYS: &[&str] = &[
    "camera",
    "size",
    "near",
    "far",
    "eps",
    "max_steps",
    "background",
    "shading",
    "light",
    "albedo",
    "bounds",
    "out",
    "depth",
    "normals",
    "frame_ms",
];

/// How hit points are shaded.
#[derive(Clone, Debug, PartialEq)]
pub enum ShadingChoice {
    /// The script's `color(p)`.
    Color,
    /// Diffuse light on the SDF's normals.
    Lambert {
        /// Towards the light.
        light: Vec3,
        /// Surface color.
        albedo: [f32; 3],
    },
}

/// A checked `render sphere_trace` block: everything needed to render, validated before any work.
pub struct RenderPlan {
    /// One camera per frame.
    pub cameras: Vec<Camera>,
    /// Image width and height.
    pub size: (u32, u32),
    /// Tracing parameters.
    pub trace: TraceSettings,
    /// Shading.
    pub shading: ShadingChoice,
    /// The color image(s): a GIF, or PNG(s).
    pub out: PathBuf,
    /// Optional depth output.
    pub depth: Option<PathBuf>,
    /// Optional normal-map output.
    pub normals: Option<PathBuf>,
    /// GIF frame time in milliseconds.
    pub frame_ms: u32,
}

/// Three numbers (a single number is repeated).
pub fn triple(v: &Spanned) -> std::result::Result<[f32; 3], Diagnostic> {
    let x = v.numbers(3)?;
    Ok([x[0] as f32, x[1] as f32, x[2] as f32])
}

fn up(args: &CallArgs) -> std::result::Result<Up, Diagnostic> {
    Ok(if args.choice("up", &["y", "z"], "y")? == "z" {
        Up::Z
    } else {
        Up::Y
    })
}

fn cameras(
    v: &Spanned,
    script_dir: &Path,
) -> std::result::Result<std::result::Result<Vec<Camera>, String>, Diagnostic> {
    let Value::Call(name, _) = &v.value else {
        return Err(Diagnostic::new(v.span, format!("expected a camera path, found {}", v.describe()))
            .with_hint("write surround(radius: 3, frames: 20, up: z, focal: 1), orbit(...) or cameras(\"file.json\")"));
    };
    let result = match name.as_str() {
        "surround" => {
            let a = CallArgs::new(v, &["radius", "frames", "up", "focal"])?;
            let frames = a.number("frames", Some(20.0))?;
            surround(
                a.number("radius", None)? as f32,
                frames as usize,
                up(&a)?,
                a.number("focal", Some(1.0))? as f32,
            )
        }
        "orbit" => {
            let a = CallArgs::new(v, &["radius", "elevation", "frames", "up", "focal"])?;
            orbit(
                a.number("radius", None)? as f32,
                a.number("elevation", Some(0.0))? as f32,
                a.number("frames", Some(36.0))? as usize,
                up(&a)?,
                a.number("focal", Some(1.0))? as f32,
            )
        }
        "cameras" => {
            let a = CallArgs::new(v, &["file"])?;
            let file = script_dir.join(a.string("file")?);
            let text = std::fs::read_to_string(&file).unwrap_or_default();
            let set = if text.contains("\"frames\"") {
                load_blender_cameras(&file)
            } else {
                load_box_cameras(&file)
            };
            set.map(|s| s.cameras)
        }
        "look_at" => {
            let a = CallArgs::new(v, &["eye", "at", "up", "focal"])?;
            let vec3 = |slot: &str, d: [f32; 3]| -> std::result::Result<Vec3, Diagnostic> {
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

/// An image output file (`.gif` or `.png`): its folder must exist; `out_dir` replaces the folder when given.
pub fn output_setting(v: &Spanned, out_dir: Option<&Path>) -> std::result::Result<PathBuf, Diagnostic> {
    let allowed = ["gif", "png"];
    let written = PathBuf::from(v.string()?);
    let path = match out_dir {
        Some(dir) => dir.join(written.file_name().unwrap_or_default()),
        None => written,
    };
    let ext = path.extension().and_then(|e| e.to_str()).unwrap_or("");
    if !allowed.contains(&ext) {
        return Err(Diagnostic::new(
            v.span,
            format!("cannot write '{}': unknown image format", path.display()),
        )
        .with_hint(format!("use a file ending in .{}", allowed.join(" or ."))));
    }
    let folder = path
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    if !folder.is_dir() {
        return Err(Diagnostic::new(
            v.span,
            format!(
                "cannot write '{}': folder '{}' does not exist",
                path.display(),
                folder.display()
            ),
        )
        .with_hint("create the folder first, or pass --out DIR"));
    }
    Ok(path)
}

/// The `camera` setting: a camera path or a camera file.
pub fn cameras_setting(program: &Program, v: &Spanned, script_dir: &Path) -> Result<Vec<Camera>> {
    let made = cameras(v, script_dir).map_err(|d| at(program, d))?;
    made.map_err(|e| at(program, Diagnostic::new(v.span, e)))
}

/// The `size` setting: `N` or `[width, height]`, 1 to 8192; 256 when absent.
pub fn size_setting(program: &Program, v: Option<Spanned>) -> Result<(u32, u32)> {
    let err = |d| at(program, d);
    Ok(match v {
        None => (256, 256),
        Some(v) => match &v.value {
            Value::List(items) if items.len() == 2 => (
                whole(&items[0], 1, 8192).map_err(err)? as u32,
                whole(&items[1], 1, 8192).map_err(err)? as u32,
            ),
            _ => {
                let n = whole(&v, 1, 8192).map_err(err)? as u32;
                (n, n)
            }
        },
    })
}

impl RenderPlan {
    /// Reads and checks a `render sphere_trace` block.
    pub fn new(
        program: &Program,
        mut s: Settings,
        script_dir: &Path,
        out_dir: Option<&Path>,
    ) -> Result<RenderPlan> {
        let err = |d| at(program, d);
        let block_span = s.span;
        let missing = |key: &str| {
            at(
                program,
                Diagnostic::new(block_span, format!("the render block needs '{key}'"))
                    .with_hint(format!("add e.g. {}", example(key))),
            )
        };
        let camera_v = s.take("camera").ok_or_else(|| missing("camera"))?;
        let cameras = cameras_setting(program, &camera_v, script_dir)?;
        let size = size_setting(program, s.take("size"))?;
        let num = |s: &mut Settings, key: &str, lo: f64, hi: f64, default: f64| -> Result<f32> {
            match s.take(key) {
                Some(v) => Ok(ranged(&v, lo, hi).map_err(|d| at(program, d))? as f32),
                None => Ok(default as f32),
            }
        };
        let near = num(&mut s, "near", 0.0, 1e6, 0.0)?;
        let far = num(&mut s, "far", 0.0, 1e9, 10.0)?;
        if far <= near {
            return Err(at(
                program,
                Diagnostic::new(block_span, format!("far ({far}) must exceed near ({near})")),
            ));
        }
        let eps = num(&mut s, "eps", 1e-12, 1.0, 1e-5)?;
        let max_steps = match s.take("max_steps") {
            Some(v) => whole(&v, 1, 1_000_000).map_err(err)? as u32,
            None => 64,
        };
        let background = match s.take("background") {
            Some(v) => triple(&v).map_err(err)?,
            None => [0.0; 3],
        };
        let bounds = match s.take("bounds") {
            None => None,
            Some(v) => {
                let a = CallArgs::new(&v, &["center", "radius"]).map_err(err)?;
                let center = match a.raw("center") {
                    Some(c) => Vec3::from_array(triple(c).map_err(err)?),
                    None => Vec3::ZERO,
                };
                Some((center, a.number("radius", None).map_err(err)? as f32))
            }
        };
        let has_color = program.signature("color").is_some();
        let shading = match s.take("shading") {
            Some(v) => name_among(&v, &["color", "lambert"]).map_err(err)?,
            None if has_color => "color".into(),
            None => "lambert".into(),
        };
        let light = match s.take("light") {
            Some(v) => Vec3::from_array(triple(&v).map_err(err)?),
            None => Vec3::new(0.5, 0.8, -0.6),
        };
        let albedo = match s.take("albedo") {
            Some(v) => triple(&v).map_err(err)?,
            None => [0.8; 3],
        };
        let shading = if shading == "color" {
            if !has_color {
                return Err(Failure::Message(
                    "shading 'color' needs a function 'fn color(p: vec3) -> vec3' in the script".into(),
                ));
            }
            ShadingChoice::Color
        } else {
            ShadingChoice::Lambert { light, albedo }
        };
        let out_v = s.take("out").ok_or_else(|| missing("out"))?;
        let out = output_setting(&out_v, out_dir).map_err(err)?;
        let depth = s
            .take("depth")
            .map(|v| output_setting(&v, out_dir))
            .transpose()
            .map_err(err)?;
        let normals = s
            .take("normals")
            .map(|v| output_setting(&v, out_dir))
            .transpose()
            .map_err(err)?;
        let frame_ms = match s.take("frame_ms") {
            Some(v) => whole(&v, 10, 10_000).map_err(err)? as u32,
            None => 50,
        };
        s.finish(KEYS).map_err(err)?;
        Ok(RenderPlan {
            cameras,
            size,
            trace: TraceSettings {
                near,
                far,
                eps,
                max_steps,
                background,
                bounds,
            },
            shading,
            out,
            depth,
            normals,
            frame_ms,
        })
    }

    /// Compiles the script's `sdf` and, for color shading, its `color`.
    pub fn compile_fields(&self, compiler: &Compiler) -> Result<(JitFn, Option<JitFn>)> {
        let vec3 = [Type::Vec(3)];
        let sdf = compiler.function("sdf", &vec3, &Type::F32, Kind::Sdf)?;
        let color = match self.shading {
            ShadingChoice::Color => Some(compiler.function("color", &vec3, &Type::Vec(3), Kind::Value)?),
            ShadingChoice::Lambert { .. } => None,
        };
        Ok((sdf, color))
    }

    /// Compiles the script's functions and renders every frame; writes the outputs and returns a summary.
    pub fn run(&self, program: &Program, params: &[f32], progress: &dyn Fn(usize)) -> Result<String> {
        let cache = KernelCache::new();
        let compiler = Compiler {
            program,
            params,
            cache: &cache,
        };
        let compile_start = Instant::now();
        let (sdf, color) = self.compile_fields(&compiler)?;
        let gradient = compiler.function("sdf", &[Type::Vec(3)], &Type::F32, Kind::Gradient)?;
        let compile_s = compile_start.elapsed().as_secs_f64();
        let shading = match (&self.shading, &color) {
            (ShadingChoice::Color, Some(c)) => Shading::Color {
                color: c,
                gradient: Some(&gradient),
            },
            (ShadingChoice::Lambert { light, albedo }, _) => Shading::Lambert {
                gradient: &gradient,
                light_dir: *light,
                albedo: *albedo,
            },
            _ => unreachable!("a color kernel exists for color shading"),
        };
        let start = Instant::now();
        let (w, h) = self.size;
        let frames = render_frames(&self.cameras, w, h, &sdf, &shading, &self.trace, Some(progress))?;
        let seconds = start.elapsed().as_secs_f64();
        write_frames(&self.out, &frames, self.frame_ms, |f| {
            rgb_image(f.width, f.height, &f.rgb, Quantize::Truncate)
        })?;
        if let Some(path) = &self.depth {
            let (near, far) = (self.trace.near, self.trace.far);
            write_frames(path, &frames, self.frame_ms, |f| {
                let gray = depth_image(f, near, far)?;
                Ok(image::DynamicImage::ImageLuma8(gray).to_rgb8())
            })?;
        }
        if let Some(path) = &self.normals {
            write_frames(path, &frames, self.frame_ms, normal_image)?;
        }
        let rays = frames.len() as f64 * f64::from(w) * f64::from(h);
        Ok(format!(
            "rendered {} frame{} of {w}×{h} in {seconds:.3} s ({:.3} ms/frame, {:.1} M rays/s; JIT compile {:.3} s) → {}",
            frames.len(),
            if frames.len() == 1 { "" } else { "s" },
            1e3 * seconds / frames.len() as f64,
            rays / seconds / 1e6,
            compile_s,
            self.out.display()
        ))
    }
}

fn example(key: &str) -> &'static str {
    match key {
        "camera" => "camera: surround(radius: 3, frames: 20, up: z, focal: 1)",
        _ => "out: \"scene.gif\"",
    }
}

/// Converts frames to images with `to_image` and writes them.
fn write_frames(
    path: &Path,
    frames: &[Frame],
    frame_ms: u32,
    to_image: impl Fn(&Frame) -> nerfjit_runtime::Result<image::RgbImage>,
) -> Result<()> {
    let images = frames
        .iter()
        .map(to_image)
        .collect::<nerfjit_runtime::Result<Vec<_>>>()?;
    write_images(path, images, frame_ms)
}
