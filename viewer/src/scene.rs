//! What the viewer shows: a script compiled for display (sphere tracing for an `sdf`, volume rendering for
//! a `density`/`opacity` field) or a bake's splats, rendered from any camera at any size, as color, depth
//! or normals.

use std::path::Path;
use std::rc::Rc;

use glam::{Vec2, Vec3};
use image::RgbImage;
use nerfjit_dsl::config::Settings;
use nerfjit_dsl::{Program, Type};
use nerfjit_jit::KernelCache;
use nerfjit_runtime::splats::SplatScene;
use nerfjit_runtime::{
    depth_image, normal_image, rgb_image, sphere_trace, Camera, Quantize, Shading, TraceSettings, VolumeFrame,
};

use nerfjit::bake_file::Bake;
use nerfjit::blocks::sphere_trace::{ShadingChoice, SphereTracePlan, TraceFields};
use nerfjit::commands::render_views::{script_cameras, Rendering};
use nerfjit::failure::{at, Failure, Result};
use nerfjit::settings::block::{Block, Outputs};
use nerfjit_field::{Compiler, JitFn, Kind, VolumeFields};

/// What a frame shows.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Layer {
    /// The shaded or composited color.
    Color,
    /// Distance from the camera, near (white) to far (black).
    Depth,
    /// Surface normals as colors (surfaces only).
    Normals,
}

impl Layer {
    /// The layer named `name` (`color`, `depth` or `normals`).
    pub fn parse(name: &str) -> Option<Layer> {
        match name {
            "color" => Some(Layer::Color),
            "depth" => Some(Layer::Depth),
            "normals" => Some(Layer::Normals),
            _ => None,
        }
    }
}

/// A camera the page asks for: a look-at camera with a focal length in NDC units of the shorter side.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ViewCamera {
    /// Camera center.
    pub eye: Vec3,
    /// The point looked at.
    pub target: Vec3,
    /// The world's up direction.
    pub up: Vec3,
    /// Focal length (1 is a 90° field of view across the shorter side).
    pub focal: f32,
}

impl Default for ViewCamera {
    /// Looking at the origin from 4 units down −z, y up, a 74° field of view.
    fn default() -> ViewCamera {
        ViewCamera {
            eye: Vec3::new(0.0, 0.0, -4.0),
            target: Vec3::ZERO,
            up: Vec3::Y,
            focal: 1.5,
        }
    }
}

impl ViewCamera {
    /// The renderer's camera.
    pub fn camera(&self) -> Result<Camera> {
        Ok(Camera::look_at(
            self.eye,
            self.target,
            self.up,
            Vec2::splat(self.focal),
            Vec2::ZERO,
        )?)
    }

    /// The look-at form of a script's camera: it looks at the point of its axis nearest the origin
    /// (4 units ahead if the origin is behind it), with the coordinate axis nearest its image-up as up.
    pub fn of(camera: &Camera) -> ViewCamera {
        let (eye, rotation) = (camera.position(), camera.rotation());
        let forward = rotation.z_axis;
        let ahead = forward.dot(-eye);
        let target = eye + forward * if ahead > 1e-3 { ahead } else { 4.0 };
        let image_up = rotation.y_axis;
        let axis = image_up.abs().max_position();
        let mut up = Vec3::ZERO;
        up[axis] = image_up[axis].signum();
        ViewCamera {
            eye,
            target,
            up,
            focal: camera.focal().y,
        }
    }
}

/// Sphere tracing of a script's `sdf`, shaded as its first `render sphere_trace` block says.
struct Surface {
    fields: TraceFields,
    gradient: JitFn,
    shading: ShadingChoice,
    trace: TraceSettings,
}

/// How a scene is drawn.
enum Renderer<'a> {
    /// A surface, sphere traced.
    Surface(Box<Surface>),
    /// Volume rendering of its `density` (or `opacity`) and `color`, with the settings it trains with.
    Volume {
        fields: VolumeFields,
        rendering: Rendering,
    },
    /// A bake's splats, drawn over its background; the depth layer spans the field's near and far.
    Splats {
        scene: Box<SplatScene<'a>>,
        background: [f32; 3],
        rendering: Rendering,
    },
}

/// A script compiled for display (or a bake of it, `'a` being the bake's lifetime), with what the page
/// offers for it.
pub struct Scene<'a> {
    program: Program,
    /// The params the renderer reads (a volume's follow a training run; a surface's are compiled in; a
    /// bake's are those of the field it was baked from, for the mesh and checkpoint exports).
    params: Vec<f32>,
    renderer: Renderer<'a>,
    /// The cameras of the script's first render block with a camera, then those of the data its train
    /// block trains on, each with a label.
    pub cameras: Vec<(String, ViewCamera)>,
    /// The script's one-number consts (the page's sliders).
    pub consts: Vec<(String, f64)>,
}

impl<'a> Scene<'a> {
    /// Compiles `program` (a script in `script_dir`) for display with `params` (a checkpoint's trained
    /// values, or the script's own).
    pub fn compile(program: Program, params: &[f32], script_dir: &Path) -> Result<Scene<'a>> {
        let cache = KernelCache::new();
        let renderer = if program.signature("sdf").is_some() {
            surface(&program, params, &cache)?
        } else {
            let rendering = Rendering::of_script(&program);
            Renderer::Volume {
                fields: VolumeFields::compile(&program, &cache, rendering.importance, rendering.products)?,
                rendering,
            }
        };
        Scene::with(program, params, script_dir, renderer)
    }

    /// `bake`'s splats made ready to draw, offering the cameras of `program` (in `script_dir`), the
    /// script of the checkpoint the bake came from, with its trained `params`. Only the splats' shader is
    /// compiled (once per process).
    pub fn of_bake(program: Program, params: &[f32], script_dir: &Path, bake: &'a Bake) -> Result<Scene<'a>> {
        let renderer = Renderer::Splats {
            scene: Box::new(SplatScene::new(&bake.splats, nerfjit_field::splat_shader()?)),
            background: bake.background,
            rendering: Rendering::of_script(&program),
        };
        Scene::with(program, params, script_dir, renderer)
    }

    /// The scene drawn by `renderer`, with the cameras of `program`'s render block and of its data.
    fn with(
        program: Program,
        params: &[f32],
        script_dir: &Path,
        renderer: Renderer<'a>,
    ) -> Result<Scene<'a>> {
        let labeled = |what: &str, cameras: Vec<Camera>| -> Vec<(String, ViewCamera)> {
            let n = cameras.len();
            let label = |i: usize| format!("{what} {} of {n}", i + 1);
            cameras
                .iter()
                .enumerate()
                .map(|(i, c)| (label(i), ViewCamera::of(c)))
                .collect()
        };
        let mut cameras = labeled("script view", script_cameras(&program)?.unwrap_or_default());
        cameras.extend(labeled(
            "data view",
            nerfjit::blocks::train::data_cameras(&program, script_dir).unwrap_or_default(),
        ));
        Ok(Scene {
            consts: program.scalar_consts(),
            program,
            params: params.to_vec(),
            renderer,
            cameras,
        })
    }

    /// The program shown.
    pub fn program(&self) -> &Program {
        &self.program
    }

    /// The params shown.
    pub fn params(&self) -> &[f32] {
        &self.params
    }

    /// What a mesh of the scene extracts: the function, its level and the half-side of the grid around
    /// the origin (a surface's zero level within 4 units, or a volume's density 10 or opacity ½ within
    /// 1.5, the bounds of the NeRF scenes).
    /// A bake's mesh is that of the field it was baked from.
    pub fn mesh_settings(&self) -> (&'static str, f32, f32) {
        const DENSITY: (&str, f32, f32) = ("density", 10.0, 1.5);
        const OPACITY: (&str, f32, f32) = ("opacity", 0.5, 1.5);
        match &self.renderer {
            Renderer::Surface(_) => ("sdf", 0.0, 4.0),
            Renderer::Volume { fields, .. } => match fields.fine.mode {
                nerfjit_runtime::volume::composite::Mode::Density => DENSITY,
                _ => OPACITY,
            },
            Renderer::Splats { .. } if self.program.signature("density").is_some() => DENSITY,
            Renderer::Splats { .. } => OPACITY,
        }
    }

    /// Renders a volume with `params` from now on (a training run's latest); a surface keeps those it
    /// was compiled with.
    pub fn set_params(&mut self, new: &[f32]) {
        if matches!(self.renderer, Renderer::Volume { .. }) && self.params.len() == new.len() {
            self.params.copy_from_slice(new);
        }
    }

    /// `surface` (sphere traced), `volume` or `splats` (a bake).
    pub fn kind(&self) -> &'static str {
        match self.renderer {
            Renderer::Surface(_) => "surface",
            Renderer::Volume { .. } => "volume",
            Renderer::Splats { .. } => "splats",
        }
    }

    /// Whether a frame at full size is cheap enough to draw at once, without coarser ones first: a bake's
    /// time goes mostly to projecting and sorting its splats, which smaller frames do not save.
    pub fn draws_full_frames_at_once(&self) -> bool {
        matches!(self.renderer, Renderer::Splats { .. })
    }

    /// The layers the scene can show.
    pub fn layers(&self) -> &'static [&'static str] {
        match self.renderer {
            Renderer::Surface(_) => &["color", "depth", "normals"],
            Renderer::Volume { .. } | Renderer::Splats { .. } => &["color", "depth"],
        }
    }

    /// The depth range of the renderer (what the depth layer maps from white to black).
    pub fn near_far(&self) -> (f32, f32) {
        match &self.renderer {
            Renderer::Surface(surface) => (surface.trace.near, surface.trace.far),
            Renderer::Volume { rendering, .. } | Renderer::Splats { rendering, .. } => {
                (rendering.near, rendering.far)
            }
        }
    }

    /// Renders `layer` from `view` at `width`×`height`.
    pub fn render(&self, view: &ViewCamera, width: u32, height: u32, layer: Layer) -> Result<RgbImage> {
        let camera = view.camera()?;
        match &self.renderer {
            Renderer::Surface(surface) => {
                let Surface {
                    fields,
                    gradient,
                    shading,
                    trace,
                } = surface.as_ref();
                let shading = match (shading, &fields.color) {
                    (ShadingChoice::Color, Some(color)) => Shading::Color {
                        color,
                        gradient: (layer == Layer::Normals)
                            .then_some(gradient as &dyn nerfjit_runtime::BatchFn),
                    },
                    (ShadingChoice::Lambert { light, albedo }, _) => Shading::Lambert {
                        gradient,
                        light_dir: *light,
                        albedo: *albedo,
                    },
                    (ShadingChoice::Color, None) => unreachable!("a color kernel exists for color shading"),
                };
                let frame = sphere_trace(&camera, width, height, &fields.traced_sdf(), &shading, trace)?;
                Ok(match layer {
                    Layer::Color => rgb_image(width, height, &frame.rgb, Quantize::Truncate)?,
                    Layer::Depth => {
                        image::DynamicImage::ImageLuma8(depth_image(&frame, trace.near, trace.far)?).to_rgb8()
                    }
                    Layer::Normals => normal_image(&frame)?,
                })
            }
            Renderer::Volume { .. } | Renderer::Splats { .. } if layer == Layer::Normals => Err(
                Failure::Message("normals are shown for surfaces (scripts with an sdf) only".into()),
            ),
            Renderer::Volume { fields, rendering } => {
                let settings = rendering.settings(fields.fine.mode);
                let frame = fields.render(&camera, width, height, &self.params, &settings)?;
                composited(&frame, layer, rendering)
            }
            Renderer::Splats {
                scene,
                background,
                rendering,
            } => {
                let (frame, _) = scene.render(&camera, width, height, *background)?;
                composited(&frame, layer, rendering)
            }
        }
    }
}

/// Compiles the sphere tracer of `program`'s `sdf`, shaded as its first `render sphere_trace` block says
/// (Lambert light, far 20, 128 steps when it has none).
fn surface(program: &Program, params: &[f32], cache: &KernelCache) -> Result<Renderer<'static>> {
    let compiler = Compiler {
        program,
        params,
        cache,
    };
    let block = program.blocks().into_iter().find(|b| {
        nerfjit::settings::schema::kind_of(b) == Some(nerfjit::settings::schema::Kind::SphereTrace)
    });
    let (shading, trace, lipschitz) = match block {
        Some(block) => {
            let settings = Settings::new(program, block).map_err(|d| at(program, d))?;
            let b = Block::new(
                program,
                settings,
                Path::new("."),
                None,
                Rc::new(Outputs::default()),
            )?;
            let plan = SphereTracePlan::new(b)?;
            (plan.shading, plan.trace, plan.lipschitz)
        }
        None => (
            ShadingChoice::Lambert {
                light: Vec3::new(0.5, 0.8, -0.6),
                albedo: [0.8; 3],
            },
            TraceSettings {
                near: 0.0,
                far: 20.0,
                eps: 1e-4,
                max_steps: 128,
                background: [0.1; 3],
                bounds: None,
            },
            1.0,
        ),
    };
    Ok(Renderer::Surface(Box::new(Surface {
        fields: TraceFields::compile(&compiler, &shading, lipschitz)?,
        gradient: compiler.function("sdf", &[Type::Vec(3)], &Type::F32, Kind::Gradient)?,
        shading,
        trace,
    })))
}

/// `layer` of a composited frame (a volume's or a bake's): its color, as the CLI's render quantizes it, or
/// its depth.
fn composited(frame: &VolumeFrame, layer: Layer, rendering: &Rendering) -> Result<RgbImage> {
    let (width, height) = (frame.width, frame.height);
    Ok(match layer {
        Layer::Depth => volume_depth(&frame.depth, &frame.opacity, width, height, rendering),
        _ => rgb_image(width, height, &frame.rgb, Quantize::Truncate)?,
    })
}

/// The expected depth of a volume render as gray (near white, far black; empty space black).
fn volume_depth(depth: &[f32], opacity: &[f32], width: u32, height: u32, rendering: &Rendering) -> RgbImage {
    let span = (rendering.far - rendering.near).max(1e-6);
    RgbImage::from_fn(width, height, |x, y| {
        let i = (y * width + x) as usize;
        let a = opacity[i];
        let level = if a > 1e-3 {
            let t = depth[i] / a;
            a.min(1.0) * (1.0 - ((t - rendering.near) / span).clamp(0.0, 1.0))
        } else {
            0.0
        };
        let v = (255.0 * level) as u8;
        image::Rgb([v, v, v])
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_script_camera_becomes_the_same_look_at_camera() {
        let program = nerfjit_dsl::compile(
            "t.sdf",
            "fn sdf(p: vec3) -> f32 = length(p) - 1\n\
             render sphere_trace { camera: orbit(radius: 5, elevation: 30, frames: 4, up: y, focal: 1.5), out: \"x.png\" }",
        )
        .unwrap();
        let params = program.param_values.clone();
        let scene = Scene::compile(program, &params, Path::new(".")).unwrap();
        assert_eq!(scene.kind(), "surface");
        assert_eq!(scene.cameras.len(), 4);
        let cameras = script_cameras(scene.program()).unwrap().unwrap();
        for ((label, view), original) in scene.cameras.iter().zip(&cameras) {
            assert!(
                label.starts_with("script view ") && label.ends_with(" of 4"),
                "{label}"
            );
            assert_eq!(view.up, Vec3::Y);
            assert!(
                view.target.length() < 1e-4,
                "orbits look at the origin: {}",
                view.target
            );
            let again = view.camera().unwrap();
            for (row, col) in [(0, 0), (7, 3), (15, 15)] {
                let (o1, d1) = original.ray(row, col, 16, 16);
                let (o2, d2) = again.ray(row, col, 16, 16);
                assert!(
                    (o1 - o2).length() < 1e-4 && (d1 - d2).length() < 1e-4,
                    "{d1} vs {d2}"
                );
            }
        }
    }

    #[test]
    fn every_layer_of_a_surface_and_of_a_volume_renders_the_object_in_the_middle() {
        let surface = "fn sdf(p: vec3) -> f32 = length(p) - 1";
        let volume =
            "fn density(p: vec3) -> f32 = 20 * relu(1 - length(p))\nfn color(p: vec3) -> vec3 = [1, 0.5, 0]";
        let view = ViewCamera {
            eye: Vec3::new(0.0, 0.0, -4.0),
            target: Vec3::ZERO,
            up: Vec3::Y,
            focal: 1.5,
        };
        for source in [surface, volume] {
            let program = nerfjit_dsl::compile("t.sdf", source).unwrap();
            let params = program.param_values.clone();
            let scene = Scene::compile(program, &params, Path::new(".")).unwrap();
            for name in scene.layers() {
                let image = scene.render(&view, 33, 31, Layer::parse(name).unwrap()).unwrap();
                assert_eq!(image.dimensions(), (33, 31));
                let (center, corner) = (image.get_pixel(16, 15).0, image.get_pixel(0, 0).0);
                assert_ne!(
                    center, corner,
                    "{name} of {source}: the object differs from the background"
                );
            }
        }
    }
}
