//! `train { ... }`: fits the script's params to images by differentiable volume rendering, with Adam,
//! checkpoints (atomic, resumable), a NaN guard, preview renders and a JSON summary.

use std::path::{Path, PathBuf};
use std::time::Instant;

use indicatif::{ProgressBar, ProgressStyle};
use nerfjit_dsl::config::{Spanned, Value};
use nerfjit_dsl::{Diagnostic, Program};
use nerfjit_jit::KernelCache;
use nerfjit_runtime::{
    load_blender_views, rgb_image, save_png, volume_step_with, DensityEma, DepthSpacing, FinePass,
    OccupancyGrid, Quantize, Rng, Schedule, StepOptions, Views, VolumeSettings,
};

use crate::block::Block;
use crate::data_source::{data_path, data_set, DataKind, DataSet};
use crate::failure::{Failure, Result};
use crate::field::{VolumeField, VolumeFields};
use crate::interrupt::Watch;
use crate::metrics_log::RunLog;
use crate::regularizers::{occupied_points, uniform_points, RegularizerKernels, Regularizers};
use crate::settings::CallArgs;
use crate::viewer::Live;

/// The columns of a volume training run's metrics log.
const LOG_COLUMNS: &[&str] = &[
    "step",
    "train_seconds",
    "lr",
    "loss",
    "psnr",
    "eikonal",
    "val_psnr",
    "val_ssim",
];

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
    batch: usize,
    schedule: Schedule,
    /// Adam's decay rates and ε.
    optimizer: AdamSettings,
    random_views: bool,
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
    /// Empty-space skipping during training: an occupancy grid of the (fine) field, rebuilt every
    /// `every` steps from step `warmup` on.
    grid: Option<TrainingGrid>,
    /// Training rays stop once their transmittance is below this (later samples are neither evaluated
    /// nor back-propagated); validation stops rays the same way, previews are exact.
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

/// The `skip_empty`, `grid_every`, `grid_warmup`, `grid_update` and `grid_seed` settings.
#[derive(Clone, Copy, Debug)]
struct TrainingGrid {
    grid: crate::volume::SkipEmpty,
    every: u32,
    warmup: u32,
    update: GridUpdate,
    /// Before the warm-up, the cells within this many cells of the data's sparse points.
    seed: Option<usize>,
}

/// The `grid_seed` setting: `points` or `points(dilate: n)` (n cells around each point, 2 by default;
/// 0 to 16), or `none`.
pub(crate) fn grid_seed(v: &Spanned) -> std::result::Result<Option<usize>, Diagnostic> {
    let hint = "write points or points(dilate: 2)";
    match &v.value {
        Value::Name(n) if n == "none" => Ok(None),
        Value::Name(n) if n == "points" => Ok(Some(2)),
        Value::Call(n, _) if n == "points" => {
            let a = CallArgs::new(v, &["dilate"])?;
            let dilate = match a.raw("dilate") {
                Some(d) => crate::settings::whole(d, 0, 16)?,
                None => 2,
            };
            Ok(Some(dilate as usize))
        }
        _ => Err(
            Diagnostic::new(v.span, format!("expected a grid seed, found {}", v.describe())).with_hint(hint),
        ),
    }
}

/// How a training grid follows the field: rebuilt from probes of every cell, or instant-ngp's running
/// maximum refreshed at random points (`grid_update: ema(decay: 0.95, fraction: 0.125)`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum GridUpdate {
    /// Probes of every cell, dilated by a cell.
    Rebuild,
    /// The running maximum, its decay per update and the fraction of the cells each update probes.
    Ema { decay: f32, fraction: f32 },
}

/// The `grid_update` setting: `rebuild` (the default) or `ema(decay: 0.95, fraction: 0.125)` (both
/// arguments optional).
pub(crate) fn grid_update(v: Option<Spanned>) -> std::result::Result<GridUpdate, Diagnostic> {
    let Some(v) = v else {
        return Ok(GridUpdate::Rebuild);
    };
    let hint = "write rebuild or ema(decay: 0.95, fraction: 0.125)";
    match &v.value {
        Value::Name(name) if name == "rebuild" => return Ok(GridUpdate::Rebuild),
        Value::Name(name) if name == "ema" => {}
        Value::Call(name, _) if name == "ema" => {}
        _ => {
            return Err(
                Diagnostic::new(v.span, format!("expected a grid update, found {}", v.describe()))
                    .with_hint(hint),
            )
        }
    }
    let (decay, fraction) = match &v.value {
        Value::Call(..) => {
            let a = CallArgs::new(&v, &["decay", "fraction"])?;
            let arg = |slot: &str, lo: f64, default: f64| match a.raw(slot) {
                None => Ok(default),
                Some(x) => crate::settings::ranged(x, lo, 1.0),
            };
            (arg("decay", 0.0, 0.95)?, arg("fraction", 1e-6, 0.125)?)
        }
        _ => (0.95, 0.125),
    };
    Ok(GridUpdate::Ema {
        decay: decay as f32,
        fraction: fraction as f32,
    })
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

/// The `val_minutes` setting: one number or a list of them, in minutes of training, as seconds in order.
pub(crate) fn minutes_list(v: &Spanned) -> std::result::Result<Vec<f64>, Diagnostic> {
    let items = match &v.value {
        Value::List(items) => items
            .iter()
            .map(|x| crate::settings::ranged(x, 0.0, 1e6))
            .collect(),
        _ => crate::settings::ranged(v, 0.0, 1e6).map(|x| vec![x]),
    };
    let mut seconds: Vec<f64> = items?.into_iter().map(|m| 60.0 * m).collect();
    seconds.sort_by(f64::total_cmp);
    Ok(seconds)
}

/// The `val` setting: `holdout(every: 8)` (every n-th view of the data, 0, n, 2n, …, kept from training) or
/// a Blender camera file (with Blender data).
fn held_out(v: &Spanned, data: &DataSet, script_dir: &Path) -> std::result::Result<HeldOut, Diagnostic> {
    if let Value::Call(name, _) = &v.value {
        if name == "holdout" {
            let a = CallArgs::new(v, &["every"])?;
            let every = a
                .raw("every")
                .map(|n| crate::settings::whole(n, 2, 1000))
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

/// The cameras of the data the first `train` block of `program` trains on (a script in `script_dir`), if
/// it names data whose camera file can be read.
pub fn data_cameras(program: &Program, script_dir: &Path) -> Option<Vec<nerfjit_runtime::Camera>> {
    let block = program
        .blocks()
        .into_iter()
        .find(|b| crate::schema::kind_of(b) == Some(crate::schema::Kind::Train))?;
    let data = nerfjit_dsl::config::Settings::new(program, block)
        .ok()?
        .take("data")?;
    data_set(&data, script_dir).ok()?.cameras().ok()
}

/// Adam's decay rates and ε: the `optimizer` setting.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AdamSettings {
    /// Decay of the first moment.
    pub beta1: f32,
    /// Decay of the second moment.
    pub beta2: f32,
    /// Added to √v̂ in the denominator.
    pub eps: f32,
    /// Whether grid tables are updated as PyTorch's SparseAdam updates them (entries with a zero gradient
    /// left alone), as instant-ngp does.
    pub sparse: bool,
}

impl Default for AdamSettings {
    /// Kingma and Ba's defaults: β = (0.9, 0.999), ε = 1e-8.
    fn default() -> AdamSettings {
        AdamSettings {
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
            sparse: false,
        }
    }
}

/// The `optimizer` setting: `adam(beta1: 0.9, beta2: 0.99, eps: 1e-15, sparse: true)` (every argument
/// optional, the default Adam when the setting is absent).
pub(crate) fn optimizer(v: Option<Spanned>) -> std::result::Result<AdamSettings, Diagnostic> {
    let defaults = AdamSettings::default();
    let Some(v) = v else {
        return Ok(defaults);
    };
    let hint = "write adam(beta1: 0.9, beta2: 0.99, eps: 1e-15, sparse: true)";
    match &v.value {
        Value::Call(name, _) if name == "adam" => {}
        Value::Name(name) if name == "adam" => return Ok(defaults),
        _ => {
            return Err(
                Diagnostic::new(v.span, format!("expected an optimizer, found {}", v.describe()))
                    .with_hint(hint),
            )
        }
    }
    let a = CallArgs::new(&v, &["beta1", "beta2", "eps", "sparse"])?;
    let decay = |slot: &str, default: f32| -> std::result::Result<f32, Diagnostic> {
        match a.raw(slot) {
            None => Ok(default),
            Some(x) => Ok(crate::settings::ranged(x, 0.0, 0.999_999)? as f32),
        }
    };
    let eps = match a.raw("eps") {
        None => defaults.eps,
        Some(x) => crate::settings::ranged(x, 1e-30, 1.0)? as f32,
    };
    Ok(AdamSettings {
        beta1: decay("beta1", defaults.beta1)?,
        beta2: decay("beta2", defaults.beta2)?,
        eps,
        sparse: a.choice("sparse", &["true", "false"], "false")? == "true",
    })
}

pub(crate) fn schedule(v: Option<Spanned>, lr: f32) -> std::result::Result<Schedule, Diagnostic> {
    let Some(v) = v else {
        return Ok(Schedule::Constant { lr });
    };
    if let Value::Name(n) = &v.value {
        if n == "constant" {
            return Ok(Schedule::Constant { lr });
        }
    }
    let Value::Call(name, _) = &v.value else {
        return Err(
            Diagnostic::new(v.span, format!("expected a schedule, found {}", v.describe())).with_hint(
                "write constant, exponential(gamma: 0.1, every: 1000) or step(factor: 0.8, every: 50)",
            ),
        );
    };
    let a = CallArgs::new(&v, &["gamma", "factor", "every"])?;
    let every = a.number("every", None)?;
    if every < 1.0 || every.fract() != 0.0 {
        return Err(Diagnostic::new(
            v.span,
            "'every' must be a whole number of steps ≥ 1",
        ));
    }
    match name.as_str() {
        "exponential" => Ok(Schedule::Exponential {
            lr,
            gamma: a.number("gamma", None)? as f32,
            steps_per_decay: every as u32,
        }),
        "step" => Ok(Schedule::Step {
            lr,
            factor: a.number("factor", None)? as f32,
            every: every as u32,
        }),
        other => Err(Diagnostic::new(v.span, format!("unknown schedule '{other}'"))
            .with_hint("use constant, exponential(gamma, every) or step(factor, every)")),
    }
}

impl TrainPlan {
    /// Reads and checks a `train` block.
    pub fn new(mut b: Block) -> Result<TrainPlan> {
        let data_v = b.required("data")?;
        let data = data_set(&data_v, b.script_dir()).map_err(|d| b.error(d))?;
        let (near, far) = b.near_far()?;
        let lr = b.number("lr")? as f32;
        let samples = b.whole("samples")? as usize;
        let spacing = b.spacing(near, far)?;
        let steps = b.whole("steps")? as u32;
        let minutes = b.number("minutes")?;
        let time_limit = (minutes > 0.0).then_some(60.0 * minutes);
        let batch = b.whole("batch")? as usize;
        if batch * samples > MAX_SAMPLES_PER_STEP {
            return Err(b.block_error(format!(
                "{batch} rays × {samples} samples is too many for one step (the limit is {MAX_SAMPLES_PER_STEP} samples)"
            )));
        }
        let seed = b.whole("seed")?;
        let checkpoint_every = b.whole("checkpoint_every")? as u32;
        let preview_every = b.whole("preview_every")? as u32;
        let eikonal_weight = b.number("eikonal_weight")? as f32;
        let eikonal_points = b.whole("eikonal_points")? as usize;
        let eikonal_bounds = b.number("eikonal_bounds")? as f32;
        let sdf = b.function("sdf")?;
        let occupied = b.choice("eikonal_sampling")?.as_deref() == Some("occupied");
        let eikonal = (eikonal_weight > 0.0).then_some(Eikonal {
            sdf,
            regularizers: Regularizers {
                points: eikonal_points,
                bound: eikonal_bounds,
                near_weight: 0.0,
                near_sharpness: 0.0,
                eikonal_weight,
            },
            occupied,
        });
        let background = b.triple("background")?;
        let schedule = schedule(b.take("schedule"), lr).map_err(|d| b.error(d))?;
        let optimizer = optimizer(b.take("optimizer")).map_err(|d| b.error(d))?;
        let random_views = b.choice("views")?.as_deref() == Some("random");
        let jitter = b.flag("jitter")?;
        let checkpoint = b.output("checkpoint")?;
        let log = b.output("log")?;
        let tensorboard = b.output("tensorboard")?;
        let summary = b.output("summary")?;
        let preview = b.output("preview")?;
        let validation = match b.take("val") {
            Some(v) => {
                let held_out = held_out(&v, &data, b.script_dir()).map_err(|d| b.error(d))?;
                let every = b.whole("val_every")? as u32;
                let views = b.whole_or_none("val_views")?.map(|n| n as usize);
                let at_seconds = match b.take("val_minutes") {
                    Some(v) => minutes_list(&v).map_err(|d| b.error(d))?,
                    None => Vec::new(),
                };
                Some(Validation {
                    held_out,
                    every,
                    at_seconds,
                    views,
                })
            }
            None => None,
        };
        let importance = b.whole("importance")? as usize;
        let skip_empty = match b.take("skip_empty") {
            None => None,
            Some(v) => crate::volume::skip_empty(&v).map_err(|d| b.error(d))?,
        };
        let every = b.whole("grid_every")? as u32;
        let warmup = b.whole("grid_warmup")? as u32;
        let update = grid_update(b.take("grid_update")).map_err(|d| b.error(d))?;
        let grid_seeding = match b.take("grid_seed") {
            Some(v) => {
                let seed = grid_seed(&v).map_err(|d| b.error(d))?;
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
            every,
            warmup,
            update,
            seed: grid_seeding,
        });
        let early_termination = b.number("early_termination")? as f32;
        b.finish()?;
        Ok(TrainPlan {
            early_termination: (early_termination > 0.0).then_some(early_termination),
            data,
            near,
            far,
            samples,
            spacing,
            background,
            steps,
            time_limit,
            batch,
            schedule,
            optimizer,
            random_views,
            jitter,
            seed,
            checkpoint,
            checkpoint_every,
            log,
            tensorboard,
            summary,
            preview,
            preview_every,
            eikonal,
            validation,
            importance,
            grid,
        })
    }

    fn settings(&self, field: &VolumeField) -> VolumeSettings {
        VolumeSettings {
            near: self.near,
            far: self.far,
            samples: self.samples,
            mode: field.mode,
            background: self.background,
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
    /// returns the ms per step of the training loop alone.
    pub fn run_steps(&self, program: &Program, params: &mut Vec<f32>, steps: u32) -> Result<String> {
        let quiet = TrainPlan {
            steps,
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
        let line = quiet.run(program, params, &KernelCache::new(), false, None)?;
        Ok(line.lines().next().unwrap_or_default().to_string())
    }

    /// The training views and the held-out views validation scores (if the block asks for validation).
    pub fn load_views(&self) -> Result<(Views, Option<Views>)> {
        let mut views = self.data.views()?;
        let val_views = match self.validation.as_ref().map(|v| (&v.held_out, v.views)) {
            Some((HeldOut::Every(n), limit)) => {
                let (train, mut held) = views.hold_out(*n)?;
                views = train;
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

    /// Trains `params` in place (resuming from the checkpoint when asked, compiling through `cache`),
    /// publishing its progress and params to a live viewer when given; returns a summary line.
    pub fn run(
        &self,
        program: &Program,
        params: &mut Vec<f32>,
        cache: &KernelCache,
        resume: bool,
        live: Option<&Live>,
    ) -> Result<String> {
        let (views, val_views) = self.load_views()?;
        let mut history: Vec<serde_json::Value> = Vec::new();
        let mut val_message = String::new();
        let mut train_seconds = 0.0f64;
        // Samples evaluated by the steps of this run.
        let mut samples = 0usize;

        let t = Instant::now();
        let fields = VolumeFields::compile(program, cache, self.importance)?;
        let field = &fields.fine;
        let regularizer_kernels = match &self.eikonal {
            Some(e) => Some(RegularizerKernels::compile(
                program,
                &e.sdf,
                &e.regularizers,
                cache,
            )?),
            None => None,
        };
        let compile_s = t.elapsed().as_secs_f64();
        let threads = rayon::current_num_threads();
        let mut eikonal_loss = 0.0f32;
        let settings = self.settings(field);
        let step_settings = VolumeSettings {
            early_termination: self.early_termination,
            ..settings
        };
        // The params before a step, to restore if the step makes one non-finite (kept between steps).
        let mut before = Vec::with_capacity(params.len());
        let (mut adam, first) = crate::checkpoint::resume_or_start(
            program,
            self.checkpoint.as_deref(),
            resume,
            params,
            self.optimizer,
            |k| self.schedule.lr(k),
        )?;
        let mut log = RunLog::open(
            self.log.as_deref(),
            self.tensorboard.as_deref(),
            LOG_COLUMNS,
            first > 0,
        )?;
        let watch = Watch::start();
        let bar = step_bar(self.steps, "training");
        bar.set_position(u64::from(first));
        let mut rng = Rng::new(self.seed ^ 0x5eed);
        let start = Instant::now();
        let mut grid: Option<OccupancyGrid> = match &self.grid {
            Some(
                g @ TrainingGrid {
                    seed: Some(dilation), ..
                },
            ) if first < g.warmup => {
                let points = self.data.sparse_points()?;
                let seeded =
                    OccupancyGrid::from_points(g.grid.bounds, g.grid.resolution, &points, *dilation)?;
                let line = format!(
                    "occupancy grid seeded from {} sparse points: {:.1}% of the cells occupied until step {}",
                    points.len(),
                    100.0 * seeded.occupancy(),
                    g.warmup
                );
                report(&bar, line);
                Some(seeded)
            }
            _ => None,
        };
        // The running occupancy of `grid_update: ema` and the random points of its updates.
        let mut ema: Option<DensityEma> = None;
        let mut ema_rng = Rng::new(self.seed ^ 0x0cc0);
        let (mut loss, mut psnr) = (f32::NAN, f32::NAN);
        let mut done = first;
        let mut next_val_time = 0;
        for step in first..self.steps {
            let step_start = Instant::now();
            let view = if self.random_views {
                rng.below(views.len() as u64) as usize
            } else {
                step as usize % views.len()
            };
            let (rays, targets) =
                views.random_rays(view, self.batch, self.seed.wrapping_add(u64::from(step)))?;
            let (forward, backward) = field.bind(params);
            if let Some(g) = &self.grid {
                // Rebuilt on schedule, and at once when a resumed run starts past the warm-up.
                if step >= g.warmup && (grid.is_none() || (step - g.warmup) % g.every == 0) {
                    let t = Instant::now();
                    let density = field.bind_density(params);
                    let (bounds, resolution) = (g.grid.bounds, g.grid.resolution);
                    let built = match (g.update, &mut ema) {
                        (GridUpdate::Rebuild, _) => OccupancyGrid::build_for_training(
                            &density,
                            bounds,
                            resolution,
                            settings.mode,
                            g.grid.threshold,
                        )?,
                        (GridUpdate::Ema { decay, fraction }, Some(state)) => {
                            state.update(&density, decay, fraction, &mut ema_rng)?;
                            state.grid(settings.mode, g.grid.threshold)?
                        }
                        (GridUpdate::Ema { .. }, state @ None) => state
                            .insert(DensityEma::sampled(&density, bounds, resolution, &mut ema_rng)?)
                            .grid(settings.mode, g.grid.threshold)?,
                    };
                    // Every rebuild is reported; running updates every 16th time.
                    let updates = (step - g.warmup) / g.every;
                    if g.update == GridUpdate::Rebuild || updates % 16 == 0 {
                        let verb = match g.update {
                            GridUpdate::Rebuild => "rebuilt",
                            GridUpdate::Ema { .. } => "updated",
                        };
                        let line = format!(
                            "step {step}: occupancy grid {verb} in {:.2} s, {:.1}% of the cells occupied",
                            t.elapsed().as_secs_f64(),
                            100.0 * built.occupancy()
                        );
                        report(&bar, line);
                    }
                    grid = Some(built);
                }
            }
            let jitter = if self.jitter { Some(&mut rng) } else { None };
            let mut result = match &fields.coarse {
                None => {
                    let options = StepOptions {
                        fine: None,
                        grid: grid.as_ref(),
                    };
                    volume_step_with(
                        &rays,
                        &targets,
                        &forward,
                        &backward,
                        &step_settings,
                        options,
                        jitter,
                    )?
                }
                Some((coarse, importance)) => {
                    let (coarse_forward, coarse_backward) = coarse.bind(params);
                    let fine = FinePass {
                        field: &forward,
                        vjp: &backward,
                        importance: *importance,
                    };
                    let options = StepOptions {
                        fine: Some(&fine),
                        grid: grid.as_ref(),
                    };
                    volume_step_with(
                        &rays,
                        &targets,
                        &coarse_forward,
                        &coarse_backward,
                        &step_settings,
                        options,
                        jitter,
                    )?
                }
            };
            if let (Some(e), Some(k)) = (&self.eikonal, &regularizer_kernels) {
                let reg = &e.regularizers;
                let points = match &grid {
                    Some(grid) if e.occupied => occupied_points(&mut rng, reg.points, reg.bound, grid),
                    _ => uniform_points(&mut rng, reg.points, reg.bound),
                };
                let [_, eikonal] = reg.add_at(k, &points, params, &mut result.param_grads, threads);
                eikonal_loss = eikonal;
            }
            if !result.loss.is_finite() || result.param_grads.iter().any(|g| !g.is_finite()) {
                bar.abandon();
                return Err(crate::checkpoint::diverged(
                    program,
                    step,
                    result.loss,
                    &result.param_grads,
                    self.checkpoint.as_deref(),
                ));
            }
            adam.lr = self.schedule.lr(step);
            before.clear();
            before.extend_from_slice(params);
            let update = std::time::Instant::now();
            adam.step(params, &result.param_grads)?;
            nerfjit_jit::profile::record(nerfjit_jit::profile::Phase::Optimizer, update.elapsed());
            samples += result.samples;
            if params.iter().any(|p| !p.is_finite()) {
                params.copy_from_slice(&before);
                return Err(Failure::Message(format!(
                    "training diverged at step {step}: a param became non-finite"
                )));
            }
            (loss, psnr) = (result.loss, result.psnr);
            nerfjit_runtime::volume::train::recycle(result.param_grads);
            let step_time = step_start.elapsed();
            nerfjit_jit::profile::record(nerfjit_jit::profile::Phase::Steps, step_time);
            train_seconds += step_time.as_secs_f64();
            done = step + 1;
            let out_of_time = self.time_limit.is_some_and(|limit| train_seconds >= limit);
            let interrupted = watch.requested();
            let last = done == self.steps || out_of_time || interrupted;
            if let (Some(v), Some(val)) = (&self.validation, &val_views) {
                let marks_before = next_val_time;
                while v
                    .at_seconds
                    .get(next_val_time)
                    .is_some_and(|&t| train_seconds >= t)
                {
                    next_val_time += 1;
                }
                let time_mark = next_val_time > marks_before;
                // An interrupted run stops at once: it is not validated.
                if done % v.every == 0 || time_mark || (last && !interrupted) {
                    let (p, s) = crate::views::means(&crate::views::score(
                        val,
                        &fields,
                        params,
                        &step_settings,
                        grid.as_ref(),
                    )?);
                    val_message = format!(" val {p:.2} dB");
                    let line = format!(
                        "step {done}: val PSNR {p:.2} dB, SSIM {s:.4} ({} views) after {train_seconds:.0} s of training",
                        val.cameras.len()
                    );
                    report(&bar, line);
                    history.push(serde_json::json!({
                        "step": done, "train_seconds": train_seconds, "val_psnr": p, "val_ssim": s,
                    }));
                    let (step, seconds) = (Some(f64::from(done)), Some(train_seconds));
                    log.record(&[step, seconds, None, None, None, None, Some(p), Some(s)])?;
                }
            }
            let mut record = None;
            if done % 10 == 0 || last {
                let elapsed = start.elapsed().as_secs_f64();
                let steps_per_s = f64::from(done - first) / elapsed;
                record = Some(serde_json::json!({
                    "step": done, "steps": self.steps, "loss": loss, "psnr": psnr,
                    "val_psnr": history.last().and_then(|h| h["val_psnr"].as_f64()),
                    "train_seconds": train_seconds, "steps_per_s": steps_per_s,
                    "eta_seconds": f64::from(self.steps - done) / steps_per_s,
                }));
                let eikonal = self.eikonal.is_some().then_some(f64::from(eikonal_loss));
                log.record(&[
                    Some(f64::from(done)),
                    Some(train_seconds),
                    Some(f64::from(adam.lr)),
                    Some(f64::from(loss)),
                    Some(f64::from(psnr)),
                    eikonal,
                    None,
                    None,
                ])?;
                let rays_per_s = steps_per_s * self.batch as f64;
                bar.set_message(format!(
                    "loss {loss:.5} PSNR {psnr:.2} dB{val_message}{} {:.0}k rays/s",
                    if self.eikonal.is_some() {
                        format!(" eikonal {eikonal_loss:.5}")
                    } else {
                        String::new()
                    },
                    rays_per_s / 1e3
                ));
            }
            bar.set_position(u64::from(done));
            if let Some(live) = live {
                live.after_step(done, last, params, record, &watch);
            }
            if let Some(path) = &self.checkpoint {
                if done % self.checkpoint_every == 0 || last {
                    crate::checkpoint::write(path, program, done, params, &adam)?;
                }
            }
            if let Some(path) = &self.preview {
                if done % self.preview_every == 0 || (last && !interrupted) {
                    self.write_preview(path, &views, &fields, params, &settings)?;
                }
            }
            if interrupted {
                break;
            }
            if out_of_time {
                report(
                    &bar,
                    format!(
                        "stopped at step {done}: the time limit of {:.1} minutes is reached",
                        train_seconds / 60.0
                    ),
                );
                break;
            }
        }
        bar.finish_and_clear();
        let seconds = start.elapsed().as_secs_f64();
        let trained = done - first;
        // Validation and previews are not training: the rate counts the steps alone.
        let ms_per_step = if trained > 0 {
            1e3 * train_seconds / f64::from(trained)
        } else {
            0.0
        };
        let samples_per_s = if train_seconds > 0.0 {
            samples as f64 / train_seconds
        } else {
            0.0
        };
        let values = describe_params(program, params);
        if let Some(path) = &self.summary {
            let json = serde_json::json!({
                "data": self.data.path.display().to_string(),
                "steps": done,
                "resumed_from": first,
                "final_loss": loss,
                "final_psnr": psnr,
                "seconds": seconds,
                "ms_per_step": ms_per_step,
                "samples_per_s": samples_per_s,
                "compile_seconds": compile_s,
                "train_seconds": train_seconds,
                "validation": history,
                "params": params_json(program, params),
            });
            crate::checkpoint::write_atomic(path, &serde_json::to_string_pretty(&json).unwrap_or_default())?;
        }
        if watch.requested() {
            return Err(crate::interrupt::stopped(done, self.checkpoint.as_deref()));
        }
        Ok(format!(
            "trained {trained} steps in {seconds:.1} s ({ms_per_step:.2} ms/step, {:.2} M samples/s, JIT compile {compile_s:.3} s): loss {loss:.6}, PSNR {psnr:.2} dB\n{values}",
            samples_per_s * 1e-6
        ))
    }

    fn write_preview(
        &self,
        path: &Path,
        views: &Views,
        fields: &VolumeFields,
        params: &[f32],
        settings: &VolumeSettings,
    ) -> Result<()> {
        let frame = fields.render(&views.cameras[0], views.width, views.height, params, settings)?;
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

/// The progress bar of a training loop of `steps` steps: `verb` (e.g. "training"), the steps, the loop's
/// message, the time taken and the time to go.
pub(crate) fn step_bar(steps: u32, verb: &str) -> ProgressBar {
    ProgressBar::new(u64::from(steps)).with_style(
        ProgressStyle::with_template(&format!(
            "{{spinner}} {verb} [{{bar:30}}] {{pos}}/{{len}} {{msg}} {{elapsed}}, {{eta}} to go"
        ))
        .unwrap_or_else(|_| ProgressStyle::default_bar()),
    )
}

/// Prints a line above the progress bar, or to standard error when the bar is hidden (not a terminal).
fn report(bar: &ProgressBar, line: String) {
    if bar.is_hidden() {
        eprintln!("{line}");
    } else {
        bar.println(line);
    }
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
