//! One training step of a volume-rendered field: sample, evaluate, composite, MSE against
//! target colors, and back through the compositor and the field to the field's parameters.
//!
//! Rays are cut into tiles of about [`TILE_POINTS`](crate::volume::render::TILE_POINTS) sample
//! points laid out sample-major (sample j of ray k at `j·rays + k`), evaluated in one field
//! call, composited and back-propagated across rays (loops that vectorize), then passed to
//! one call of the field's backward pass with their cotangents. Tiles are grouped into
//! chunks of about [`CHUNK_POINTS`] points; chunk c adds its gradients to accumulator
//! c mod [`ACCUMULATORS`], whose chunks run in order in one parallel task, and the accumulators are
//! summed in order, so a step's result does not depend on the number of threads. The accumulators and
//! the gradient they sum to live in the caller's [`StepWorkspace`], reused from step to step; `gradients`
//! holds it and the sum.
//!
//! A hash grid's table is most of a field's params, and its gradient is scattered: where the field's
//! backward passes can hold their scatters back ([`KeptPasses::hold_scatters`]), no task writes the
//! table's gradient, the accumulators are summed outside it, and after the tasks each level of the table
//! is scattered on its own thread, every task's points in task order, into the first accumulator. A
//! step then writes one table-sized gradient instead of four and sums none (docs/LOG.md measures what
//! that saved).

mod gradients;

pub use gradients::StepWorkspace;

use rayon::prelude::*;

use crate::cameras::rays::RayBatch;
use crate::error::{Error, Result};
use crate::field::{check_vjp_arity, BatchFn, BatchVjp, HeldScatters, KeptForward, KeptPasses};
use crate::rng::Rng;
use crate::training::metrics::psnr;
use crate::volume::appearance::{ColorTransform, TRANSFORM_VALUES};
use crate::volume::composite::{Distortion, RayOutput, SharedDepths};
use crate::volume::occupancy::OccupancyGrid;
use crate::volume::pass::{self, with_scratch, Depths, Output, Pass, Scratch};
use crate::volume::render::{check_field, VolumeSettings};
use crate::volume::sampler::jittered_depth;
use gradients::{complement, sum_into, windows, Accumulator};

/// Sample points per chunk of tiles.
pub const CHUNK_POINTS: usize = 32768;

/// Sample points per tile of rays (at least one ray) when the backward pass reads the values the forward
/// pass kept: few enough that they stay in the L2 cache between the two passes. On 2026-11-25 (W4 and W6,
/// the course's NeRF and VolSDF, 128 samples a ray) a step took about the same with tiles of 128 and 256
/// points, 5–8% longer with 512 and 1,024, and 1.6× as long with the 8,192 of recomputing passes.
pub const KEPT_TILE_POINTS: usize = 128;

/// The memory a tile's kept passes may hold at most, where a grid or early termination has the field
/// called several times a tile (on the usual tiles of about 8,192 samples, most of which the grid
/// skips): past it, say for wide networks, the backward pass recomputes the forward pass.
pub const KEPT_TILE_BYTES: usize = 32 << 20;

/// Gradient accumulators of a step at most (its parallel tasks).
pub const ACCUMULATORS: usize = 4;

/// The outcome of [`volume_step`].
#[derive(Debug, Clone, PartialEq)]
pub struct StepResult {
    /// Mean squared error over rays and color channels.
    pub loss: f32,
    /// PSNR of that error for colors in [0, 1].
    pub psnr: f32,
    /// With hierarchical sampling: the coarse pass's error (`loss` is the fine pass's).
    pub coarse_loss: Option<f32>,
    /// Samples the field was evaluated at (both passes; skipped samples not counted).
    pub samples: usize,
    /// ∂loss/∂values of the step's colour transform ([`StepOptions::appearance`]), if it had one.
    pub appearance_grads: Option<[f32; TRANSFORM_VALUES]>,
    /// The distortion loss's part of the step's loss ([`StepOptions::distortion`]; 0 without): its
    /// weight times the mean over the rays (both passes'), whose gradient the step's includes.
    pub distortion_loss: f32,
}

/// The fine pass of hierarchical sampling: a second field evaluated at the coarse depths plus
/// `importance` depths drawn from the coarse weights (see [`crate::volume::importance`]).
pub struct FinePass<'a> {
    /// The fine field.
    pub field: &'a dyn BatchFn,
    /// Its backward pass.
    pub vjp: &'a dyn BatchVjp,
    /// Depths drawn per ray from the coarse weights.
    pub importance: usize,
}

/// What a training step may add to plain volume rendering.
#[derive(Default)]
pub struct StepOptions<'a> {
    /// Stratified depths with uniform jitter drawn from this generator (else `linspace` depths).
    pub jitter: Option<&'a mut Rng>,
    /// Hierarchical sampling: the fine pass.
    pub fine: Option<&'a FinePass<'a>>,
    /// Empty-space skipping: samples in the grid's empty cells (or outside it) are neither
    /// evaluated nor back-propagated; they composite as empty space.
    pub grid: Option<&'a OccupancyGrid>,
    /// Recompute the fields' forward pass in their backward pass even where they could keep its values
    /// (see [`volume_step_with`]), to compare.
    pub recompute_forward: bool,
    /// The colour transform of the view the rays come from ([`crate::volume::appearance`]): the rays'
    /// colours are mapped by it before they are compared with the targets, and its gradient is returned.
    pub appearance: Option<ColorTransform>,
    /// The weight of mip-NeRF 360's distortion loss ([`Distortion`]) in the step's loss: the mean over
    /// the rays of their distortion loss times this is added to the colour MSE (0: none).
    pub distortion: f32,
}

/// What every tile of a step needs to know.
struct Job<'a> {
    rays: &'a RayBatch,
    targets: &'a [[f32; 3]],
    field: &'a dyn BatchFn,
    vjp: &'a dyn BatchVjp,
    settings: &'a VolumeSettings,
    /// The fine pass and its settings (samples = coarse + importance), if sampling is hierarchical.
    fine: Option<(&'a FinePass<'a>, VolumeSettings)>,
    grid: Option<&'a OccupancyGrid>,
    /// The depths of every ray when they are not jittered, and their δ.
    fixed_depths: Option<(Vec<f32>, Vec<f32>)>,
    /// ∂loss/∂color = scale·(color − target).
    scale: f32,
    /// Whether the fields' backward passes read the values their forward passes kept.
    keep: bool,
    /// The view's colour transform, if it has one.
    appearance: Option<ColorTransform>,
    /// The distortion loss, its weight divided by the rays, if the step has one.
    distortion: Option<Distortion>,
}

/// The kept passes ([`BatchVjp::kept_passes`]) of a task's coarse (or only) and fine field, if used.
struct Kept<'a> {
    coarse: Option<Box<dyn KeptPasses + 'a>>,
    fine: Option<Box<dyn KeptPasses + 'a>>,
}

/// What a tile of rays adds to a step besides its gradient.
#[derive(Clone, Copy, Default)]
struct TileTotals {
    /// Summed squared error of the coarse pass, then of the fine pass if there is one.
    squared_error: [f64; 2],
    /// Summed distortion loss of both passes, times its weight over the rays.
    distortion: f64,
    /// Samples evaluated.
    samples: usize,
    /// ∂loss/∂values of the colour transform (both passes).
    appearance_grads: [f64; TRANSFORM_VALUES],
}

impl std::ops::AddAssign for TileTotals {
    fn add_assign(&mut self, other: TileTotals) {
        self.squared_error[0] += other.squared_error[0];
        self.squared_error[1] += other.squared_error[1];
        self.distortion += other.distortion;
        self.samples += other.samples;
        for (sum, g) in self.appearance_grads.iter_mut().zip(other.appearance_grads) {
            *sum += g;
        }
    }
}

/// The rays of a tile: `first..first + n` of the step's.
#[derive(Clone, Copy)]
struct TileRays {
    first: usize,
    n: usize,
}

/// A field a pass evaluates and its backward pass, at depths shared by every ray when given.
struct PassField<'a> {
    field: &'a dyn BatchFn,
    vjp: &'a dyn BatchVjp,
    shared_depths: Option<SharedDepths<'a>>,
}

/// Where a pass adds its gradients: the params' (through its kept passes, when it has them) and the
/// colour transform's.
struct PassGrads<'g, 'k> {
    params: &'g mut [f32],
    kept: Option<&'g mut (dyn KeptPasses + 'k)>,
    appearance: &'g mut [f64; TRANSFORM_VALUES],
}

/// What one pass over a tile adds to the step.
struct PassTotals {
    /// Summed squared error of the rays' colours.
    squared_error: f64,
    /// Summed distortion loss, times its weight over the rays.
    distortion: f64,
    /// Samples evaluated.
    samples: usize,
}

/// Runs the tile's rays of the step: adds their gradient to `grads`, returns their totals. Jitter, if
/// any, comes from a generator per ray seeded with the ray's entry of `seeds`.
fn train_tile(
    job: &Job,
    s: &mut Scratch,
    rays: TileRays,
    seeds: &[u64],
    grads: &mut [f32],
    kept: &mut Kept,
) -> TileTotals {
    let n = rays.n;
    let samples = job.settings.samples;
    let len = n * samples;
    s.reserve(len, n);
    let mut rngs: Vec<Rng> = seeds.iter().map(|&seed| Rng::new(seed)).collect();
    let depths = &mut s.depths[..len];
    match &job.fixed_depths {
        Some((fixed, _)) => {
            for (row, &t) in depths.chunks_exact_mut(n).zip(fixed) {
                row.fill(t);
            }
        }
        None => {
            let VolumeSettings {
                near, far, spacing, ..
            } = *job.settings;
            let bin = (far - near) / samples as f32;
            for (k, rng) in rngs.iter_mut().enumerate() {
                for j in 0..samples {
                    depths[j * n + k] = spacing.warp(near, far, jittered_depth(near, bin, j, rng.next_f32()));
                }
            }
        }
    }
    let shared = job
        .fixed_depths
        .as_ref()
        .map(|(t, delta)| SharedDepths { t, delta });
    let mut appearance_grads = [0.0; TRANSFORM_VALUES];
    let coarse_field = PassField {
        field: job.field,
        vjp: job.vjp,
        shared_depths: shared,
    };
    let coarse_grads = PassGrads {
        params: grads,
        kept: kept.coarse.as_deref_mut(),
        appearance: &mut appearance_grads,
    };
    let coarse = run_pass(job, coarse_field, job.settings, s, rays, coarse_grads);
    let Some((fine, fine_settings)) = &job.fine else {
        return TileTotals {
            squared_error: [coarse.squared_error, 0.0],
            distortion: coarse.distortion,
            samples: coarse.samples,
            appearance_grads,
        };
    };
    let jitter = job.fixed_depths.is_none().then_some(rngs.as_mut_slice());
    pass::draw_fine_depths(job.settings, fine.importance, s, n, jitter);
    let fine_field = PassField {
        field: fine.field,
        vjp: fine.vjp,
        shared_depths: None,
    };
    let fine_grads = PassGrads {
        params: grads,
        kept: kept.fine.as_deref_mut(),
        appearance: &mut appearance_grads,
    };
    let fine = run_pass(job, fine_field, fine_settings, s, rays, fine_grads);
    TileTotals {
        squared_error: [coarse.squared_error, fine.squared_error],
        distortion: coarse.distortion + fine.distortion,
        samples: coarse.samples + fine.samples,
        appearance_grads,
    }
}

/// Evaluates the pass's field at the depths in `s.depths` of the tile's rays (the same shared depths on
/// every ray, when given), composites, and adds the gradient of the MSE through its backward pass to the
/// params' gradient; returns the summed squared error, the distortion loss (summed, times the job's
/// weight) and the number of samples evaluated. With kept passes (a pass that evaluates every sample in
/// one call), the forward pass is theirs and the backward pass goes on from what it kept. With the view's
/// colour transform, adds its gradient to the transform's.
fn run_pass(
    job: &Job,
    PassField {
        field,
        vjp,
        shared_depths,
    }: PassField,
    settings: &VolumeSettings,
    s: &mut Scratch,
    TileRays { first, n }: TileRays,
    PassGrads {
        params: grads,
        kept,
        appearance: appearance_grads,
    }: PassGrads,
) -> PassTotals {
    let len = n * settings.samples;
    let kept = kept.map(|k| KeptForward::new(k, field.n_inputs(), field.n_outputs()));
    let pass = Pass {
        field: kept.as_ref().map_or(field, |k| k as &dyn BatchFn),
        compositor: settings.compositor(),
        grid: job.grid,
        samples: settings.samples,
    };
    s.load_rays(job.rays, first, n);
    let depths = shared_depths.map_or(Depths::PerRay, Depths::Shared);
    let evaluated = pass::run(&pass, depths, s, Output::Samples);
    let kept = kept.map(KeptForward::into_inner);
    let Scratch {
        inputs,
        outputs: [raw, r, g, b],
        cotangents: [g_raw, g_r, g_g, g_b],
        depths,
        lanes,
        ..
    } = s;
    let depths = &depths[..len];
    let inputs: Vec<&[f32]> = inputs[..field.n_inputs()].iter().map(|c| &c[..len]).collect();
    let compositor = settings.compositor();
    // The rows (sample indices) where the pass evaluated no ray hold zeros: the sweeps step over them.
    let skip = match (&evaluated, &job.distortion) {
        (Some(index), None) => {
            let mut empty = vec![true; settings.samples];
            for &i in index {
                empty[i / n] = false;
            }
            Some(empty)
        }
        _ => None,
    };
    let mut squared_error = 0.0f64;
    lanes.reset(n);
    let distortion = lanes.forward_backward(
        &compositor,
        depths,
        &raw[..len],
        [&r[..len], &g[..len], &b[..len]],
        [
            &mut g_raw[..len],
            &mut g_r[..len],
            &mut g_g[..len],
            &mut g_b[..len],
        ],
        (job.distortion.as_ref(), skip.as_deref()),
        |k, out| {
            let target = job.targets[first + k];
            let background = settings.background.unwrap_or([0.0; 3]);
            let predicted = job.appearance.map_or(out.rgb, |t| t.apply(out, background));
            let error = [0, 1, 2].map(|c| predicted[c] - target[c]);
            squared_error += error.iter().map(|e| f64::from(e * e)).sum::<f64>();
            let g = error.map(|e| job.scale * e);
            match &job.appearance {
                Some(t) => t.backward(out, background, g, appearance_grads),
                None => RayOutput {
                    rgb: g,
                    ..RayOutput::default()
                },
            }
        },
    );
    let cotangents: [&[f32]; 4] = [&g_raw[..len], &g_r[..len], &g_g[..len], &g_b[..len]];
    let samples = evaluated.as_ref().map_or(len, Vec::len);
    if let Some(kept) = kept {
        // The kept values are those of the evaluated samples, in the order of evaluation.
        match &evaluated {
            None => kept.backward(len, &cotangents, grads),
            Some(index) => {
                let cotangents = pass::gather(&cotangents, index);
                let cotangents: Vec<&[f32]> = cotangents.iter().map(Vec::as_slice).collect();
                kept.backward(index.len(), &cotangents, grads);
            }
        }
        return PassTotals {
            squared_error,
            distortion,
            samples,
        };
    }
    let backward = evaluated.map(|mut index| {
        // In order, for the cache; samples past a ray's end have all-zero cotangents: leaving them out
        // is exact.
        index.sort_unstable();
        if compositor.early_termination.is_some() {
            index.retain(|&i| cotangents.iter().any(|c| c[i] != 0.0));
        }
        index
    });
    pass::backward(vjp, &inputs, backward.as_deref(), &cotangents, grads);
    PassTotals {
        squared_error,
        distortion,
        samples,
    }
}

/// One training step on `rays` with target colors `targets` (one per ray): samples each ray
/// between `settings.near` and `settings.far` (`linspace` spread by the settings' spacing, or stratified with uniform jitter
/// drawn from `jitter` when given), evaluates `field`, composites, takes the mean squared
/// error over rays and channels, and back-propagates it through the compositor and `vjp`
/// (the field's backward pass) to the field's parameters: their gradient is left in `workspace`
/// ([`StepWorkspace::grads`]).
pub fn volume_step(
    rays: &RayBatch,
    targets: &[[f32; 3]],
    field: &dyn BatchFn,
    vjp: &dyn BatchVjp,
    settings: &VolumeSettings,
    jitter: Option<&mut Rng>,
    workspace: &mut StepWorkspace,
) -> Result<StepResult> {
    let options = StepOptions {
        jitter,
        ..StepOptions::default()
    };
    volume_step_with(rays, targets, field, vjp, settings, options, workspace)
}

/// [`volume_step`] with options. With hierarchical sampling, `field` is the coarse field, sampled
/// as in [`volume_step`]; `options.fine` is evaluated at those depths and `fine.importance` more
/// per ray drawn from the coarse compositing weights (stratified when jittering); the loss is the
/// sum of both passes' MSE (both fields are trained) and the reported loss and PSNR are the fine
/// pass's. With a grid, both passes skip the samples in its empty cells.
pub fn volume_step_with(
    rays: &RayBatch,
    targets: &[[f32; 3]],
    field: &dyn BatchFn,
    vjp: &dyn BatchVjp,
    settings: &VolumeSettings,
    options: StepOptions,
    workspace: &mut StepWorkspace,
) -> Result<StepResult> {
    let fine = options.fine;
    if rays.is_empty() || targets.len() != rays.len() {
        return Err(Error::Invalid(format!(
            "a training step needs at least one ray and one target color per ray, got {} rays and {} targets",
            rays.len(),
            targets.len()
        )));
    }
    rays.check()?;
    settings.check()?;
    check_field(field)?;
    check_vjp_arity(vjp, field.n_inputs(), field.n_outputs())?;
    if let Some(f) = fine {
        check_field(f.field)?;
        check_vjp_arity(f.vjp, f.field.n_inputs(), f.field.n_outputs())?;
        if f.importance == 0 {
            return Err(Error::Invalid(
                "hierarchical sampling needs at least one importance sample".into(),
            ));
        }
    }
    let fine = fine.map(|f| {
        let fine_settings = VolumeSettings {
            samples: settings.samples + f.importance,
            ..*settings
        };
        (f, fine_settings)
    });
    // The backward pass reads the values the forward pass kept where the fields keep them: passes that
    // evaluate every sample in one call on tiles small enough that they stay in the cache; passes that
    // call the field several times a tile (skipping samples, stopping rays) on the usual tiles, if what
    // they could keep fits KEPT_TILE_BYTES.
    let samples = fine.as_ref().map_or(settings.samples, |(_, f)| f.samples);
    let one_call = options.grid.is_none() && settings.early_termination.is_none();
    let fits = |vjp: &dyn BatchVjp| {
        vjp.kept_passes().is_some_and(|kept| {
            one_call || settings.rays_per_tile() * samples * kept.bytes_per_point() <= KEPT_TILE_BYTES
        })
    };
    let keep = !options.recompute_forward && fits(vjp) && fine.as_ref().is_none_or(|(f, _)| fits(f.vjp));
    let tile = if keep && one_call {
        (KEPT_TILE_POINTS / samples).clamp(1, 1024)
    } else {
        settings.rays_per_tile()
    };
    let n_tiles = rays.len().div_ceil(tile);
    // One seed per ray, drawn in order: the jitter depends neither on the scheduling nor on the tiles.
    let (fixed_depths, seeds) = match options.jitter {
        Some(rng) => (None, (0..rays.len()).map(|_| rng.next_u64()).collect()),
        None => {
            let mut depths = vec![0.0; settings.samples];
            settings.fixed_depths(&mut depths);
            let deltas = pass::deltas(&depths);
            (Some((depths, deltas)), vec![0; rays.len()])
        }
    };
    let job = Job {
        rays,
        targets,
        field,
        vjp,
        settings,
        fine,
        grid: options.grid,
        fixed_depths,
        scale: 2.0 / (3.0 * rays.len() as f32),
        keep,
        appearance: options.appearance,
        distortion: (options.distortion > 0.0).then(|| Distortion {
            weight: options.distortion / rays.len() as f32,
            near: settings.near,
            far: settings.far,
            spacing: settings.spacing,
        }),
    };
    let tiles_per_chunk = (CHUNK_POINTS / (tile * settings.samples)).max(1);
    let n_chunks = n_tiles.div_ceil(tiles_per_chunk);
    let n_tasks = n_chunks.min(ACCUMULATORS);
    let n_params = vjp.n_params();
    let accumulators: Vec<Accumulator> = (0..n_tasks).map(|_| workspace.accumulator(n_params)).collect();
    let tasks: Vec<(TileTotals, Vec<f32>, Kept)> = accumulators
        .into_par_iter()
        .enumerate()
        .map(|(task, accumulator)| {
            let mut grads = accumulator.cleared(n_params);
            let mut totals = TileTotals::default();
            let mut kept = Kept {
                coarse: job.keep.then(|| job.vjp.kept_passes()).flatten(),
                fine: job
                    .fine
                    .as_ref()
                    .and_then(|(f, _)| job.keep.then(|| f.vjp.kept_passes()).flatten()),
            };
            // A single field's grid scatters are held back and added after the tasks, level by level
            // into one gradient (see below).
            if job.fine.is_none() {
                if let Some(passes) = &mut kept.coarse {
                    passes.hold_scatters();
                }
            }
            with_scratch(|s| {
                for c in (task..n_chunks).step_by(n_tasks) {
                    let tiles = c * tiles_per_chunk..((c + 1) * tiles_per_chunk).min(n_tiles);
                    for t in tiles {
                        let first = t * tile;
                        let n = tile.min(rays.len() - first);
                        let seeds = &seeds[first..first + n];
                        let rays = TileRays { first, n };
                        totals += train_tile(&job, s, rays, seeds, &mut grads, &mut kept);
                    }
                }
            });
            for passes in [&mut kept.coarse, &mut kept.fine].into_iter().flatten() {
                passes.finish(&mut grads);
            }
            (totals, grads, kept)
        })
        .collect();
    let mut totals = TileTotals::default();
    for (t, _, _) in &tasks {
        totals += *t;
    }
    let squared_error = totals.squared_error;
    let (accumulators, mut kept): (Vec<Vec<f32>>, Vec<Kept>) =
        tasks.into_iter().map(|(_, g, k)| (g, k)).unzip();
    let held: Option<Vec<Box<dyn HeldScatters + '_>>> = kept
        .iter_mut()
        .map(|k| k.coarse.as_mut().and_then(|passes| passes.take_scatters()))
        .collect();
    let mut accumulators = accumulators.into_iter();
    let mut param_grads = accumulators.next().unwrap_or_else(|| vec![0.0; n_params]);
    let mut rest: Vec<Vec<f32>> = accumulators.collect();
    // The grids' gradients were held back (no task wrote them): the accumulators are summed elsewhere,
    // and the grids' levels are scattered into the first accumulator, a level at a time on each thread,
    // each level's scatters in task order.
    let grid_params = held
        .as_ref()
        .and_then(|h| h.first())
        .map_or(&[][..], |h| h.parts());
    sum_into(&mut param_grads, &mut rest, &complement(grid_params, n_params));
    if let Some(held) = &held {
        windows(&mut param_grads, grid_params)
            .into_par_iter()
            .enumerate()
            .for_each(|(part, grads)| held.iter().for_each(|h| h.add(part, grads)));
    }
    workspace.zeroed = rest;
    workspace.grads = param_grads;
    let mse = |e: f64| (e / (3.0 * rays.len() as f64)) as f32;
    let (loss, coarse_loss) = match job.fine {
        Some(_) => (mse(squared_error[1]), Some(mse(squared_error[0]))),
        None => (mse(squared_error[0]), None),
    };
    Ok(StepResult {
        loss,
        psnr: psnr(loss),
        coarse_loss,
        samples: totals.samples,
        distortion_loss: totals.distortion as f32,
        appearance_grads: options
            .appearance
            .map(|_| totals.appearance_grads.map(|g| g as f32)),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cameras::camera::Camera;
    use crate::field::{ClosureFn, ClosureVjp};
    use crate::volume::composite::Mode;
    use crate::volume::sampler::DepthSpacing;
    use glam::{Vec2, Vec3};

    /// A Gaussian blob e = exp(−|p − c|²) around c = (θ₁, θ₂, θ₃) of density (or opacity)
    /// θ₀·e and color (θ₄·e, θ₅·|d_x|, θ₆·p_y) (d the view direction).
    fn blob_value(theta: &[f32], p: &[f32]) -> [f32; 4] {
        let q = [p[0] - theta[1], p[1] - theta[2], p[2] - theta[3]];
        let e = (-(q[0] * q[0] + q[1] * q[1] + q[2] * q[2])).exp();
        [theta[0] * e, theta[4] * e, theta[5] * p[3].abs(), theta[6] * p[1]]
    }

    fn blob_vjp(theta: &[f32], p: &[f32], cot: &[f32], grads: &mut [f32]) {
        let q = [p[0] - theta[1], p[1] - theta[2], p[2] - theta[3]];
        let e = (-(q[0] * q[0] + q[1] * q[1] + q[2] * q[2])).exp();
        let d_e = cot[0] * theta[0] + cot[1] * theta[4];
        grads[0] += cot[0] * e;
        for i in 0..3 {
            grads[1 + i] += d_e * e * 2.0 * q[i];
        }
        grads[4] += cot[1] * e;
        grads[5] += cot[2] * p[3].abs();
        grads[6] += cot[3] * p[1];
    }

    fn rays() -> RayBatch {
        let cam = Camera::look_at(
            Vec3::new(0.3, 0.5, -3.0),
            Vec3::ZERO,
            Vec3::Y,
            Vec2::splat(1.5),
            Vec2::ZERO,
        )
        .unwrap();
        RayBatch::random_pixels(&cam, 16, 16, 150, 5).unwrap().0
    }

    fn targets(n: usize) -> Vec<[f32; 3]> {
        (0..n)
            .map(|k| [0.1 * (k % 7) as f32, 0.5, 0.05 * (k % 13) as f32])
            .collect()
    }

    /// 96 samples in [1, 5] of a density on a colored background.
    fn blob_settings(early_termination: Option<f32>) -> VolumeSettings {
        VolumeSettings {
            spacing: DepthSpacing::Linear,
            near: 1.0,
            far: 5.0,
            samples: 96,
            mode: Mode::Density,
            background: Some([0.3, 0.9, 0.1]),
            early_termination,
        }
    }

    /// A step's result with its gradient, as the tests read them.
    #[derive(Debug, PartialEq)]
    struct Stepped {
        result: StepResult,
        param_grads: Vec<f32>,
    }

    impl std::ops::Deref for Stepped {
        type Target = StepResult;
        fn deref(&self) -> &StepResult {
            &self.result
        }
    }

    /// [`volume_step_with`] in a workspace of its own.
    fn stepped(
        rays: &RayBatch,
        targets: &[[f32; 3]],
        field: &dyn BatchFn,
        vjp: &dyn BatchVjp,
        settings: &VolumeSettings,
        options: StepOptions,
    ) -> Result<Stepped> {
        let mut workspace = StepWorkspace::default();
        let result = volume_step_with(rays, targets, field, vjp, settings, options, &mut workspace)?;
        Ok(Stepped {
            result,
            param_grads: workspace.grads,
        })
    }

    /// [`stepped`] with jitter drawn from `jitter`, if given.
    fn jittered(jitter: Option<&mut Rng>) -> StepOptions<'_> {
        StepOptions {
            jitter,
            ..StepOptions::default()
        }
    }

    fn step(theta: &[f32], settings: &VolumeSettings, jitter: Option<&mut Rng>) -> Stepped {
        let theta2 = theta.to_vec();
        let field = ClosureFn::new(6, 4, move |p, out| out.copy_from_slice(&blob_value(&theta2, p)));
        let theta3 = theta.to_vec();
        let vjp = ClosureVjp::new(6, 4, 7, move |p, c, g| blob_vjp(&theta3, p, c, g));
        let rays = rays();
        stepped(
            &rays,
            &targets(rays.len()),
            &field,
            &vjp,
            settings,
            jittered(jitter),
        )
        .unwrap()
    }

    /// A step of the blob with `options`, without jitter.
    fn step_with(theta: &[f32], settings: &VolumeSettings, options: StepOptions) -> Stepped {
        let (t2, t3) = (theta.to_vec(), theta.to_vec());
        let field = ClosureFn::new(6, 4, move |p, out| out.copy_from_slice(&blob_value(&t2, p)));
        let vjp = ClosureVjp::new(6, 4, 7, move |p, c, g| blob_vjp(&t3, p, c, g));
        let rays = rays();
        stepped(&rays, &targets(rays.len()), &field, &vjp, settings, options).unwrap()
    }

    /// The blob's backward pass with kept passes: the forward pass keeps the points, the backward pass
    /// reads them; counts the forward passes run.
    struct KeptBlob {
        theta: Vec<f32>,
        forwards: std::sync::atomic::AtomicUsize,
    }

    struct BlobPasses<'a> {
        blob: &'a KeptBlob,
        points: Vec<[f32; 6]>,
        held: Vec<f32>,
    }

    impl BatchVjp for KeptBlob {
        fn n_inputs(&self) -> usize {
            6
        }
        fn n_outputs(&self) -> usize {
            4
        }
        fn n_params(&self) -> usize {
            7
        }
        fn vjp(&self, n: usize, inputs: &[&[f32]], cotangents: &[&[f32]], grads: &mut [f32]) {
            for i in 0..n {
                let p: Vec<f32> = inputs.iter().map(|c| c[i]).collect();
                let c: Vec<f32> = cotangents.iter().map(|c| c[i]).collect();
                blob_vjp(&self.theta, &p, &c, grads);
            }
        }
        fn kept_passes(&self) -> Option<Box<dyn KeptPasses + '_>> {
            Some(Box::new(BlobPasses {
                blob: self,
                points: Vec::new(),
                held: vec![0.0; 7],
            }))
        }
    }

    impl KeptPasses for BlobPasses<'_> {
        fn forward(&mut self, n: usize, inputs: &[&[f32]], outputs: &mut [&mut [f32]]) {
            self.blob
                .forwards
                .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            let first = self.points.len();
            self.points
                .extend((0..n).map(|i| std::array::from_fn::<f32, 6, _>(|k| inputs[k][i])));
            for (i, p) in self.points[first..].iter().enumerate() {
                for (o, v) in outputs.iter_mut().zip(blob_value(&self.blob.theta, p)) {
                    o[i] = v;
                }
            }
        }
        fn backward(&mut self, n: usize, cotangents: &[&[f32]], _grads: &mut [f32]) {
            assert_eq!(n, self.points.len());
            for (i, p) in self.points.drain(..).enumerate() {
                let c: Vec<f32> = cotangents.iter().map(|c| c[i]).collect();
                blob_vjp(&self.blob.theta, &p, &c, &mut self.held);
            }
        }
        fn bytes_per_point(&self) -> usize {
            24
        }
        fn finish(&mut self, grads: &mut [f32]) {
            for (g, h) in grads.iter_mut().zip(&mut self.held) {
                *g += std::mem::take(h);
            }
        }
    }

    /// Steps whose backward passes read what the forward passes kept give the steps that recompute
    /// them, with and without hierarchical sampling, jittered (the same depths on tiles of other sizes)
    /// or not, with an occupancy grid and early termination (several forward passes a tile, then one
    /// backward pass) or without.
    #[test]
    fn kept_passes_give_the_step_of_recomputing_ones() {
        let theta = [1.5f32, 0.2, -0.1, 0.3, 0.6, 0.8, 0.2];
        let field = ClosureFn::new(6, 4, move |p, out| out.copy_from_slice(&blob_value(&theta, p)));
        let kept = KeptBlob {
            theta: theta.to_vec(),
            forwards: Default::default(),
        };
        let rays = rays();
        let targets = targets(rays.len());
        let fine = FinePass {
            field: &field,
            vjp: &kept,
            importance: 32,
        };
        // Empty beyond 1.2 of the blob's center.
        let cut = ClosureFn::new(3, 4, move |p, out| {
            let q = [p[0] - theta[1], p[1] - theta[2], p[2] - theta[3]];
            let far = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] > 1.44;
            out.copy_from_slice(&[if far { 0.0 } else { 1.0 }, 0.0, 0.0, 0.0]);
        });
        let grid = OccupancyGrid::build(&cut, ([-1.5; 3], [1.5; 3]), 32, Mode::Density, 0.5).unwrap();
        for (settings, hierarchical, jitter, grid) in [
            (blob_settings(None), false, false, None),
            (blob_settings(None), true, true, None),
            (blob_settings(None), false, true, None),
            (blob_settings(Some(1e-3)), false, false, None),
            (blob_settings(Some(1e-3)), false, true, Some(&grid)),
            (blob_settings(None), true, false, Some(&grid)),
            (blob_settings(Some(1e-3)), true, true, Some(&grid)),
        ] {
            let run = |recompute_forward: bool| {
                let mut rng = Rng::new(3);
                let options = StepOptions {
                    jitter: jitter.then_some(&mut rng),
                    fine: hierarchical.then_some(&fine),
                    grid,
                    recompute_forward,
                    appearance: None,
                    distortion: 0.0,
                };
                let before = kept.forwards.load(std::sync::atomic::Ordering::Relaxed);
                let step = stepped(&rays, &targets, &field, &kept, &settings, options).unwrap();
                (
                    step,
                    kept.forwards.load(std::sync::atomic::Ordering::Relaxed) - before,
                )
            };
            let (recomputed, none) = run(true);
            let (keeping, forwards) = run(false);
            assert_eq!(none, 0);
            let one_call = settings.early_termination.is_none() && grid.is_none();
            let passes = if hierarchical { 2 } else { 1 };
            if one_call {
                // One forward pass per ray (128 points a tile) and pass.
                assert_eq!(forwards, passes * rays.len());
            } else {
                // At least one a tile of rays_per_tile rays.
                let tiles = rays.len().div_ceil(settings.rays_per_tile());
                assert!(forwards >= passes * tiles, "{forwards} forward passes");
            }
            assert_eq!(keeping.samples, recomputed.samples);
            assert!((keeping.loss - recomputed.loss).abs() <= 1e-6 * recomputed.loss);
            let scale = recomputed.param_grads.iter().fold(0.0f32, |m, g| m.max(g.abs()));
            for (a, b) in keeping.param_grads.iter().zip(&recomputed.param_grads) {
                assert!((a - b).abs() <= 1e-5 * scale, "{a} vs {b}");
            }
        }
    }

    #[test]
    fn gradients_match_finite_differences_of_the_loss() {
        let theta = [1.5f32, 0.2, -0.1, 0.3, 0.6, 0.8, 0.2];
        for mode in [Mode::Density, Mode::Opacity] {
            let theta = match mode {
                Mode::Density => theta,
                Mode::Opacity => [0.05, theta[1], theta[2], theta[3], theta[4], theta[5], theta[6]],
            };
            let settings = VolumeSettings {
                spacing: DepthSpacing::Linear,
                near: 1.0,
                far: 5.0,
                // Small tiles: several tiles and chunks per step.
                samples: 1000,
                mode,
                background: Some([0.3, 0.9, 0.1]),
                early_termination: None,
            };
            let result = step(&theta, &settings, None);
            assert_eq!(result.param_grads.len(), 7);
            assert!((result.psnr - psnr(result.loss)).abs() < 1e-6);
            for i in 0..7 {
                let h = 0.01 * theta[i].abs().max(0.1);
                let (mut plus, mut minus) = (theta, theta);
                plus[i] += h;
                minus[i] -= h;
                let fd = (step(&plus, &settings, None).loss - step(&minus, &settings, None).loss) / (2.0 * h);
                let got = result.param_grads[i];
                assert!(
                    (got - fd).abs() <= 2e-3 * fd.abs().max(1e-2),
                    "{mode:?} θ{i}: {got} vs {fd}"
                );
            }
        }
    }

    #[test]
    fn the_distortion_loss_joins_the_step_and_its_gradients_match_finite_differences() {
        let theta = [1.5f32, 0.2, -0.1, 0.3, 0.6, 0.8, 0.2];
        for spacing in [DepthSpacing::Linear, DepthSpacing::LinDisp { split: 2.0 }] {
            let settings = VolumeSettings {
                samples: 200,
                spacing,
                ..blob_settings(None)
            };
            let run = |theta: &[f32; 7], distortion: f32| {
                let options = StepOptions {
                    distortion,
                    ..StepOptions::default()
                };
                let step = step_with(theta, &settings, options);
                (step.loss + step.distortion_loss, step)
            };
            let (_, plain) = run(&theta, 0.0);
            let (total, with) = run(&theta, 0.5);
            assert_eq!(plain.distortion_loss, 0.0);
            assert_eq!(with.loss, plain.loss, "the colour loss is the same");
            assert!(
                with.distortion_loss > 1e-3 * total,
                "{spacing:?}: {}",
                with.distortion_loss
            );
            assert_ne!(with.param_grads, plain.param_grads);
            for i in 0..7 {
                let h = 0.01 * theta[i].abs().max(0.1);
                let (mut plus, mut minus) = (theta, theta);
                plus[i] += h;
                minus[i] -= h;
                let fd = (run(&plus, 0.5).0 - run(&minus, 0.5).0) / (2.0 * h);
                let got = with.param_grads[i];
                assert!(
                    (got - fd).abs() <= 2e-3 * fd.abs().max(1e-2),
                    "{spacing:?} θ{i}: {got} vs {fd}"
                );
            }
        }
    }

    #[test]
    fn a_colour_transform_maps_the_prediction_and_its_gradients_match_finite_differences() {
        let theta = [1.5f32, 0.2, -0.1, 0.3, 0.6, 0.8, 0.2];
        let transform = ColorTransform([0.8, 0.1, 0.0, -0.05, 1.2, 0.1, 0.0, 0.2, 0.9, 0.05, -0.1, 0.02]);
        let settings = VolumeSettings {
            samples: 1000,
            ..blob_settings(None)
        };
        let run = |theta: &[f32; 7], appearance: Option<ColorTransform>| {
            let options = StepOptions {
                appearance,
                ..StepOptions::default()
            };
            step_with(theta, &settings, options)
        };
        // The identity is the plain step, bit for bit.
        let (plain, identity) = (run(&theta, None), run(&theta, Some(ColorTransform::IDENTITY)));
        assert_eq!(
            (plain.loss, &plain.param_grads),
            (identity.loss, &identity.param_grads)
        );
        assert_eq!(plain.appearance_grads, None);
        let result = run(&theta, Some(transform));
        assert!(
            (result.loss - plain.loss).abs() > 1e-4 * plain.loss,
            "the transform changed nothing"
        );
        let grads = result.appearance_grads.unwrap();
        for (k, got) in grads.iter().enumerate() {
            let h = 1e-2;
            let (mut plus, mut minus) = (transform, transform);
            plus.0[k] += h;
            minus.0[k] -= h;
            let fd = (run(&theta, Some(plus)).loss - run(&theta, Some(minus)).loss) / (2.0 * h);
            assert!(
                (got - fd).abs() <= 2e-3 * fd.abs().max(1e-2),
                "value {k}: {got} vs {fd}"
            );
        }
        for i in 0..7 {
            let h = 0.01 * theta[i].abs().max(0.1);
            let (mut plus, mut minus) = (theta, theta);
            plus[i] += h;
            minus[i] -= h;
            let fd = (run(&plus, Some(transform)).loss - run(&minus, Some(transform)).loss) / (2.0 * h);
            let got = result.param_grads[i];
            assert!(
                (got - fd).abs() <= 2e-3 * fd.abs().max(1e-2),
                "θ{i}: {got} vs {fd}"
            );
        }
    }

    #[test]
    fn a_step_gives_the_same_bits_on_any_number_of_threads() {
        let theta = [1.5f32, 0.2, -0.1, 0.3, 0.6, 0.8, 0.2];
        // 1000 samples a ray: tiles of a few rays, more chunks than accumulators.
        let settings = VolumeSettings {
            samples: 1000,
            ..blob_settings(None)
        };
        let tile = settings.rays_per_tile();
        let chunks = rays()
            .len()
            .div_ceil(tile * (CHUNK_POINTS / (tile * 1000)).max(1));
        assert!(chunks > ACCUMULATORS, "{chunks} chunks");
        let on = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| step(&theta, &settings, Some(&mut Rng::new(7))))
        };
        let one = on(1);
        for threads in [2, 3] {
            let many = on(threads);
            assert_eq!(one.loss.to_bits(), many.loss.to_bits());
            let bits = |r: &Stepped| r.param_grads.iter().map(|g| g.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&one), bits(&many), "{threads} threads");
        }
    }

    #[test]
    fn grid_skipping_is_exact_where_the_field_is_empty_and_evaluates_less() {
        use std::sync::atomic::{AtomicUsize, Ordering};
        // The blob cut to a ball of radius 0.7 around its center: zero outside.
        let theta = [1.5f32, 0.2, -0.1, 0.3, 0.6, 0.8, 0.2];
        let inside = move |p: &[f32]| {
            let q = [p[0] - theta[1], p[1] - theta[2], p[2] - theta[3]];
            q[0] * q[0] + q[1] * q[1] + q[2] * q[2] < 0.49
        };
        let evaluated = AtomicUsize::new(0);
        let field = ClosureFn::new(6, 4, |p, out| {
            evaluated.fetch_add(1, Ordering::Relaxed);
            let v = blob_value(&theta, p);
            out.copy_from_slice(&if inside(p) { v } else { [0.0; 4] });
        });
        let vjp = ClosureVjp::new(6, 4, 7, |p, c, g| {
            if inside(p) {
                blob_vjp(&theta, p, c, g)
            }
        });
        let settings = blob_settings(None);
        let rays = rays();
        let targets = targets(rays.len());
        let exact = stepped(&rays, &targets, &field, &vjp, &settings, StepOptions::default()).unwrap();
        let all = evaluated.swap(0, Ordering::Relaxed);
        let grid = OccupancyGrid::build(&field, ([-1.5; 3], [1.5; 3]), 32, Mode::Density, 0.0).unwrap();
        evaluated.store(0, Ordering::Relaxed);
        let options = StepOptions {
            grid: Some(&grid),
            ..StepOptions::default()
        };
        let skipped = stepped(&rays, &targets, &field, &vjp, &settings, options).unwrap();
        let some = evaluated.load(Ordering::Relaxed);
        assert!(some * 3 < all, "{some} of {all} samples evaluated");
        assert_eq!(
            (exact.samples, skipped.samples),
            (all, some),
            "the steps count what they evaluate"
        );
        assert!((skipped.loss - exact.loss).abs() <= 1e-6 * exact.loss.max(1.0));
        for (a, b) in skipped.param_grads.iter().zip(&exact.param_grads) {
            assert!((a - b).abs() <= 1e-5 * b.abs().max(1e-3), "{a} vs {b}");
        }
    }

    #[test]
    fn early_termination_evaluates_less_and_matches_every_sample_composited_one_by_one() {
        use crate::volume::composite::{SampleGrads, Samples};
        use std::sync::atomic::{AtomicUsize, Ordering};
        // A dense blob: rays through it end inside, so their later samples do not count.
        let theta = [60.0f32, 0.2, -0.1, 0.3, 0.6, 0.8, 0.2];
        let (evaluated, back_propagated) = (AtomicUsize::new(0), AtomicUsize::new(0));
        let field = ClosureFn::new(6, 4, |p, out| {
            evaluated.fetch_add(1, Ordering::Relaxed);
            out.copy_from_slice(&blob_value(&theta, p));
        });
        let vjp = ClosureVjp::new(6, 4, 7, |p, c, g| {
            back_propagated.fetch_add(1, Ordering::Relaxed);
            blob_vjp(&theta, p, c, g)
        });
        let settings = blob_settings(Some(1e-3));
        let rays = rays();
        let targets = targets(rays.len());
        let result = stepped(&rays, &targets, &field, &vjp, &settings, StepOptions::default()).unwrap();
        let all = rays.len() * settings.samples;
        let (some, fewer) = (
            evaluated.load(Ordering::Relaxed),
            back_propagated.load(Ordering::Relaxed),
        );
        assert!(some * 5 < all * 4, "{some} of {all} samples evaluated");
        assert!(
            fewer < some,
            "{fewer} of {some} evaluated samples back-propagated"
        );

        // The reference: every sample evaluated, composited ray by ray, every sample back-propagated.
        let compositor = settings.compositor();
        let mut t = vec![0.0; settings.samples];
        settings.fixed_depths(&mut t);
        let (mut squared_error, mut grads) = (0.0f64, vec![0.0f32; 7]);
        for (k, target) in targets.iter().enumerate() {
            let (o, d) = rays.ray(k).unwrap();
            let inputs: Vec<[f32; 6]> = t
                .iter()
                .map(|&t| {
                    let p = o + t * d;
                    [p.x, p.y, p.z, d.x, d.y, d.z]
                })
                .collect();
            let values: Vec<[f32; 4]> = inputs.iter().map(|p| blob_value(&theta, p)).collect();
            let column = |c: usize| values.iter().map(|v| v[c]).collect::<Vec<f32>>();
            let (raw, r, g, b) = (column(0), column(1), column(2), column(3));
            let samples = Samples::new(&t, &raw, [&r, &g, &b]).unwrap();
            let mut sample_grads: [Vec<f32>; 4] = std::array::from_fn(|_| vec![0.0; t.len()]);
            let [g_raw, g_r, g_g, g_b] = &mut sample_grads;
            let mut out_grads = SampleGrads::new(g_raw, [g_r, g_g, g_b]).unwrap();
            compositor
                .forward_backward(&samples, &mut out_grads, |out| {
                    let error = [0, 1, 2].map(|c| out.rgb[c] - target[c]);
                    squared_error += error.iter().map(|e| f64::from(e * e)).sum::<f64>();
                    RayOutput {
                        rgb: error.map(|e| 2.0 / (3.0 * rays.len() as f32) * e),
                        ..RayOutput::default()
                    }
                })
                .unwrap();
            for (j, p) in inputs.iter().enumerate() {
                let cot = sample_grads.each_ref().map(|c| c[j]);
                blob_vjp(&theta, p, &cot, &mut grads);
            }
        }
        let loss = (squared_error / (3.0 * rays.len() as f64)) as f32;
        assert!(
            (result.loss - loss).abs() <= 1e-5 * loss,
            "{} vs {loss}",
            result.loss
        );
        for (a, b) in result.param_grads.iter().zip(&grads) {
            assert!((a - b).abs() <= 1e-4 * b.abs().max(1e-3), "{a} vs {b}");
        }
    }

    #[test]
    fn jitter_is_seeded_and_changes_the_samples() {
        let theta = [1.5f32, 0.2, -0.1, 0.3, 0.6, 0.8, 0.2];
        let settings = VolumeSettings {
            spacing: DepthSpacing::Linear,
            near: 1.0,
            far: 5.0,
            samples: 32,
            mode: Mode::Density,
            background: None,
            early_termination: None,
        };
        let a = step(&theta, &settings, Some(&mut Rng::new(1)));
        let b = step(&theta, &settings, Some(&mut Rng::new(1)));
        let c = step(&theta, &settings, Some(&mut Rng::new(2)));
        let fixed = step(&theta, &settings, None);
        assert_eq!(a, b);
        assert_ne!(a.loss, c.loss);
        assert_ne!(a.loss, fixed.loss);
        // Jittered and fixed samples estimate the same image.
        assert!(
            (a.loss - fixed.loss).abs() < 0.05 * fixed.loss,
            "{} vs {}",
            a.loss,
            fixed.loss
        );
    }

    #[test]
    fn bad_arguments_are_errors() {
        let rays = rays();
        let field = ClosureFn::new(3, 4, |_, out| out.fill(0.5));
        let vjp = ClosureVjp::new(3, 4, 1, |_, _, _| {});
        let settings = VolumeSettings {
            spacing: DepthSpacing::Linear,
            near: 0.0,
            far: 5.0,
            samples: 8,
            mode: Mode::Opacity,
            background: None,
            early_termination: None,
        };
        let t = targets(rays.len());
        let ok = stepped(&rays, &t, &field, &vjp, &settings, StepOptions::default()).unwrap();
        // Opacity 0.5 per sample, color 0.5: the image is 0.5·(1 − 2⁻⁸) everywhere.
        let c = 0.5 * (1.0 - 0.5f32.powi(8));
        let mse = t.iter().flatten().map(|x| (x - c) * (x - c)).sum::<f32>() / (3 * t.len()) as f32;
        assert!((ok.loss - mse).abs() < 1e-6, "{} vs {mse}", ok.loss);
        assert_eq!(ok.param_grads, vec![0.0]);
        let e = stepped(&rays, &t[1..], &field, &vjp, &settings, StepOptions::default()).unwrap_err();
        assert!(e.to_string().contains("149 targets"), "{e}");
        let vjp6 = ClosureVjp::new(6, 4, 1, |_, _, _| {});
        assert!(stepped(&rays, &t, &field, &vjp6, &settings, StepOptions::default()).is_err());
        let bad = VolumeSettings {
            samples: 0,
            ..settings
        };
        assert!(stepped(&rays, &t, &field, &vjp, &bad, StepOptions::default()).is_err());
        assert!(stepped(
            &RayBatch::default(),
            &[],
            &field,
            &vjp,
            &settings,
            StepOptions::default()
        )
        .is_err());
        let mut broken = rays.clone();
        broken.oy.pop();
        assert!(stepped(&broken, &t, &field, &vjp, &settings, StepOptions::default()).is_err());
    }
}
