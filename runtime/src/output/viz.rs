//! Visual aids for learners: the pixel grid in NDC, the ray directions, and the sample points
//! along rays of one camera as seen by another.

use glam::Vec3;
use image::{Rgb, RgbImage};

use crate::cameras::camera::Camera;
use crate::cameras::rays::RayBatch;
use crate::error::{check_size, Error, Result};
use crate::output::image_out::Quantize;
use crate::rng::Rng;

fn color(c: Vec3) -> Rgb<u8> {
    Rgb(c.to_array().map(|x| Quantize::Round.byte(x)))
}

/// The NDC coordinates of every pixel center as colors: red = (x + 1)/2, green = (y + 1)/2
/// (x points left and y up, so the top left is yellow and the bottom right black).
pub fn pixel_grid_image(camera: &Camera, width: u32, height: u32) -> Result<RgbImage> {
    check_size(width, height)?;
    Ok(RgbImage::from_fn(width, height, |col, row| {
        let ndc = camera.pixel_ndc(row as f32 + 0.5, col as f32 + 0.5, width, height);
        color(Vec3::new(0.5 * (ndc.x + 1.0), 0.5 * (ndc.y + 1.0), 0.0))
    }))
}

/// The world direction of every pixel's ray as colors: |d| per channel.
pub fn ray_directions_image(camera: &Camera, width: u32, height: u32) -> Result<RgbImage> {
    check_size(width, height)?;
    Ok(RgbImage::from_fn(width, height, |col, row| {
        color(camera.ray(row, col, width, height).1.abs())
    }))
}

/// Which sample points [`sample_points_image`] draws.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SamplePoints {
    /// Number of rays, through distinct random pixels.
    pub rays: usize,
    /// Stratified samples per ray: one uniform in each of `samples` equal bins of [near, far].
    pub samples: usize,
    /// Start of the sampled interval along each ray.
    pub near: f32,
    /// End of the sampled interval along each ray.
    pub far: f32,
    /// Seed of the pixel choice and the jitter.
    pub seed: u64,
}

/// Draws the stratified sample points along random rays of camera `from` as dots (3×3
/// pixels, blue near to red far) in a `width`×`height` image taken by camera `view`.
pub fn sample_points_image(
    view: &Camera,
    from: &Camera,
    width: u32,
    height: u32,
    points: &SamplePoints,
) -> Result<RgbImage> {
    if points.samples == 0 || !(points.near.is_finite() && points.far.is_finite() && points.far > points.near)
    {
        return Err(Error::Invalid(format!(
            "sample points need at least 1 sample and finite near < far, got {} samples on [{}, {}]",
            points.samples, points.near, points.far
        )));
    }
    let (rays, _) = RayBatch::random_pixels(from, width, height, points.rays, points.seed)?;
    let mut jitter = Rng::new(points.seed ^ 0x5EED_5EED);
    let mut image = RgbImage::new(width, height);
    let bin = (points.far - points.near) / points.samples as f32;
    for i in 0..rays.len() {
        let Some((o, d)) = rays.ray(i) else { continue };
        for k in 0..points.samples {
            let t = points.near + (k as f32 + jitter.next_f32()) * bin;
            let Some((row, col)) = view.project(o + d * t, width, height) else {
                continue;
            };
            let fraction = k as f32 / (points.samples.max(2) - 1) as f32;
            let dot = color(Vec3::new(fraction, 0.2, 1.0 - fraction));
            draw_dot(&mut image, row.floor(), col.floor(), dot);
        }
    }
    Ok(image)
}

/// Paints the 3×3 pixels around pixel (row, col), clipped to the image.
fn draw_dot(image: &mut RgbImage, row: f32, col: f32, dot: Rgb<u8>) {
    for dr in -1..=1 {
        for dc in -1..=1 {
            let (r, c) = (row + dr as f32, col + dc as f32);
            if r >= 0.0 && c >= 0.0 && r < image.height() as f32 && c < image.width() as f32 {
                image.put_pixel(c as u32, r as u32, dot);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec2;

    fn camera(eye: Vec3) -> Camera {
        Camera::look_at(eye, Vec3::ZERO, Vec3::Y, Vec2::ONE, Vec2::ZERO).unwrap()
    }

    #[test]
    fn pixel_grid_and_directions() {
        let cam = camera(Vec3::new(-2.5, 0.0, 0.0));
        let grid = pixel_grid_image(&cam, 8, 8).unwrap();
        // Top left: NDC (+0.875, +0.875); bottom right: (−0.875, −0.875).
        assert_eq!(grid.get_pixel(0, 0).0, [239, 239, 0]);
        assert_eq!(grid.get_pixel(7, 7).0, [16, 16, 0]);
        let dirs = ray_directions_image(&cam, 9, 9).unwrap();
        // The central ray looks down +x.
        assert_eq!(dirs.get_pixel(4, 4).0, [255, 0, 0]);
        assert!(pixel_grid_image(&cam, 0, 8).is_err());
    }

    #[test]
    fn sample_points_of_a_camera_seen_by_itself_cover_their_pixels() {
        let cam = camera(Vec3::new(0.0, 0.0, -3.0));
        let points = SamplePoints {
            rays: 20,
            samples: 8,
            near: 1.0,
            far: 5.0,
            seed: 3,
        };
        let image = sample_points_image(&cam, &cam, 32, 32, &points).unwrap();
        let (_, pixels) = RayBatch::random_pixels(&cam, 32, 32, 20, 3).unwrap();
        for p in pixels {
            let lit = image.get_pixel(p as u32 % 32, p as u32 / 32).0;
            assert_ne!(lit, [0, 0, 0], "pixel {p}");
        }
        let lit = image.pixels().filter(|p| p.0 != [0, 0, 0]).count();
        assert!(lit <= 20 * 9, "{lit}");

        // From the side, the samples of one ray spread over many pixels.
        let side = camera(Vec3::new(-4.0, 0.0, 0.0));
        let one = SamplePoints { rays: 1, ..points };
        let image = sample_points_image(&side, &cam, 32, 32, &one).unwrap();
        let lit = image.pixels().filter(|p| p.0 != [0, 0, 0]).count();
        assert!(lit > 3 * 9, "{lit}");
        let bad = SamplePoints { samples: 0, ..points };
        assert!(sample_points_image(&side, &cam, 32, 32, &bad).is_err());
    }
}
