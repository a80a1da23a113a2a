//! `render volume { ... }`: volume rendering of the script's density (or opacity) and color.

use std::path::{Path, PathBuf};
use std::time::Instant;

use nerfjit_dsl::Program;
use nerfjit_jit::{KernelCache, Precision};
use nerfjit_runtime::{
    rgb_image, Camera, DepthSpacing, Mode, OccupancyGrid, Quantize, VolumeFrame, VolumeSettings,
};

use crate::diagnostics::nonfinite::{self, ProbeRays};
use crate::failure::{Failure, Result};
use crate::folder_lock::lock_output_folders;
use crate::frame_files::write_images;
use crate::settings::block::Block;
use crate::settings::typed::typed_settings;
use crate::settings::values::skip_empty;
pub use crate::settings::values::SkipEmpty;
use nerfjit_field::{VolumeField, VolumeFields};

/// A checked `render volume` block.
pub struct VolumePlan {
    /// One camera per frame.
    pub cameras: Vec<Camera>,
    /// Image width and height.
    pub size: (u32, u32),
    /// Sampling and compositing (the mode is filled in from the script's functions).
    pub near: f32,
    /// End of the sampled interval.
    pub far: f32,
    /// Samples per ray.
    pub samples: usize,
    /// Background seen through the remaining transmittance.
    pub background: Option<[f32; 3]>,
    /// Transmittance below which a ray stops.
    pub early_termination: Option<f32>,
    /// How the samples are spread between near and far.
    pub spacing: DepthSpacing,
    /// Empty-space skipping, if asked for.
    pub skip_empty: Option<SkipEmpty>,
    /// Importance samples per ray (hierarchical sampling with the script's coarse field; 0: none).
    pub importance: usize,
    /// The arithmetic of the networks' products.
    pub products: Precision,
    /// Color frames.
    pub out: PathBuf,
    /// Depth frames.
    pub depth: Option<PathBuf>,
    /// GIF frame time.
    pub frame_ms: u32,
}

typed_settings! {
    /// The settings of a `render volume` block, as read.
    pub struct RenderVolumeSettings for crate::settings::schema::RENDER_VOLUME {
        camera: required,
        size: size,
        near: number,
        far: number,
        samples: whole,
        background: triple,
        early_termination: number,
        spacing: value,
        skip_empty: value,
        importance: whole,
        products: choice,
        out: required_output,
        depth: output,
        frame_ms: whole,
    }
}

impl VolumePlan {
    /// Reads and checks a `render volume` block.
    pub fn new(mut b: Block) -> Result<VolumePlan> {
        let s = RenderVolumeSettings::read(&mut b)?;
        let cameras = b.cameras_of(&s.camera)?;
        let size = s.size;
        b.check_pixels(cameras.len(), size)?;
        let (near, far) = b.interval(s.near, s.far)?;
        let samples = s.samples as usize;
        let early = s.early_termination as f32;
        let spacing = b.spacing_of(s.spacing.as_ref(), near, far)?;
        let background = s.background;
        let skip_empty = match &s.skip_empty {
            None => None,
            Some(v) => skip_empty(v).map_err(|d| b.error(d))?,
        };
        let (out, depth, frame_ms) = (s.out, s.depth, s.frame_ms as u32);
        let importance = s.importance as usize;
        let products = s
            .products
            .as_deref()
            .and_then(Precision::named)
            .unwrap_or_default();
        b.finish()?;
        Ok(VolumePlan {
            cameras,
            size,
            near,
            far,
            samples,
            background,
            early_termination: (early > 0.0).then_some(early),
            spacing,
            skip_empty,
            importance,
            products,
            out,
            depth,
            frame_ms,
        })
    }

    /// The renderer settings for a field of `mode`.
    pub fn settings(&self, field: &VolumeField) -> VolumeSettings {
        VolumeSettings {
            near: self.near,
            far: self.far,
            samples: self.samples,
            mode: field.mode,
            background: self.background,
            early_termination: self.early_termination,
            spacing: self.spacing,
        }
    }

    /// Renders every frame with `params` (compiling through `cache`) and writes the outputs; returns a
    /// summary line. With `skip_empty`, the frames skip the cells of `trained` (the grid a `train` block
    /// of these params ended with) when it has the block's bounds, resolution and space, and those of a
    /// grid built from the field otherwise.
    pub fn run(
        &self,
        program: &Program,
        params: &[f32],
        cache: &KernelCache,
        trained: Option<&OccupancyGrid>,
        progress: &dyn Fn(usize),
    ) -> Result<String> {
        let _locks = lock_output_folders(std::iter::once(self.out.as_path()).chain(self.depth.as_deref()))?;
        let t = Instant::now();
        let fields = VolumeFields::compile(program, cache, self.importance, self.products)?;
        let field = &fields.fine;
        let compile_s = t.elapsed().as_secs_f64();
        let settings = self.settings(field);
        let (w, h) = self.size;
        let start = Instant::now();
        let built;
        let (grid, grid_note) = match self.skip_empty {
            Some(s) => match trained.filter(|g| s.fits(g)) {
                Some(g) => (Some(g), "; the train block's occupancy grid".to_string()),
                None => {
                    built = field.occupancy_grid(
                        program,
                        params,
                        cache,
                        (s.bounds, s.resolution, s.threshold, s.space),
                        s.thickness,
                    )?;
                    let note = format!("; occupancy grid built in {:.3} s", start.elapsed().as_secs_f64());
                    (Some(&built), note)
                }
            },
            None => (None, String::new()),
        };
        let start = Instant::now();
        // Each rank of an MPI job renders its share of the frames; rank 0 gathers and writes them.
        let mut done = 0;
        let rendered = crate::cluster::split(self.cameras.len(), |i| -> Result<Vec<u8>> {
            let frame = fields.render_with(&self.cameras[i], (w, h), params, &settings, grid)?;
            done += 1;
            progress(done);
            Ok(frame_bytes(&frame))
        })
        .map_err(Failure::Message)?;
        let Some(rendered) = rendered else {
            return Ok(String::new());
        };
        let frames: Vec<VolumeFrame> = rendered.iter().map(|b| frame_of(b, (w, h))).collect();
        let seconds = start.elapsed().as_secs_f64();
        if let Some(camera) = self.cameras.first() {
            let rays = ProbeRays {
                camera,
                size: (w, h),
                near: self.near,
                far: self.far,
            };
            let name = match field.mode {
                Mode::Density => "density",
                Mode::Opacity => "opacity",
            };
            let warning = nonfinite::warning(name, &field.bind_density(params), rays)
                .or_else(|| nonfinite::warning("color", &field.bind(params).0, rays));
            if let Some(line) = warning {
                crate::console::note(&line);
            }
        }
        write(&self.out, &frames, self.frame_ms, |f| f.rgb.clone())?;
        if let Some(path) = self.depth.as_ref().filter(|p| crate::frame_files::is_npy(p)) {
            // Expected depth along the unit ray, Σ wᵢtᵢ / Σ wᵢ; +∞ where (almost) nothing is hit.
            let depths = frames.iter().map(|f| {
                f.depth
                    .iter()
                    .zip(&f.opacity)
                    .map(|(&d, &a)| if a > 1e-3 { d / a } else { f32::INFINITY })
                    .collect()
            });
            crate::frame_files::write_depths(path, (w, h), depths.collect())?;
        } else if let Some(path) = &self.depth {
            // Depth in [near, far] as gray, scaled by the opacity (empty space stays black).
            let (near, far) = (self.near, self.far);
            write(path, &frames, self.frame_ms, |f| {
                f.depth
                    .iter()
                    .zip(&f.opacity)
                    .map(|(&d, &a)| {
                        let v = if a > 1e-3 {
                            (1.0 - (d / a - near) / (far - near)).clamp(0.0, 1.0) * a
                        } else {
                            0.0
                        };
                        [v; 3]
                    })
                    .collect()
            })?;
        }
        Ok(format!(
            "volume-rendered {} frame{} of {w}×{h}×{} samples in {seconds:.3} s ({:.2} ms/frame; JIT compile {compile_s:.3} s{grid_note}) → {}",
            frames.len(),
            if frames.len() == 1 { "" } else { "s" },
            self.samples,
            1e3 * seconds / frames.len() as f64,
            self.out.display()
        ))
    }
}

/// A frame's colors, depths and opacities as bytes, to send between ranks.
pub(crate) fn frame_bytes(frame: &VolumeFrame) -> Vec<u8> {
    let rgb = frame.rgb.iter().flatten();
    crate::cluster::f32_bytes(rgb.chain(&frame.depth).chain(&frame.opacity))
}

/// The `size` frame that [`frame_bytes`] made `bytes` of.
pub(crate) fn frame_of(bytes: &[u8], (width, height): (u32, u32)) -> VolumeFrame {
    let values = crate::cluster::f32s_of(bytes);
    let n = (width * height) as usize;
    VolumeFrame {
        width,
        height,
        rgb: values[..3 * n]
            .chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect(),
        depth: values[3 * n..4 * n].to_vec(),
        opacity: values[4 * n..5 * n].to_vec(),
    }
}

/// Converts frames to images with `pixels` and writes them.
fn write(
    path: &Path,
    frames: &[VolumeFrame],
    frame_ms: u32,
    pixels: impl Fn(&VolumeFrame) -> Vec<[f32; 3]>,
) -> Result<()> {
    let images = frames
        .iter()
        .map(|f| rgb_image(f.width, f.height, &pixels(f), Quantize::Truncate))
        .collect::<nerfjit_runtime::Result<Vec<_>>>()?;
    write_images(path, images, frame_ms)
}
