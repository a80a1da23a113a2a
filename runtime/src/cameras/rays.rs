//! Batches of camera rays in structure-of-arrays layout.

use std::collections::HashSet;

use glam::Vec3;

use crate::cameras::camera::Camera;
use crate::error::{check_size, Error, Result};
use crate::rng::Rng;

/// Rays in structure-of-arrays layout: origins (`ox`, `oy`, `oz`) and unit directions
/// (`dx`, `dy`, `dz`), all of the same length.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RayBatch {
    /// Origin x of each ray.
    pub ox: Vec<f32>,
    /// Origin y of each ray.
    pub oy: Vec<f32>,
    /// Origin z of each ray.
    pub oz: Vec<f32>,
    /// Direction x of each ray.
    pub dx: Vec<f32>,
    /// Direction y of each ray.
    pub dy: Vec<f32>,
    /// Direction z of each ray.
    pub dz: Vec<f32>,
}

impl RayBatch {
    /// An empty batch with room for `n` rays.
    pub(crate) fn with_capacity(n: usize) -> Self {
        let v = || Vec::with_capacity(n);
        RayBatch {
            ox: v(),
            oy: v(),
            oz: v(),
            dx: v(),
            dy: v(),
            dz: v(),
        }
    }

    /// Appends the ray from `origin` along `direction`.
    pub(crate) fn push(&mut self, origin: Vec3, direction: Vec3) {
        self.ox.push(origin.x);
        self.oy.push(origin.y);
        self.oz.push(origin.z);
        self.dx.push(direction.x);
        self.dy.push(direction.y);
        self.dz.push(direction.z);
    }

    /// The rays through the centers of pixels `pixels` (row-major indices `row·width + col`).
    fn through_pixels(
        camera: &Camera,
        width: u32,
        height: u32,
        pixels: impl ExactSizeIterator<Item = usize>,
    ) -> Self {
        let mut batch = RayBatch::with_capacity(pixels.len());
        let w = width as usize;
        for index in pixels {
            let (row, col) = ((index / w) as u32, (index % w) as u32);
            let (o, d) = camera.ray(row, col, width, height);
            batch.push(o, d);
        }
        batch
    }

    /// One ray per pixel of a `width`×`height` image, in row-major pixel order.
    pub fn full_image(camera: &Camera, width: u32, height: u32) -> Result<Self> {
        check_size(width, height)?;
        let n = width as usize * height as usize;
        Ok(Self::through_pixels(camera, width, height, 0..n))
    }

    /// The rays of `count` distinct pixels drawn uniformly at random (deterministic for a given
    /// `seed`), with their row-major pixel indices.
    pub fn random_pixels(
        camera: &Camera,
        width: u32,
        height: u32,
        count: usize,
        seed: u64,
    ) -> Result<(Self, Vec<usize>)> {
        check_size(width, height)?;
        let n = width as usize * height as usize;
        if count > n {
            return Err(Error::Invalid(format!(
                "cannot draw {count} distinct pixels from a {width}×{height} image"
            )));
        }
        // Floyd's algorithm: `count` distinct indices in `count` draws.
        let mut rng = Rng::new(seed);
        let mut taken = HashSet::with_capacity(count);
        let mut pixels = Vec::with_capacity(count);
        for j in n - count..n {
            let t = rng.below(j as u64 + 1) as usize;
            let pick = if taken.contains(&t) { j } else { t };
            taken.insert(pick);
            pixels.push(pick);
        }
        let batch = Self::through_pixels(camera, width, height, pixels.iter().copied());
        Ok((batch, pixels))
    }

    /// Checks that the six columns have the same length (the fields are public).
    pub(crate) fn check(&self) -> Result<()> {
        let lens = [&self.ox, &self.oy, &self.oz, &self.dx, &self.dy, &self.dz].map(Vec::len);
        if lens.iter().any(|&l| l != lens[0]) {
            return Err(Error::Invalid(format!(
                "ray batch columns ox, oy, oz, dx, dy, dz have different lengths {lens:?}"
            )));
        }
        Ok(())
    }

    /// Number of rays.
    pub fn len(&self) -> usize {
        self.ox.len()
    }

    /// True if the batch holds no ray.
    pub fn is_empty(&self) -> bool {
        self.ox.is_empty()
    }

    /// Origin and direction of ray `i`, if it exists.
    pub fn ray(&self, i: usize) -> Option<(Vec3, Vec3)> {
        let o = Vec3::new(*self.ox.get(i)?, *self.oy.get(i)?, *self.oz.get(i)?);
        let d = Vec3::new(*self.dx.get(i)?, *self.dy.get(i)?, *self.dz.get(i)?);
        Some((o, d))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec2;

    fn camera() -> Camera {
        Camera::look_at(
            Vec3::new(0.0, 0.0, -3.0),
            Vec3::ZERO,
            Vec3::Y,
            Vec2::ONE,
            Vec2::ZERO,
        )
        .unwrap()
    }

    #[test]
    fn full_image_is_row_major() {
        let cam = camera();
        let batch = RayBatch::full_image(&cam, 5, 3).unwrap();
        assert_eq!(batch.len(), 15);
        assert_eq!(batch.ray(7), Some(cam.ray(1, 2, 5, 3)));
        assert_eq!(batch.ray(15), None);
        let (_, d) = batch.ray(14).unwrap();
        assert!((d.length() - 1.0).abs() < 1e-6);
        assert!(RayBatch::full_image(&cam, 0, 3).is_err());
        assert!(batch.check().is_ok());
        let mut broken = batch;
        broken.dz.pop();
        let e = broken.check().unwrap_err().to_string();
        assert!(e.contains("[15, 15, 15, 15, 15, 14]"), "{e}");
    }

    #[test]
    fn random_pixels_are_distinct_seeded_and_match_their_rays() {
        let cam = camera();
        let (batch, pixels) = RayBatch::random_pixels(&cam, 10, 8, 30, 42).unwrap();
        assert_eq!((batch.len(), pixels.len()), (30, 30));
        let unique: HashSet<_> = pixels.iter().collect();
        assert_eq!(unique.len(), 30);
        assert!(pixels.iter().all(|&p| p < 80));
        for (i, &p) in pixels.iter().enumerate() {
            assert_eq!(batch.ray(i), Some(cam.ray(p as u32 / 10, p as u32 % 10, 10, 8)));
        }
        let (_, again) = RayBatch::random_pixels(&cam, 10, 8, 30, 42).unwrap();
        let (_, other) = RayBatch::random_pixels(&cam, 10, 8, 30, 43).unwrap();
        assert_eq!(pixels, again);
        assert_ne!(pixels, other);
        // All pixels can be drawn, not more.
        let (_, all) = RayBatch::random_pixels(&cam, 10, 8, 80, 1).unwrap();
        assert_eq!(all.iter().collect::<HashSet<_>>().len(), 80);
        assert!(RayBatch::random_pixels(&cam, 10, 8, 81, 1).is_err());
    }
}
