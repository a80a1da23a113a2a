//! `nerfjit render` and `nerfjit eval-views`: a script's volume field (or a training checkpoint's)
//! rendered from every camera of a Blender-format camera file, written as PNGs/GIF or scored against the
//! file's images with PSNR and SSIM.

use std::path::{Path, PathBuf};
use std::time::Instant;

use nerfjit_dsl::Program;
use nerfjit_jit::KernelCache;
use nerfjit_runtime::composite::Mode;
use nerfjit_runtime::{
    load_blender_cameras, load_blender_views, psnr, rgb_image, ssim, ImageF32, Quantize, Views,
    VolumeSettings,
};

use crate::failure::{Failure, Result};
use crate::field::VolumeFields;
use crate::output::write_images;

/// Where the field comes from and how to render it.
pub struct ViewArgs<'a> {
    /// A script, or a checkpoint written by `train` (it holds its script).
    pub source: &'a str,
    /// A Blender `transforms_*.json`.
    pub cameras: &'a Path,
    /// Image side in pixels.
    pub size: u32,
    /// Sampled interval and samples per ray.
    pub near: f32,
    /// End of the sampled interval.
    pub far: f32,
    /// Samples per ray.
    pub samples: usize,
    /// Background color (the data's alpha is composited on it too).
    pub background: [f32; 3],
    /// Importance samples per ray (hierarchical sampling with the script's coarse field; 0: none).
    pub importance: usize,
}

/// The program and params: a checkpoint's (a `.safetensors` or `.json` file), or a script's initial ones.
pub(crate) fn load(source: &str) -> Result<(Program, Vec<f32>)> {
    let is_checkpoint = source.ends_with(".safetensors") || source.ends_with(".json");
    if is_checkpoint {
        crate::checkpoint::load_trained(Path::new(source))
    } else {
        let program = crate::script::load(source)?;
        let params = program.param_values.clone();
        Ok((program, params))
    }
}

/// The renderer settings of `args` for a field of `mode`.
pub(crate) fn settings(args: &ViewArgs, mode: Mode) -> VolumeSettings {
    VolumeSettings {
        near: args.near,
        far: args.far,
        samples: args.samples,
        mode,
        background: Some(args.background),
        early_termination: None,
    }
}

/// `nerfjit render`: one PNG per camera in `out`, or a GIF of all.
pub fn render(args: &ViewArgs, out: &Path, gif: bool) -> Result<String> {
    if !out.is_dir() {
        std::fs::create_dir_all(out)
            .map_err(|e| Failure::Message(format!("cannot create output folder '{}': {e}", out.display())))?;
    }
    let (program, params) = load(args.source)?;
    let set = load_blender_cameras(args.cameras)?;
    let cache = KernelCache::new();
    let fields = VolumeFields::compile(&program, &cache, args.importance)?;
    let settings = settings(args, fields.fine.mode);
    let start = Instant::now();
    let images = set
        .cameras
        .iter()
        .map(|camera| {
            let f = fields.render(camera, args.size, args.size, &params, &settings)?;
            Ok(rgb_image(f.width, f.height, &f.rgb, Quantize::Truncate)?)
        })
        .collect::<Result<Vec<_>>>()?;
    let seconds = start.elapsed().as_secs_f64();
    let n = images.len();
    let target: PathBuf = if gif {
        out.join("views.gif")
    } else {
        out.join("view.png")
    };
    write_images(&target, images, 100)?;
    let size = args.size;
    let per_view = seconds / n.max(1) as f64;
    let written = if gif {
        target.display().to_string()
    } else {
        out.display().to_string()
    };
    Ok(format!(
        "rendered {n} views of {size}×{size} in {seconds:.2} s ({per_view:.2} s/view) → {written}"
    ))
}

/// PSNR and SSIM of `fields` rendered from every camera of `views` against its image.
pub fn score(
    views: &Views,
    fields: &VolumeFields,
    params: &[f32],
    settings: &VolumeSettings,
) -> Result<Vec<(f32, f32)>> {
    views
        .cameras
        .iter()
        .zip(&views.images)
        .map(|(camera, target)| {
            let f = fields.render(camera, views.width, views.height, params, settings)?;
            let rendered = ImageF32 {
                width: f.width,
                height: f.height,
                pixels: f.rgb,
            };
            let mse = nerfjit_runtime::mse(&rendered, target)?;
            Ok((psnr(mse), ssim(&rendered, target)?))
        })
        .collect()
}

/// The mean PSNR and SSIM of scores.
pub fn means(scores: &[(f32, f32)]) -> (f64, f64) {
    let n = scores.len().max(1) as f64;
    let sum = |f: fn(&(f32, f32)) -> f32| scores.iter().map(|x| f64::from(f(x))).sum::<f64>() / n;
    (sum(|x| x.0), sum(|x| x.1))
}

/// `nerfjit eval-views`: PSNR and SSIM of every view, and their means.
pub fn eval(args: &ViewArgs) -> Result<String> {
    let (program, params) = load(args.source)?;
    let views = load_blender_views(args.cameras, Some(args.size), args.background, None)?;
    let cache = KernelCache::new();
    let fields = VolumeFields::compile(&program, &cache, args.importance)?;
    let scores = score(&views, &fields, &params, &settings(args, fields.fine.mode))?;
    let mut lines = String::from("view  PSNR (dB)  SSIM\n");
    for (i, (p, s)) in scores.iter().enumerate() {
        lines += &format!("{i:>4}  {p:>9.2}  {s:.4}\n");
    }
    let (p, s) = means(&scores);
    lines += &format!("mean  {p:>9.2}  {s:.4}\n");
    Ok(lines)
}
