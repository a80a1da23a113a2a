//! `train sdf { ... }`: fits a script's (neural) SDF to a point cloud: zero on the points, no surface
//! near random points, and an eikonal term (|∇ₓd| − 1)² whose param gradient comes from the JIT's
//! second-order kernel. An optional pre-training pulls the SDF toward a sphere first.
//!
//! Per step, with cloud points xᵢ (N) and uniform points yⱼ (M) in [−b, b]³:
//! L = mean |d(xᵢ)| + w_near · mean exp(−α|d(yⱼ)|) + w_eik · mean (|∇d(yⱼ)| − 1)²
//!   (+ w_clear · mean max(cⱼ − |d(zⱼ)|, 0) at M more uniform points zⱼ, with cⱼ the distance from zⱼ to
//!   the nearest cloud point less twice the cloud's spacing, and d(zⱼ) itself for |d(zⱼ)| where zⱼ is
//!   known to be outside: a surface only where points are; see [`crate::training::clearance`]).

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use nerfjit_dsl::kernel_graphs::{self, SdfLoss};
use nerfjit_dsl::{Diagnostic, Program, Type};
use nerfjit_jit::{Kernel, KernelCache, Options, Precision};
use nerfjit_runtime::{bounding_box, read_points, render_points, PointFrame, Rng, Schedule};

use crate::failure::{Failure, Result};
use crate::folder_lock::lock_output_folders;
use crate::observe::{NoBars, ProgressBars};
use crate::settings::block::Block;
use crate::settings::primitives::CallArgs;
use crate::settings::schema::Kind;
use crate::settings::typed::typed_settings;
use crate::training::clearance::Clearance;
use crate::training::metrics_log::{log_record, LogRecord};
use crate::training::regularizers::{uniform_points, RegularizerKernels, Regularizers};
use crate::training::train_loop::{self, Gradient, LoopSettings, Objective, Progress, Ui};

log_record! {
    /// A line of a neural SDF's metrics log: a step's rate, loss and its three terms.
    struct SdfRecord {
        /// Steps done.
        step: u32,
        /// Seconds of training.
        seconds: f64,
        /// The step's learning rate.
        lr: Option<f32>,
        /// The step's loss.
        loss: Option<f32>,
        /// Its surface term.
        surface: Option<f32>,
        /// Its near-surface term.
        near: Option<f32>,
        /// Its eikonal term.
        eikonal: Option<f32>,
    }
}

/// A checked `train sdf` block.
pub struct TrainSdfPlan {
    data: PathBuf,
    key: Option<String>,
    /// Fit the cloud scaled into the unit sphere ([`PointFrame::unit_sphere`]), not merely mean-centered.
    normalize: bool,
    function: String,
    steps: u32,
    batch: usize,
    random: usize,
    bound: f32,
    /// Adam's learning rate over the steps (pre-training included).
    schedule: Schedule,
    /// Adam's decay rates and ε.
    optimizer: crate::settings::values::AdamSettings,
    near_weight: f32,
    near_sharpness: f32,
    eikonal_weight: f32,
    /// w_clear: the clearance term's weight (0: off).
    clearance_weight: f32,
    /// σ of the noise that moves cloud points into eikonal points (0: none).
    eikonal_jitter: f32,
    pretrain_steps: u32,
    pretrain_radius: f32,
    seed: u64,
    checkpoint: Option<PathBuf>,
    checkpoint_every: u32,
    /// The metrics log (JSON Lines, or CSV).
    log: Option<PathBuf>,
    /// A TensorBoard folder the metrics also go to.
    tensorboard: Option<PathBuf>,
    summary: Option<PathBuf>,
    points_gif: Option<PathBuf>,
    /// The arithmetic of the network's products.
    products: Precision,
}

/// The loss kernels of one SDF: each gives its per-point loss terms and their param gradient in one pass.
struct Kernels {
    /// (d(y) − (|y| − r))² / m on random points: pre-training toward a sphere.
    sphere: Arc<Kernel>,
    /// |d(x)| / n on cloud points.
    surface: Arc<Kernel>,
    regularizers: RegularizerKernels,
    /// The eikonal term alone at the batch's cloud points moved by Gaussian noise, when asked for.
    jittered: Option<RegularizerKernels>,
    /// w_clear · max(c − |d(z)|, 0) / m on uniform points z with their clearance c, when asked for.
    clearance: Option<Arc<Kernel>>,
}

/// The slots of `train sdf`'s `data: points(...)`.
const POINTS_ARGS: &[&str] = &["file", "key", "normalize"];

/// The frame of the script's point-cloud fit when its data says `normalize: true` (meshes of the fitted
/// function are then written in the cloud's units), reading the cloud from `script_dir`; None without such
/// a fit.
pub fn fitted_frame(program: &Program, script_dir: &str) -> Result<Option<PointFrame>> {
    let first = || crate::settings::block::first_block(program, Kind::TrainSdf, script_dir);
    let Ok(mut block) = first() else {
        return Ok(None);
    };
    let data = block.required("data")?;
    let normalize = CallArgs::new(&data, POINTS_ARGS)
        .and_then(|a| a.choice("normalize", &["true", "false"], "false"))
        .map_err(|d| block.error(d))?;
    if normalize != "true" {
        return Ok(None);
    }
    TrainSdfPlan::new(first()?)?.normalized_frame()
}

typed_settings! {
    /// The settings of a `train sdf` block, as read.
    pub struct TrainSdfSettings for crate::settings::schema::TRAIN_SDF {
        data: required,
        function: function,
        products: choice,
        steps: whole,
        batch: whole,
        random: whole,
        bounds: number,
        lr: number,
        schedule: value,
        optimizer: value,
        near_weight: number,
        near_sharpness: number,
        eikonal_weight: number,
        clearance_weight: number,
        eikonal_jitter: number,
        pretrain_steps: whole,
        pretrain_radius: number,
        seed: whole,
        checkpoint: output,
        checkpoint_every: whole,
        log: output,
        tensorboard: output,
        summary: output,
        points_gif: output,
    }
}

impl TrainSdfPlan {
    /// Reads and checks a `train sdf` block.
    pub fn new(mut b: Block) -> Result<TrainSdfPlan> {
        let s = TrainSdfSettings::read(&mut b)?;
        let data_v = &s.data;
        let (file, key, normalize) = CallArgs::new(data_v, POINTS_ARGS)
            .and_then(|a| {
                Ok((
                    a.string("file")?,
                    a.raw("key").map(|k| k.string().map(str::to_string)).transpose()?,
                    a.choice("normalize", &["true", "false"], "false")? == "true",
                ))
            })
            .map_err(|d| b.error(d))?;
        let data = crate::training::data_source::data_path(&file, b.script_dir());
        if !data.is_file() {
            return Err(b.error(
                Diagnostic::new(data_v.span, format!("data file '{}' not found", data.display()))
                    .with_hint("paths are relative to the working folder or to the script"),
            ));
        }
        let schedule = crate::settings::values::schedule(s.schedule, s.lr as f32).map_err(|d| b.error(d))?;
        let optimizer = crate::settings::values::optimizer(s.optimizer).map_err(|d| b.error(d))?;
        let plan = TrainSdfPlan {
            data,
            key,
            normalize,
            function: s.function,
            steps: s.steps as u32,
            batch: s.batch as usize,
            random: s.random as usize,
            bound: s.bounds as f32,
            schedule,
            optimizer,
            near_weight: s.near_weight as f32,
            near_sharpness: s.near_sharpness as f32,
            eikonal_weight: s.eikonal_weight as f32,
            clearance_weight: s.clearance_weight as f32,
            eikonal_jitter: s.eikonal_jitter as f32,
            pretrain_steps: s.pretrain_steps as u32,
            pretrain_radius: s.pretrain_radius as f32,
            seed: s.seed,
            checkpoint: s.checkpoint,
            checkpoint_every: s.checkpoint_every as u32,
            log: s.log,
            tensorboard: s.tensorboard,
            summary: s.summary,
            points_gif: s.points_gif,
            products: s
                .products
                .as_deref()
                .and_then(Precision::named)
                .unwrap_or_default(),
        };
        b.finish()?;
        Ok(plan)
    }

    fn compile(&self, program: &Program, cache: &KernelCache) -> Result<Kernels> {
        nerfjit_field::check_signature(program, &self.function, &[&[Type::Vec(3)]], &Type::F32)?;
        let lowered = program.lower(&self.function)?;
        let options = Options {
            products: self.products,
            ..Options::default()
        };
        let loss = |loss: SdfLoss| {
            cache.get(
                &kernel_graphs::sdf_loss(&lowered, program.n_params(), loss),
                options,
            )
        };
        let sphere = SdfLoss::Sphere {
            radius: f64::from(self.pretrain_radius),
            scale: 1.0 / self.random_here() as f64,
        };
        let surface = SdfLoss::Surface {
            scale: 1.0 / self.batch_here() as f64,
        };
        Ok(Kernels {
            sphere: loss(sphere)?,
            surface: loss(surface)?,
            regularizers: RegularizerKernels::compile(
                program,
                &self.function,
                &self.regularizers(),
                cache,
                self.products,
            )?,
            jittered: match self.jittered() {
                Some(reg) => Some(RegularizerKernels::compile(
                    program,
                    &self.function,
                    &reg,
                    cache,
                    self.products,
                )?),
                None => None,
            },
            clearance: match self.clearance_weight > 0.0 {
                true => Some(loss(SdfLoss::Clearance {
                    scale: f64::from(self.clearance_weight) / self.random_here() as f64,
                })?),
                false => None,
            },
        })
    }

    /// Runs only `steps` fitting steps (no pre-training, checkpoints, summary or GIF), for benchmarks;
    /// returns the summary line, with the ms per step of the training loop alone.
    pub fn run_steps(self, program: &Program, params: &mut Vec<f32>, steps: u32) -> Result<String> {
        let quiet = TrainSdfPlan {
            steps,
            pretrain_steps: 0,
            checkpoint: None,
            log: None,
            summary: None,
            points_gif: None,
            ..self
        };
        let line = quiet.run(program, params, &KernelCache::new(), false, &NoBars)?;
        Ok(line.lines().next().unwrap_or_default().to_string())
    }

    /// Trains `params` in place (resuming from the checkpoint when asked, compiling through `cache`);
    /// returns a summary.
    pub fn run(
        &self,
        program: &Program,
        params: &mut Vec<f32>,
        cache: &KernelCache,
        resume: bool,
        bars: &dyn ProgressBars,
    ) -> Result<String> {
        crate::cluster::check_batch(self.batch, "train sdf's batch").map_err(Failure::Message)?;
        crate::cluster::check_batch(self.random, "train sdf's random").map_err(Failure::Message)?;
        // Before anything is written: a second run in the folder refuses here, naming the first.
        let _locks = lock_output_folders(self.checkpoint.iter().chain(&self.log).map(PathBuf::as_path))?;
        let input = read_points(&self.data, self.key.as_deref())?;
        let frame = self.frame_of(&input)?;
        let cloud: Vec<[f32; 3]> = input.iter().map(|&p| frame.to_frame(p)).collect();
        if let Some(path) = &self.points_gif {
            write_points_gif(path, &cloud)?;
        }
        let t = Instant::now();
        let kernels = self.compile(program, cache)?;
        let compile_s = t.elapsed().as_secs_f64();
        let clearance = (self.clearance_weight > 0.0).then(|| Clearance::new(&cloud, self.bound));
        let mut objective = SdfObjective {
            plan: self,
            kernels: &kernels,
            cloud: &cloud,
            clearance: clearance.as_ref(),
            // Each rank of an MPI job draws its own points.
            rng: Rng::new(self.seed ^ 0xB0_77 ^ ((crate::cluster::current().rank() as u64) << 40)),
            threads: rayon::current_num_threads(),
            terms: [f32::NAN; 3],
            grads: Vec::new(),
        };
        let settings = LoopSettings {
            steps: self.pretrain_steps + self.steps,
            schedule: &self.schedule,
            optimizer: self.optimizer,
            time_limit: None,
            checkpoint: self.checkpoint.as_deref(),
            checkpoint_every: self.checkpoint_every,
            resume,
            log: self.log.as_deref(),
            tensorboard: self.tensorboard.as_deref(),
            log_columns: SdfRecord::COLUMNS,
            verb: "fitting",
            bars,
        };
        let end = train_loop::train(program, params, &settings, &mut objective)?;
        if end.complete {
            return Ok(end.already_complete(self.checkpoint.as_deref()));
        }
        let terms = objective.terms;
        let (seconds, ms) = (end.train_seconds, end.ms_per_step());
        if let Some(path) = self
            .summary
            .as_ref()
            .filter(|_| crate::cluster::current().rank() == 0)
        {
            let json = serde_json::json!({
                "data": self.data.display().to_string(),
                "points": cloud.len(),
                "frame": {"center": frame.center, "scale": frame.scale, "normalized": self.normalize},
                "steps": end.done,
                "resumed_from": end.first,
                "surface_loss": terms[0],
                "near_loss": terms[1],
                "eikonal_loss": terms[2],
                "seconds": seconds,
                "ms_per_step": ms,
                "compile_seconds": compile_s,
                "params": crate::blocks::train::params_json(program, params),
            });
            nerfjit_runtime::write_whole(
                path,
                serde_json::to_string_pretty(&json).unwrap_or_default().as_bytes(),
            )?;
        }
        end.stopped(self.checkpoint.as_deref())?;
        Ok(format!(
            "fitted '{}' to {} points in {} steps, {seconds:.1} s ({ms:.2} ms/step, JIT compile {compile_s:.2} s): \
             mean |d| on the points {:.5}, near-surface term {:.5}, eikonal term {:.5}\n{}",
            self.function,
            cloud.len(),
            end.trained(),
            terms[0],
            terms[1],
            terms[2],
            crate::blocks::train::describe_params(program, params)
        ))
    }

    /// The frame the fit sees the cloud in: scaled into the unit sphere when the data says
    /// `normalize: true`, mean-centered otherwise.
    fn frame_of(&self, input: &[[f32; 3]]) -> Result<PointFrame> {
        if !self.normalize {
            return Ok(PointFrame::mean_centered(input));
        }
        PointFrame::unit_sphere(input)
            .map_err(|e| Failure::Message(format!("cannot normalize {}: {e}", self.data.display())))
    }

    /// The frame the fit sees its cloud in when it is scaled into the unit sphere (`normalize: true`),
    /// which meshes of the fitted function are mapped back from.
    pub fn normalized_frame(&self) -> Result<Option<PointFrame>> {
        if !self.normalize {
            return Ok(None);
        }
        Ok(Some(
            self.frame_of(&read_points(&self.data, self.key.as_deref())?)?,
        ))
    }

    /// Pre-training toward the sphere of `pretrain_radius`: mean (d(y) − (|y| − r))².
    fn sphere_step(
        &self,
        k: &Kernels,
        params: &[f32],
        grads: &mut [f32],
        rng: &mut Rng,
        threads: usize,
    ) -> f32 {
        let ys = uniform_points(rng, self.random_here(), self.bound);
        let ins: Vec<&[f32]> = ys.iter().map(Vec::as_slice).collect();
        summed_terms(&k.sphere, &ins, params, grads, threads)
    }

    /// One step of the fit; returns the three loss terms (already weighted; the clearance term, if any,
    /// counted with the near-surface term: both keep the surface off the uniform points).
    #[allow(clippy::too_many_arguments)]
    fn fit_step(
        &self,
        k: &Kernels,
        params: &[f32],
        grads: &mut [f32],
        cloud: &[[f32; 3]],
        clearance: Option<&Clearance>,
        rng: &mut Rng,
        threads: usize,
    ) -> [f32; 3] {
        // Points on the surface: mean |d|.
        let nb = self.batch_here();
        let mut xs = [
            Vec::with_capacity(nb),
            Vec::with_capacity(nb),
            Vec::with_capacity(nb),
        ];
        for _ in 0..nb {
            let p = cloud[rng.below(cloud.len() as u64) as usize];
            for (c, v) in xs.iter_mut().zip(p) {
                c.push(v);
            }
        }
        let ins: Vec<&[f32]> = xs.iter().map(Vec::as_slice).collect();
        let surface = summed_terms(&k.surface, &ins, params, grads, threads);

        // Random points: the near-surface penalty on d and the eikonal term on ∇d.
        let [mut near, mut eikonal] = self
            .regularizers()
            .add(&k.regularizers, params, grads, rng, threads);
        if let (Some(kernel), Some(clearance)) = (&k.clearance, clearance) {
            near += self.clearance_step(kernel, clearance, params, grads, rng, threads);
        }
        // And the eikonal term about the surface (IGR's sampling): the same cloud points, jittered.
        if let (Some(kernels), Some(reg)) = (&k.jittered, self.jittered()) {
            for column in &mut xs {
                for x in column.iter_mut() {
                    *x += self.eikonal_jitter * rng.normal();
                }
            }
            eikonal += reg.add_at(kernels, &xs, params, grads, threads)[1];
        }
        [surface, near, eikonal]
    }

    /// The clearance term at this rank's share of a step's uniform points: max(c − |d|, 0), weighted.
    fn clearance_step(
        &self,
        kernel: &Kernel,
        clearance: &Clearance,
        params: &[f32],
        grads: &mut [f32],
        rng: &mut Rng,
        threads: usize,
    ) -> f32 {
        let m = self.random_here();
        let [x, y, z] = uniform_points(rng, m, self.bound);
        let points: Vec<[f32; 3]> = (0..m).map(|i| [x[i], y[i], z[i]]).collect();
        let (c, outside) = clearance.targets(&points);
        summed_terms(kernel, &[&x, &y, &z, &c, &outside], params, grads, threads)
    }

    /// The eikonal term at the batch's jittered cloud points, when `eikonal_jitter` asks for it.
    fn jittered(&self) -> Option<Regularizers> {
        (self.eikonal_jitter > 0.0 && self.eikonal_weight > 0.0).then_some(Regularizers {
            points: self.batch_here(),
            near_weight: 0.0,
            ..self.regularizers()
        })
    }

    /// This rank's part of a step's cloud points (all of them in one process).
    fn batch_here(&self) -> usize {
        let cluster = crate::cluster::current();
        crate::cluster::part(self.batch, cluster.rank(), cluster.size())
    }

    /// This rank's part of a step's random points.
    fn random_here(&self) -> usize {
        let cluster = crate::cluster::current();
        crate::cluster::part(self.random, cluster.rank(), cluster.size())
    }

    fn regularizers(&self) -> Regularizers {
        Regularizers {
            points: self.random_here(),
            bound: self.bound,
            near_weight: self.near_weight,
            near_sharpness: self.near_sharpness,
            eikonal_weight: self.eikonal_weight,
        }
    }
}

/// Evaluates a loss kernel of one term per point on the columns `inputs` (adding its param gradient to
/// `grads`) and returns the sum of its terms.
fn summed_terms(
    kernel: &Kernel,
    inputs: &[&[f32]],
    params: &[f32],
    grads: &mut [f32],
    threads: usize,
) -> f32 {
    let n = inputs.first().map_or(0, |c| c.len());
    let mut terms = vec![0.0f32; n];
    kernel.eval_parallel(n, inputs, &mut [&mut terms], params, grads, threads);
    terms.iter().map(|&t| f64::from(t)).sum::<f64>() as f32
}

/// A `train sdf` block's objective: pre-training toward a sphere for the first `pretrain_steps`, then the
/// fit's three terms; each step's terms are logged and shown on the progress bar.
struct SdfObjective<'a> {
    plan: &'a TrainSdfPlan,
    kernels: &'a Kernels,
    cloud: &'a [[f32; 3]],
    /// The indexed cloud of the clearance term, when asked for.
    clearance: Option<&'a Clearance>,
    rng: Rng,
    threads: usize,
    /// The last step's surface, near-surface and eikonal terms.
    terms: [f32; 3],
    /// The last step's gradient.
    grads: Vec<f32>,
}

impl Objective for SdfObjective<'_> {
    fn gradient(&mut self, step: u32, _lr: f32, params: &[f32], _ui: &Ui) -> Result<Gradient<'_>> {
        let (plan, k, threads) = (self.plan, self.kernels, self.threads);
        let grads = &mut self.grads;
        grads.clear();
        grads.resize(params.len(), 0.0);
        self.terms = if step < plan.pretrain_steps {
            let sphere = plan.sphere_step(k, params, grads, &mut self.rng, threads);
            [sphere, 0.0, 0.0]
        } else {
            plan.fit_step(
                k,
                params,
                grads,
                self.cloud,
                self.clearance,
                &mut self.rng,
                threads,
            )
        };
        Ok(Gradient {
            loss: self.terms.iter().sum(),
            grads: &mut self.grads,
            samples: 0,
        })
    }

    fn after_step(&mut self, p: &Progress, _params: &[f32], ui: &mut Ui) -> Result<()> {
        if !(p.done.is_multiple_of(10) || p.last) {
            return Ok(());
        }
        let terms = self.terms;
        ui.record(&SdfRecord {
            step: p.done,
            seconds: p.train_seconds,
            lr: Some(p.lr),
            loss: Some(p.loss),
            surface: Some(terms[0]),
            near: Some(terms[1]),
            eikonal: Some(terms[2]),
        })?;
        let pretraining = if p.done <= self.plan.pretrain_steps {
            " (pre-training)"
        } else {
            ""
        };
        ui.message(format!(
            "surface {:.5} near {:.5} eikonal {:.5}{pretraining}",
            terms[0], terms[1], terms[2]
        ));
        Ok(())
    }
}

/// A turntable GIF of a point cloud, framing its bounding box.
fn write_points_gif(path: &std::path::Path, points: &[[f32; 3]]) -> Result<()> {
    let Some(bounds) = bounding_box(points) else {
        return Ok(());
    };
    let frames = crate::settings::camera::turntable(bounds, nerfjit_runtime::Up::Y)?
        .iter()
        .map(|camera| render_points(camera, 256, 256, points, 1.5, [0.9, 0.8, 0.6], [0.1, 0.11, 0.14]))
        .collect::<nerfjit_runtime::Result<Vec<_>>>()?;
    crate::frame_files::write_images(path, frames, 50)
}
