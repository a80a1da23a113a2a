//! What a volume is rendered and trained from, so that no caller branches on hierarchical sampling: one
//! field, or NeRF's coarse field whose compositing weights place `importance` more samples per ray for
//! the fine field.

use crate::cameras::camera::Camera;
use crate::cameras::rays::RayBatch;
use crate::error::Result;
use crate::field::{BatchFn, BatchVjp};
use crate::rng::Rng;
use crate::volume::appearance::ColorTransform;
use crate::volume::hierarchical::{render_hierarchical, CoarseFine};
use crate::volume::occupancy::OccupancyGrid;
use crate::volume::render::{render_volume_with, VolumeFrame, VolumeSettings};
use crate::volume::train::{volume_step_with, FinePass, StepOptions, StepResult, StepWorkspace};

/// A volume as rendered: its field (the fine one with hierarchical sampling), and with hierarchical
/// sampling the coarse field and the importance samples per ray.
#[derive(Clone, Copy)]
pub struct VolumeModel<'a> {
    /// The field that makes the image.
    pub field: &'a dyn BatchFn,
    /// The coarse field, sampled at the fixed depths, and the samples per ray drawn from its weights.
    pub coarse: Option<(&'a dyn BatchFn, usize)>,
}

impl VolumeModel<'_> {
    /// Renders a `width`×`height` view ([`render_volume_with`] or [`render_hierarchical`]), skipping the
    /// cells `grid` marks empty when given.
    pub fn render(
        &self,
        camera: &Camera,
        (width, height): (u32, u32),
        settings: &VolumeSettings,
        grid: Option<&OccupancyGrid>,
    ) -> Result<VolumeFrame> {
        match self.coarse {
            None => render_volume_with(camera, width, height, self.field, settings, grid),
            Some((coarse, importance)) => {
                let fields = CoarseFine {
                    coarse,
                    fine: self.field,
                    importance,
                };
                render_hierarchical(camera, (width, height), fields, settings, grid)
            }
        }
    }
}

/// A volume as trained: each field with its backward pass.
#[derive(Clone, Copy)]
pub struct TrainableModel<'a> {
    /// The field that makes the image.
    pub field: &'a dyn BatchFn,
    /// Its backward pass.
    pub vjp: &'a dyn BatchVjp,
    /// With hierarchical sampling: the coarse field, whose weights place more samples for `field`.
    pub coarse: Option<CoarsePass<'a>>,
    /// Recompute the forward pass in the backward pass even where the fields could keep its values
    /// ([`StepOptions::recompute_forward`]).
    pub recompute_forward: bool,
    /// The colour transform of the view the step's rays come from ([`StepOptions::appearance`]).
    pub appearance: Option<ColorTransform>,
    /// The weight of the distortion loss ([`StepOptions::distortion`]; 0: none).
    pub distortion: f32,
}

/// The coarse pass of hierarchical sampling, as trained: the coarse field, sampled at the fixed depths,
/// its backward pass, and the samples per ray drawn from its weights for the fine field.
#[derive(Clone, Copy)]
pub struct CoarsePass<'a> {
    /// The coarse field.
    pub field: &'a dyn BatchFn,
    /// Its backward pass.
    pub vjp: &'a dyn BatchVjp,
    /// Depths drawn per ray from its weights.
    pub importance: usize,
}

impl TrainableModel<'_> {
    /// One training step on `rays` toward `targets` ([`volume_step_with`]: both fields trained with
    /// hierarchical sampling), skipping the cells `grid` marks empty when given, with stratified depths
    /// drawn from `jitter` when given; the gradient is left in `workspace`.
    pub fn step(
        &self,
        rays: &RayBatch,
        targets: &[[f32; 3]],
        settings: &VolumeSettings,
        grid: Option<&OccupancyGrid>,
        jitter: Option<&mut Rng>,
        workspace: &mut StepWorkspace,
    ) -> Result<StepResult> {
        // With hierarchical sampling the step samples the coarse field, and the fine pass follows it.
        let fine = self.coarse.map(|coarse| FinePass {
            field: self.field,
            vjp: self.vjp,
            importance: coarse.importance,
        });
        let (field, vjp) = self.coarse.map_or((self.field, self.vjp), |c| (c.field, c.vjp));
        let options = StepOptions {
            jitter,
            fine: fine.as_ref(),
            grid,
            recompute_forward: self.recompute_forward,
            appearance: self.appearance,
            distortion: self.distortion,
        };
        volume_step_with(rays, targets, field, vjp, settings, options, workspace)
    }
}
