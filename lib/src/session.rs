//! A script and its state between calls: the checked program, its current params, one kernel cache, and
//! a plan for each block. `nerfjit run` is a [`Session`] run block by block with progress bars; a Rust
//! program can run the same blocks, read and change the params between them, and render with what a
//! `train` block learned without compiling the field again.
//!
//! Fitting the course's box from Rust (its four views are first rendered by a script of the true box):
//!
//! ```
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! use nerfjit::session::Session;
//! let dir = std::env::temp_dir().join(format!("nerfjit-session-{}", std::process::id()));
//! std::fs::create_dir_all(&dir)?;
//! let camera = |image: &str, eye: &str| format!(r#"{{"image": "{image}", "focal": 1.0, "principal_point": [0, 0],
//!     "eye": {eye}, "scene_center": [0, 0, 0], "up": [0, 1, 0]}}"#);
//! let cameras = [camera("v_000.png", "[-2.5, 0.3, 0]"), camera("v_001.png", "[-1, 0.5, -2.2]"),
//!                camera("v_002.png", "[0, -0.4, -2.5]"), camera("v_003.png", "[1.8, 0.8, -1.6]")];
//! let json = format!(r#"{{"image_size": [40, 40], "cameras": [{}]}}"#, cameras.join(","));
//! std::fs::write(dir.join("cams.json"), json)?;
//! let field = "fn opacity(p: vec3) -> f32 = opacity_laplace(box(p - center, sides), alpha: 1.0, beta: 0.05)
//!              fn color(p: vec3) -> vec3 = clamp(abs(p - center), 0.02, 0.98)";
//! let truth = format!("const center = [0.2, -0.1, 0.1]\nconst sides = [1.2, 0.8, 1.0]\n{field}\n\
//!     render volume {{ camera: cameras(\"cams.json\"), size: 40, near: 0, far: 5, samples: 48, out: \"v.png\" }}");
//! Session::from_source("truth.sdf", &truth, &dir)?.run()?;
//! let fit = format!("param center: vec3 = [0, 0, 0]\nparam sides: vec3 = [1, 1, 1]\n{field}\n\
//!     train {{ data: views(\"cams.json\"), near: 0, far: 5, samples: 48, steps: 300, batch: 800, lr: 0.01 }}");
//! let mut session = Session::from_source("fit.sdf", &fit, &dir)?;
//! session.run()?;
//! let center = session.param("center").expect("a param of the script");
//! for (got, want) in center.iter().zip([0.2, -0.1, 0.1]) {
//!     assert!((got - want).abs() < 0.01, "learned center {center:?}");
//! }
//! # std::fs::remove_dir_all(&dir)?;
//! # Ok(())
//! # }
//! ```

use std::path::{Path, PathBuf};
use std::rc::Rc;

use nerfjit_dsl::config::Settings;
use nerfjit_dsl::{compile_with, Program};
use nerfjit_jit::KernelCache;
use nerfjit_runtime::OccupancyGrid;

use crate::blocks::bake::BakePlan;
use crate::blocks::mesh::MeshPlan;
use crate::blocks::sphere_trace::SphereTracePlan;
use crate::blocks::train::TrainPlan;
use crate::blocks::train_sdf::TrainSdfPlan;
use crate::blocks::viz::VizPlan;
use crate::blocks::volume::VolumePlan;
use crate::failure::{at, Failure, Result};
use crate::observe::{NoBars, ProgressBars, TrainingObserver};
use crate::script;
use crate::settings::block::{Block, Outputs};
use crate::settings::schema::Kind;

/// The field a `bake` block bakes: the script's program with its params as they are when the block runs.
pub struct FieldToBake<'a> {
    /// The checked program.
    pub program: &'a Program,
    /// The params as they are at that point of the script.
    pub params: &'a [f32],
    /// The script's path: relative inputs (the train block's data) are found next to it, and the bake
    /// records it as what it was baked from.
    pub script: &'a Path,
    /// The occupancy grid the last `train` block ended with, while the params are the ones it trained.
    pub grid: Option<&'a OccupancyGrid>,
    /// The checkpoint the last `train` block wrote: it holds the script as it ran (`--set` overrides
    /// included), whose data and protocol the bake records as its source.
    pub checkpoint: Option<&'a Path>,
}

/// Bakes the field of a `bake` block as the block's plan says and writes the bake; returns a summary. The
/// baking lives above the session, in the commands: `nerfjit run` gives
/// [`crate::commands::bake::bake_block`].
pub type Baker<'a> = dyn Fn(&BakePlan, &FieldToBake<'_>) -> Result<String> + Sync + 'a;

/// What a caller follows of a running block, and how training starts and blocks bake.
#[derive(Default)]
pub struct Observer<'a> {
    /// Called as a render block finishes frames, with the frames done so far.
    pub frames: Option<&'a (dyn Fn(usize) + Sync)>,
    /// A live viewer that follows training (its progress and params).
    pub live: Option<&'a dyn TrainingObserver>,
    /// Training continues from the block's checkpoint when there is one.
    pub resume: bool,
    /// The progress bars of training (none when not given).
    pub bars: Option<&'a dyn ProgressBars>,
    /// What runs `bake` blocks (without one, a `bake` block is an error).
    pub baker: Option<&'a Baker<'a>>,
}

impl Observer<'_> {
    /// The progress bars to draw (none when not given).
    pub fn bars(&self) -> &dyn ProgressBars {
        self.bars.unwrap_or(&NoBars)
    }
}

/// What one block of a script does, with its settings read and checked.
enum Plan {
    SphereTrace(SphereTracePlan),
    Volume(VolumePlan),
    Train(Box<TrainPlan>),
    Viz(VizPlan),
    TrainSdf(TrainSdfPlan),
    Mesh(MeshPlan),
    Bake(BakePlan),
}

/// A checked script with its params and compiled kernels, ready to run its blocks.
pub struct Session {
    program: Program,
    /// The script's path (relative inputs are found next to it).
    script: PathBuf,
    params: Vec<f32>,
    cache: KernelCache,
    plans: Vec<Plan>,
    /// The occupancy grid the last `train` block ended with, while the params are the ones it trained.
    trained_grid: Option<OccupancyGrid>,
    /// The checkpoint the last `train` block wrote (none after a `train sdf` block).
    trained_checkpoint: Option<PathBuf>,
}

impl Session {
    /// Reads and checks the script at `path` (or the embedded example it names) with `--set` style
    /// `overrides`; relative inputs are found next to the script and outputs written to `out_dir` (created
    /// if needed) or, without one, next to the script. Every block is checked before any runs.
    pub fn open(path: &str, overrides: &[String], out_dir: Option<&Path>) -> Result<Session> {
        let program = script::load_with(path, overrides)?;
        Session::of(program, Path::new(path), out_dir)
    }

    /// Checks the script `source` (called `name` in messages) whose relative files live in `dir`, where
    /// its outputs are written too.
    pub fn from_source(name: &str, source: &str, dir: &Path) -> Result<Session> {
        let program = compile_with(name, source, &[]).map_err(Failure::Script)?;
        Session::of(program, &dir.join(name), Some(dir))
    }

    /// Plans the blocks of `program`, compiled from the script at `script`.
    fn of(program: Program, script: &Path, out_dir: Option<&Path>) -> Result<Session> {
        let script_dir = script.parent().unwrap_or(Path::new("."));
        if let Some(dir) = out_dir {
            std::fs::create_dir_all(dir).map_err(|e| {
                Failure::Message(format!("cannot create output folder '{}': {e}", dir.display()))
            })?;
        }
        let outputs = Rc::new(Outputs::default());
        let mut plans = Vec::new();
        for block in program.blocks() {
            let settings = Settings::new(&program, block).map_err(|d| at(&program, d))?;
            let b = Block::new(&program, settings, script_dir, out_dir, Rc::clone(&outputs))?;
            plans.push(match b.schema().id {
                Kind::SphereTrace => Plan::SphereTrace(SphereTracePlan::new(b)?),
                Kind::Volume => Plan::Volume(VolumePlan::new(b)?),
                Kind::Train => Plan::Train(Box::new(TrainPlan::new(b)?)),
                Kind::Viz => Plan::Viz(VizPlan::new(b)?),
                Kind::TrainSdf => Plan::TrainSdf(TrainSdfPlan::new(b)?),
                Kind::Mesh => Plan::Mesh(MeshPlan::new(b)?),
                Kind::Bake => Plan::Bake(BakePlan::new(b)?),
            });
        }
        let params = program.param_values.clone();
        Ok(Session {
            program,
            script: script.to_path_buf(),
            params,
            cache: KernelCache::new(),
            plans,
            trained_grid: None,
            trained_checkpoint: None,
        })
    }

    /// The checked program.
    pub fn program(&self) -> &Program {
        &self.program
    }

    /// The current values of all params, in the program's order (`ParamInfo::offset`): the script's
    /// initial values until a training block has run.
    pub fn params(&self) -> &[f32] {
        &self.params
    }

    /// The current values of the param called `name`.
    pub fn param(&self, name: &str) -> Option<&[f32]> {
        let p = self.program.params.iter().find(|p| p.name == name)?;
        Some(&self.params[p.offset..p.offset + p.ty.scalars()])
    }

    /// Replaces the values of the param called `name` (which must hold as many values as its type).
    pub fn set_param(&mut self, name: &str, values: &[f32]) -> Result<()> {
        let p = self
            .program
            .params
            .iter()
            .find(|p| p.name == name)
            .ok_or_else(|| Failure::Message(format!("the script has no param '{name}'")))?;
        if values.len() != p.ty.scalars() {
            return Err(Failure::Message(format!(
                "param '{name}' of type {} holds {} values, not {}",
                p.ty,
                p.ty.scalars(),
                values.len()
            )));
        }
        self.params[p.offset..p.offset + values.len()].copy_from_slice(values);
        self.trained_grid = None;
        Ok(())
    }

    /// How many blocks the script has.
    pub fn len(&self) -> usize {
        self.plans.len()
    }

    /// Whether the script has no block to run.
    pub fn is_empty(&self) -> bool {
        self.plans.is_empty()
    }

    /// The kind of block `index`.
    pub fn kind(&self, index: usize) -> Kind {
        match &self.plans[index] {
            Plan::SphereTrace(_) => Kind::SphereTrace,
            Plan::Volume(_) => Kind::Volume,
            Plan::Train(_) => Kind::Train,
            Plan::Viz(_) => Kind::Viz,
            Plan::TrainSdf(_) => Kind::TrainSdf,
            Plan::Mesh(_) => Kind::Mesh,
            Plan::Bake(_) => Kind::Bake,
        }
    }

    /// The frames a render block writes (0 for other blocks).
    pub fn frames(&self, index: usize) -> usize {
        match &self.plans[index] {
            Plan::SphereTrace(p) => p.cameras.len(),
            Plan::Volume(p) => p.cameras.len(),
            _ => 0,
        }
    }

    /// The seconds of training block `index` is given by time: a `train` block's `minutes`, a `bake`
    /// block's `tune` (`None` for other blocks and those without a time limit).
    pub fn timed_seconds(&self, index: usize) -> Option<f64> {
        match &self.plans[index] {
            Plan::Train(p) => p.time_limit(),
            Plan::Bake(p) => (p.tune_seconds > 0.0).then_some(p.tune_seconds),
            _ => None,
        }
    }

    /// Runs block `index` with the current params (a training block updates them); returns its summary.
    pub fn run_block(&mut self, index: usize, observer: &Observer) -> Result<String> {
        let frames = |done: usize| {
            if let Some(f) = observer.frames {
                f(done)
            }
        };
        let (program, params, cache) = (&self.program, &mut self.params, &self.cache);
        // In an MPI job, diagrams are made by rank 0 alone (meshes are split over the ranks by slabs).
        let not_root = crate::cluster::current().rank() != 0;
        if not_root && matches!(self.plans[index], Plan::Viz(_)) {
            return Ok(String::new());
        }
        match &self.plans[index] {
            Plan::SphereTrace(p) => p.run(program, params, cache, &frames),
            Plan::Volume(p) => p.run(program, params, cache, self.trained_grid.as_ref(), &frames),
            Plan::Train(p) => {
                self.trained_grid = None;
                self.trained_checkpoint = None;
                let trained = p.run(
                    program,
                    params,
                    cache,
                    observer.resume,
                    observer.live,
                    observer.bars(),
                )?;
                self.trained_grid = trained.occupancy;
                self.trained_checkpoint = p.checkpoint().filter(|c| c.is_file()).map(Path::to_path_buf);
                Ok(trained.summary)
            }
            Plan::Viz(p) => p.run(),
            Plan::TrainSdf(p) => {
                self.trained_grid = None;
                self.trained_checkpoint = None;
                p.run(program, params, cache, observer.resume, observer.bars())
            }
            Plan::Mesh(p) => {
                // A mesh of a function fitted to a cloud scaled into the unit sphere is written in the cloud's
                // units: the frame of the last point-cloud fit before this block.
                let fit = self.plans[..index].iter().rev().find_map(|p| match p {
                    Plan::TrainSdf(fit) => Some(fit),
                    _ => None,
                });
                let frame = fit.map(TrainSdfPlan::normalized_frame).transpose()?.flatten();
                p.run(program, params, cache, frame)
            }
            Plan::Bake(p) => {
                let baker = observer.baker.ok_or_else(|| {
                    Failure::Message(format!(
                        "block {} is a bake block, and this run has no baker: run the script with `nerfjit run` \
                         (or give the session's Observer `nerfjit::commands::bake::bake_block` as its baker)",
                        index + 1
                    ))
                })?;
                let field = FieldToBake {
                    program,
                    params,
                    script: &self.script,
                    grid: self.trained_grid.as_ref(),
                    checkpoint: self.trained_checkpoint.as_deref(),
                };
                baker(p, &field)
            }
        }
    }

    /// Runs every block in order, quietly; returns their summaries.
    pub fn run(&mut self) -> Result<Vec<String>> {
        (0..self.len())
            .map(|i| self.run_block(i, &Observer::default()))
            .collect()
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    fn session(source: &str) -> Session {
        Session::from_source("test.sdf", source, &std::env::temp_dir()).expect("a valid script")
    }

    #[test]
    fn params_are_read_and_replaced_by_name() {
        let mut s = session(
            "param c: vec3 = [1, 2, 3]\nparam r: f32 = 0.5\nfn sdf(p: vec3) -> f32 = length(p - c) - r\n",
        );
        assert_eq!(s.param("c"), Some(&[1.0, 2.0, 3.0][..]));
        assert_eq!(s.param("nothing"), None);
        s.set_param("r", &[0.25]).unwrap();
        assert_eq!(s.params(), &[1.0, 2.0, 3.0, 0.25]);
        let wrong = s.set_param("c", &[1.0]).unwrap_err().to_string();
        assert!(wrong.contains("holds 3 values, not 1"), "{wrong}");
        let unknown = s.set_param("d", &[1.0]).unwrap_err().to_string();
        assert!(unknown.contains("no param 'd'"), "{unknown}");
        assert!(s.is_empty());
    }

    #[test]
    fn blocks_run_one_at_a_time_with_the_params_set_between_them() {
        let out = std::env::temp_dir().join(format!("nerfjit-session-test-{}", std::process::id()));
        std::fs::create_dir_all(&out).unwrap();
        let source = "param r: f32 = 0.5\nfn sdf(p: vec3) -> f32 = length(p) - r\n\
                      mesh { resolution: 16, bounds: 1.0, out: \"ball.obj\" }\n";
        let mut s = Session::from_source("ball.sdf", source, &out).unwrap();
        assert_eq!((s.len(), s.kind(0), s.frames(0)), (1, Kind::Mesh, 0));
        let size = |s: &mut Session| {
            s.run_block(0, &Observer::default()).unwrap();
            let obj = std::fs::read_to_string(out.join("ball.obj")).unwrap();
            obj.lines()
                .filter_map(|l| l.strip_prefix("v "))
                .map(|v| {
                    v.split(' ')
                        .map(|x| x.parse::<f32>().unwrap().abs())
                        .fold(0.0, f32::max)
                })
                .fold(0.0, f32::max)
        };
        let small = size(&mut s);
        s.set_param("r", &[0.8]).unwrap();
        let large = size(&mut s);
        assert!(
            (small - 0.5).abs() < 0.05 && (large - 0.8).abs() < 0.05,
            "{small} {large}"
        );
        std::fs::remove_dir_all(&out).unwrap();
    }

    /// A new folder in the OS temp folder named after `name` holding `cams.json`: one 8×8 camera looking at
    /// the origin (its image is not there; sessions plan without reading it).
    pub(crate) fn folder_with_one_camera(name: &str) -> PathBuf {
        let out = std::env::temp_dir().join(format!("nerfjit-{name}-{}", std::process::id()));
        std::fs::create_dir_all(&out).unwrap();
        std::fs::write(
            out.join("cams.json"),
            r#"{"image_size": [8, 8], "cameras": [{"image": "v_000.png", "focal": 1.0,
            "principal_point": [0, 0], "eye": [0, 0, -3], "scene_center": [0, 0, 0], "up": [0, 1, 0]}]}"#,
        )
        .unwrap();
        out
    }

    #[test]
    fn a_bake_block_goes_to_the_baker_with_its_settings_and_the_current_params() {
        let out = folder_with_one_camera("session-bake");
        let source = "param r: f32 = 0.5\nfn density(p: vec3) -> f32 = relu(r - length(p))\n\
                      fn color(p: vec3) -> vec3 = [1, 1, 1]\n\
                      train { data: views(\"cams.json\"), steps: 1, checkpoint: none }\n\
                      bake { out: \"ball.bake\", tune: 2.5, sh_degree: 0, size: 64 }\n";
        let mut s = Session::from_source("ball.sdf", source, &out).unwrap();
        assert_eq!(s.kind(1), Kind::Bake);
        let refused = s.run_block(1, &Observer::default()).unwrap_err().to_string();
        assert!(refused.contains("no baker"), "{refused}");
        s.set_param("r", &[0.75]).unwrap();
        let baker = |plan: &BakePlan, field: &FieldToBake| -> Result<String> {
            assert_eq!(plan.out, out.join("ball.bake"));
            assert_eq!((plan.tune_seconds, plan.sh_degree, plan.size), (2.5, 0, Some(64)));
            assert_eq!((plan.min_weight, plan.min_opacity), (1.0, 0.5));
            assert_eq!(field.script, out.join("ball.sdf"));
            assert!(field.grid.is_none());
            Ok(format!("baked r = {:?}", field.params))
        };
        let observer = Observer {
            baker: Some(&baker),
            ..Observer::default()
        };
        assert_eq!(s.run_block(1, &observer).unwrap(), "baked r = [0.75]");
        std::fs::remove_dir_all(&out).unwrap();
    }

    #[test]
    fn renders_after_training_skip_the_cells_of_the_trained_grid() {
        let out = std::env::temp_dir().join(format!("nerfjit-session-grid-{}", std::process::id()));
        std::fs::create_dir_all(&out).unwrap();
        let camera = |image: &str, eye: &str| {
            format!(
                r#"{{"image": "{image}", "focal": 1.0, "principal_point": [0, 0], "eye": {eye},
                "scene_center": [0, 0, 0], "up": [0, 1, 0]}}"#
            )
        };
        let json = format!(
            r#"{{"image_size": [16, 16], "cameras": [{}, {}]}}"#,
            camera("v_000.png", "[-2.5, 0.3, 0]"),
            camera("v_001.png", "[0, -0.4, -2.5]")
        );
        std::fs::write(out.join("cams.json"), json).unwrap();
        let field = "fn opacity(p: vec3) -> f32 = opacity_laplace(box(p - center, [1, 0.8, 1]), alpha: 1.0, beta: 0.05)\n\
                     fn color(p: vec3) -> vec3 = clamp(abs(p - center), 0.02, 0.98)\n";
        let views = "camera: cameras(\"cams.json\"), size: 16, near: 0, far: 5, samples: 32";
        let truth =
            format!("const center = [0.2, 0, 0]\n{field}render volume {{ {views}, out: \"v.png\" }}\n");
        Session::from_source("truth.sdf", &truth, &out)
            .unwrap()
            .run()
            .unwrap();
        let grid = |resolution: u32| {
            format!("skip_empty: grid(bounds: 2, resolution: {resolution}, threshold: 0.001)")
        };
        let fit = format!(
            "param center: vec3 = [0, 0, 0]\n{field}\
             train {{ data: views(\"cams.json\"), near: 0, far: 5, samples: 32, steps: 20, batch: 128, \
             checkpoint: none, {}, grid_warmup: 10, grid_every: 5 }}\n\
             render volume {{ {views}, {}, out: \"same.png\" }}\n\
             render volume {{ {views}, {}, out: \"other.png\" }}\n",
            grid(16),
            grid(16),
            grid(8)
        );
        let mut s = Session::from_source("fit.sdf", &fit, &out).unwrap();
        let summaries = s.run().unwrap();
        assert!(
            summaries[1].contains("the train block's occupancy grid"),
            "{}",
            summaries[1]
        );
        assert!(
            summaries[2].contains("occupancy grid built in"),
            "{}",
            summaries[2]
        );
        // Params changed after training: the trained grid no longer describes them.
        s.set_param("center", &[0.1, 0.0, 0.0]).unwrap();
        let again = s.run_block(1, &Observer::default()).unwrap();
        assert!(again.contains("occupancy grid built in"), "{again}");
        std::fs::remove_dir_all(&out).unwrap();
    }
}
