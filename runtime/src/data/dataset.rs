//! Training views: cameras with the images they took, as in the course's `box_cameras.json`.

use std::path::Path;

use crate::cameras::camera::Camera;
use crate::cameras::camera_files::load_box_cameras;
use crate::cameras::rays::RayBatch;
use crate::data::decode::decode_checked;
use crate::data::npy::{read_npy_rgb, ImageF32};
use crate::error::{Error, Result};
use crate::rng::Rng;

/// Cameras and their images, all of one size.
#[derive(Debug, Clone)]
pub struct Views {
    /// The cameras, in file order.
    pub cameras: Vec<Camera>,
    /// The image of each camera.
    pub images: Vec<ImageF32>,
    /// Width of every image in pixels.
    pub width: u32,
    /// Height of every image in pixels.
    pub height: u32,
    /// The opacity of each pixel of each image, when the images are kept premultiplied (composited on
    /// black) so that training can composite them on any background ([`Views::random_rays_on`]).
    pub alpha: Option<Vec<Vec<f32>>>,
    /// The pixels of each image that a masked score counts (the data's object masks, as DTU's protocol
    /// scores renders inside them); `None` scores whole images only.
    pub masks: Option<Vec<Vec<bool>>>,
}

/// Reads an RGB image: a float32 `.npy` of shape (H, W, 3), or any PNG (values scaled to
/// [0, 1]; an alpha channel is composited on black).
pub fn read_rgb_image(path: &Path) -> Result<ImageF32> {
    let is_png = path.extension().is_some_and(|e| e.eq_ignore_ascii_case("png"));
    if !is_png {
        return read_npy_rgb(path);
    }
    let rgba = decode_checked(path, Some(image::ImageFormat::Png))?.to_rgba32f();
    Ok(ImageF32 {
        width: rgba.width(),
        height: rgba.height(),
        pixels: rgba
            .pixels()
            .map(|p| [p[0] * p[3], p[1] * p[3], p[2] * p[3]])
            .collect(),
    })
}

/// Reads the course's `box_cameras.json` and the images it names (`.npy` or `.png`, relative
/// to the JSON file), checking that every image has the size the file states.
pub fn load_box_views(path: &Path) -> Result<Views> {
    let set = load_box_cameras(path)?;
    let mut images = Vec::with_capacity(set.images.len());
    let mut size = set.image_size;
    for file in &set.images {
        let image = read_rgb_image(file)?;
        let (width, height) = *size.get_or_insert((image.width, image.height));
        if (image.width, image.height) != (width, height) {
            return Err(Error::format(
                file,
                format!(
                    "image is {}×{} but {} states {width}×{height}",
                    image.width,
                    image.height,
                    path.display()
                ),
            ));
        }
        images.push(image);
    }
    let (width, height) = size.unwrap_or_default();
    Ok(Views {
        cameras: set.cameras,
        images,
        width,
        height,
        alpha: None,
        masks: None,
    })
}

impl Views {
    /// Number of views.
    pub fn len(&self) -> usize {
        self.cameras.len()
    }

    /// True if there is no view.
    pub fn is_empty(&self) -> bool {
        self.cameras.is_empty()
    }

    /// Splits off every `every`-th view (views 0, every, 2·every, …) as held-out views, as
    /// mip-NeRF 360 and nerfstudio do for captures: (training views, held-out views). Both keep
    /// at least one view.
    pub fn hold_out(self, every: usize) -> Result<(Views, Views)> {
        if every < 2 || self.len() < 2 {
            return Err(Error::Invalid(format!(
                "holding out every {every}th of {} views leaves nothing to train on or to score: \
                 it needs at least 2 views and every ≥ 2",
                self.len()
            )));
        }
        let (width, height) = (self.width, self.height);
        let (with_alpha, with_masks) = (self.alpha.is_some(), self.masks.is_some());
        let empty = || Views {
            cameras: Vec::new(),
            images: Vec::new(),
            width,
            height,
            alpha: with_alpha.then(Vec::new),
            masks: with_masks.then(Vec::new),
        };
        let (mut train, mut held) = (empty(), empty());
        let mut alpha = self.alpha.map(|a| a.into_iter());
        let mut masks = self.masks.map(|m| m.into_iter());
        for (i, (camera, image)) in self.cameras.into_iter().zip(self.images).enumerate() {
            let to = if i % every == 0 { &mut held } else { &mut train };
            to.cameras.push(camera);
            to.images.push(image);
            if let (Some(all), Some(kept)) = (alpha.as_mut(), to.alpha.as_mut()) {
                kept.extend(all.next());
            }
            if let (Some(all), Some(kept)) = (masks.as_mut(), to.masks.as_mut()) {
                kept.extend(all.next());
            }
        }
        Ok((train, held))
    }

    /// The rays of `count` distinct random pixels of view `view` (seeded by `seed`) and the
    /// colors of those pixels in its image.
    pub fn random_rays(&self, view: usize, count: usize, seed: u64) -> Result<(RayBatch, Vec<[f32; 3]>)> {
        self.random_rays_on(view, count, seed, None)
    }

    /// As [`Views::random_rays`], with the colors composited on `background` where the views keep
    /// their alpha (premultiplied color + (1 − alpha)·background); as they are otherwise.
    pub fn random_rays_on(
        &self,
        view: usize,
        count: usize,
        seed: u64,
        background: Option<[f32; 3]>,
    ) -> Result<(RayBatch, Vec<[f32; 3]>)> {
        let (Some(camera), Some(_)) = (self.cameras.get(view), self.images.get(view)) else {
            return Err(Error::Invalid(format!(
                "view {view} does not exist: there are {} views",
                self.len()
            )));
        };
        let (rays, pixels) = RayBatch::random_pixels(camera, self.width, self.height, count, seed)?;
        let colors = pixels
            .iter()
            .map(|&p| self.color_on(view, p, background))
            .collect();
        Ok((rays, colors))
    }

    /// The color of pixel `p` of view `view`, composited on `background` where the views keep their alpha.
    fn color_on(&self, view: usize, p: usize, background: Option<[f32; 3]>) -> [f32; 3] {
        let c = self.images[view].pixels[p];
        match (self.alpha.as_ref().and_then(|a| a.get(view)), background) {
            (Some(alpha), Some(bg)) => std::array::from_fn(|k| c[k] + (1.0 - alpha[p]) * bg[k]),
            _ => c,
        }
    }

    /// The rays of `count` pixels drawn uniformly at random from all the views' pixels (a view and a
    /// pixel of it per ray, independently, seeded by `seed`), as instant-ngp and nerfstudio draw a
    /// step's rays, with their colors composited as [`Views::random_rays_on`] composites them.
    pub fn random_rays_across(
        &self,
        count: usize,
        seed: u64,
        background: Option<[f32; 3]>,
    ) -> Result<(RayBatch, Vec<[f32; 3]>)> {
        let pixels = self.width as usize * self.height as usize;
        if self.is_empty() || pixels == 0 {
            return Err(Error::Invalid("there are no views to draw rays from".into()));
        }
        let mut rng = Rng::new(seed);
        let mut rays = RayBatch::with_capacity(count);
        let mut colors = Vec::with_capacity(count);
        let width = self.width as usize;
        for _ in 0..count {
            let view = rng.below(self.len() as u64) as usize;
            let p = rng.below(pixels as u64) as usize;
            let (o, d) =
                self.cameras[view].ray((p / width) as u32, (p % width) as u32, self.width, self.height);
            rays.push(o, d);
            colors.push(self.color_on(view, p, background));
        }
        Ok((rays, colors))
    }

    /// The views composited on `background` where they keep their alpha (which they then no longer
    /// keep); as they are otherwise.
    pub fn on_background(self, background: [f32; 3]) -> Views {
        let Some(alpha) = self.alpha else {
            return self;
        };
        let images = self
            .images
            .into_iter()
            .zip(alpha)
            .map(|(image, alpha)| ImageF32 {
                pixels: image
                    .pixels
                    .iter()
                    .zip(alpha)
                    .map(|(c, a)| std::array::from_fn(|k| c[k] + (1.0 - a) * background[k]))
                    .collect(),
                ..image
            })
            .collect();
        Views {
            images,
            alpha: None,
            ..self
        }
    }

    /// The same views with masks of the pixels whose alpha is at least half (the object masks of a data
    /// set whose alpha comes from them); unchanged without alpha.
    pub fn masked_by_alpha(self) -> Views {
        let masks = self.alpha.as_ref().map(|alpha| {
            alpha
                .iter()
                .map(|a| a.iter().map(|&a| a >= 0.5).collect())
                .collect()
        });
        Views { masks, ..self }
    }

    /// The views loaded twice, on black (`on_black`) and on white (`on_white`), as premultiplied images
    /// with their alpha. Loading composites linearly (color·alpha + background·(1 − alpha), then
    /// undistortion and area resampling, both linear), so the difference of the two is exactly
    /// 1 − alpha in every channel.
    pub fn with_alpha(on_black: Views, on_white: Views) -> Result<Views> {
        if on_black.len() != on_white.len()
            || (on_black.width, on_black.height) != (on_white.width, on_white.height)
        {
            return Err(Error::Invalid(
                "the views on black and on white differ in number or size".into(),
            ));
        }
        let alpha = on_black
            .images
            .iter()
            .zip(&on_white.images)
            .map(|(black, white)| {
                black
                    .pixels
                    .iter()
                    .zip(&white.pixels)
                    .map(|(b, w)| (1.0 - (w[0] - b[0])).clamp(0.0, 1.0))
                    .collect()
            })
            .collect();
        Ok(Views {
            alpha: Some(alpha),
            ..on_black
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data::npy::write_npy_rgb;
    use crate::data::scratch_folder;

    /// Two pixels of color c and alpha a, composited on `background` as loaders composite them.
    fn composited(background: [f32; 3]) -> Views {
        let camera = Camera::look_at(
            glam::Vec3::new(0.0, 0.0, -3.0),
            glam::Vec3::ZERO,
            glam::Vec3::Y,
            glam::Vec2::ONE,
            glam::Vec2::ZERO,
        )
        .unwrap();
        let pixels = [([0.2, 0.4, 0.6], 1.0), ([0.9, 0.1, 0.5], 0.25)]
            .map(|(c, a): ([f32; 3], f32)| std::array::from_fn(|k| c[k] * a + background[k] * (1.0 - a)));
        Views {
            cameras: vec![camera],
            images: vec![ImageF32 {
                width: 2,
                height: 1,
                pixels: pixels.to_vec(),
            }],
            width: 2,
            height: 1,
            alpha: None,
            masks: None,
        }
    }

    #[test]
    fn views_with_alpha_composite_on_any_background() {
        let views = Views::with_alpha(composited([0.0; 3]), composited([1.0; 3])).unwrap();
        let alpha = views.alpha.as_ref().unwrap();
        assert!((alpha[0][0] - 1.0).abs() < 1e-6 && (alpha[0][1] - 0.25).abs() < 1e-6);
        let background = [0.3, 0.7, 0.1];
        let (_, colors) = views.random_rays_on(0, 2, 5, Some(background)).unwrap();
        let want = composited(background).images[0].pixels.clone();
        for color in colors {
            assert!(
                want.iter()
                    .any(|w| (0..3).all(|k| (w[k] - color[k]).abs() < 1e-6)),
                "{color:?} is not one of {want:?}"
            );
        }
        let on = views.on_background(background);
        assert!(on.alpha.is_none());
        for (got, want) in on.images[0].pixels.iter().zip(&want) {
            assert!(
                (0..3).all(|k| (got[k] - want[k]).abs() < 1e-6),
                "{got:?} {want:?}"
            );
        }
    }

    #[test]
    fn rays_across_the_views_are_the_rays_and_colors_of_the_pixels_they_draw() {
        // Three 4×3 views from different places, each pixel's color naming its view and pixel.
        let (width, height) = (4u32, 3u32);
        let cameras: Vec<Camera> = (0..3)
            .map(|v| {
                let eye = glam::Vec3::new(v as f32 - 1.0, 0.5, -3.0);
                Camera::look_at(
                    eye,
                    glam::Vec3::ZERO,
                    glam::Vec3::Y,
                    glam::Vec2::ONE,
                    glam::Vec2::ZERO,
                )
                .unwrap()
            })
            .collect();
        let image = |v: usize| ImageF32 {
            width,
            height,
            pixels: (0..12).map(|p| [v as f32, p as f32, 0.5]).collect(),
        };
        let views = Views {
            cameras: cameras.clone(),
            images: (0..3).map(image).collect(),
            width,
            height,
            alpha: Some((0..3).map(|_| vec![0.25; 12]).collect()),
            masks: None,
        };
        let background = [1.0, 2.0, 4.0];
        let (rays, colors) = views.random_rays_across(600, 9, Some(background)).unwrap();
        assert_eq!((rays.len(), colors.len()), (600, 600));
        let mut seen = [0usize; 3];
        for (i, c) in colors.iter().enumerate() {
            // Premultiplied color plus (1 - alpha) of the background: 0.75, 1.5 and 3 added.
            let (v, p) = ((c[0] - 0.75).round() as usize, (c[1] - 1.5).round() as usize);
            assert!((c[2] - 3.5).abs() < 1e-6, "{c:?}");
            let (o, d) = cameras[v].ray(p as u32 / width, p as u32 % width, width, height);
            let got = (
                [rays.ox[i], rays.oy[i], rays.oz[i]],
                [rays.dx[i], rays.dy[i], rays.dz[i]],
            );
            assert_eq!(
                got,
                (o.to_array(), d.to_array()),
                "ray {i} of view {v}, pixel {p}"
            );
            seen[v] += 1;
        }
        // Every view is drawn, each about a third of the time.
        assert!(seen.iter().all(|&n| (150..250).contains(&n)), "{seen:?}");
        assert_eq!(
            views.random_rays_across(600, 9, Some(background)).unwrap().1,
            colors
        );
    }

    #[test]
    fn every_nth_view_is_held_out() {
        let camera = |x: f32| {
            Camera::look_at(
                glam::Vec3::new(x, 0.0, -3.0),
                glam::Vec3::ZERO,
                glam::Vec3::Y,
                glam::Vec2::ONE,
                glam::Vec2::ZERO,
            )
            .unwrap()
        };
        let image = |v: f32| ImageF32 {
            width: 1,
            height: 1,
            pixels: vec![[v; 3]],
        };
        let views = Views {
            cameras: (0..10).map(|i| camera(i as f32)).collect(),
            images: (0..10).map(|i| image(i as f32)).collect(),
            width: 1,
            height: 1,
            alpha: None,
            masks: None,
        };
        let (train, held) = views.clone().hold_out(4).unwrap();
        let values = |v: &Views| {
            v.images
                .iter()
                .map(|i| i.pixels[0][0] as usize)
                .collect::<Vec<_>>()
        };
        assert_eq!(values(&held), [0, 4, 8]);
        assert_eq!(values(&train), [1, 2, 3, 5, 6, 7, 9]);
        assert_eq!(held.cameras[1], views.cameras[4]);
        assert!(views.clone().hold_out(1).is_err());
        let one = Views {
            cameras: vec![camera(0.0)],
            images: vec![image(0.0)],
            width: 1,
            height: 1,
            alpha: None,
            masks: None,
        };
        assert!(one.hold_out(8).is_err());
        // Alpha follows its views.
        let with_alpha = Views {
            alpha: Some((0..10).map(|i| vec![i as f32 / 10.0]).collect()),
            ..views
        };
        let (train, held) = with_alpha.clone().hold_out(4).unwrap();
        assert_eq!(held.alpha, Some(vec![vec![0.0], vec![0.4], vec![0.8]]));
        assert_eq!(train.alpha.map(|a| a.len()), Some(7));
        // So do masks, which keep the pixels of alpha at least half and outlive compositing.
        let (_, held) = with_alpha.masked_by_alpha().hold_out(4).unwrap();
        let held = held.on_background([1.0; 3]);
        assert_eq!(held.masks, Some(vec![vec![false], vec![false], vec![true]]));
    }
    use std::path::PathBuf;

    fn cameras_json(dir: &Path, images: &[&str], size: &str) -> PathBuf {
        let cams: Vec<String> = images
            .iter()
            .enumerate()
            .map(|(k, image)| {
                format!(
                    r#"{{"image": "{image}", "focal": 1.0, "principal_point": [0.0, 0.0],
                    "eye": [-2.5, {k}.0, 0.0], "scene_center": [0.0, 0.0, 0.0], "up": [0.0, 1.0, 0.0]}}"#
                )
            })
            .collect();
        let path = dir.join("cams.json");
        let text = format!(r#"{{"image_size": {size}, "cameras": [{}]}}"#, cams.join(","));
        std::fs::write(&path, text).unwrap();
        path
    }

    fn gradient_image(width: u32, height: u32) -> ImageF32 {
        ImageF32 {
            width,
            height,
            pixels: (0..width * height)
                .map(|k| [(k % width) as f32 / width as f32, 0.5, 0.25])
                .collect(),
        }
    }

    #[test]
    fn npy_and_png_views_load_and_give_pixel_colors() {
        let dir_scratch = scratch_folder("dataset-ok");
        let dir = dir_scratch.path();
        write_npy_rgb(&dir.join("a.npy"), &gradient_image(6, 4)).unwrap();
        // An RGBA PNG: alpha is composited on black.
        let png = image::RgbaImage::from_fn(6, 4, |x, _| image::Rgba([255, 51 * x as u8, 0, 128]));
        png.save(dir.join("b.png")).unwrap();
        let views = load_box_views(&cameras_json(dir, &["a.npy", "b.png"], "[4, 6]")).unwrap();
        assert_eq!(
            (views.len(), views.width, views.height, views.is_empty()),
            (2, 6, 4, false)
        );
        assert_eq!(views.images[0], gradient_image(6, 4));
        let alpha = 128.0 / 255.0;
        let px = views.images[1].pixels[3];
        assert!(
            (px[0] - alpha).abs() < 1e-6 && (px[1] - 0.6 * alpha).abs() < 1e-6 && px[2] == 0.0,
            "{px:?}"
        );
        let (rays, colors) = views.random_rays(0, 10, 3).unwrap();
        assert_eq!((rays.len(), colors.len()), (10, 10));
        let (_, pixels) = RayBatch::random_pixels(&views.cameras[0], 6, 4, 10, 3).unwrap();
        for (c, p) in colors.iter().zip(pixels) {
            assert_eq!(*c, views.images[0].pixels[p]);
        }
        assert!(views
            .random_rays(2, 10, 3)
            .unwrap_err()
            .to_string()
            .contains("2 views"));
        assert!(views.random_rays(1, 25, 3).is_err());
    }

    #[test]
    fn missing_and_wrong_size_images_name_the_file() {
        let dir_scratch = scratch_folder("dataset-bad");
        let dir = dir_scratch.path();
        write_npy_rgb(&dir.join("a.npy"), &gradient_image(6, 4)).unwrap();
        write_npy_rgb(&dir.join("small.npy"), &gradient_image(3, 4)).unwrap();
        let e = load_box_views(&cameras_json(dir, &["a.npy", "small.npy"], "[4, 6]")).unwrap_err();
        let small = dir.join("small.npy");
        assert_eq!(
            e.to_string(),
            format!(
                "{}: image is 3×4 but {} states 6×4",
                small.display(),
                dir.join("cams.json").display()
            )
        );
        let e = load_box_views(&cameras_json(dir, &["a.npy", "gone.png"], "[4, 6]")).unwrap_err();
        assert_eq!(
            e.to_string(),
            format!("cannot read {}: file not found", dir.join("gone.png").display())
        );
        let e = load_box_views(&cameras_json(dir, &["gone.npy"], "[4, 6]")).unwrap_err();
        assert!(e
            .to_string()
            .starts_with(&format!("cannot read {}", dir.join("gone.npy").display())));
        std::fs::write(dir.join("junk.png"), b"not a png").unwrap();
        let e = load_box_views(&cameras_json(dir, &["junk.png"], "[4, 6]")).unwrap_err();
        assert!(e
            .to_string()
            .starts_with(&format!("{}: invalid PNG", dir.join("junk.png").display())));
    }

    #[test]
    fn a_png_too_large_to_decode_is_refused_before_decoding() {
        let dir_scratch = scratch_folder("dataset-huge");
        let dir = dir_scratch.path();
        let path = dir.join("huge.png");
        // An 11000² gray image would need 11000² · (1 + 40) bytes, more than a 1 GiB limit: its header,
        // patched from a row of 11000 pixels, is all that is read.
        image::GrayImage::new(11000, 1).save(&path).unwrap();
        let mut bytes = std::fs::read(&path).unwrap();
        bytes[20..24].copy_from_slice(&11000u32.to_be_bytes());
        let crc = crc32(&bytes[12..29]);
        bytes[29..33].copy_from_slice(&crc.to_be_bytes());
        std::fs::write(&path, bytes).unwrap();
        // No other test of this crate checks the memory limit; its images are far smaller.
        nerfjit_dsl::budget::set_max_memory(1 << 30);
        let e = read_rgb_image(&path).unwrap_err().to_string();
        assert!(
            e.starts_with(&format!(
                "{}: decoding its 11000×11000 pixels would need 4.6 GiB",
                path.display()
            )),
            "{e}"
        );
    }

    /// The CRC-32 of a PNG chunk's type and data.
    fn crc32(bytes: &[u8]) -> u32 {
        let mut crc = !0u32;
        for &b in bytes {
            crc ^= u32::from(b);
            for _ in 0..8 {
                crc = if crc & 1 == 1 {
                    (crc >> 1) ^ 0xedb8_8320
                } else {
                    crc >> 1
                };
            }
        }
        !crc
    }

    #[test]
    fn course_views_load_when_present() {
        let path = Path::new("/work/shared/data/assignment3/box_cameras.json");
        if !path.exists() {
            eprintln!("note: {} not found, skipping", path.display());
            return;
        }
        let views = load_box_views(path).unwrap();
        assert_eq!((views.len(), views.width, views.height), (4, 256, 256));
        for image in &views.images {
            assert_eq!(image.pixels.len(), 256 * 256);
            // The box covers the center of every view, the corners are background.
            let center = image.pixels[128 * 256 + 128];
            assert!(center.iter().sum::<f32>() > 0.05, "{center:?}");
            assert!(
                image.pixels[0].iter().all(|c| c.abs() < 0.02),
                "{:?}",
                image.pixels[0]
            );
        }
    }
}
