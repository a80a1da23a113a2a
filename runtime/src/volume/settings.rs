//! The settings of volume rendering and training ([`VolumeSettings`]) and the sizes of the volume pass's
//! tiles and field calls: what both the pass and the renders read.

use crate::error::{Error, Result};
use crate::volume::composite::{Compositor, Mode};
use crate::volume::sampler::{linspace, DepthSpacing};

/// About this many sample points are evaluated per field call.
pub const TILE_POINTS: usize = 8192;

/// Samples per field call when early termination is on.
pub const CHUNK_SAMPLES: usize = 16;

/// Rays per tile at most when an occupancy grid skips samples (tiles are also kept small
/// enough for eight a thread).
pub const PACKED_TILE_RAYS: usize = 16384;

/// Occupied samples a live ray gives a field call at most when early termination is on and a grid
/// skips samples.
pub const PACKED_CHUNK_SAMPLES: usize = 8;

/// With early termination and a grid, each field call takes about this many points: every live ray
/// its next `PACKED_CALL_POINTS / live` occupied samples (1 to [`PACKED_CHUNK_SAMPLES`]), so that few
/// are evaluated past where a ray stops while the calls stay large.
pub const PACKED_CALL_POINTS: usize = 4096;

/// Parameters of volume rendering and training.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VolumeSettings {
    /// Depth of the first sample (>= 0).
    pub near: f32,
    /// Depth of the last sample (> near).
    pub far: f32,
    /// Samples per ray (>= 2).
    pub samples: usize,
    /// Whether the field's first output is a density or an opacity.
    pub mode: Mode,
    /// Color seen through the remaining transmittance; `None` is black.
    pub background: Option<[f32; 3]>,
    /// Stop a ray once its transmittance falls below this (in (0, 1]); `None` is exact.
    pub early_termination: Option<f32>,
    /// How the samples are spread between near and far.
    pub spacing: DepthSpacing,
}

impl VolumeSettings {
    /// Checks the settings.
    pub(crate) fn check(&self) -> Result<()> {
        let ok = self.near.is_finite() && self.far.is_finite() && 0.0 <= self.near && self.near < self.far;
        if !ok || self.samples < 2 {
            return Err(Error::Invalid(format!(
                "volume rendering needs finite 0 <= near < far and at least 2 samples, got near {}, far {}, {} samples",
                self.near, self.far, self.samples
            )));
        }
        self.spacing.check(self.near, self.far)?;
        self.compositor().check()
    }

    /// The fixed sample depths of a ray: `linspace(near, far, out.len())` spread by the spacing.
    pub(crate) fn fixed_depths(&self, out: &mut [f32]) {
        linspace(self.near, self.far, out);
        self.spacing.warp_all(self.near, self.far, out);
    }

    /// The compositor of these settings.
    pub(crate) fn compositor(&self) -> Compositor {
        Compositor {
            mode: self.mode,
            background: self.background,
            early_termination: self.early_termination,
        }
    }

    /// Rays per tile: about [`TILE_POINTS`] points.
    pub(crate) fn rays_per_tile(&self) -> usize {
        (TILE_POINTS / self.samples).clamp(1, 1024)
    }
}
