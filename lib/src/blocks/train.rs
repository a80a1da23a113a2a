//! `train { ... }`: fits the script's params to images by differentiable volume rendering, with Adam,
//! checkpoints (atomic, resumable), a NaN guard, preview renders and a JSON summary.

use std::path::{Path, PathBuf};
use std::time::Instant;

use nerfjit_dsl::config::{Spanned, Value};
use nerfjit_dsl::{Diagnostic, Program};
use nerfjit_jit::{KernelCache, Precision};
use nerfjit_runtime::{
    check_thickness, load_blender_views, rgb_image, save_png, DensityEma, DepthSpacing, GridSpace,
    OccupancyGrid, Quantize, Rng, Schedule, StepWorkspace, TrainableModel, Views, VolumeSettings,
};

use crate::failure::{Failure, Result};
use crate::folder_lock::lock_output_folders;
use crate::observe::{NoBars, ProgressBars, TrainingObserver};
use crate::settings::block::Block;
use crate::settings::primitives::CallArgs;
use crate::settings::typed::typed_settings;
pub use crate::settings::values::AdamSettings;
use crate::settings::values::{grid_seed, grid_update, minutes_list, optimizer, schedule, GridUpdate};
use crate::training::appearance::Appearance;
use crate::training::data_source::{data_path, data_set, DataKind, DataSet};
use crate::training::metrics_log::{log_record, LogRecord};
use crate::training::regularizers::{occupied_points, uniform_points, RegularizerKernels, Regularizers};
use crate::training::train_loop::{self, Gradient, LoopSettings, Objective, Progress, Ui};
use nerfjit_field::{VolumeField, VolumeFields};

log_record! {
    /// A line of a volume training's metrics log: a step's figures, or a validation's scores.
    pub(crate) struct VolumeRecord {
        /// Steps done.
        step: u32,
        /// Seconds of training.
        train_seconds: f64,
        /// The step's learning rate.
        lr: Option<f32>,
        /// The step's loss.
        loss: Option<f32>,
        /// The PSNR of the step's rays.
        psnr: Option<f32>,
        /// The step's eikonal term, if it has one.
        eikonal: Option<f32>,
        /// The step's distortion loss (its weighted part of the loss), if it has one.
        distortion: Option<f32>,
        /// The validation's mean PSNR.
        val_psnr: Option<f64>,
        /// The validation's mean SSIM.
        val_ssim: Option<f64>,
    }
}

typed_settings! {
    /// The settings of a `train` block, as read.
    pub struct TrainSettings for crate::settings::schema::TRAIN {
        data: required,
        near: number,
        far: number,
        samples: whole,
        background: triple,
        steps: whole,
        batch: whole,
        batch_samples: whole_or_none,
        lr: number,
        schedule: value,
        views: choice,
        jitter: flag,
        random_background: flag,
        appearance: flag,
        distortion: number,
        seed: whole,
        checkpoint: output,
        checkpoint_every: whole,
        summary: output,
        preview: output,
        preview_every: whole,
        sdf: function,
        eikonal_weight: number,
        eikonal_points: whole,
        eikonal_bounds: number,
        eikonal_sampling: choice,
        val: value,
        val_every: whole,
        val_views: whole_or_none,
        val_minutes: value,
        importance: whole,
        skip_empty: value,
        products: choice,
        recompute_forward: flag,
        grid_every: whole,
        grid_warmup: whole,
        grid_update: value,
        grid_seed: value,
        minutes: number,
        early_termination: number,
        spacing: value,
        optimizer: value,
        log: output,
        tensorboard: output,
    }
}

/// The most samples (rays × samples per ray) one training step may evaluate: their buffers must fit in
/// memory.
const MAX_SAMPLES_PER_STEP: usize = 1 << 26;

/// A checked `train` block.
pub struct TrainPlan {
    data: DataSet,
    near: f32,
    far: f32,
    samples: usize,
    spacing: DepthSpacing,
    background: Option<[f32; 3]>,
    steps: u32,
    /// Stop once the steps alone have taken this many seconds (validation and previews excluded).
    time_limit: Option<f64>,
    /// Rays of the first step (of every step unless `batch_samples` is set).
    batch: usize,
    /// Steps sized in samples: the ray count adapts so that a step evaluates about this many.
    batch_samples: Option<usize>,
    schedule: Schedule,
    /// Adam's decay rates and ε.
    optimizer: AdamSettings,
    /// Which views each step's rays come from (`views`).
    views: ViewChoice,
    /// Each step composites its rays and their targets on a random color (`random_background`).
    random_background: bool,
    /// A colour transform per training view, learnt with the field (`appearance`).
    appearance: bool,
    /// The weight of the distortion loss (`distortion`; 0: none).
    distortion: f32,
    jitter: bool,
    seed: u64,
    checkpoint: Option<PathBuf>,
    checkpoint_every: u32,
    /// The metrics log (JSON Lines, or CSV).
    log: Option<PathBuf>,
    /// A TensorBoard folder the metrics also go to.
    tensorboard: Option<PathBuf>,
    summary: Option<PathBuf>,
    preview: Option<PathBuf>,
    preview_every: u32,
    /// VolSDF-style training: the eikonal term on the script's SDF at random points.
    eikonal: Option<Eikonal>,
    /// Held-out views scored during training (Blender data only).
    validation: Option<Validation>,
    /// Importance samples per ray for hierarchical sampling (0: one field, no fine pass).
    importance: usize,
    /// The arithmetic of the networks' products.
    products: Precision,
    /// Recompute the networks' forward pass in their backward pass instead of keeping its values.
    recompute_forward: bool,
    /// Empty-space skipping during training: an occupancy grid of the (fine) field, rebuilt every
    /// `every` steps from step `warmup` on.
    grid: Option<TrainingGrid>,
    /// Training rays stop once their transmittance is below this (later samples are neither evaluated
    /// nor back-propagated); validation and previews stop rays the same way.
    early_termination: Option<f32>,
}

/// The eikonal term of VolSDF-style training.
#[derive(Clone, Debug)]
struct Eikonal {
    /// The script's SDF (its name).
    sdf: String,
    /// The term's weight and points.
    regularizers: Regularizers,
    /// Points in the occupancy grid's occupied cells (while there is one) instead of uniform ones.
    occupied: bool,
}

/// What a `train` block leaves for the blocks after it.
pub struct Trained {
    /// The block's summary line.
    pub summary: String,
    /// The occupancy grid its last validation rendered with (as its checkpoint keeps it, for a run
    /// already complete), if it skips empty space: render blocks of the same grid take it rather than
    /// building one from the field, as `eval-views` of the checkpoint does.
    pub occupancy: Option<OccupancyGrid>,
}

/// The `skip_empty`, `grid_every`, `grid_warmup`, `grid_update` and `grid_seed` settings.
#[derive(Clone, Copy, Debug)]
struct TrainingGrid {
    grid: crate::settings::values::SkipEmpty,
    every: u32,
    warmup: u32,
    update: GridUpdate,
    /// Before the warm-up, the cells within this many cells of the data's sparse points.
    seed: Option<usize>,
}

/// Which views validation scores.
#[derive(Clone, Debug)]
enum HeldOut {
    /// A Blender camera file of held-out views (with Blender data).
    File(PathBuf),
    /// Every n-th view of the data set (0, n, 2n, …), which training then does not see.
    Every(usize),
}

/// The `val` settings: held-out views rendered and scored every `every` steps, once the training time
/// passes each of `at_seconds`, and at the end (the first `views` of them, all if None).
#[derive(Clone, Debug)]
struct Validation {
    held_out: HeldOut,
    every: u32,
    at_seconds: Vec<f64>,
    views: Option<usize>,
}

/// The `val` setting: `holdout(every: 8)` (every n-th view of the data, 0, n, 2n, …, kept from training) or
/// a Blender camera file (with Blender data).
fn held_out(v: &Spanned, data: &DataSet, script_dir: &Path) -> std::result::Result<HeldOut, Diagnostic> {
    if let Value::Call(name, _) = &v.value {
        if name == "holdout" {
            let a = CallArgs::new(v, &["every"])?;
            let every = a
                .raw("every")
                .map(|n| crate::settings::primitives::whole(n, 2, 1000))
                .transpose()?;
            return Ok(HeldOut::Every(every.unwrap_or(8) as usize));
        }
    }
    let file = data_path(v.string()?, script_dir);
    if data.blender().is_none() {
        return Err(Diagnostic::new(
            v.span,
            "a validation camera file scores held-out Blender views: it needs data: blender(...)",
        )
        .with_hint("for other data, hold out every n-th view: val: holdout(every: 8)"));
    }
    if !file.is_file() {
        return Err(Diagnostic::new(
            v.span,
            format!("validation file '{}' not found", file.display()),
        ));
    }
    Ok(HeldOut::File(file))
}

/// The data the first `train` block of `program` trains on (a script in `script_dir`), if it names data
/// that exists.
pub fn train_data(program: &Program, script_dir: &Path) -> Option<DataSet> {
    let block = program
        .blocks()
        .into_iter()
        .find(|b| crate::settings::schema::kind_of(b) == Some(crate::settings::schema::Kind::Train))?;
    let data = nerfjit_dsl::config::Settings::new(program, block)
        .ok()?
        .take("data")?;
    data_set(&data, script_dir).ok()
}

/// The cameras of the data the first `train` block of `program` trains on (a script in `script_dir`), if
/// it names data whose camera file can be read.
pub fn data_cameras(program: &Program, script_dir: &Path) -> Option<Vec<nerfjit_runtime::Camera>> {
    train_data(program, script_dir)?.cameras().ok()
}

impl TrainPlan {
    /// Reads and checks a `train` block.
    pub fn new(mut b: Block) -> Result<TrainPlan> {
        let s = TrainSettings::read(&mut b)?;
        let data = data_set(&s.data, b.script_dir()).map_err(|d| b.error(d))?;
        let (near, far) = b.interval(s.near, s.far)?;
        let samples = s.samples as usize;
        let spacing = b.spacing_of(s.spacing.as_ref(), near, far)?;
        let batch = s.batch as usize;
        if batch * samples > MAX_SAMPLES_PER_STEP {
            return Err(b.block_error(format!(
                "{batch} rays × {samples} samples is too many for one step (the limit is {MAX_SAMPLES_PER_STEP} samples)"
            )));
        }
        let eikonal_weight = s.eikonal_weight as f32;
        let eikonal = (eikonal_weight > 0.0).then(|| Eikonal {
            sdf: s.sdf,
            regularizers: Regularizers {
                points: s.eikonal_points as usize,
                bound: s.eikonal_bounds as f32,
                near_weight: 0.0,
                near_sharpness: 0.0,
                eikonal_weight,
            },
            occupied: s.eikonal_sampling.as_deref() == Some("occupied"),
        });
        let schedule = schedule(s.schedule, s.lr as f32).map_err(|d| b.error(d))?;
        let optimizer = optimizer(s.optimizer).map_err(|d| b.error(d))?;
        let views = match s.views.as_deref() {
            Some("random") => ViewChoice::Random,
            Some("all") => ViewChoice::All,
            _ => ViewChoice::Cycle,
        };
        let validation = match &s.val {
            Some(v) => Some(Validation {
                held_out: held_out(v, &data, b.script_dir()).map_err(|d| b.error(d))?,
                every: s.val_every as u32,
                at_seconds: match &s.val_minutes {
                    Some(v) => minutes_list(v).map_err(|d| b.error(d))?,
                    None => Vec::new(),
                },
                views: s.val_views.map(|n| n as usize),
            }),
            None => None,
        };
        let skip_empty = match &s.skip_empty {
            None => None,
            Some(v) => crate::settings::values::skip_empty(v).map_err(|d| b.error(d))?,
        };
        let update = grid_update(s.grid_update).map_err(|d| b.error(d))?;
        let grid_seeding = match &s.grid_seed {
            Some(v) => {
                let seed = grid_seed(v).map_err(|d| b.error(d))?;
                if seed.is_some() && !matches!(data.kind, DataKind::Colmap(..)) {
                    return Err(b.error(
                        Diagnostic::new(v.span, "only a COLMAP model has sparse points to seed the grid")
                            .with_hint("use data: colmap(...), or remove grid_seed"),
                    ));
                }
                if seed.is_some() && skip_empty.is_none() {
                    return Err(b.error(
                        Diagnostic::new(v.span, "grid_seed seeds the occupancy grid of skip_empty")
                            .with_hint("add e.g. skip_empty: grid(bounds: 1.5)"),
                    ));
                }
                seed
            }
            None => None,
        };
        let grid = skip_empty.map(|grid| TrainingGrid {
            grid,
            every: s.grid_every as u32,
            warmup: s.grid_warmup as u32,
            update,
            seed: grid_seeding,
        });
        if s.appearance && views == ViewChoice::All {
            return Err(b.block_error(
                "appearance: true learns a colour transform per view from steps whose rays come from one view; \
                 views: all draws each ray from any view: choose views: random or cycle"
                    .into(),
            ));
        }
        if s.appearance && s.checkpoint.as_deref().is_some_and(crate::checkpoint::is_json) {
            return Err(b.block_error(
                "a JSON checkpoint cannot keep the colour transforms of appearance: true; name the checkpoint \
                 *.safetensors"
                    .into(),
            ));
        }
        b.finish()?;
        let early_termination = s.early_termination as f32;
        Ok(TrainPlan {
            early_termination: (early_termination > 0.0).then_some(early_termination),
            data,
            near,
            far,
            samples,
            spacing,
            background: s.background,
            steps: s.steps as u32,
            time_limit: (s.minutes > 0.0).then_some(60.0 * s.minutes),
            batch,
            batch_samples: s.batch_samples.map(|n| n as usize),
            schedule,
            optimizer,
            views,
            random_background: s.random_background,
            appearance: s.appearance,
            distortion: s.distortion as f32,
            jitter: s.jitter,
            seed: s.seed,
            checkpoint: s.checkpoint,
            checkpoint_every: s.checkpoint_every as u32,
            log: s.log,
            tensorboard: s.tensorboard,
            summary: s.summary,
            preview: s.preview,
            preview_every: s.preview_every as u32,
            eikonal,
            validation,
            importance: s.importance as usize,
            products: s
                .products
                .as_deref()
                .and_then(Precision::named)
                .unwrap_or_default(),
            recompute_forward: s.recompute_forward,
            grid,
        })
    }

    fn settings(&self, field: &VolumeField) -> VolumeSettings {
        VolumeSettings {
            near: self.near,
            far: self.far,
            samples: self.samples,
            mode: field.mode,
            // Missed rays show the data's background unless the block says otherwise: renders on black
            // against views on white would have to learn a white fog.
            background: Some(self.background.unwrap_or_else(|| self.data.background())),
            early_termination: None,
            spacing: self.spacing,
        }
    }

    /// The same plan with every sample evaluated: no occupancy grid, no early termination (the
    /// benchmark workloads' setting).
    pub fn exact(self) -> TrainPlan {
        TrainPlan {
            grid: None,
            early_termination: None,
            ..self
        }
    }

    /// Runs only the first `steps` steps (no checkpoints, previews or summary file), for benchmarks;
    /// returns the ms per step of the training loop alone. The block's time limit is dropped: a schedule
    /// `over: run` runs over the steps, whatever the machine's speed, so that the same build gives the same
    /// losses (with the limit, slow steps made the learning rate follow the clock).
    pub fn run_steps(&self, program: &Program, params: &mut Vec<f32>, steps: u32) -> Result<String> {
        let quiet = TrainPlan {
            steps,
            time_limit: None,
            checkpoint: None,
            log: None,
            tensorboard: None,
            summary: None,
            preview: None,
            data: self.data.clone(),
            eikonal: self.eikonal.clone(),
            validation: None,
            ..*self
        };
        let trained = quiet.run(program, params, &KernelCache::new(), false, None, &NoBars)?;
        Ok(trained.summary.lines().next().unwrap_or_default().to_string())
    }

    /// The training views and the held-out views validation scores (if the block asks for validation).
    /// With `random_background` the training views keep their alpha; held-out views are always on the
    /// data's background.
    pub fn load_views(&self) -> Result<(Views, Option<Views>)> {
        let mut views = self.data.load(self.random_background)?;
        let val_views = match self.validation.as_ref().map(|v| (&v.held_out, v.views)) {
            Some((HeldOut::Every(n), limit)) => {
                let (train, held) = views.hold_out(*n)?;
                views = train;
                let mut held = held.on_background(self.data.background());
                held.cameras.truncate(limit.unwrap_or(usize::MAX));
                held.images.truncate(limit.unwrap_or(usize::MAX));
                Some(held)
            }
            Some((HeldOut::File(file), limit)) => match self.data.blender() {
                Some(b) => Some(load_blender_views(file, Some(b.size), b.background, limit)?),
                None => None,
            },
            None => None,
        };
        Ok((views, val_views))
    }

    /// A warning when the data set's `aabb_scale` puts the scene beyond the occupancy grid's box (a grid in
    /// contracted or NDC space covers all of space or the frustum): samples outside the box are never
    /// evaluated.
    fn aabb_warning(&self) -> Result<Option<String>> {
        let Some(g) = self.grid.as_ref().filter(|g| g.grid.space == GridSpace::Scene) else {
            return Ok(None);
        };
        let Some(extent) = self.data.aabb_extent()? else {
            return Ok(None);
        };
        let (lo, hi) = g.grid.bounds;
        let covered = lo.iter().all(|&l| l <= -extent) && hi.iter().all(|&h| h >= extent);
        Ok((!covered).then(|| {
            format!(
                "warning: {}'s aabb_scale puts its scene within ±{extent:.2} of the training frame's origin, beyond \
                 the occupancy grid's box ({lo:?} to {hi:?}): nothing outside the box is sampled, so the scene there \
                 stays black. For a capture with a background, train with `space: contracted` in `skip_empty` \
                 (examples/instant_capture.sdf), or widen the grid's bounds",
                self.data.path.display()
            )
        }))
    }

    /// A warning when the data set's depth bounds put scene content nearer the cameras than the block's
    /// `near`: the rays start behind it, and it is never trained.
    fn near_warning(&self) -> Result<Option<String>> {
        let Some((nearest, _)) = self.data.depth_bounds()? else {
            return Ok(None);
        };
        Ok((self.near > nearest).then(|| {
            format!(
                "warning: {}'s depth bounds put the nearest scene content {nearest:.2} from the cameras in the \
                 training frame, nearer than `near: {}`: the rays start behind it, so it is never sampled. Lower \
                 `near` (to about {:.2}) unless that content is to be cut away",
                self.data.path.display(),
                self.near,
                0.9 * nearest
            )
        }))
    }

    /// The checkpoint it writes (`None`: `checkpoint: none`).
    pub fn checkpoint(&self) -> Option<&Path> {
        self.checkpoint.as_deref()
    }

    /// The seconds of training its `minutes` setting allows (`None`: no time limit).
    pub fn time_limit(&self) -> Option<f64> {
        self.time_limit
    }

    /// Every how many views of its data the block holds out (`holdout(every: n)`) and how many of them
    /// validation scores (all if None); `None` when it validates on a file or not at all.
    pub fn held_out_every(&self) -> Option<(usize, Option<usize>)> {
        match self.validation.as_ref()? {
            Validation {
                held_out: HeldOut::Every(n),
                views,
                ..
            } => Some((*n, *views)),
            _ => None,
        }
    }

    /// Which views the block holds out, in words (for reports of the protocol scored).
    pub fn held_out_description(&self) -> Option<String> {
        let v = self.validation.as_ref()?;
        let first = v.views.map_or(String::new(), |n| format!(" (the first {n})"));
        Some(match &v.held_out {
            HeldOut::Every(n) => format!("every {n}th view of {}{first}", self.data.path.display()),
            HeldOut::File(file) => format!("the views of {}{first}", file.display()),
        })
    }

    /// Trains `params` in place (resuming from the checkpoint when asked, compiling through `cache`),
    /// publishing its progress and params to a live viewer when given; returns its summary line and
    /// final occupancy grid.
    pub fn run(
        &self,
        program: &Program,
        params: &mut Vec<f32>,
        cache: &KernelCache,
        resume: bool,
        live: Option<&dyn TrainingObserver>,
        bars: &dyn ProgressBars,
    ) -> Result<Trained> {
        crate::cluster::check_batch(self.batch, "the train block's batch").map_err(Failure::Message)?;
        // Before anything is read or written: a second run in the folder refuses here, naming the first.
        let _locks = lock_output_folders(self.checkpoint.iter().chain(&self.log).map(PathBuf::as_path))?;
        for line in [self.aabb_warning()?, self.near_warning()?].into_iter().flatten() {
            crate::console::note(&line);
        }
        let t = Instant::now();
        let fields = VolumeFields::compile(program, cache, self.importance, self.products)?;
        if self.grid.as_ref().is_some_and(|g| g.grid.thickness) {
            // Refused before the views load and the steps run, not when the grid is first built.
            check_thickness(fields.fine.mode)?;
        }
        let regularizers = match &self.eikonal {
            Some(e) => Some(RegularizerKernels::compile(
                program,
                &e.sdf,
                &e.regularizers,
                cache,
                self.products,
            )?),
            None => None,
        };
        let compile_s = t.elapsed().as_secs_f64();
        let (views, val_views) = self.load_views()?;
        let settings = self.settings(&fields.fine);
        let mut objective = VolumeObjective {
            plan: self,
            views: &views,
            val_views: val_views.as_ref(),
            fields: &fields,
            regularizers: regularizers.as_ref(),
            step_settings: VolumeSettings {
                early_termination: self.early_termination,
                ..settings
            },
            live,
            step_rng: Rng::new(self.seed ^ 0x5eed),
            rng: Rng::new(self.seed ^ 0xd1ce ^ ((crate::cluster::current().rank() as u64) << 40)),
            grid: None,
            ema: None,
            ema_rng: Rng::new(self.seed ^ 0x0cc0),
            psnr: f32::NAN,
            eikonal_loss: 0.0,
            distortion_loss: 0.0,
            history: Vec::new(),
            next_val_time: 0,
            rays: self.batch,
            appearance: self
                .appearance
                .then(|| Appearance::new(views.len(), self.optimizer)),
            workspace: StepWorkspace::default(),
        };
        let loop_settings = LoopSettings {
            steps: self.steps,
            schedule: &self.schedule,
            optimizer: self.optimizer,
            time_limit: self.time_limit,
            checkpoint: self.checkpoint.as_deref(),
            checkpoint_every: self.checkpoint_every,
            resume,
            log: self.log.as_deref(),
            tensorboard: self.tensorboard.as_deref(),
            log_columns: VolumeRecord::COLUMNS,
            verb: "training",
            bars,
        };
        let end = train_loop::train(program, params, &loop_settings, &mut objective)?;
        if end.complete {
            let occupancy = match (&self.grid, &self.checkpoint) {
                (Some(_), Some(path)) => crate::checkpoint::saved_occupancy(path)?,
                _ => None,
            };
            return Ok(Trained {
                summary: end.already_complete(self.checkpoint.as_deref()),
                occupancy,
            });
        }
        let (loss, psnr) = (end.loss, objective.psnr);
        let (ms_per_step, samples_per_s) = (end.ms_per_step(), end.samples_per_s());
        if let Some(path) = self
            .summary
            .as_ref()
            .filter(|_| crate::cluster::current().rank() == 0)
        {
            let json = serde_json::json!({
                "data": self.data.path.display().to_string(),
                "steps": end.done,
                "resumed_from": end.first,
                "final_loss": loss,
                "final_psnr": psnr,
                "seconds": end.wall_seconds,
                "ms_per_step": ms_per_step,
                "samples_per_s": samples_per_s,
                "rays_per_step": objective.rays,
                "compile_seconds": compile_s,
                "train_seconds": end.train_seconds,
                "validation": objective.history,
                "occupied_cells": objective.grid.as_ref().map(OccupancyGrid::occupancy),
                "appearance": objective.appearance.as_ref().map(Appearance::summary),
                "params": params_json(program, params),
            });
            nerfjit_runtime::write_whole(
                path,
                serde_json::to_string_pretty(&json).unwrap_or_default().as_bytes(),
            )?;
        }
        end.stopped(self.checkpoint.as_deref())?;
        let rays = match self.batch_samples {
            Some(_) => format!(", {} rays a step at the end", objective.rays),
            None => String::new(),
        };
        let summary = format!(
            "trained {} steps in {:.1} s of training, {:.1} s in all ({ms_per_step:.2} ms/step, {:.2} M samples/s{rays}, JIT compile {compile_s:.3} s): loss {loss:.6}, PSNR {psnr:.2} dB\n{}",
            end.trained(),
            end.train_seconds,
            end.wall_seconds,
            samples_per_s * 1e-6,
            describe_params(program, params)
        );
        Ok(Trained {
            summary,
            occupancy: objective.grid.take(),
        })
    }

    fn write_preview(
        &self,
        path: &Path,
        views: &Views,
        fields: &VolumeFields,
        params: &[f32],
        settings: &VolumeSettings,
        grid: Option<&OccupancyGrid>,
    ) -> Result<()> {
        let size = (views.width, views.height);
        let frame = fields.render_with(&views.cameras[0], size, params, settings, grid)?;
        // The preview shows the render next to the target view.
        let target = &views.images[0];
        let (w, h) = (views.width as usize, views.height as usize);
        let mut side = vec![[0.0f32; 3]; 2 * w * h];
        for row in 0..h {
            for col in 0..w {
                side[row * 2 * w + col] = frame.rgb[row * w + col];
                side[row * 2 * w + w + col] = target.pixels[row * w + col];
            }
        }
        save_png(
            path,
            rgb_image(2 * views.width, views.height, &side, Quantize::Truncate)?,
        )?;
        Ok(())
    }
}

/// A `train` block's objective: the photometric loss of random rays of the training views (with the
/// eikonal term of VolSDF-style training), the occupancy grid kept up to date before the steps, and
/// validation, previews, log records and the live viewer after them.
struct VolumeObjective<'a> {
    plan: &'a TrainPlan,
    views: &'a Views,
    val_views: Option<&'a Views>,
    fields: &'a VolumeFields,
    regularizers: Option<&'a RegularizerKernels>,
    /// The steps', validation's and previews' settings (with early termination when asked).
    step_settings: VolumeSettings,
    live: Option<&'a dyn TrainingObserver>,
    /// The step's view and background colour: the same on every rank of an MPI job, whose ranks then
    /// split a step of one process (rays of one view). With a view per rank instead, the DTU NeuS recipe
    /// (its eikonal term) trained to 16.7 dB over 2 ranks against 22.0–22.5 in one process.
    step_rng: Rng,
    /// The samples' jitter and the eikonal term's points: this rank's own.
    rng: Rng,
    grid: Option<OccupancyGrid>,
    /// The running occupancy of `grid_update: ema` and the random points of its updates.
    ema: Option<DensityEma>,
    ema_rng: Rng,
    /// The last step's training PSNR and eikonal term.
    psnr: f32,
    eikonal_loss: f32,
    /// The last step's distortion loss (its weighted part of the loss).
    distortion_loss: f32,
    /// Every validation's scores, for the summary.
    history: Vec<serde_json::Value>,
    /// The first of the block's validation times not reached yet.
    next_val_time: usize,
    /// Rays of the next step (all ranks'): `batch`, or adapted to `batch_samples`.
    rays: usize,
    /// The training views' colour transforms (`appearance: true`).
    appearance: Option<Appearance>,
    /// The memory the steps reuse, and the last step's gradient.
    workspace: StepWorkspace,
}

impl VolumeObjective<'_> {
    /// Rebuilds (or updates) the occupancy grid when its schedule says so, and at once when a resumed
    /// run starts past the warm-up.
    fn update_grid(&mut self, step: u32, params: &[f32], ui: &Ui) -> Result<()> {
        let Some(g) = &self.plan.grid else {
            return Ok(());
        };
        if step < g.warmup || (self.grid.is_some() && !(step - g.warmup).is_multiple_of(g.every)) {
            return Ok(());
        }
        let t = Instant::now();
        let (bounds, resolution, mode) = (g.grid.bounds, g.grid.resolution, self.step_settings.mode);
        let (ema, rng) = (&mut self.ema, &mut self.ema_rng);
        let built = g.grid.space.with_grid_field(
            &self.fields.fine.bind_density(params),
            (bounds, resolution),
            (mode, g.grid.thickness),
            |density| {
                Ok(match (g.update, ema) {
                    (GridUpdate::Rebuild, _) => OccupancyGrid::build_for_training(
                        density,
                        bounds,
                        resolution,
                        mode,
                        g.grid.threshold,
                    )?,
                    (GridUpdate::Ema { decay, fraction }, Some(state)) => {
                        state.update(density, decay, fraction, rng)?;
                        state.grid(mode, g.grid.threshold)?
                    }
                    (GridUpdate::Ema { .. }, state @ None) => state
                        .insert(DensityEma::sampled(density, bounds, resolution, rng)?)
                        .grid(mode, g.grid.threshold)?,
                })
            },
        )?;
        let built = built.in_space(g.grid.space);
        // Every rebuild is reported; running updates every 16th time.
        let updates = (step - g.warmup) / g.every;
        if g.update == GridUpdate::Rebuild || updates.is_multiple_of(16) {
            let verb = match g.update {
                GridUpdate::Rebuild => "rebuilt",
                GridUpdate::Ema { .. } => "updated",
            };
            ui.report(format!(
                "step {step}: occupancy grid {verb} in {:.2} s, {:.1}% of the cells occupied",
                t.elapsed().as_secs_f64(),
                100.0 * built.occupancy()
            ));
        }
        self.grid = Some(built);
        Ok(())
    }

    /// Scores the held-out views when the block's validation is due after `p`'s step.
    fn validate(&mut self, p: &Progress, params: &[f32], ui: &mut Ui) -> Result<()> {
        let (Some(v), Some(val)) = (&self.plan.validation, self.val_views) else {
            return Ok(());
        };
        let marks_before = self.next_val_time;
        while v
            .at_seconds
            .get(self.next_val_time)
            .is_some_and(|&t| p.train_seconds >= t)
        {
            self.next_val_time += 1;
        }
        let time_mark = self.next_val_time > marks_before;
        // An interrupted run stops at once: it is not validated.
        if !(p.done.is_multiple_of(v.every) || time_mark || (p.last && !p.interrupted)) {
            return Ok(());
        }
        // In an MPI job the ranks (which agree on the step and the training time) share the views; rank 0,
        // which alone reports and logs, gets every score.
        let render = crate::training::validation::field_renderer(
            self.fields,
            params,
            &self.step_settings,
            self.grid.as_ref(),
        );
        let Some(scores) = crate::training::validation::score_on_ranks(val, &render)? else {
            return Ok(());
        };
        let means = crate::training::validation::means(&scores);
        let (psnr, ssim) = (means.psnr, means.ssim);
        let masked = means
            .masked_psnr
            .map_or(String::new(), |m| format!(", masked PSNR {m:.2} dB"));
        ui.report(format!(
            "step {}: val PSNR {psnr:.2} dB, SSIM {ssim:.4}{masked} ({} views) after {:.0} s of training",
            p.done,
            val.cameras.len(),
            p.train_seconds
        ));
        self.history.push(serde_json::json!({
            "step": p.done, "train_seconds": p.train_seconds, "val_psnr": psnr, "val_ssim": ssim,
            "val_masked_psnr": means.masked_psnr,
        }));
        ui.record(&VolumeRecord {
            step: p.done,
            train_seconds: p.train_seconds,
            val_psnr: Some(psnr),
            val_ssim: Some(ssim),
            ..VolumeRecord::default()
        })
    }

    /// The progress record of `p`'s step (every 10th step and the last), logged and shown on the bar.
    fn record(&self, p: &Progress, ui: &mut Ui) -> Result<Option<serde_json::Value>> {
        if !(p.done.is_multiple_of(10) || p.last) {
            return Ok(None);
        }
        let steps_per_s = f64::from(p.done - p.first) / p.wall_seconds;
        let val_psnr = self.history.last().and_then(|h| h["val_psnr"].as_f64());
        let record = serde_json::json!({
            "step": p.done, "steps": p.steps, "loss": p.loss, "psnr": self.psnr,
            "val_psnr": val_psnr, "train_seconds": p.train_seconds, "steps_per_s": steps_per_s,
            "eta_seconds": f64::from(p.steps - p.done) / steps_per_s,
        });
        let eikonal = self.plan.eikonal.is_some().then_some(self.eikonal_loss);
        ui.record(&VolumeRecord {
            step: p.done,
            train_seconds: p.train_seconds,
            lr: Some(p.lr),
            loss: Some(p.loss),
            psnr: Some(self.psnr),
            eikonal,
            distortion: (self.plan.distortion > 0.0).then_some(self.distortion_loss),
            ..VolumeRecord::default()
        })?;
        ui.message(format!(
            "loss {:.5} PSNR {:.2} dB{}{} {:.0}k rays/s",
            p.loss,
            self.psnr,
            val_psnr.map_or(String::new(), |v| format!(" val {v:.2} dB")),
            eikonal.map_or(String::new(), |e| format!(" eikonal {e:.5}")),
            steps_per_s * self.rays as f64 / 1e3
        ));
        Ok(Some(record))
    }
}

impl Objective for VolumeObjective<'_> {
    fn occupancy(&self) -> Option<&OccupancyGrid> {
        self.grid.as_ref()
    }

    fn appearance(&self) -> Option<Vec<f32>> {
        self.appearance.as_ref().map(Appearance::state)
    }

    fn start(&mut self, first: u32, _params: &[f32], ui: &Ui) -> Result<()> {
        // A resumed run goes on with the colour transforms its checkpoint kept.
        if let (Some(appearance), Some(path), true) = (&mut self.appearance, &self.plan.checkpoint, first > 0)
        {
            if let Some(state) = crate::checkpoint::saved_appearance(path)? {
                *appearance = Appearance::from_state(self.views.len(), &state, self.plan.optimizer)?;
            }
        }
        let Some(
            g @ TrainingGrid {
                seed: Some(dilation), ..
            },
        ) = &self.plan.grid
        else {
            return Ok(());
        };
        if first >= g.warmup {
            return Ok(());
        }
        let points = self.plan.data.sparse_points()?;
        let in_grid: Vec<[f32; 3]> = points.iter().map(|&p| g.grid.space.point(p)).collect();
        let seeded = OccupancyGrid::from_points(g.grid.bounds, g.grid.resolution, &in_grid, *dilation)?
            .in_space(g.grid.space);
        ui.report(format!(
            "occupancy grid seeded from {} sparse points: {:.1}% of the cells occupied until step {}",
            points.len(),
            100.0 * seeded.occupancy(),
            g.warmup
        ));
        self.grid = Some(seeded);
        Ok(())
    }

    fn gradient(&mut self, step: u32, lr: f32, params: &[f32], ui: &Ui) -> Result<Gradient<'_>> {
        self.update_grid(step, params, ui)?;
        let plan = self.plan;
        let view = match plan.views {
            ViewChoice::Random => self.step_rng.below(self.views.len() as u64) as usize,
            ViewChoice::Cycle | ViewChoice::All => step as usize % self.views.len(),
        };
        let settings = match plan.random_background {
            true => VolumeSettings {
                background: Some([(); 3].map(|_| self.step_rng.next_f32())),
                ..self.step_settings
            },
            false => self.step_settings,
        };
        // Each rank of an MPI job draws its own part of the step's rays.
        let (rank, ranks) = (crate::cluster::current().rank(), crate::cluster::current().size());
        let (count, seed) = (
            crate::cluster::part(self.rays, rank, ranks),
            plan.seed
                .wrapping_add(u64::from(step))
                .wrapping_add((rank as u64) << 32),
        );
        let (rays, targets) = match plan.views {
            ViewChoice::All => self.views.random_rays_across(count, seed, settings.background)?,
            _ => self
                .views
                .random_rays_on(view, count, seed, settings.background)?,
        };
        let jitter = if plan.jitter { Some(&mut self.rng) } else { None };
        let fields = self.fields.bind(params);
        let model = TrainableModel {
            recompute_forward: plan.recompute_forward,
            appearance: self.appearance.as_ref().map(|a| a.of(view)),
            distortion: plan.distortion,
            ..fields.trainable()
        };
        let grid = self.grid.as_ref();
        let result = model.step(&rays, &targets, &settings, grid, jitter, &mut self.workspace)?;
        if let (Some(appearance), Some(mut grads)) = (&mut self.appearance, result.appearance_grads) {
            // The ranks' mean, as for the field's params: every rank takes the same step.
            if ranks > 1 {
                crate::cluster::current().all_reduce_sum(&mut grads);
                grads.iter_mut().for_each(|g| *g /= ranks as f32);
            }
            if grads.iter().all(|g| g.is_finite()) {
                appearance.step(view, grads, lr)?;
            }
        }
        if let (Some(e), Some(k)) = (&plan.eikonal, self.regularizers) {
            let reg = &e.regularizers;
            let points = match &self.grid {
                Some(grid) if e.occupied => occupied_points(&mut self.rng, reg.points, reg.bound, grid),
                _ => uniform_points(&mut self.rng, reg.points, reg.bound),
            };
            let threads = rayon::current_num_threads();
            let grads = self.workspace.grads_mut();
            let [_, eikonal] = reg.add_at(k, &points, params, grads, threads);
            self.eikonal_loss = eikonal;
        }
        self.psnr = result.psnr;
        self.distortion_loss = result.distortion_loss;
        if let Some(target) = plan.batch_samples {
            // This rank's samples stand for every rank's; at most a view's pixels a step (the distinct
            // pixels of one view, unless `views: all`).
            let pixels = self.views.width as usize * self.views.height as usize;
            let limits = (
                ranks.max(1),
                (MAX_SAMPLES_PER_STEP / plan.samples.max(1)).min(pixels),
            );
            self.rays = next_ray_count(self.rays, result.samples * ranks, target, limits);
        }
        Ok(Gradient {
            loss: result.loss,
            grads: self.workspace.grads_mut(),
            samples: result.samples,
        })
    }

    fn after_step(&mut self, p: &Progress, params: &[f32], ui: &mut Ui) -> Result<()> {
        self.validate(p, params, ui)?;
        let record = self.record(p, ui)?;
        if let Some(live) = self.live {
            live.after_step(p.done, p.last, params, record, ui.watch());
        }
        if let Some(path) = &self.plan.preview {
            if p.done.is_multiple_of(self.plan.preview_every) || (p.last && !p.interrupted) {
                self.plan.write_preview(
                    path,
                    self.views,
                    self.fields,
                    params,
                    &self.step_settings,
                    self.grid.as_ref(),
                )?;
            }
        }
        Ok(())
    }
}

/// Where a step's rays come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum ViewChoice {
    /// One view, the views in turn.
    Cycle,
    /// One view drawn at random.
    Random,
    /// Each ray from a view and pixel drawn at random among all (instant-ngp's and nerfstudio's batches).
    All,
}

/// The rays of the next step when steps are sized in samples: the last step's `rays` scaled by
/// `target / evaluated` (doubled when no sample was evaluated), in multiples of 64 above 64, within
/// `min..=max`. instant-ngp sizes its steps the same way, so that a step's work stays the same as the
/// occupancy grid empties.
fn next_ray_count(rays: usize, evaluated: usize, target: usize, (min, max): (usize, usize)) -> usize {
    let scaled = match evaluated {
        0 => rays.saturating_mul(2),
        _ => (rays as f64 * target as f64 / evaluated as f64).round() as usize,
    };
    let rounded = match scaled > 64 {
        true => scaled.div_ceil(64).saturating_mul(64),
        false => scaled,
    };
    rounded.clamp(min.max(1), max.max(min).max(1))
}

/// The params of `program` with their values, one per line.
pub fn describe_params(program: &Program, params: &[f32]) -> String {
    program
        .params
        .iter()
        .map(|p| {
            let values = &params[p.offset..p.offset + p.ty.scalars()];
            if values.len() <= 8 {
                let v: Vec<String> = values.iter().map(|x| format!("{x:.4}")).collect();
                format!("  {} = [{}]", p.name, v.join(", "))
            } else {
                format!("  {}: {} values", p.name, values.len())
            }
        })
        .collect::<Vec<_>>()
        .join("\n")
}

/// The params of `program` by name, as JSON (a grid encoding's table as its type, size and mean |value|).
pub fn params_json(program: &Program, params: &[f32]) -> serde_json::Value {
    let map: serde_json::Map<String, serde_json::Value> = program
        .params
        .iter()
        .map(|p| {
            let values = &params[p.offset..p.offset + p.ty.scalars()];
            let value = match p.ty {
                // A grid's table (millions of floats) stays in the checkpoint; the summary describes it.
                nerfjit_dsl::Type::Grid(_) => serde_json::json!({
                    "type": p.ty.to_string(),
                    "values": values.len(),
                    "mean_abs": values.iter().map(|x| f64::from(x.abs())).sum::<f64>() / values.len().max(1) as f64,
                }),
                _ => serde_json::json!(values),
            };
            (p.name.clone(), value)
        })
        .collect();
    serde_json::Value::Object(map)
}

#[cfg(test)]
mod tests {
    use super::next_ray_count;

    #[test]
    fn ray_counts_scale_to_the_target_in_multiples_of_64() {
        // 1,024 rays evaluated 4 samples each: 16,384 rays give 65,536.
        assert_eq!(next_ray_count(1024, 4096, 65536, (1, 1 << 20)), 16384);
        // 128 samples a ray (before the grid exists): 512 rays.
        assert_eq!(next_ray_count(1024, 131_072, 65536, (1, 1 << 20)), 512);
        // Rounded up to a multiple of 64 above 64, kept as it is below.
        assert_eq!(next_ray_count(1000, 1000, 1001, (1, 1 << 20)), 1024);
        assert_eq!(next_ray_count(10, 100, 300, (1, 1 << 20)), 30);
    }

    #[test]
    fn ray_counts_stay_within_their_limits() {
        assert_eq!(
            next_ray_count(1024, 0, 65536, (1, 1 << 20)),
            2048,
            "nothing evaluated: doubled"
        );
        assert_eq!(next_ray_count(1 << 19, 1, 1 << 26, (1, 1 << 19)), 1 << 19);
        assert_eq!(next_ray_count(usize::MAX, 0, 1, (2, 100)), 100);
        assert_eq!(
            next_ray_count(4, 1 << 20, 256, (2, 100)),
            2,
            "never fewer rays than ranks"
        );
    }
}
