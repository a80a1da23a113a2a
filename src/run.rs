//! `nerfjit run`: does what the script's blocks say.

use std::path::Path;
use std::rc::Rc;
use std::sync::Arc;

use indicatif::{ProgressBar, ProgressStyle};
use nerfjit_dsl::config::Settings;
use nerfjit_jit::KernelCache;

use crate::block::{Block, Outputs};
use crate::failure::{at, Failure, Result};
use crate::mesh::MeshPlan;
use crate::render::RenderPlan;
use crate::schema::Kind;
use crate::script;
use crate::train::TrainPlan;
use crate::train_sdf::SdfTrainPlan;
use crate::viewer::{Document, Live, ViewArgs};
use crate::viz::VizPlan;
use crate::volume::VolumePlan;

/// What one block of a script does.
enum Plan {
    Trace(RenderPlan),
    Volume(VolumePlan),
    Train(Box<TrainPlan>),
    Viz(VizPlan),
    FitSdf(SdfTrainPlan),
    Mesh(MeshPlan),
}

fn bar(len: usize, what: &str) -> ProgressBar {
    ProgressBar::new(len as u64).with_style(
        ProgressStyle::with_template(&format!(
            "{{spinner}} {what} [{{bar:30}}] {{pos}}/{{len}} frames {{elapsed}}"
        ))
        .unwrap_or_else(|_| ProgressStyle::default_bar()),
    )
}

/// Runs every block of the script in order; all blocks are checked before the first one runs. Training
/// updates the params that later blocks render with. With `view`, a live viewer follows the training
/// (and stays open after the last block until the process is stopped).
pub fn run(
    path: &str,
    overrides: &[String],
    out_dir: Option<&Path>,
    resume: bool,
    view: Option<&ViewArgs>,
) -> Result<()> {
    let program = script::load_with(path, overrides)?;
    if let Some(dir) = out_dir {
        std::fs::create_dir_all(dir)
            .map_err(|e| Failure::Message(format!("cannot create output folder '{}': {e}", dir.display())))?;
    }
    let script_dir = Path::new(path).parent().unwrap_or(Path::new("."));
    let mut plans = Vec::new();
    let outputs = Rc::new(Outputs::default());
    for block in program.blocks() {
        let settings = Settings::new(&program, block).map_err(|d| at(&program, d))?;
        let b = Block::new(&program, settings, script_dir, out_dir, Rc::clone(&outputs))?;
        plans.push(match b.schema().id {
            Kind::SphereTrace => Plan::Trace(RenderPlan::new(b)?),
            Kind::Volume => Plan::Volume(VolumePlan::new(b)?),
            Kind::Train => Plan::Train(Box::new(TrainPlan::new(b)?)),
            Kind::Viz => Plan::Viz(VizPlan::new(b)?),
            Kind::TrainSdf => Plan::FitSdf(SdfTrainPlan::new(b)?),
            Kind::Mesh => Plan::Mesh(MeshPlan::new(b)?),
        });
    }
    if plans.is_empty() {
        return Err(Failure::Message(format!(
            "{path} has nothing to run: add a block such as 'render sphere_trace {{ camera: ..., out: \"scene.gif\" }}'"
        )));
    }
    let live = match view {
        Some(args) => {
            let live = Arc::new(Live::new());
            let document = Document::of(&program, program.param_values.clone(), false)?;
            crate::viewer::attach(args, document, Arc::clone(&live))?;
            Some(live)
        }
        None => None,
    };
    let mut params = program.param_values.clone();
    // One cache for every block: a field trained and then rendered or meshed is compiled once.
    let cache = KernelCache::new();
    for plan in &plans {
        let summary = match plan {
            Plan::Trace(p) => {
                let bar = bar(p.cameras.len(), "rendering");
                let summary = p.run(&program, &params, &cache, &|done| bar.set_position(done as u64))?;
                bar.finish_and_clear();
                summary
            }
            Plan::Volume(p) => {
                let bar = bar(p.cameras.len(), "volume rendering");
                let summary = p.run(&program, &params, &cache, &|done| bar.set_position(done as u64))?;
                bar.finish_and_clear();
                summary
            }
            Plan::Train(p) => p.run(&program, &mut params, &cache, resume, live.as_deref())?,
            Plan::Viz(p) => p.run()?,
            Plan::FitSdf(p) => p.run(&program, &mut params, resume)?,
            Plan::Mesh(p) => p.run(&program, &params, &cache)?,
        };
        crate::emit(&format!("{summary}\n"));
    }
    if live.is_some() {
        eprintln!("done: the viewer stays open until Ctrl-C");
        loop {
            std::thread::park();
        }
    }
    Ok(())
}
