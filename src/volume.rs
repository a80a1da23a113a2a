//! `render volume { ... }`: volume rendering of the script's density (or opacity) and color.

use std::path::{Path, PathBuf};
use std::time::Instant;

use nerfjit_dsl::Program;
use nerfjit_jit::KernelCache;
use nerfjit_runtime::{render_volume, rgb_image, Camera, Quantize, VolumeFrame, VolumeSettings};

use crate::block::Block;
use crate::failure::Result;
use crate::field::VolumeField;
use crate::output::write_images;

const KEYS: &[&str] = &[
    "camera",
    "size",
    "near",
    "far",
    "samples",
    "background",
    "early_termination",
    "out",
    "depth",
    "frame_ms",
];

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
    /// Color frames.
    pub out: PathBuf,
    /// Depth frames.
    pub depth: Option<PathBuf>,
    /// GIF frame time.
    pub frame_ms: u32,
}

impl VolumePlan {
    /// Reads and checks a `render volume` block.
    pub fn new(mut b: Block) -> Result<VolumePlan> {
        let cameras = b.cameras()?;
        let size = b.size()?;
        let (near, far) = b.near_far(5.0)?;
        let samples = b.whole("samples", 2, 4096, 64)? as usize;
        let early = b.number("early_termination", 0.0, 1.0, 0.0)? as f32;
        let background = b.triple("background")?;
        let out = b.required_image_output("out", "out: \"volume.gif\"")?;
        let depth = b.image_output("depth")?;
        let frame_ms = b.whole("frame_ms", 10, 10_000, 50)? as u32;
        b.finish(KEYS)?;
        Ok(VolumePlan {
            cameras,
            size,
            near,
            far,
            samples,
            background,
            early_termination: (early > 0.0).then_some(early),
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
        }
    }

    /// Renders every frame with `params` and writes the outputs; returns a summary line.
    pub fn run(&self, program: &Program, params: &[f32], progress: &dyn Fn(usize)) -> Result<String> {
        let cache = KernelCache::new();
        let t = Instant::now();
        let field = VolumeField::compile(program, &cache)?;
        let compile_s = t.elapsed().as_secs_f64();
        let (forward, _) = field.bind(params);
        let settings = self.settings(&field);
        let (w, h) = self.size;
        let start = Instant::now();
        let mut frames = Vec::with_capacity(self.cameras.len());
        for (i, camera) in self.cameras.iter().enumerate() {
            frames.push(render_volume(camera, w, h, &forward, &settings)?);
            progress(i + 1);
        }
        let seconds = start.elapsed().as_secs_f64();
        write(&self.out, &frames, self.frame_ms, |f| f.rgb.clone())?;
        if let Some(path) = &self.depth {
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
            "volume-rendered {} frame{} of {w}×{h}×{} samples in {seconds:.3} s ({:.2} ms/frame; JIT compile {compile_s:.3} s) → {}",
            frames.len(),
            if frames.len() == 1 { "" } else { "s" },
            self.samples,
            1e3 * seconds / frames.len() as f64,
            self.out.display()
        ))
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
