//! The one training loop of `train` (volume rendering) and `train sdf` (point clouds): where to start
//! (a checkpoint or step 0), Adam steps on a learning-rate schedule, the guard against divergence, the
//! checkpoint every so many steps and at the end, the training-time limit, Ctrl-C, the progress bar and
//! the metrics log. What is trained is an [`Objective`]: it gives each step's loss and param gradient, and
//! its hooks do the rest of a block's work (an occupancy grid before a step; validation, previews, log
//! records and a live viewer after it).
//!
//! Per step k from the first (0, or the checkpoint's step when resuming) to `steps`:
//! 1. [`Objective::gradient`] at the params (with what belongs to the step's time, such as an occupancy
//!    grid's update, first);
//! 2. Adam at the schedule's rate for step k, whose pass over the params also checks them: a non-finite
//!    loss or gradient stops the run with [`crate::checkpoint::diverged`] (the checkpoint on disk is the
//!    last good one: it is only ever written after a finite step), and so does a param that would become
//!    non-finite (Adam leaves each such element as it was; the run stops before anything is written);
//! 3. [`Objective::after_step`] with the [`Progress`]; the checkpoint when due; the run ends after the last
//!    step, once the steps (hooks excluded) have taken the time limit, or when Ctrl-C asked it to.

use std::path::Path;
use std::time::Instant;

use nerfjit_dsl::Program;
use nerfjit_jit::profile::{self, Phase};
use nerfjit_runtime::Schedule;

use crate::cluster::Reduction;
use crate::failure::{Failure, Result};
use crate::interrupt::Watch;
use crate::observe::{BarKind, ProgressBar, ProgressBars};
use crate::settings::values::AdamSettings;
use crate::training::metrics_log::{LogRecord, RunLog};

/// How a block trains, whatever it trains.
pub struct LoopSettings<'a> {
    /// The step the run ends after (pre-training steps included).
    pub steps: u32,
    /// Adam's learning rate by step.
    pub schedule: &'a Schedule,
    /// Adam's decay rates and ε.
    pub optimizer: AdamSettings,
    /// Stop once the steps alone have taken this many seconds.
    pub time_limit: Option<f64>,
    /// Where the checkpoint is written (atomically), and read from when resuming.
    pub checkpoint: Option<&'a Path>,
    /// Steps between checkpoints (the last step always writes one).
    pub checkpoint_every: u32,
    /// Continue from the checkpoint when there is one.
    pub resume: bool,
    /// The metrics log (JSON Lines, or CSV).
    pub log: Option<&'a Path>,
    /// A TensorBoard folder the metrics also go to.
    pub tensorboard: Option<&'a Path>,
    /// The columns of the metrics log, the step first: the [`LogRecord::COLUMNS`] of the objective's records.
    pub log_columns: &'static [&'static str],
    /// What the progress bar says the run is doing ("training", "fitting").
    pub verb: &'a str,
    /// Where the progress bar is drawn.
    pub bars: &'a dyn ProgressBars,
}

/// One step's loss and the gradient of the params, which the objective keeps (and reuses next step).
pub struct Gradient<'a> {
    /// The loss (all terms).
    pub loss: f32,
    /// ∂loss/∂params, one per param value (the loop may lengthen it while it all-reduces, and shortens it
    /// again).
    pub grads: &'a mut Vec<f32>,
    /// Field samples the step evaluated (0 where the objective does not count them).
    pub samples: usize,
}

/// Where a run is, as hooks see it after a step.
#[derive(Clone, Copy, Debug)]
pub struct Progress {
    /// Steps done, the one just taken included.
    pub done: u32,
    /// The step the run started at (the checkpoint's when resuming).
    pub first: u32,
    /// The step the run ends after.
    pub steps: u32,
    /// Seconds taken by the steps of this run (hooks excluded).
    pub train_seconds: f64,
    /// Seconds since the loop started (hooks included).
    pub wall_seconds: f64,
    /// The learning rate of the step just taken.
    pub lr: f32,
    /// The step's loss.
    pub loss: f32,
    /// Whether this is the run's last step (the steps are done, the time is up, or Ctrl-C was pressed).
    pub last: bool,
    /// Whether Ctrl-C (or SIGTERM) asked the run to stop.
    pub interrupted: bool,
}

/// What hooks may use of the loop: its progress bar, its metrics log and its signal watch.
pub struct Ui {
    bar: Box<dyn ProgressBar>,
    log: RunLog,
    watch: Watch,
}

impl Ui {
    /// Prints a line above the progress bar (or to standard error when there is no terminal).
    pub fn report(&self, line: String) {
        self.bar.println(line);
    }

    /// Sets the progress bar's message.
    pub fn message(&self, message: String) {
        self.bar.set_message(message);
    }

    /// Writes one record to the metrics log (whose columns are the record's, [`LoopSettings::log_columns`]).
    pub fn record<R: LogRecord>(&mut self, record: &R) -> Result<()> {
        debug_assert_eq!(R::COLUMNS, self.log.columns(), "a record of another log");
        self.log.record(&record.values())
    }

    /// The run's claim on Ctrl-C (a live viewer's pause ends when it is pressed).
    pub fn watch(&self) -> &Watch {
        &self.watch
    }
}

/// What a training loop trains.
pub trait Objective {
    /// Called once before the first step, `first` being the step the run starts at.
    fn start(&mut self, _first: u32, _params: &[f32], _ui: &Ui) -> Result<()> {
        Ok(())
    }

    /// The loss of step `step` at `params` and its gradient, after the work that belongs to the step's
    /// time (e.g. updating an occupancy grid, which may report to `ui`); `lr` is the step's learning rate,
    /// for what the objective trains itself beside the params.
    fn gradient(&mut self, step: u32, lr: f32, params: &[f32], ui: &Ui) -> Result<Gradient<'_>>;

    /// Work after each step, outside the training time: log records, validation, previews, viewers.
    fn after_step(&mut self, progress: &Progress, params: &[f32], ui: &mut Ui) -> Result<()>;

    /// The occupancy grid the objective renders with now (validation included), kept in checkpoints.
    fn occupancy(&self) -> Option<&nerfjit_runtime::OccupancyGrid> {
        None
    }

    /// The state of the training views' colour transforms, if the objective learns them, kept in
    /// checkpoints (see [`crate::training::appearance`]).
    fn appearance(&self) -> Option<Vec<f32>> {
        None
    }
}

/// How a run ended.
#[derive(Clone, Copy, Debug)]
pub struct Finished {
    /// The step the run started at.
    pub first: u32,
    /// Steps done (the checkpoint holds the params after this many).
    pub done: u32,
    /// The last step's loss (NaN if no step was taken).
    pub loss: f32,
    /// Seconds taken by the steps of this run.
    pub train_seconds: f64,
    /// Seconds since the loop started.
    pub wall_seconds: f64,
    /// Samples evaluated by the steps of this run.
    pub samples: usize,
    /// Whether Ctrl-C (or SIGTERM) stopped the run.
    pub interrupted: bool,
    /// Whether the resumed checkpoint already held every step: nothing was trained, logged or written.
    pub complete: bool,
}

impl Finished {
    /// The message of a run that was already complete (see [`Finished::complete`]), whose results —
    /// checkpoint, log, summary — are kept as they were.
    pub fn already_complete(&self, checkpoint: Option<&Path>) -> String {
        let at = checkpoint.map_or(String::new(), |p| format!(": '{}'", p.display()));
        format!(
            "the run is already complete{at} holds all {} steps; nothing trained, its results are kept \
             (raise 'steps' to train further, or train without --resume to start again)",
            self.done
        )
    }

    /// Steps taken by this run.
    pub fn trained(&self) -> u32 {
        self.done - self.first
    }

    /// Milliseconds a step of this run took on average (0 without steps).
    pub fn ms_per_step(&self) -> f64 {
        match self.trained() {
            0 => 0.0,
            n => 1e3 * self.train_seconds / f64::from(n),
        }
    }

    /// Samples evaluated a second of training (0 without training time).
    pub fn samples_per_s(&self) -> f64 {
        if self.train_seconds > 0.0 {
            self.samples as f64 / self.train_seconds
        } else {
            0.0
        }
    }

    /// The run's outcome once its summary is written: the error of a run that Ctrl-C stopped (saying where
    /// its checkpoint is), or nothing.
    pub fn stopped(&self, checkpoint: Option<&Path>) -> Result<()> {
        if self.interrupted {
            return Err(crate::interrupt::stopped(self.done, checkpoint));
        }
        Ok(())
    }
}

/// Trains `params` of `program` in place by `objective` (see the module docs).
pub fn train(
    program: &Program,
    params: &mut Vec<f32>,
    settings: &LoopSettings,
    objective: &mut dyn Objective,
) -> Result<Finished> {
    let schedule = settings.schedule;
    let step_fraction = |step: u32| f64::from(step) / f64::from(settings.steps.max(1));
    let crate::checkpoint::Start {
        mut adam,
        step: first,
        run_fraction: resumed_fraction,
    } = crate::checkpoint::resume_or_start(
        program,
        settings.checkpoint,
        settings.resume,
        params,
        settings.optimizer,
        |k, fraction| schedule.lr(k, fraction),
        step_fraction,
    )?;
    // The fraction of the run done before a step: of its steps or of its time limit, whichever is further
    // (a resumed run's time limit covers what its checkpoint had left).
    let run_fraction = |step: u32, train_seconds: f64| {
        let timed = settings.time_limit.map_or(0.0, |limit| {
            resumed_fraction + (1.0 - resumed_fraction) * train_seconds / limit.max(1e-9)
        });
        step_fraction(step).max(timed).min(1.0)
    };
    let mut finished = Finished {
        first,
        done: first,
        loss: f32::NAN,
        train_seconds: 0.0,
        wall_seconds: 0.0,
        samples: 0,
        interrupted: false,
        complete: first >= settings.steps,
    };
    if finished.complete {
        return Ok(finished);
    }
    // In an MPI job every rank trains the same params on its own rays (data parallel); rank 0 alone logs and
    // writes checkpoints.
    let cluster = crate::cluster::current();
    let (root, ranks) = (cluster.rank() == 0, cluster.size());
    let log = RunLog::open(
        settings.log.filter(|_| root),
        settings.tensorboard.filter(|_| root),
        settings.log_columns,
        first > 0,
    )?;
    let mut ui = Ui {
        bar: settings
            .bars
            .bar(u64::from(settings.steps), BarKind::Steps(settings.verb)),
        log,
        watch: Watch::start(),
    };
    ui.bar.set_position(u64::from(first));
    let start = Instant::now();
    objective.start(first, params, &ui)?;
    let mut reduce = AllReduce::new(cluster, Reduction::from_env().map_err(Failure::Message)?);
    if ranks > 1 {
        ui.report(reduce.plan(params.len()));
    }
    // Seconds of the steps alone (hooks excluded), for the all-reduce's share.
    let mut step_seconds = 0.0;
    // In an MPI job the ranks keep one clock: the mean of their training times, agreed at each all-reduce
    // (validation times, the time limit and the logs then agree on every rank). `tail`: this rank's seconds of
    // the last step after its all-reduce, counted at the next one.
    let mut tail = 0.0;
    for step in first..settings.steps {
        let step_start = Instant::now();
        let lr = schedule.lr(step, run_fraction(step, finished.train_seconds));
        let Gradient {
            mut loss,
            grads,
            samples,
        } = objective.gradient(step, lr, params, &ui)?;
        // Data parallel: every rank takes the mean of the ranks' gradients, losses and clocks, and stops when
        // any rank is interrupted, so that the params stay the same on every rank.
        let mut agreed = None;
        let mut reduced_at = step_start;
        if ranks > 1 {
            let spent = finished.train_seconds + tail + step_start.elapsed().as_secs_f64();
            let mean = reduce.mean(grads, loss, ui.watch.requested(), spent);
            reduced_at = Instant::now();
            loss = mean.loss;
            agreed = Some(mean);
        }
        let threads = rayon::current_num_threads() as u32;
        let diverged = |grads: &[f32]| {
            ui.bar.abandon();
            crate::checkpoint::diverged(program, step, loss, grads, settings.checkpoint)
        };
        if !loss.is_finite() {
            return Err(diverged(grads));
        }
        adam.lr = lr;
        let update = Instant::now();
        let rejected = adam.step(params, grads)?;
        // Adam runs on every thread: its time summed over them, as the kernels' phases are.
        profile::record(Phase::Optimizer, update.elapsed() * threads);
        // Adam reads the params, gradients and both moments and writes all but the gradients.
        profile::count(Phase::Optimizer, 28 * params.len() as u64);
        if rejected > 0 {
            if !grads.iter().all(|g| g.is_finite()) {
                return Err(diverged(grads));
            }
            ui.bar.abandon();
            return Err(Failure::Message(format!(
                "training diverged at step {step}: {rejected} param values would become non-finite"
            )));
        }
        let step_time = step_start.elapsed();
        profile::record(Phase::Steps, step_time);
        profile::count(Phase::Steps, samples as u64);
        step_seconds += step_time.as_secs_f64();
        finished.interrupted = match agreed {
            Some(agreed) => {
                finished.train_seconds = agreed.train_seconds;
                tail = reduced_at.elapsed().as_secs_f64();
                agreed.interrupted
            }
            None => {
                finished.train_seconds += step_time.as_secs_f64();
                ui.watch.requested()
            }
        };
        finished.samples += samples;
        finished.loss = loss;
        finished.done = step + 1;
        let out_of_time = settings
            .time_limit
            .is_some_and(|limit| finished.train_seconds >= limit);
        let progress = Progress {
            done: finished.done,
            first,
            steps: settings.steps,
            train_seconds: finished.train_seconds,
            wall_seconds: start.elapsed().as_secs_f64(),
            lr: adam.lr,
            loss,
            last: finished.done == settings.steps || out_of_time || finished.interrupted,
            interrupted: finished.interrupted,
        };
        if ranks > 1 && (finished.done.is_multiple_of(100) || progress.last) {
            check_same_params(cluster, params, finished.done)?;
        }
        objective.after_step(&progress, params, &mut ui)?;
        ui.bar.set_position(u64::from(finished.done));
        if let Some(path) = settings.checkpoint.filter(|_| root) {
            if finished.done.is_multiple_of(settings.checkpoint_every) || progress.last {
                let kept = crate::checkpoint::Kept {
                    occupancy: objective.occupancy(),
                    appearance: objective.appearance(),
                    run_fraction: Some(run_fraction(finished.done, finished.train_seconds)),
                };
                crate::checkpoint::write(path, program, finished.done, params, &adam, kept)?;
            }
        }
        if ranks > 1 && progress.last {
            // No rank leaves (and, interrupted, ends the job) before rank 0 has written the last checkpoint.
            cluster.barrier();
        }
        if finished.interrupted {
            break;
        }
        if out_of_time {
            ui.report(format!(
                "stopped at step {}: the time limit of {:.1} minutes is reached",
                finished.done,
                finished.train_seconds / 60.0
            ));
            break;
        }
    }
    if ranks > 1 && finished.done > first {
        ui.report(reduce.summary(finished.done - first, step_seconds));
    }
    ui.bar.finish_and_clear();
    finished.wall_seconds = start.elapsed().as_secs_f64();
    Ok(finished)
}

/// What the ranks of a data-parallel job agree on in a step's all-reduce.
struct Agreed {
    /// The mean of the ranks' losses.
    loss: f32,
    /// Whether any rank was interrupted.
    interrupted: bool,
    /// The mean of the ranks' training times.
    train_seconds: f64,
}

/// A run's all-reduces: how the gradients travel (fixed by `NERFJIT_ALL_REDUCE`, or each step the cheaper
/// way when `forced` is `None`) and what they cost.
struct AllReduce<'c> {
    cluster: &'c dyn crate::cluster::Cluster,
    forced: Option<Reduction>,
    /// Bytes this rank sent.
    bytes_sent: f64,
    /// Steps that sent only the non-zero values.
    sparse_steps: u32,
    /// Seconds spent in the all-reduces (waiting for the slowest rank included).
    seconds: f64,
}

impl<'c> AllReduce<'c> {
    fn new(cluster: &'c dyn crate::cluster::Cluster, forced: Option<Reduction>) -> AllReduce<'c> {
        AllReduce {
            cluster,
            forced,
            bytes_sent: 0.0,
            sparse_steps: 0,
            seconds: 0.0,
        }
    }

    /// What each step will reduce, for a gradient of `params` values, in a line.
    fn plan(&self, params: usize) -> String {
        // Every gradient, the loss, the Ctrl-C flag and the rank's clock.
        let floats = params + 3;
        format!(
            "data parallel over {} ranks: each step all-reduces {floats} floats ({:.2} MB), {}",
            self.cluster.size(),
            floats as f64 * 4e-6,
            match self.forced {
                Some(Reduction::Dense) => "every value",
                Some(Reduction::Sparse) => "the non-zero ones (NERFJIT_ALL_REDUCE=sparse)",
                None => "every value or only the non-zero ones, whichever sends fewer bytes (NERFJIT_ALL_REDUCE=auto)",
            }
        )
    }

    /// Replaces this rank's `grads` by the ranks' mean, and agrees on the mean loss, whether any rank was
    /// `interrupted` and the mean of the seconds they `spent`.
    fn mean(&mut self, grads: &mut Vec<f32>, loss: f32, interrupted: bool, spent: f64) -> Agreed {
        let ranks = self.cluster.size();
        grads.extend([loss, f32::from(u8::from(interrupted)), spent as f32]);
        let reducing = Instant::now();
        // This rank's non-zero values (only the sparse reductions need them), as a count for all ranks.
        let nonzero = match self.forced {
            Some(Reduction::Dense) => 0,
            _ => grads.iter().filter(|g| **g != 0.0).count() * ranks,
        };
        let reduction = self.forced.unwrap_or_else(|| {
            // The ranks agree on the non-zero count first (one float), then on the reduction.
            let mut total = [(nonzero / ranks) as f32];
            self.cluster.all_reduce_sum(&mut total);
            Reduction::cheaper(grads.len(), total[0] as usize, ranks)
        });
        self.bytes_sent += reduction.bytes_sent(grads.len(), nonzero, ranks);
        match reduction {
            Reduction::Dense => self.cluster.all_reduce_sum(grads),
            Reduction::Sparse => {
                self.sparse_steps += 1;
                crate::cluster::all_reduce_sparse_sum(self.cluster, grads);
            }
        }
        self.seconds += reducing.elapsed().as_secs_f64();
        let scale = 1.0 / ranks as f32;
        let sums = grads.split_off(grads.len() - 3);
        grads.iter_mut().for_each(|g| *g *= scale);
        Agreed {
            loss: sums[0] * scale,
            interrupted: sums[1] > 0.0,
            train_seconds: f64::from(sums[2] * scale),
        }
    }

    /// What the all-reduces of `steps` steps cost, against the `step_seconds` the steps took, in a line.
    fn summary(&self, steps: u32, step_seconds: f64) -> String {
        let steps = f64::from(steps);
        format!(
            "all-reduce: {:.2} ms a step ({:.1}% of the training time; waiting for the slowest rank included), \
             {:.2} MB sent a step by each rank, only the non-zero values in {} of {steps} steps",
            1e3 * self.seconds / steps,
            100.0 * self.seconds / step_seconds.max(1e-9),
            self.bytes_sent * 1e-6 / steps,
            self.sparse_steps
        )
    }
}

/// Fails (on rank 0) unless every rank of the job holds the same params, bit for bit.
fn check_same_params(cluster: &dyn crate::cluster::Cluster, params: &[f32], done: u32) -> Result<()> {
    let hash = params.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, p| {
        (h ^ u64::from(p.to_bits())).wrapping_mul(0x0100_0000_01b3)
    });
    match cluster.gather(&hash.to_le_bytes()) {
        Some(all) if all.iter().any(|h| *h != all[0]) => {
            Err(Failure::Message(format!(
            "after step {done} the ranks' params differ (checksums {:?}): data-parallel training lost step",
            all.iter().map(|h| u64::from_le_bytes(h[..8].try_into().unwrap_or([0; 8]))).collect::<Vec<_>>()
        )))
        }
        _ => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A program of one param, `p: vec3`.
    fn program() -> Program {
        nerfjit_dsl::compile_with("loop.sdf", "param p: vec3 = [0, 0, 0]\n", &[]).expect("a valid script")
    }

    /// Pulls the params toward `target`: loss Σ (p − target)²; the gradient of step `poison` is NaN.
    struct Quadratic {
        target: [f32; 3],
        poison: Option<u32>,
        started_at: Option<u32>,
        seen: Vec<Progress>,
        grads: Vec<f32>,
    }

    impl Quadratic {
        fn new(poison: Option<u32>) -> Quadratic {
            Quadratic {
                target: [1.0, -2.0, 0.5],
                poison,
                started_at: None,
                seen: Vec::new(),
                grads: Vec::new(),
            }
        }
    }

    impl Objective for Quadratic {
        fn start(&mut self, first: u32, _params: &[f32], _ui: &Ui) -> Result<()> {
            self.started_at = Some(first);
            Ok(())
        }

        fn gradient(&mut self, step: u32, _lr: f32, params: &[f32], _ui: &Ui) -> Result<Gradient<'_>> {
            let diff: Vec<f32> = params.iter().zip(self.target).map(|(p, t)| p - t).collect();
            self.grads = diff.iter().map(|d| 2.0 * d).collect();
            if self.poison == Some(step) {
                self.grads[1] = f32::NAN;
            }
            Ok(Gradient {
                loss: diff.iter().map(|d| d * d).sum(),
                grads: &mut self.grads,
                samples: 3,
            })
        }

        fn after_step(&mut self, progress: &Progress, _params: &[f32], _ui: &mut Ui) -> Result<()> {
            self.seen.push(*progress);
            Ok(())
        }
    }

    fn settings<'a>(steps: u32, schedule: &'a Schedule, checkpoint: Option<&'a Path>) -> LoopSettings<'a> {
        LoopSettings {
            steps,
            schedule,
            optimizer: AdamSettings::default(),
            time_limit: None,
            checkpoint,
            checkpoint_every: 5,
            resume: true,
            log: None,
            tensorboard: None,
            log_columns: &["step"],
            verb: "testing",
            bars: &crate::observe::NoBars,
        }
    }

    /// A checkpoint's path in a fresh folder, and the folder (removed when it drops).
    fn temp(name: &str) -> (tempfile::TempDir, std::path::PathBuf) {
        let dir = tempfile::Builder::new()
            .prefix(&format!("nerfjit-loop-{name}-"))
            .tempdir()
            .unwrap();
        let path = dir.path().join("run.ckpt");
        (dir, path)
    }

    #[test]
    fn the_loop_minimizes_and_calls_its_hooks_once_a_step() {
        let (program, schedule) = (program(), Schedule::Constant { lr: 0.05 });
        let mut params = program.param_values.clone();
        let mut objective = Quadratic::new(None);
        let end = train(
            &program,
            &mut params,
            &settings(400, &schedule, None),
            &mut objective,
        )
        .unwrap();
        assert_eq!(
            (end.first, end.done, end.trained(), end.samples),
            (0, 400, 400, 1200)
        );
        assert!(!end.interrupted);
        assert_eq!(objective.started_at, Some(0));
        for (p, t) in params.iter().zip(objective.target) {
            assert!((p - t).abs() < 1e-2, "{params:?}");
        }
        let steps: Vec<u32> = objective.seen.iter().map(|p| p.done).collect();
        assert_eq!(steps, (1..=400).collect::<Vec<_>>());
        let lasts: Vec<bool> = objective.seen.iter().map(|p| p.last).collect();
        assert_eq!(lasts.iter().filter(|&&l| l).count(), 1);
        assert!(lasts[399]);
        assert!(objective
            .seen
            .iter()
            .all(|p| p.lr == 0.05 && p.first == 0 && p.steps == 400));
    }

    #[test]
    fn a_resumed_run_starts_at_the_checkpoint_and_a_finished_one_takes_no_step() {
        let (program, schedule) = (program(), Schedule::Constant { lr: 0.05 });
        let (_folder, path) = temp("resume");
        let mut params = program.param_values.clone();
        let mut first = Quadratic::new(None);
        train(
            &program,
            &mut params,
            &settings(12, &schedule, Some(&path)),
            &mut first,
        )
        .unwrap();
        // A fresh run with the same settings resumes from step 12 and ends where one run of 20 steps ends.
        let mut resumed_params = program.param_values.clone();
        let mut second = Quadratic::new(None);
        let end = train(
            &program,
            &mut resumed_params,
            &settings(20, &schedule, Some(&path)),
            &mut second,
        )
        .unwrap();
        assert_eq!(
            (second.started_at, end.first, end.done, end.trained()),
            (Some(12), 12, 20, 8)
        );
        let mut straight = program.param_values.clone();
        train(
            &program,
            &mut straight,
            &settings(20, &schedule, None),
            &mut Quadratic::new(None),
        )
        .unwrap();
        assert_eq!(resumed_params, straight);
        let mut again = program.param_values.clone();
        let end = train(
            &program,
            &mut again,
            &settings(20, &schedule, Some(&path)),
            &mut Quadratic::new(None),
        )
        .unwrap();
        assert_eq!((end.trained(), end.loss.is_nan(), end.complete), (0, true, true));
        assert_eq!(again, straight);
        assert!(end.already_complete(Some(&path)).starts_with(&format!(
            "the run is already complete: '{}' holds all 20 steps",
            path.display()
        )));
        std::fs::remove_dir_all(path.parent().unwrap()).unwrap();
    }

    #[test]
    fn a_non_finite_gradient_stops_the_run_and_keeps_the_last_good_checkpoint() {
        let (program, schedule) = (program(), Schedule::Constant { lr: 0.05 });
        let (_folder, path) = temp("diverge");
        let mut params = program.param_values.clone();
        let error = train(
            &program,
            &mut params,
            &settings(20, &schedule, Some(&path)),
            &mut Quadratic::new(Some(7)),
        )
        .expect_err("the NaN gradient stops the run")
        .to_string();
        assert!(error.contains("training diverged at step 7"), "{error}");
        assert!(
            error.contains("'p' (1 of 3 elements, the first 1 = NaN)"),
            "{error}"
        );
        assert!(error.contains("last good checkpoint is kept"), "{error}");
        // The checkpoint holds step 5's params: resuming continues from there.
        let mut resumed = program.param_values.clone();
        let mut objective = Quadratic::new(None);
        let end = train(
            &program,
            &mut resumed,
            &settings(6, &schedule, Some(&path)),
            &mut objective,
        )
        .unwrap();
        assert_eq!((end.first, end.trained()), (5, 1));
        std::fs::remove_dir_all(path.parent().unwrap()).unwrap();
    }

    #[test]
    fn a_schedule_over_the_run_decays_by_its_gamma_and_resumes_at_the_fraction_its_checkpoint_kept() {
        let program = program();
        let schedule = Schedule::ExponentialOverRun { lr: 0.1, gamma: 0.01 };
        let close = |a: f32, b: f64| (f64::from(a) - b).abs() <= 1e-4 * b;
        // Without a time limit the fraction done is the steps'.
        let mut objective = Quadratic::new(None);
        let mut params = program.param_values.clone();
        train(
            &program,
            &mut params,
            &settings(20, &schedule, None),
            &mut objective,
        )
        .unwrap();
        for (k, p) in objective.seen.iter().enumerate() {
            let expected = 0.1 * 0.01f64.powf(k as f64 / 20.0);
            assert!(close(p.lr, expected), "step {k}: {} against {expected}", p.lr);
        }
        let folder = tempfile::Builder::new()
            .prefix("nerfjit-loop-fraction-")
            .tempdir()
            .unwrap();
        for name in ["run.ckpt.safetensors", "run.json"] {
            let path = folder.path().join(name);
            // A checkpoint at step 2 of a timed run that had taken half its time.
            let kept = crate::checkpoint::Kept {
                run_fraction: Some(0.5),
                ..Default::default()
            };
            let adam = nerfjit_runtime::Adam::new(3, 0.0);
            crate::checkpoint::write(&path, &program, 2, &program.param_values, &adam, kept).unwrap();
            // Resumed under a time limit (its steps take a negligible share of it): on from half way.
            let timed = |steps| LoopSettings {
                time_limit: Some(1e6),
                ..settings(steps, &schedule, Some(&path))
            };
            let mut objective = Quadratic::new(None);
            let mut params = program.param_values.clone();
            train(&program, &mut params, &timed(20), &mut objective).unwrap();
            assert_eq!(objective.started_at, Some(2), "{name}");
            assert!(
                close(objective.seen[0].lr, 0.01),
                "{name}: {}",
                objective.seen[0].lr
            );
            // Its last checkpoint says the run was done: resumed for more steps, the rate stays at the end's.
            let mut objective = Quadratic::new(None);
            train(&program, &mut params, &timed(30), &mut objective).unwrap();
            assert_eq!(objective.started_at, Some(20), "{name}");
            assert!(objective.seen.iter().all(|p| close(p.lr, 0.001)), "{name}");
            // Without a time limit the steps' fraction rules (20 of 40).
            let mut objective = Quadratic::new(None);
            train(
                &program,
                &mut params,
                &settings(40, &schedule, Some(&path)),
                &mut objective,
            )
            .unwrap();
            assert_eq!(objective.started_at, Some(30), "{name}");
            assert!(close(objective.seen[0].lr, 0.1 * 0.01f64.powf(0.75)), "{name}");
        }
    }

    #[test]
    fn the_time_limit_ends_the_run_after_the_step_that_reaches_it() {
        let (program, schedule) = (program(), Schedule::Constant { lr: 0.05 });
        let mut params = program.param_values.clone();
        let mut objective = Quadratic::new(None);
        let limited = LoopSettings {
            time_limit: Some(0.0),
            ..settings(100, &schedule, None)
        };
        let end = train(&program, &mut params, &limited, &mut objective).unwrap();
        assert_eq!(end.done, 1);
        assert!(objective.seen[0].last && !objective.seen[0].interrupted);
        assert!(end.stopped(None).is_ok());
    }
}
