//! `render sphere_trace { ... }`: the block's settings, checked before any work, and the render itself.

use std::path::{Path, PathBuf};
use std::time::Instant;

use glam::Vec3;
use nerfjit_dsl::ir::Op;
use nerfjit_dsl::{Lowered, Program, Type};
use nerfjit_jit::KernelCache;
use nerfjit_runtime::{
    depth_image, normal_image, render_frames, rgb_image, BatchFn, Camera, Frame, Quantize, Shading,
    TraceSettings, WithBounds,
};

use crate::diagnostics::nonfinite::{self, ProbeRays};
use crate::diagnostics::steepness;
use crate::failure::{Failure, Result};
use crate::folder_lock::lock_output_folders;
use crate::frame_files::write_images;
use crate::settings::block::Block;
use crate::settings::typed::typed_settings;
use crate::settings::values::bounding_sphere;
use nerfjit_field::{Compiler, JitFn, Kind};

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
pub struct SphereTracePlan {
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
    /// A bound on the norm of the SDF's gradient: the tracer marches sdf / lipschitz.
    pub lipschitz: f32,
}

typed_settings! {
    /// The settings of a `render sphere_trace` block, as read.
    pub struct SphereTraceSettings for crate::settings::schema::RENDER_SPHERE_TRACE {
        camera: required,
        size: size,
        near: number,
        far: number,
        eps: number,
        max_steps: whole,
        lipschitz: number,
        background: triple,
        shading: choice,
        light: triple,
        albedo: triple,
        bounds: value,
        out: required_output,
        depth: output,
        normals: output,
        frame_ms: whole,
    }
}

impl SphereTracePlan {
    /// Reads and checks a `render sphere_trace` block.
    pub fn new(mut b: Block) -> Result<SphereTracePlan> {
        let s = SphereTraceSettings::read(&mut b)?;
        let cameras = b.cameras_of(&s.camera)?;
        let size = s.size;
        b.check_pixels(cameras.len(), size)?;
        let (near, far) = b.interval(s.near, s.far)?;
        let (eps, max_steps, lipschitz) = (s.eps as f32, s.max_steps as u32, s.lipschitz as f32);
        let background = s.background.expect("a default");
        let bounds = match &s.bounds {
            None => None,
            Some(v) => Some(bounding_sphere(v).map_err(|d| b.error(d))?),
        };
        let has_color = b.program().signature("color").is_some();
        let shading = s
            .shading
            .unwrap_or_else(|| if has_color { "color" } else { "lambert" }.to_string());
        let light = Vec3::from_array(s.light.expect("a default"));
        let albedo = s.albedo.expect("a default");
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
        let (out, depth, normals, frame_ms) = (s.out, s.depth, s.normals, s.frame_ms as u32);
        b.finish()?;
        Ok(SphereTracePlan {
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
            lipschitz,
        })
    }

    /// Compiles the script's functions this block traces ([`TraceFields::compile`]).
    pub fn compile_fields(&self, compiler: &Compiler) -> Result<TraceFields> {
        TraceFields::compile(compiler, &self.shading, self.lipschitz)
    }

    /// Compiles the script's functions (through `cache`) and renders every frame; writes the outputs and
    /// returns a summary.
    pub fn run(
        &self,
        program: &Program,
        params: &[f32],
        cache: &KernelCache,
        progress: &(dyn Fn(usize) + Sync),
    ) -> Result<String> {
        let _locks = lock_output_folders(std::iter::once(self.out.as_path()).chain(self.depth.as_deref()))?;
        let compiler = Compiler {
            program,
            params,
            cache,
        };
        let compile_start = Instant::now();
        let fields = self.compile_fields(&compiler)?;
        let (sdf, color) = (fields.traced_sdf(), &fields.color);
        let gradient = compiler.function("sdf", &[Type::Vec(3)], &Type::F32, Kind::Gradient)?;
        let compile_s = compile_start.elapsed().as_secs_f64();
        let shading = match (&self.shading, &color) {
            (ShadingChoice::Color, Some(c)) => Shading::Color {
                color: c,
                // Normals cost a gradient evaluation per hit: only when a normal map is asked for.
                gradient: self.normals.as_ref().map(|_| &gradient as &dyn BatchFn),
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
        // Each rank of an MPI job traces its share of the frames (in one call, which keeps the thread pool
        // awake from frame to frame); rank 0 gathers and writes them.
        let (n, cluster) = (self.cameras.len(), crate::cluster::current());
        let mine: Vec<Camera> = crate::cluster::share(n, cluster.rank(), cluster.size())
            .map(|i| self.cameras[i])
            .collect();
        let mut traced = render_frames(&mine, w, h, &sdf, &shading, &self.trace, Some(progress))
            .map(|frames| frames.into_iter());
        // `split` asks for this rank's share in order: the frames just traced.
        let rendered = crate::cluster::split(n, |_| match &mut traced {
            Ok(frames) => frames
                .next()
                .map(|f| frame_bytes(&f))
                .ok_or_else(|| "a frame of this rank's share was not traced".to_string()),
            Err(e) => Err(e.to_string()),
        })
        .map_err(Failure::Message)?;
        let Some(rendered) = rendered else {
            return Ok(String::new());
        };
        let frames: Vec<Frame> = rendered.iter().map(|b| frame_of(b, (w, h))).collect();
        let seconds = start.elapsed().as_secs_f64();
        if let Some(camera) = self.cameras.first() {
            let rays = ProbeRays {
                camera,
                size: (w, h),
                near: self.trace.near,
                far: self.trace.far,
            };
            let color = color.as_ref().and_then(|c| nonfinite::warning("color", c, rays));
            let steep = steepness::warning(&gradient, rays, self.lipschitz);
            for line in [nonfinite::warning("sdf", &sdf, rays), color, steep]
                .into_iter()
                .flatten()
            {
                crate::console::note(&line);
            }
        }
        write_frames(&self.out, &frames, self.frame_ms, |f| {
            rgb_image(f.width, f.height, &f.rgb, Quantize::Truncate)
        })?;
        if let Some(path) = self.depth.as_ref().filter(|p| crate::frame_files::is_npy(p)) {
            // The hit distance along the unit ray; +∞ where the ray missed.
            let depths = frames.iter().map(|f| f.depth.clone()).collect();
            crate::frame_files::write_depths(path, (w, h), depths)?;
        } else if let Some(path) = &self.depth {
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

/// A frame's colors, depths, normals and hits as bytes, to send between ranks.
fn frame_bytes(frame: &Frame) -> Vec<u8> {
    let hits: Vec<f32> = frame.hit.iter().map(|&h| f32::from(u8::from(h))).collect();
    let (rgb, normal) = (frame.rgb.iter().flatten(), frame.normal.iter().flatten());
    crate::cluster::f32_bytes(rgb.chain(&frame.depth).chain(normal).chain(&hits))
}

/// The `size` frame that [`frame_bytes`] made `bytes` of.
fn frame_of(bytes: &[u8], (width, height): (u32, u32)) -> Frame {
    let values = crate::cluster::f32s_of(bytes);
    let n = (width * height) as usize;
    let triples = |v: &[f32]| v.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
    Frame {
        width,
        height,
        rgb: triples(&values[..3 * n]),
        depth: values[3 * n..4 * n].to_vec(),
        normal: triples(&values[4 * n..7 * n]),
        hit: values[7 * n..8 * n].iter().map(|&h| h > 0.5).collect(),
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

/// `f` with its outputs divided by `by` (`f` itself for 1).
fn divided(mut f: Lowered, by: f32) -> Lowered {
    if by != 1.0 {
        let factor = f.graph.constant(1.0 / f64::from(by));
        let outputs = f.graph.outputs.clone();
        f.graph.outputs = outputs
            .into_iter()
            .map(|v| f.graph.push(Op::Mul(v, factor)))
            .collect();
    }
    f
}

/// SDFs of fewer IR nodes are traced without skipping the space their interval bounds prove empty, which
/// costs more than it saves where a step is cheap. Frames of 256² with skipping against without
/// (2026-11-25, three runs each): W1's 16-node torus 0.44–0.50 against 0.38–0.42 ms, the 172-node
/// `showcase.sdf` 6.9–7.7 against 6.0–7.2 ms, the 359-node `complex_scene.sdf` 6.1–7.9 against 8.4–10.1
/// ms, the 6,425-node city of `nerfjit bench large` 84–96 against 136–139 ms.
const SKIP_EMPTY_SPACE_MIN_NODES: usize = 256;

/// The compiled functions of a `render sphere_trace` block.
pub struct TraceFields {
    /// The SDF, with its fused marcher.
    pub sdf: JitFn,
    /// The SDF's interval bounds over boxes, where interval arithmetic bounds it: the sphere tracer skips
    /// the space they prove empty.
    pub bounds: Option<JitFn>,
    /// The color, for color shading.
    pub color: Option<JitFn>,
}

impl TraceFields {
    /// Compiles the script's `sdf` divided by `lipschitz` (a bound on its gradient's norm, so that the
    /// quotient is at most the distance to its surface), its interval bounds if it is large enough for
    /// them to pay (256 IR nodes or more) and, for color shading, its `color`.
    pub fn compile(compiler: &Compiler, shading: &ShadingChoice, lipschitz: f32) -> Result<TraceFields> {
        let vec3 = [Type::Vec(3)];
        let traced = divided(compiler.lowered("sdf", &vec3, &Type::F32)?, lipschitz);
        let sdf = compiler.compile(&traced, Kind::Sdf)?;
        let bounds = if sdf.nodes() >= SKIP_EMPTY_SPACE_MIN_NODES {
            compiler.compile_bounds(&traced)?
        } else {
            None
        };
        let color = match shading {
            ShadingChoice::Color => Some(compiler.function("color", &vec3, &Type::Vec(3), Kind::Value)?),
            ShadingChoice::Lambert { .. } => None,
        };
        Ok(TraceFields { sdf, bounds, color })
    }

    /// The SDF with its bounds, as the sphere tracer takes it.
    pub fn traced_sdf(&self) -> WithBounds<'_> {
        WithBounds {
            function: &self.sdf,
            bounds: self.bounds.as_ref().map(|b| b as &dyn BatchFn),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::settings::block::first_block;
    use crate::settings::schema::Kind as BlockKind;

    #[test]
    fn large_sdfs_are_traced_with_their_interval_bounds_and_small_ones_without() {
        let city = crate::commands::import::convert(&crate::city_model::city(), "city.vm").expect("converts");
        let torus = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../examples/torus.sdf"))
            .expect("the torus example");
        let cache = KernelCache::new();
        for (script, large) in [(city, true), (torus, false)] {
            let program = nerfjit_dsl::compile("scene.sdf", &script).expect("compiles");
            let block = first_block(&program, BlockKind::SphereTrace, ".").expect("a sphere-trace block");
            let plan = SphereTracePlan::new(block).expect("valid settings");
            let compiler = Compiler {
                program: &program,
                params: &program.param_values,
                cache: &cache,
            };
            let fields = plan.compile_fields(&compiler).expect("compiles");
            assert_eq!(fields.sdf.nodes() >= SKIP_EMPTY_SPACE_MIN_NODES, large);
            assert_eq!(fields.traced_sdf().interval_bounds().is_some(), large);
        }
    }

    /// The hits of a 64² frame of `scale` times the torus's distance, traced with `lipschitz`.
    fn torus_hits(scale: f32, lipschitz: f32) -> Vec<bool> {
        let script = format!(
            "fn sdf(p: vec3) -> f32 = {scale:?} * torus(p, 1.0, 0.25)\n\
             render sphere_trace {{ camera: orbit(radius: 4.0, elevation: 30, frames: 1), size: 64, far: 8.0,\n\
             max_steps: 256, eps: 1e-4, lipschitz: {lipschitz:?}, out: \"t.png\" }}"
        );
        let program = nerfjit_dsl::compile("scaled.sdf", &script).expect("compiles");
        let block = first_block(&program, BlockKind::SphereTrace, ".").expect("a sphere-trace block");
        let plan = SphereTracePlan::new(block).expect("valid settings");
        let cache = KernelCache::new();
        let compiler = Compiler {
            program: &program,
            params: &program.param_values,
            cache: &cache,
        };
        let fields = plan.compile_fields(&compiler).expect("compiles");
        let gradient = compiler
            .function("sdf", &[Type::Vec(3)], &Type::F32, Kind::Gradient)
            .expect("compiles");
        let shading = Shading::Lambert {
            gradient: &gradient,
            light_dir: Vec3::Y,
            albedo: [1.0; 3],
        };
        let mut frame = Frame::empty();
        nerfjit_runtime::sphere_trace_into(
            &plan.cameras[0],
            64,
            64,
            &fields.traced_sdf(),
            &shading,
            &plan.trace,
            &mut frame,
        )
        .expect("renders");
        frame.hit
    }

    #[test]
    fn a_field_steeper_than_a_distance_is_traced_divided_by_its_lipschitz_bound() {
        let torus = torus_hits(1.0, 1.0);
        let hits = torus.iter().filter(|&&h| h).count();
        assert!(hits > 150, "the torus covers part of the frame: {hits} hits");
        // Ten times the distance: full steps jump through the tube, a tenth of them find the torus.
        let differ = |a: &[bool], b: &[bool]| a.iter().zip(b).filter(|(x, y)| x != y).count();
        let overshot = differ(&torus_hits(10.0, 1.0), &torus);
        assert!(
            overshot > hits / 10,
            "stepping 10 × the distance lost only {overshot} of {hits} hits"
        );
        assert!(differ(&torus_hits(10.0, 10.0), &torus) <= 2);
    }
}
