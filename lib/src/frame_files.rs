//! Writing rendered frames: a GIF or an MP4 (H.264) of all frames, a PNG of one, or numbered PNGs
//! (`name_000.png`, ...); depths as float32 NumPy arrays.

use std::path::Path;

use image::RgbImage;
use nerfjit_runtime::{save_gif, save_mp4, save_png, write_npy_f32};

use crate::failure::Result;

/// Writes `images` to `path` by its extension.
pub fn write_images(path: &Path, images: Vec<RgbImage>, frame_ms: u32) -> Result<()> {
    if path.extension().is_some_and(|e| e == "gif") {
        save_gif(path, &images, frame_ms)?;
    } else if path.extension().is_some_and(|e| e == "mp4") {
        save_mp4(path, &images, frame_ms)?;
    } else if images.len() == 1 {
        save_png(path, images.into_iter().next().expect("one image"))?;
    } else {
        let stem = path.file_stem().and_then(|s| s.to_str()).unwrap_or("frame");
        for (i, img) in images.into_iter().enumerate() {
            save_png(&path.with_file_name(format!("{stem}_{i:03}.png")), img)?;
        }
    }
    Ok(())
}

/// Whether `path` names a NumPy `.npy` file.
pub fn is_npy(path: &Path) -> bool {
    path.extension().is_some_and(|e| e == "npy")
}

/// Writes the depths of frames of `width`×`height` as one float32 `.npy` array: shape (H, W) for one
/// frame, (frames, H, W) for more.
pub fn write_depths(path: &Path, (width, height): (u32, u32), frames: Vec<Vec<f32>>) -> Result<()> {
    let (w, h) = (width as usize, height as usize);
    let shape = match frames.len() {
        1 => vec![h, w],
        n => vec![n, h, w],
    };
    let values: Vec<f32> = frames.into_iter().flatten().collect();
    write_npy_f32(path, &shape, &values)?;
    Ok(())
}
