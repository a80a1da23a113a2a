//! Gaussian splats: a scene as 3D Gaussians, each with a center, a color, an opacity and an oriented
//! ellipsoid (standard deviations along the axes of a rotation), the representation of 3D Gaussian
//! splatting. A trained field is baked into them (`nerfjit bake`), [`render_splats`] draws them on the
//! CPU (colors that change with the view by degree-one spherical harmonics, where the splats have them,
//! through a [`SplatShader`] that a script function compiled by the JIT implements),
//! [`splat_loss_gradients`] and [`SplatTuner`] fine-tune them against images, [`write_splat_ply`] writes
//! the `.ply` layout that splat viewers read, and [`splat_surface`] meshes the surface they make.

mod gradients;
mod ply;
mod raster;
mod shading;
pub mod surface;
mod tune;

pub use gradients::{splat_loss_gradients, SplatGradients};
pub use ply::write_splat_ply;
pub use raster::{render_splats, SplatFrameStats, SplatScene, SPLAT_PHASES};
pub use shading::{SplatShader, SHADER_INPUTS};
pub use tune::{SplatTuner, TuneRates};

pub use surface::{splat_surface, SplatColors, SplatGrid, SurfaceOptions};

use crate::error::{Error, Result};

/// The most splats a scene may hold.
pub const MAX_SPLATS: usize = 1 << 26;

/// Gaussian splats, one entry per splat in each field.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Splats {
    /// Centers, in scene units.
    pub positions: Vec<[f32; 3]>,
    /// Colors in [0, 1] (seen from every side alike).
    pub colors: Vec<[f32; 3]>,
    /// Opacities at the center, in [0, 1].
    pub opacities: Vec<f32>,
    /// Standard deviations along the rotated axes, in scene units (> 0).
    pub scales: Vec<[f32; 3]>,
    /// Unit quaternions (w, x, y, z) turning the axes.
    pub rotations: Vec<[f32; 4]>,
    /// Each splat's degree-one spherical harmonics (three RGB coefficients, `f_rest` of the `.ply` layout),
    /// by which its color changes with the direction it is seen from (see `shading`); empty when the
    /// splats look alike from every side.
    pub sh: Vec<[[f32; 3]; 3]>,
}

impl Splats {
    /// How many splats there are.
    pub fn len(&self) -> usize {
        self.positions.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }

    /// Keeps the splats whose opacity reaches `min_opacity`; returns how many went.
    pub fn prune(&mut self, min_opacity: f32) -> usize {
        let keep: Vec<bool> = self.opacities.iter().map(|&o| o >= min_opacity).collect();
        self.retain(&keep)
    }

    /// Keeps splat `i` where `keep[i]` (those past the end of `keep` too); returns how many went.
    pub fn retain(&mut self, keep: &[bool]) -> usize {
        let before = self.len();
        keep_where(&mut self.positions, keep);
        keep_where(&mut self.colors, keep);
        keep_where(&mut self.opacities, keep);
        keep_where(&mut self.scales, keep);
        keep_where(&mut self.rotations, keep);
        keep_where(&mut self.sh, keep);
        before - self.len()
    }

    /// Checks that every field has one finite entry per splat, within its range; says what is wrong.
    pub fn check(&self) -> Result<()> {
        let n = self.len();
        if n > MAX_SPLATS {
            return Err(Error::Invalid(format!(
                "{n} splats, more than the {MAX_SPLATS} a scene may hold"
            )));
        }
        let lengths = [
            ("colors", self.colors.len()),
            ("opacities", self.opacities.len()),
            ("scales", self.scales.len()),
            ("rotations", self.rotations.len()),
        ];
        if !self.sh.is_empty() && self.sh.len() != n {
            return Err(Error::Invalid(format!(
                "{n} splat positions but {} sets of spherical harmonics",
                self.sh.len()
            )));
        }
        if let Some((name, len)) = lengths.iter().find(|(_, len)| *len != n) {
            return Err(Error::Invalid(format!("{n} splat positions but {len} {name}")));
        }
        for i in 0..n {
            let bad = |what: &str| Err(Error::Invalid(format!("splat {i}: {what}")));
            if !self.positions[i].iter().all(|x| x.is_finite()) {
                return bad("its position is not finite");
            }
            if !self.colors[i].iter().all(|c| (0.0..=1.0).contains(c)) {
                return bad("its color is not in [0, 1]");
            }
            if !(0.0..=1.0).contains(&self.opacities[i]) {
                return bad("its opacity is not in [0, 1]");
            }
            if !self.scales[i].iter().all(|s| s.is_finite() && *s > 0.0) {
                return bad("its scales are not finite and positive");
            }
            if self
                .sh
                .get(i)
                .is_some_and(|h| !h.iter().flatten().all(|x| x.is_finite()))
            {
                return bad("its spherical harmonics are not finite");
            }
            let q = self.rotations[i];
            let norm = q.iter().map(|x| x * x).sum::<f32>().sqrt();
            if !norm.is_finite() || (norm - 1.0).abs() > 1e-3 {
                return bad("its rotation is not a unit quaternion");
            }
        }
        Ok(())
    }
}

/// Keeps the values whose entry of `keep` is true.
fn keep_where<T>(values: &mut Vec<T>, keep: &[bool]) {
    let mut kept = keep.iter();
    values.retain(|_| *kept.next().unwrap_or(&true));
}
