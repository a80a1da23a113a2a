//! Decoding images with their declared size checked first: every image nerfjit reads (Blender views,
//! capture frames, the course's PNG views) goes through [`decode_checked`], which reads the header and
//! refuses an image whose pixels, or the memory its decoding and conversion need, exceed the limits before
//! the decoder allocates anything. A small file can declare an enormous image (a PNG of zeros compresses
//! a thousandfold).

use std::path::Path;

use image::{ImageDecoder, ImageFormat};
use nerfjit_dsl::budget;

use crate::error::{Error, Result};

/// The most pixels an image may declare in its header; larger ones are refused before they are decoded.
pub const MAX_IMAGE_PIXELS: u64 = 1 << 27;

/// Bytes a pixel takes after decoding besides the decoder's own buffer: the RGBA float copy (16) and
/// two RGB float images made from it (12 each: composited, then undistorted or resized).
pub const CONVERTED_BYTES_PER_PIXEL: u64 = 40;

/// Decodes the image at `path` (of `format`, or of the format its first bytes show) after checking the
/// size its header declares against [`MAX_IMAGE_PIXELS`] and against the memory limit
/// ([`budget::check`]) for the decoder's buffer and the conversions that follow.
pub fn decode_checked(path: &Path, format: Option<ImageFormat>) -> Result<image::DynamicImage> {
    let reader = image::ImageReader::open(path).map_err(|e| Error::reading(path, e))?;
    let reader = match format {
        Some(format) => {
            let mut reader = reader;
            reader.set_format(format);
            reader
        }
        None => reader.with_guessed_format().map_err(|e| Error::read(path, e))?,
    };
    let Some(format) = reader.format() else {
        return Err(Error::format(path, "not an image nerfjit reads (PNG or JPEG)"));
    };
    let name = format.extensions_str().first().unwrap_or(&"image").to_uppercase();
    let bad = |e: &dyn std::fmt::Display| Error::format(path, format!("invalid {name}: {e}"));
    let decoder = reader.into_decoder().map_err(|e| bad(&e))?;
    let (w, h) = decoder.dimensions();
    let pixels = u64::from(w) * u64::from(h);
    if pixels > MAX_IMAGE_PIXELS {
        return Err(Error::format(
            path,
            format!("the image declares {w}×{h} pixels, more than the {MAX_IMAGE_PIXELS} nerfjit decodes"),
        ));
    }
    let bytes = decoder
        .total_bytes()
        .saturating_add(budget::bytes_of(pixels, CONVERTED_BYTES_PER_PIXEL));
    let what = || format!("decoding its {w}×{h} pixels");
    budget::check(what, bytes).map_err(|e| Error::format(path, format!("{e}: {}", budget::HINT)))?;
    image::DynamicImage::from_decoder(decoder).map_err(|e| bad(&e))
}
