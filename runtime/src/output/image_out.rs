//! Turning frames into 8-bit images and writing them as PNG files and looping GIFs.

use std::path::Path;

use image::codecs::gif::{GifEncoder, Repeat};
use image::{Delay, DynamicImage, GrayImage, ImageFormat, Rgb, RgbImage};

use crate::error::{Error, Result};
use crate::output::frame::Frame;
use crate::whole_file::OutputFile;

/// How a float channel in [0, 1] becomes a byte (values are clamped to [0, 1] first, NaN
/// becomes 0).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Quantize {
    /// `(x·255).round()`: the nearest byte.
    Round,
    /// `(x·255)` truncated towards zero, like the course's PyTorch reference renders
    /// (`(img * 255).astype(np.uint8)`); use it to compare with them byte for byte.
    Truncate,
}

impl Quantize {
    /// The byte of channel value `x`.
    pub fn byte(self, x: f32) -> u8 {
        let x = if x.is_nan() { 0.0 } else { x.clamp(0.0, 1.0) } * 255.0;
        match self {
            Quantize::Round => x.round() as u8,
            Quantize::Truncate => x as u8,
        }
    }
}

fn check_len(what: &str, len: usize, width: u32, height: u32) -> Result<()> {
    if len != width as usize * height as usize || len == 0 {
        return Err(Error::Invalid(format!(
            "{what} has {len} pixels, which does not fit a non-empty {width}×{height} image"
        )));
    }
    Ok(())
}

/// An RGB8 image of `width`×`height` float pixels in row-major order.
pub fn rgb_image(width: u32, height: u32, pixels: &[[f32; 3]], quantize: Quantize) -> Result<RgbImage> {
    check_len("the color buffer", pixels.len(), width, height)?;
    Ok(RgbImage::from_fn(width, height, |x, y| {
        let p = pixels[(y * width + x) as usize];
        Rgb(p.map(|c| quantize.byte(c)))
    }))
}

/// The depth map of `frame` in grayscale: white at `near`, black at `far` and beyond, black
/// where the ray missed.
pub fn depth_image(frame: &Frame, near: f32, far: f32) -> Result<GrayImage> {
    check_len("the depth buffer", frame.depth.len(), frame.width, frame.height)?;
    check_len("the hit mask", frame.hit.len(), frame.width, frame.height)?;
    if !(near.is_finite() && far.is_finite() && far > near) {
        return Err(Error::Invalid(format!(
            "depth range needs finite near < far, got {near} and {far}"
        )));
    }
    Ok(GrayImage::from_fn(frame.width, frame.height, |x, y| {
        let i = (y * frame.width + x) as usize;
        let d = frame.depth[i];
        let v = if frame.hit[i] && d.is_finite() {
            1.0 - (d - near) / (far - near)
        } else {
            0.0
        };
        image::Luma([Quantize::Round.byte(v)])
    }))
}

/// The normal map of `frame`: `(n + 1) / 2` as RGB where hit, black where missed.
pub fn normal_image(frame: &Frame) -> Result<RgbImage> {
    check_len("the normal buffer", frame.normal.len(), frame.width, frame.height)?;
    check_len("the hit mask", frame.hit.len(), frame.width, frame.height)?;
    Ok(RgbImage::from_fn(frame.width, frame.height, |x, y| {
        let i = (y * frame.width + x) as usize;
        if frame.hit[i] {
            Rgb(frame.normal[i].map(|c| Quantize::Round.byte(0.5 * (c + 1.0))))
        } else {
            Rgb([0, 0, 0])
        }
    }))
}

/// Writes an image (e.g. an [`RgbImage`] or a [`GrayImage`]) as a PNG file, whole or not at all.
pub fn save_png(path: &Path, image: impl Into<DynamicImage>) -> Result<()> {
    let mut file = OutputFile::create(path)?;
    image
        .into()
        .write_to(&mut file, ImageFormat::Png)
        .map_err(|e| Error::write(path, e))?;
    file.finish()
}

/// The size of `frames`, which must be at least one and all of one size (for an animation at `path`).
pub(crate) fn frame_size(path: &Path, frames: &[RgbImage]) -> Result<(u32, u32)> {
    let Some(first) = frames.first() else {
        return Err(Error::write(path, "an animation needs at least one frame"));
    };
    let size = first.dimensions();
    if let Some(k) = frames.iter().position(|f| f.dimensions() != size) {
        return Err(Error::write(
            path,
            format!(
                "frame {k} is {}×{} but frame 0 is {}×{}",
                frames[k].width(),
                frames[k].height(),
                size.0,
                size.1
            ),
        ));
    }
    Ok(size)
}

/// NeuQuant sampling factor of the GIF palette (1 best and slowest, 30 fastest).
const GIF_SPEED: i32 = 10;

/// Writes `frames` (all of the same size, at most 65535 pixels a side) as a GIF that loops
/// forever, showing each frame for `delay_ms` milliseconds (GIF stores hundredths of a
/// second, so this is rounded down to a multiple of 10 ms).
pub fn save_gif(path: &Path, frames: &[RgbImage], delay_ms: u32) -> Result<()> {
    let size = frame_size(path, frames)?;
    if size.0 == 0 || size.1 == 0 || size.0 > 65535 || size.1 > 65535 {
        return Err(Error::write(
            path,
            format!(
                "GIF frames must be 1 to 65535 pixels a side, not {}×{}",
                size.0, size.1
            ),
        ));
    }
    let mut file = OutputFile::create(path)?;
    let mut encoder = GifEncoder::new_with_speed(&mut file, GIF_SPEED);
    let delay = Delay::from_numer_denom_ms(delay_ms, 1);
    encoder
        .set_repeat(Repeat::Infinite)
        .map_err(|e| Error::write(path, e))?;
    for frame in frames {
        let rgba = DynamicImage::ImageRgb8(frame.clone()).into_rgba8();
        encoder
            .encode_frame(image::Frame::from_parts(rgba, 0, 0, delay))
            .map_err(|e| Error::write(path, e))?;
    }
    // The encoder writes the GIF's trailer when dropped.
    drop(encoder);
    file.finish()
}

#[cfg(test)]
mod tests {
    use super::*;
    use image::AnimationDecoder;
    use std::path::PathBuf;

    fn temp_dir() -> PathBuf {
        let dir = std::env::temp_dir().join(format!("nerfjit-image-out-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    fn frame() -> Frame {
        Frame {
            width: 2,
            height: 1,
            rgb: vec![[0.5, 1.5, -1.0], [f32::NAN, 0.999, 0.0]],
            depth: vec![3.0, f32::INFINITY],
            normal: vec![[0.0, 1.0, -1.0], [0.0; 3]],
            hit: vec![true, false],
        }
    }

    #[test]
    fn quantization_rounds_or_truncates_after_clamping() {
        assert_eq!(Quantize::Round.byte(0.5), 128);
        assert_eq!(Quantize::Truncate.byte(0.5), 127);
        assert_eq!(Quantize::Truncate.byte(0.999), 254);
        assert_eq!(Quantize::Round.byte(2.0), 255);
        assert_eq!(Quantize::Round.byte(-1.0), 0);
        assert_eq!(Quantize::Truncate.byte(f32::NAN), 0);
        let f = frame();
        let img = rgb_image(2, 1, &f.rgb, Quantize::Truncate).unwrap();
        assert_eq!(img.get_pixel(0, 0).0, [127, 255, 0]);
        assert_eq!(img.get_pixel(1, 0).0, [0, 254, 0]);
        assert!(rgb_image(3, 1, &f.rgb, Quantize::Round).is_err());
        assert!(rgb_image(0, 0, &[], Quantize::Round).is_err());
    }

    #[test]
    fn depth_and_normal_maps() {
        let f = frame();
        let depth = depth_image(&f, 2.0, 6.0).unwrap();
        assert_eq!(depth.get_pixel(0, 0).0, [191]); // 1 − (3 − 2)/4 = 0.75
        assert_eq!(depth.get_pixel(1, 0).0, [0]);
        assert!(depth_image(&f, 2.0, 2.0).is_err());
        let normals = normal_image(&f).unwrap();
        assert_eq!(normals.get_pixel(0, 0).0, [128, 255, 0]);
        assert_eq!(normals.get_pixel(1, 0).0, [0, 0, 0]);
    }

    #[test]
    fn png_round_trip() {
        let path = temp_dir().join("rgb.png");
        let img = rgb_image(2, 1, &frame().rgb, Quantize::Round).unwrap();
        save_png(&path, img.clone()).unwrap();
        let back = image::open(&path).unwrap().into_rgb8();
        assert_eq!(back, img);
    }

    #[test]
    fn gif_loops_with_all_frames() {
        let path = temp_dir().join("anim.gif");
        let frames: Vec<RgbImage> = (0..3u8)
            .map(|k| RgbImage::from_pixel(8, 6, Rgb([k * 100, 50, 200])))
            .collect();
        save_gif(&path, &frames, 40).unwrap();
        let file = std::io::BufReader::new(std::fs::File::open(&path).unwrap());
        let decoded = image::codecs::gif::GifDecoder::new(file)
            .unwrap()
            .into_frames()
            .collect_frames()
            .unwrap();
        assert_eq!(decoded.len(), 3);
        for (k, f) in decoded.iter().enumerate() {
            assert_eq!(f.buffer().dimensions(), (8, 6));
            assert_eq!(f.delay().numer_denom_ms(), (40, 1));
            let red = f.buffer().get_pixel(3, 3).0[0] as i32;
            assert!((red - 100 * k as i32).abs() <= 8, "frame {k}: red {red}");
        }
        let bytes = std::fs::read(&path).unwrap();
        assert!(
            bytes.windows(11).any(|w| w == b"NETSCAPE2.0"),
            "no loop extension"
        );
    }

    #[test]
    fn bad_outputs_are_errors_naming_the_path() {
        let img = RgbImage::new(2, 2);
        let e = save_gif(Path::new("no-such-folder/x.gif"), std::slice::from_ref(&img), 10).unwrap_err();
        assert_eq!(
            e.to_string(),
            "cannot write no-such-folder/x.gif: folder 'no-such-folder' does not exist"
        );
        let e = save_png(Path::new("no-such-folder/x.png"), img.clone()).unwrap_err();
        assert!(e.to_string().contains("folder 'no-such-folder' does not exist"));
        let path = temp_dir().join("bad.gif");
        assert!(save_gif(&path, &[], 10).is_err());
        let e = save_gif(&path, &[img, RgbImage::new(3, 2)], 10).unwrap_err();
        assert!(e.to_string().contains("frame 1 is 3×2"), "{e}");
    }
}
