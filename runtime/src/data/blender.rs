//! Blender / NeRF-synthetic data sets (`transforms_*.json` with RGBA PNGs) as training and
//! evaluation [`Views`]: alpha composited onto a background color, optionally area-downscaled,
//! decoded in parallel and cached on disk.
//!
//! Pixel values are used as stored (no gamma change), scaled to [0, 1]. The Blender camera is
//! defined by `camera_angle_x` and the image width, so the same [`Camera`](crate::Camera)
//! serves every image size: pixel (i, j) of an `n`×`n` image covers the source footprint
//! rows [i·H/n, (i+1)·H/n) × columns [j·W/n, (j+1)·W/n), whose center is the point the ray of
//! the downscaled pixel goes through.
//!
//! Downscaled views are cached in a folder (`$NERFJIT_CACHE` if set, else `target/nerfjit-cache`
//! when the current folder has a `target` folder, else `nerfjit-cache` in the OS temp folder),
//! one file per request keyed by the JSON path, its modification time and length, the size,
//! the background and the limit. Each image's modification time and length are stored in the
//! file: a changed image makes the entry stale, a deleted one does not (the cache still holds
//! its pixels). An unreadable, stale or unwritable cache only means decoding again.

use std::ffi::OsString;
use std::path::{Path, PathBuf};
use std::time::UNIX_EPOCH;

use rayon::prelude::*;

use crate::cameras::camera_files::load_blender_cameras;
use crate::data::dataset::Views;
use crate::data::decode::decode_checked;
use crate::data::npy::ImageF32;
use crate::error::{check_size, Error, Result};

const PNG_SIGNATURE: &[u8] = b"\x89PNG\r\n\x1a\n";
const CACHE_MAGIC: &[u8] = b"nerfjit blender views v1\n";

/// What to make of the frames of a `transforms_*.json`.
#[derive(Debug, Clone, Copy)]
struct Request {
    size: Option<u32>,
    background: [f32; 3],
    limit: Option<usize>,
}

/// Reads a Blender / NeRF-synthetic `transforms_*.json` and its RGBA PNGs as views: the first
/// `limit` frames when given (all otherwise), alpha composited onto `background`
/// (rgb·a + background·(1 − a), values as stored in [0, 1]), and area-downscaled to
/// `size`×`size` when `size` is given (square images only). The cameras fit any size.
///
/// Images are decoded in parallel; downscaled views are cached on disk so that loading them
/// again is fast (see the [module docs](self)). Errors name the file: missing or invalid
/// images, images of different sizes, bad JSON.
pub fn load_blender_views(
    path: &Path,
    size: Option<u32>,
    background: [f32; 3],
    limit: Option<usize>,
) -> Result<Views> {
    let cache = cache_folder(std::env::var_os("NERFJIT_CACHE"), Path::new(""));
    let request = Request {
        size,
        background,
        limit,
    };
    load_views(path, request, Some(&cache))
}

/// The cache folder: `env` (`$NERFJIT_CACHE`) if set, else `cwd/target/nerfjit-cache` if
/// `cwd/target` is a folder, else `nerfjit-cache` in the OS temp folder.
fn cache_folder(env: Option<OsString>, cwd: &Path) -> PathBuf {
    match env {
        Some(folder) if !folder.is_empty() => PathBuf::from(folder),
        _ if cwd.join("target").is_dir() => cwd.join("target").join("nerfjit-cache"),
        _ => std::env::temp_dir().join("nerfjit-cache"),
    }
}

/// [`load_blender_views`] with an explicit cache folder (`None`: no cache).
fn load_views(path: &Path, request: Request, cache: Option<&Path>) -> Result<Views> {
    check_request(&request)?;
    let mut set = load_blender_cameras(path)?;
    if let Some(limit) = request.limit {
        check_limit(path, limit, set.images.len())?;
        set.cameras.truncate(limit);
        set.images.truncate(limit);
    }
    let entry = match (request.size, cache) {
        (Some(_), Some(folder)) => Some(CacheEntry::new(folder, path, &request)),
        _ => None,
    };
    let stamps: Vec<Option<u64>> = set.images.iter().map(|f| stamp(f)).collect();
    let cached = entry.as_ref().and_then(|e| e.read(&stamps));
    let images = match cached {
        Some(images) => images,
        None => {
            let images = decode_all(&set.images, &request)?;
            if let Some(entry) = &entry {
                // A cache that cannot be written is no reason to fail.
                entry.write(&stamps, &images).ok();
            }
            images
        }
    };
    let (width, height) = images.first().map_or((0, 0), |i| (i.width, i.height));
    Ok(Views {
        cameras: set.cameras,
        images,
        width,
        height,
        alpha: None,
        masks: None,
    })
}

fn check_request(request: &Request) -> Result<()> {
    if let Some(size) = request.size {
        check_size(size, size)?;
    }
    if !request.background.iter().all(|c| c.is_finite()) {
        return Err(Error::Invalid(format!(
            "background {:?} must be finite",
            request.background
        )));
    }
    Ok(())
}

fn check_limit(path: &Path, limit: usize, frames: usize) -> Result<()> {
    if limit == 0 || limit > frames {
        return Err(Error::Invalid(format!(
            "limit {limit} must be between 1 and the {frames} frames of {}",
            path.display()
        )));
    }
    Ok(())
}

/// Decodes all images in parallel, checking that their source sizes agree.
fn decode_all(files: &[PathBuf], request: &Request) -> Result<Vec<ImageF32>> {
    let decoded: Vec<((u32, u32), ImageF32)> = files
        .par_iter()
        .map(|file| decode_view(file, request))
        .collect::<Result<_>>()?;
    if let Some((first, _)) = decoded.first() {
        let odd = decoded.iter().zip(files).find(|((size, _), _)| size != first);
        if let Some(((size, _), file)) = odd {
            return Err(Error::format(
                file,
                format!(
                    "image is {}×{} but {} is {}×{}",
                    size.0,
                    size.1,
                    files[0].display(),
                    first.0,
                    first.1
                ),
            ));
        }
    }
    Ok(decoded.into_iter().map(|(_, image)| image).collect())
}

/// Decodes one RGBA PNG into its source (width, height) and the composited, resized image.
fn decode_view(file: &Path, request: &Request) -> Result<((u32, u32), ImageF32)> {
    let mut start = [0u8; PNG_SIGNATURE.len()];
    let mut opened = std::fs::File::open(file).map_err(|e| Error::reading(file, e))?;
    let read = std::io::Read::read(&mut opened, &mut start).map_err(|e| Error::read(file, e))?;
    if start[..read] != *PNG_SIGNATURE {
        return Err(Error::format(file, "not a PNG file"));
    }
    let rgba = decode_checked(file, Some(image::ImageFormat::Png))?.to_rgba32f();
    let source = rgba.dimensions();
    let image = composite(&rgba, request.background);
    let Some(size) = request.size else {
        return Ok((source, image));
    };
    if source.0 != source.1 {
        return Err(Error::format(
            file,
            format!(
                "image is {}×{}: resizing to {size}×{size} needs square images",
                source.0, source.1
            ),
        ));
    }
    Ok((source, area_resize(&image, size, size)))
}

/// Straight alpha composited onto `background`: rgb·a + background·(1 − a).
pub(crate) fn composite(rgba: &image::Rgba32FImage, background: [f32; 3]) -> ImageF32 {
    ImageF32 {
        width: rgba.width(),
        height: rgba.height(),
        pixels: rgba
            .pixels()
            .map(|p| std::array::from_fn(|c| p[c] * p[3] + background[c] * (1.0 - p[3])))
            .collect(),
    }
}

/// The source pixels under one output pixel: the first index and the weight of each, the
/// fraction of the footprint it covers (the weights sum to 1).
type Footprint = (usize, Vec<f32>);

/// The footprints of `to` output pixels over `from` source pixels. In units of 1/`to` source
/// pixels, output pixel j spans [j·from, (j+1)·from) and source pixel i spans [i·to, (i+1)·to),
/// so overlaps are exact integers.
fn footprints(from: u32, to: u32) -> Vec<Footprint> {
    let (from, to) = (u64::from(from), u64::from(to));
    (0..to)
        .map(|j| {
            let (lo, hi) = (j * from, (j + 1) * from);
            let first = lo / to;
            let weights = (first..=(hi - 1) / to)
                .map(|i| (hi.min((i + 1) * to) - lo.max(i * to)) as f32 / from as f32)
                .collect();
            (first as usize, weights)
        })
        .collect()
}

fn weighted_sum((first, weights): &Footprint, pixel: impl Fn(usize) -> [f32; 3]) -> [f32; 3] {
    let mut sum = [0.0; 3];
    for (k, w) in weights.iter().enumerate() {
        let p = pixel(first + k);
        for c in 0..3 {
            sum[c] += w * p[c];
        }
    }
    sum
}

/// Area (box-filter) resampling to `width`×`height`: each output pixel is the mean of the
/// source over its exact footprint, partial source pixels weighted by the area they cover.
pub(crate) fn area_resize(image: &ImageF32, width: u32, height: u32) -> ImageF32 {
    let columns = footprints(image.width, width);
    let rows = footprints(image.height, height);
    let w = width as usize;
    let narrow: Vec<[f32; 3]> = image
        .pixels
        .chunks_exact(image.width as usize)
        .flat_map(|row| columns.iter().map(|f| weighted_sum(f, |i| row[i])))
        .collect();
    let narrow = &narrow;
    let pixels = rows
        .iter()
        .flat_map(|f| (0..w).map(move |x| weighted_sum(f, |i| narrow[i * w + x])))
        .collect();
    ImageF32 {
        width,
        height,
        pixels,
    }
}

/// FNV-1a, a hash that is stable across runs and Rust versions.
fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, &b| {
        (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3)
    })
}

/// A hash of the modification time and length of `file`; `None` if they cannot be read.
fn stamp(file: &Path) -> Option<u64> {
    let meta = std::fs::metadata(file).ok()?;
    let time = meta.modified().ok()?.duration_since(UNIX_EPOCH).ok()?;
    Some(fnv1a(format!("{}:{}", time.as_nanos(), meta.len()).as_bytes()))
}

/// One cache file, named by a hash of its key; the key itself is stored in the file too.
struct CacheEntry {
    file: PathBuf,
    key: String,
}

impl CacheEntry {
    fn new(folder: &Path, json: &Path, request: &Request) -> CacheEntry {
        let canonical = json.canonicalize().unwrap_or_else(|_| json.to_path_buf());
        let key = format!(
            "json {}\nstamp {:?}\nsize {:?}\nbackground {:?}\nlimit {:?}\n",
            canonical.display(),
            stamp(json),
            request.size,
            request.background.map(f32::to_bits),
            request.limit
        );
        let folder_name = canonical.parent().and_then(Path::file_name).unwrap_or_default();
        let stem = canonical.file_stem().unwrap_or_default();
        let name: String = format!("{}-{}", folder_name.to_string_lossy(), stem.to_string_lossy())
            .chars()
            .map(|c| {
                if c.is_ascii_alphanumeric() || c == '_' {
                    c
                } else {
                    '-'
                }
            })
            .collect();
        CacheEntry {
            file: folder.join(format!("{name}-{:016x}.views", fnv1a(key.as_bytes()))),
            key,
        }
    }

    /// The cached images if the entry exists, is intact and no existing image changed.
    fn read(&self, stamps: &[Option<u64>]) -> Option<Vec<ImageF32>> {
        let bytes = crate::input::read_capped(&self.file).ok()?;
        let mut r = ByteReader(&bytes);
        let key_len = u32::try_from(self.key.len()).ok()?;
        let header_ok = r.take(CACHE_MAGIC.len())? == CACHE_MAGIC
            && r.u32()? == key_len
            && r.take(self.key.len())? == self.key.as_bytes()
            && r.u32()? as usize == stamps.len();
        if !header_ok {
            return None;
        }
        let (width, height) = (r.u32()?, r.u32()?);
        for stamp in stamps {
            let stored = r.u64()?;
            if stamp.is_some_and(|s| s != stored) {
                return None;
            }
        }
        let n = width as usize * height as usize;
        let images = stamps
            .iter()
            .map(|_| {
                let pixels = r.pixels(n)?;
                Some(ImageF32 {
                    width,
                    height,
                    pixels,
                })
            })
            .collect::<Option<Vec<_>>>()?;
        r.0.is_empty().then_some(images)
    }

    /// Writes the entry through a temporary file, so that readers never see a partial one.
    fn write(&self, stamps: &[Option<u64>], images: &[ImageF32]) -> std::io::Result<()> {
        let (width, height) = images.first().map_or((0, 0), |i| (i.width, i.height));
        let pixels: usize = images.iter().map(|i| i.pixels.len()).sum();
        let mut bytes =
            Vec::with_capacity(CACHE_MAGIC.len() + self.key.len() + 16 + 8 * stamps.len() + 12 * pixels);
        bytes.extend_from_slice(CACHE_MAGIC);
        bytes.extend_from_slice(&(self.key.len() as u32).to_le_bytes());
        bytes.extend_from_slice(self.key.as_bytes());
        for value in [stamps.len() as u32, width, height] {
            bytes.extend_from_slice(&value.to_le_bytes());
        }
        for stamp in stamps {
            bytes.extend_from_slice(&stamp.unwrap_or(0).to_le_bytes());
        }
        for value in images.iter().flat_map(|i| i.pixels.iter().flatten()) {
            bytes.extend_from_slice(&value.to_le_bytes());
        }
        if let Some(folder) = self.file.parent() {
            std::fs::create_dir_all(folder)?;
        }
        let temporary = self.file.with_extension(format!("tmp{}", std::process::id()));
        std::fs::write(&temporary, bytes)?;
        std::fs::rename(&temporary, &self.file).inspect_err(|_| {
            std::fs::remove_file(&temporary).ok();
        })
    }
}

/// Little-endian values from the front of a byte slice; `None` when it runs out.
struct ByteReader<'a>(&'a [u8]);

impl ByteReader<'_> {
    fn take(&mut self, n: usize) -> Option<&[u8]> {
        let (head, rest) = self.0.split_at_checked(n)?;
        self.0 = rest;
        Some(head)
    }

    fn u32(&mut self) -> Option<u32> {
        Some(u32::from_le_bytes(self.take(4)?.try_into().ok()?))
    }

    fn u64(&mut self) -> Option<u64> {
        Some(u64::from_le_bytes(self.take(8)?.try_into().ok()?))
    }

    fn pixels(&mut self, n: usize) -> Option<Vec<[f32; 3]>> {
        let bytes = self.take(n.checked_mul(12)?)?;
        let value = |b: &[u8]| f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
        Some(
            bytes
                .chunks_exact(12)
                .map(|p| [value(&p[0..4]), value(&p[4..8]), value(&p[8..12])])
                .collect(),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cameras::rays::RayBatch;
    use crate::data::scratch_folder;
    use glam::Vec3;
    use std::time::{Duration, Instant, SystemTime};

    fn request(size: Option<u32>, background: [f32; 3]) -> Request {
        Request {
            size,
            background,
            limit: None,
        }
    }

    const COLOR: [u8; 4] = [200, 100, 50, 64];

    /// A 2-frame data set of `side`×`side` RGBA PNGs: frame 0 is the uniform `COLOR`, frame 1
    /// a checkerboard of opaque white and fully transparent pixels.
    fn synthetic_set(dir: &Path, side: u32) -> PathBuf {
        std::fs::create_dir_all(dir.join("train")).unwrap();
        image::RgbaImage::from_pixel(side, side, image::Rgba(COLOR))
            .save(dir.join("train/r_0.png"))
            .unwrap();
        image::RgbaImage::from_fn(side, side, |x, y| {
            image::Rgba(if (x + y) % 2 == 0 { [255; 4] } else { [0; 4] })
        })
        .save(dir.join("train/r_1.png"))
        .unwrap();
        let matrix = |z: f32| format!("[[1,0,0,0],[0,1,0,0],[0,0,1,{z}],[0,0,0,1]]");
        let text = format!(
            r#"{{"camera_angle_x": 0.69, "frames": [
                {{"file_path": "./train/r_0", "transform_matrix": {}}},
                {{"file_path": "./train/r_1.png", "transform_matrix": {}}}]}}"#,
            matrix(4.0),
            matrix(5.0)
        );
        let path = dir.join("transforms_train.json");
        std::fs::write(&path, text).unwrap();
        path
    }

    fn patterned(width: u32, height: u32) -> ImageF32 {
        let pixels = (0..width * height)
            .map(|k| {
                let v = ((k * 37 + 11) % 101) as f32 / 100.0;
                [v, 1.0 - v, (k % 7) as f32 / 6.0]
            })
            .collect();
        ImageF32 {
            width,
            height,
            pixels,
        }
    }

    fn checkerboard(side: u32) -> ImageF32 {
        let pixels = (0..side * side)
            .map(|k| [((k % side + k / side) % 2) as f32; 3])
            .collect();
        ImageF32 {
            width: side,
            height: side,
            pixels,
        }
    }

    fn mass(image: &ImageF32) -> [f64; 3] {
        let mut sum = [0.0; 3];
        for p in &image.pixels {
            for c in 0..3 {
                sum[c] += f64::from(p[c]);
            }
        }
        sum
    }

    fn assert_close(a: [f32; 3], b: [f32; 3], tolerance: f32) {
        assert!(
            a.iter().zip(b).all(|(x, y)| (x - y).abs() <= tolerance),
            "{a:?} vs {b:?}"
        );
    }

    #[test]
    fn area_resize_keeps_constants_averages_checkerboards_and_preserves_mass() {
        for (from, to) in [(16, 8), (16, 5), (800, 128), (5, 16)] {
            let constant = ImageF32 {
                width: from,
                height: from,
                pixels: vec![[0.3, 0.6, 0.9]; (from * from) as usize],
            };
            let out = area_resize(&constant, to, to);
            assert_eq!(out.pixels.len(), (to * to) as usize);
            for p in &out.pixels {
                assert_close(*p, [0.3, 0.6, 0.9], 1e-6);
            }
        }
        // An integer factor averages each 2×2 block exactly; a fractional footprint of f×f
        // pixels is off by at most 0.5/f² (the uncovered part of a partial checker).
        for (from, to, tolerance) in [
            (16, 8, 0.0),
            (16, 5, 0.5 / 3.2f32.powi(2)),
            (800, 128, 0.5 / 6.25f32.powi(2)),
        ] {
            for p in &area_resize(&checkerboard(from), to, to).pixels {
                assert_close(*p, [0.5; 3], tolerance + 1e-6);
            }
        }
        for (from, to) in [((16, 16), (5, 5)), ((16, 12), (7, 5)), ((800, 800), (128, 128))] {
            let image = patterned(from.0, from.1);
            let out = area_resize(&image, to.0, to.1);
            let scale = f64::from(from.0 * from.1) / f64::from(to.0 * to.1);
            for (a, b) in mass(&image).iter().zip(mass(&out)) {
                assert!((a - b * scale).abs() < 1e-5 * a, "{a} vs {}", b * scale);
            }
        }
    }

    #[test]
    fn area_resize_matches_an_upsampled_block_mean() {
        // Replicating each source pixel into to×to copies makes every output footprint a whole
        // block of from×from copies, whose plain mean is the exact area average.
        let (from, to) = (16u32, 5u32);
        let image = patterned(from, from);
        let out = area_resize(&image, to, to);
        for (k, p) in out.pixels.iter().enumerate() {
            let (row, col) = (k as u32 / to, k as u32 % to);
            let mut sum = [0.0f64; 3];
            for y in row * from..(row + 1) * from {
                for x in col * from..(col + 1) * from {
                    let source = image.pixels[((y / to) * from + x / to) as usize];
                    for c in 0..3 {
                        sum[c] += f64::from(source[c]);
                    }
                }
            }
            let mean = sum.map(|s| (s / f64::from(from * from)) as f32);
            assert_close(*p, mean, 1e-6);
        }
    }

    #[test]
    fn rays_of_downscaled_views_go_through_footprint_centers() {
        let folder = scratch_folder("blender-rays");
        let path = synthetic_set(folder.path(), 16);
        let camera = load_blender_cameras(&path).unwrap().cameras[0];
        for to in [5u32, 8] {
            let scale = 16.0 / to as f32;
            for (row, col) in [(0, 0), (1, 3), (to - 1, to - 2)] {
                let (_, d) = camera.ray(row, col, to, to);
                let (_, expected) =
                    camera.ray_at((row as f32 + 0.5) * scale, (col as f32 + 0.5) * scale, 16, 16);
                assert!(d.abs_diff_eq(expected, 1e-6), "{d} vs {expected}");
            }
        }
        let p = Vec3::new(0.3, -0.2, 1.0);
        let (r16, c16) = camera.project(p, 16, 16).unwrap();
        let (r5, c5) = camera.project(p, 5, 5).unwrap();
        assert!((r5 * 16.0 / 5.0 - r16).abs() < 1e-4 && (c5 * 16.0 / 5.0 - c16).abs() < 1e-4);
    }

    #[test]
    fn synthetic_views_are_composited_and_downscaled() {
        let folder = scratch_folder("blender-views");
        let path = synthetic_set(folder.path(), 16);
        let a = f32::from(COLOR[3]) / 255.0;
        let rgb = |c: usize| f32::from(COLOR[c]) / 255.0;
        for (background, checker) in [([0.0; 3], 0.5), ([1.0; 3], 1.0)] {
            let b = background[0];
            let expected = [0, 1, 2].map(|c| rgb(c) * a + b * (1.0 - a));
            let full = load_views(&path, request(None, background), None).unwrap();
            assert_eq!((full.len(), full.width, full.height), (2, 16, 16));
            assert_close(full.images[0].pixels[17], expected, 1e-6);
            assert_eq!(full.images[1].pixels[0], [1.0; 3]);
            assert_eq!(full.images[1].pixels[1], [b; 3]);
            for size in [8, 5] {
                let views = load_views(&path, request(Some(size), background), None).unwrap();
                assert_eq!((views.len(), views.width, views.height), (2, size, size));
                for (image, value) in views.images.iter().zip([expected, [checker; 3]]) {
                    assert_eq!((image.width, image.height), (size, size));
                    let tolerance = if size == 8 { 1e-6 } else { 0.05 };
                    image
                        .pixels
                        .iter()
                        .for_each(|p| assert_close(*p, value, tolerance));
                }
                let (rays, colors) = views.random_rays(1, 10, 7).unwrap();
                assert_eq!((rays.len(), colors.len()), (10, 10));
            }
        }
        let one = Request {
            limit: Some(1),
            ..request(Some(8), [0.0; 3])
        };
        let views = load_views(&path, one, None).unwrap();
        assert_eq!((views.len(), views.images.len()), (1, 1));
        let (rays, _) = RayBatch::random_pixels(&views.cameras[0], 8, 8, 4, 1).unwrap();
        assert_eq!(rays.len(), 4);
    }

    #[test]
    fn second_load_comes_from_the_cache_keyed_by_background() {
        let dir_scratch = scratch_folder("blender-cache");
        let dir = dir_scratch.path();
        let path = synthetic_set(dir, 16);
        let cache = dir.join("cache");
        let black = request(Some(5), [0.0; 3]);
        let first = load_views(&path, black, Some(&cache)).unwrap();
        assert_eq!(std::fs::read_dir(&cache).unwrap().count(), 1);
        std::fs::remove_dir_all(dir.join("train")).unwrap();
        let second = load_views(&path, black, Some(&cache)).unwrap();
        assert_eq!((&second.images, &second.cameras), (&first.images, &first.cameras));
        assert_eq!((second.width, second.height), (5, 5));
        // Another background, size or limit is another key: decoding fails without the PNGs.
        let white = request(Some(5), [1.0; 3]);
        let e = load_views(&path, white, Some(&cache)).unwrap_err();
        assert!(e.to_string().ends_with("file not found"), "{e}");
        assert!(load_views(&path, request(Some(4), [0.0; 3]), Some(&cache)).is_err());
        let one = Request {
            limit: Some(1),
            ..black
        };
        assert!(load_views(&path, one, Some(&cache)).is_err());
        // Without a size nothing is cached.
        assert!(load_views(&path, request(None, [0.0; 3]), Some(&cache)).is_err());
    }

    #[test]
    fn stale_or_corrupt_cache_entries_are_decoded_again() {
        let dir_scratch = scratch_folder("blender-stale");
        let dir = dir_scratch.path();
        let path = synthetic_set(dir, 16);
        let cache = dir.join("cache");
        let black = request(Some(8), [0.0; 3]);
        let first = load_views(&path, black, Some(&cache)).unwrap();
        // A changed image (new content, new time) makes the entry stale.
        let png = dir.join("train/r_0.png");
        image::RgbaImage::from_pixel(16, 16, image::Rgba([255; 4]))
            .save(&png)
            .unwrap();
        let later = SystemTime::now() + Duration::from_secs(10);
        std::fs::File::options()
            .write(true)
            .open(&png)
            .unwrap()
            .set_modified(later)
            .unwrap();
        let changed = load_views(&path, black, Some(&cache)).unwrap();
        assert_eq!(changed.images[0].pixels[0], [1.0; 3]);
        assert_ne!(changed.images[0], first.images[0]);
        // Truncated or garbage entries are decoded again and rewritten.
        let entry = std::fs::read_dir(&cache).unwrap().next().unwrap().unwrap().path();
        for junk in [&b"nerfjit"[..], b""] {
            std::fs::write(&entry, junk).unwrap();
            assert_eq!(
                load_views(&path, black, Some(&cache)).unwrap().images,
                changed.images
            );
        }
        assert!(std::fs::metadata(&entry).unwrap().len() > 2 * 8 * 8 * 12);
        // An unusable cache folder (a file) is no error either.
        let blocked = dir.join("blocked");
        std::fs::write(&blocked, "a file").unwrap();
        assert_eq!(
            load_views(&path, black, Some(&blocked)).unwrap().images,
            changed.images
        );
    }

    #[test]
    fn bad_inputs_give_errors_naming_the_file() {
        let dir_scratch = scratch_folder("blender-bad");
        let dir = dir_scratch.path();
        let path = synthetic_set(dir, 16);
        let black = request(Some(8), [0.0; 3]);
        let load = |r: Request| load_views(&path, r, None).unwrap_err().to_string();
        let r1 = dir.join("train/r_1.png");

        image::RgbaImage::new(8, 8).save(&r1).unwrap();
        let expected = format!(
            "{}: image is 8×8 but {} is 16×16",
            r1.display(),
            dir.join("train/r_0.png").display()
        );
        assert_eq!(load(black), expected);
        assert_eq!(load(request(None, [0.0; 3])), expected);

        image::RgbaImage::new(16, 8).save(&r1).unwrap();
        let e = load(black);
        assert!(e.starts_with(&format!("{}: image is 16×8", r1.display())), "{e}");

        std::fs::write(&r1, b"GIF89a").unwrap();
        assert_eq!(load(black), format!("{}: not a PNG file", r1.display()));
        std::fs::write(&r1, PNG_SIGNATURE).unwrap();
        let e = load(black);
        assert!(e.starts_with(&format!("{}: invalid PNG", r1.display())), "{e}");
        std::fs::remove_file(&r1).unwrap();
        assert_eq!(
            load(black),
            format!("cannot read {}: file not found", r1.display())
        );

        for limit in [0, 3] {
            let e = load(Request {
                limit: Some(limit),
                ..black
            });
            assert!(
                e.contains(&format!("limit {limit}")) && e.ends_with(&path.display().to_string()),
                "{e}"
            );
        }
        assert!(load(request(Some(0), [0.0; 3])).contains("empty"));
        assert!(load(request(None, [f32::NAN; 3])).contains("finite"));

        std::fs::write(&path, "{ not json").unwrap();
        assert!(load(black).starts_with(&format!("{}: invalid JSON", path.display())));
        let missing = dir.join("nothing.json");
        let e = load_views(&missing, black, None).unwrap_err().to_string();
        assert_eq!(e, format!("cannot read {}: file not found", missing.display()));
    }

    #[test]
    fn cache_folder_prefers_the_variable_then_target_then_temp() {
        let dir_scratch = scratch_folder("blender-folder");
        let dir = dir_scratch.path();
        assert_eq!(cache_folder(Some("/x/c".into()), dir), PathBuf::from("/x/c"));
        let temp = std::env::temp_dir().join("nerfjit-cache");
        assert_eq!(cache_folder(Some("".into()), dir), temp);
        assert_eq!(cache_folder(None, dir), temp);
        std::fs::create_dir(dir.join("target")).unwrap();
        assert_eq!(cache_folder(None, dir), dir.join("target/nerfjit-cache"));
    }

    #[test]
    fn lego_views_load_and_cache_when_present() {
        let path = Path::new("/work/shared/data/lego/transforms_val.json");
        if !path.exists() {
            eprintln!("note: {} not found, skipping", path.display());
            return;
        }
        let cache_scratch = scratch_folder("blender-lego");
        let cache = cache_scratch.path();
        let black = request(Some(64), [0.0; 3]);
        let start = Instant::now();
        let views = load_views(path, black, Some(cache)).unwrap();
        let decoded = start.elapsed();
        let start = Instant::now();
        let cached = load_views(path, black, Some(cache)).unwrap();
        let from_cache = start.elapsed();
        eprintln!("lego val at 64×64: first load {decoded:.2?}, cached load {from_cache:.2?}");
        assert_eq!((views.len(), views.width, views.height), (10, 64, 64));
        assert_eq!(cached.images, views.images);
        for image in &views.images {
            assert_eq!((image.width, image.height), (64, 64));
            assert!(image.pixels.iter().flatten().all(|v| (0.0..=1.0).contains(v)));
            let mean = mass(image).iter().sum::<f64>() / (3.0 * 64.0 * 64.0);
            assert!(mean > 0.01, "{mean}");
        }
    }
}
