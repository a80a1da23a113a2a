//! Training checkpoints: params and optimizer state with the script that wrote them, written atomically
//! (temporary file, then rename) so that an interrupted write never replaces a good checkpoint. The
//! format follows the file name: a `.json` name gets readable JSON (`json`), any other the binary
//! safetensors format (`binary`); both are read whatever the name.

mod binary_format;
mod json_format;

use std::path::Path;

use nerfjit_dsl::{budget, Program, Type};
use nerfjit_runtime::volume::appearance::TRANSFORM_VALUES;
use nerfjit_runtime::{Adam, OccupancyGrid};

use crate::failure::{Failure, Result};
use crate::settings::values::AdamSettings;

/// The floats a training view keeps in a checkpoint: its colour transform, then its Adam state
/// (`[steps, m…, v…]`).
pub const VIEW_STATE: usize = TRANSFORM_VALUES + 1 + 2 * TRANSFORM_VALUES;

/// The script a checkpoint holds: enough to compile its program again.
pub struct Script {
    /// The script's file name when it was run.
    pub name: String,
    /// Its text.
    pub source: String,
    /// The `--set` overrides it was run with.
    pub overrides: Vec<String>,
}

impl Script {
    /// The script `program` was compiled from.
    pub fn of(program: &Program) -> Script {
        // The source map holds the prelude, the script, then each `--set` override.
        let files = &program.sources.files;
        let (name, source) = files
            .get(1)
            .map(|f| (f.name.clone(), f.text.clone()))
            .unwrap_or_default();
        let overrides = files.iter().skip(2).map(|f| f.text.clone()).collect();
        Script {
            name,
            source,
            overrides,
        }
    }

    /// Compiles the script again, as held by `checkpoint`: its errors say that they are in that copy of
    /// the script (which may differ from the file of the same name, or no longer compile with this version
    /// of nerfjit), not in a file on disk.
    pub fn compile_embedded(&self, checkpoint: &Path) -> Result<Program> {
        nerfjit_dsl::compile_with(&self.name, &self.source, &self.overrides).map_err(|mut report| {
            for d in &mut report.diagnostics {
                d.message = format!(
                    "{} (in the copy of '{}' embedded in checkpoint '{}')",
                    d.message,
                    self.name,
                    checkpoint.display()
                );
            }
            Failure::Script(report)
        })
    }
}

/// A saved training state.
pub struct Saved {
    /// The script that wrote it.
    pub script: Script,
    /// Steps done.
    pub step: u32,
    /// Param values.
    pub params: Vec<f32>,
    /// The optimizer (its learning rate is set by the schedule when training resumes).
    pub adam: Adam,
    /// The fraction of its run the training had done, if the checkpoint says (see [`Kept::run_fraction`]).
    pub run_fraction: Option<f64>,
}

/// Whether `path` names a JSON checkpoint.
pub fn is_json(path: &Path) -> bool {
    path.extension().is_some_and(|e| e == "json")
}

/// What a run keeps in its checkpoint besides its params and Adam's state.
#[derive(Default)]
pub struct Kept<'a> {
    /// The occupancy grid the run renders with.
    pub occupancy: Option<&'a OccupancyGrid>,
    /// The state of the training views' colour transforms ([`crate::training::appearance`]).
    pub appearance: Option<Vec<f32>>,
    /// The fraction of its run the training has done (of its steps or of its time limit, whichever is
    /// further): where a schedule over the run resumes.
    pub run_fraction: Option<f64>,
}

/// Saves a checkpoint, with the script it belongs to (so that `nerfjit render`, `mesh` and `eval-views`
/// can use the checkpoint alone) and what the run keeps (binary checkpoints only: a `train` block with
/// colour transforms refuses a JSON checkpoint, see [`is_json`]), in the format its name asks for.
pub fn write(
    path: &Path,
    program: &Program,
    step: u32,
    params: &[f32],
    adam: &Adam,
    kept: Kept,
) -> Result<()> {
    if is_json(path) {
        let text = json_format::encode(&Script::of(program), step, params, adam, kept.run_fraction);
        Ok(nerfjit_runtime::write_whole(path, text.as_bytes())?)
    } else {
        binary_format::write(path, program, step, params, adam, kept)
    }
}

/// The occupancy grid the run that wrote a binary checkpoint rendered its last validation with, if
/// it kept one (JSON checkpoints keep none).
pub fn saved_occupancy(path: &Path) -> Result<Option<OccupancyGrid>> {
    if is_json(path) {
        return Ok(None);
    }
    binary_format::read_occupancy(path)
}

/// The state of the colour transforms a binary checkpoint keeps, if it keeps them.
pub fn saved_appearance(path: &Path) -> Result<Option<Vec<f32>>> {
    if is_json(path) {
        return Ok(None);
    }
    binary_format::read_appearance(path)
}

/// The script a checkpoint was written by, and its params: the program is compiled again from the source
/// the checkpoint holds.
pub fn load_trained(path: &Path) -> Result<(Program, Vec<f32>)> {
    let (program, saved) = load(path)?;
    Ok((program, saved.params))
}

/// Reads a checkpoint (parsed once, in either format) and compiles the script it holds; its params must
/// fit that script.
fn load(path: &Path) -> Result<(Program, Saved)> {
    let bad = |why: &str| Failure::Message(format!("checkpoint '{}' is not usable: {why}", path.display()));
    let mut start = [0u8; 1];
    let opened = std::fs::File::open(path).and_then(|mut f| std::io::Read::read(&mut f, &mut start));
    opened.map_err(|e| bad(&e.to_string()))?;
    if start[0] != b'{' {
        return binary_format::read(path, &bad);
    }
    let text = nerfjit_runtime::input::read_text_capped(path).map_err(|e| bad(&e.to_string()))?;
    let saved = json_format::decode(&text, &bad)?;
    let program = saved.script.compile_embedded(path)?;
    let n_params = program.n_params();
    if saved.params.len() != n_params {
        return Err(bad(&format!(
            "it holds {} params but the script has {n_params}",
            saved.params.len()
        )));
    }
    Ok((program, saved))
}

/// Where training starts: params, optimizer, step and fraction of the run done from `checkpoint` when
/// resuming and it exists (refused if a script with other params wrote it; a checkpoint that does not
/// say its fraction is taken to be `default_fraction(step)` through its run), else fresh Adam at `lr`
/// from step 0 (params untouched); either way with the decay rates and ε of `settings`. Says on standard
/// error what it resumed, or that there was nothing to resume.
pub fn resume_or_start(
    program: &Program,
    checkpoint: Option<&Path>,
    resume: bool,
    params: &mut Vec<f32>,
    settings: AdamSettings,
    lr: impl Fn(u32, f64) -> f32,
    default_fraction: impl Fn(u32) -> f64,
) -> Result<Start> {
    let n = params.len();
    let what = || format!("training {n} params (values, gradients and Adam's two moments)");
    budget::check(what, budget::bytes_of(n as u64, 16))?;
    let fresh = || {
        Ok(Start {
            adam: configured(Adam::new(n, lr(0, 0.0)), settings, program),
            step: 0,
            run_fraction: 0.0,
        })
    };
    let path = match checkpoint {
        Some(path) if resume && path.exists() => path,
        Some(path) if resume => {
            crate::console::note(&format!(
                "nothing to resume: no checkpoint at '{}' yet; starting at step 0",
                path.display()
            ));
            return fresh();
        }
        None if resume => {
            crate::console::note(
                "nothing to resume: the training block writes no checkpoint; starting at step 0",
            );
            return fresh();
        }
        _ => return fresh(),
    };
    let (written_by, saved) = load(path)?;
    let (theirs, ours) = (param_layout(&written_by), param_layout(program));
    if theirs != ours {
        return Err(Failure::Message(format!(
            "checkpoint '{}' was written by a script with other params ({}) than this one ({}): \
             resume from a checkpoint of this script, or train without --resume",
            path.display(),
            theirs.join(", "),
            ours.join(", ")
        )));
    }
    *params = saved.params;
    let mut adam = saved.adam;
    let run_fraction = saved.run_fraction.unwrap_or_else(|| default_fraction(saved.step));
    adam.lr = lr(saved.step, run_fraction);
    crate::console::note(&format!(
        "resuming from {} at step {}",
        path.display(),
        saved.step
    ));
    Ok(Start {
        adam: configured(adam, settings, program),
        step: saved.step,
        run_fraction,
    })
}

/// Where a training run starts (see [`resume_or_start`]).
pub struct Start {
    /// Adam, its moments and learning rate.
    pub adam: Adam,
    /// The first step to take.
    pub step: u32,
    /// The fraction of the run already done.
    pub run_fraction: f64,
}

/// Each param of `program` as `name: type`.
fn param_layout(program: &Program) -> Vec<String> {
    program
        .params
        .iter()
        .map(|p| format!("{}: {}", p.name, p.ty))
        .collect()
}

/// `adam` with the decay rates and ε of `settings`, and `program`'s grid tables as its sparse ranges if
/// `settings` asks for sparse updates.
fn configured(mut adam: Adam, settings: AdamSettings, program: &Program) -> Adam {
    adam.beta1 = settings.beta1;
    adam.beta2 = settings.beta2;
    adam.eps = settings.eps;
    adam.sparse = if settings.sparse {
        program
            .params
            .iter()
            .filter(|p| matches!(p.ty, Type::Grid(_)))
            .map(|p| p.offset..p.offset + p.ty.scalars())
            .collect()
    } else {
        Vec::new()
    };
    adam
}

/// The error of a training run that produced a non-finite loss or gradient at `step`, saying whether a
/// good checkpoint was kept.
pub fn diverged(
    program: &Program,
    step: u32,
    loss: f32,
    grads: &[f32],
    checkpoint: Option<&Path>,
) -> Failure {
    let kept = match checkpoint {
        Some(p) if p.exists() => format!("the last good checkpoint is kept in '{}'", p.display()),
        _ => "no checkpoint was written".to_string(),
    };
    Failure::Message(format!(
        "training diverged at step {step}: {}; {kept}",
        non_finite(program, loss, grads)
    ))
}

/// What is not finite: the params whose gradients are (each with its first bad element and value), or the
/// loss alone.
fn non_finite(program: &Program, loss: f32, grads: &[f32]) -> String {
    let bad: Vec<String> = program
        .params
        .iter()
        .filter_map(|p| {
            let values = grads.get(p.offset..p.offset + p.ty.scalars())?;
            let (i, g) = values.iter().enumerate().find(|(_, g)| !g.is_finite())?;
            let count = values.iter().filter(|g| !g.is_finite()).count();
            Some(format!(
                "'{}' ({count} of {} elements, the first {i} = {g})",
                p.name,
                values.len()
            ))
        })
        .collect();
    if bad.is_empty() {
        format!("the loss is {loss} while every gradient is finite")
    } else {
        format!(
            "the gradient of {} is not finite (loss {loss}); look for sqrt, log or division of values \
             that can reach 0 or below in the functions reading them",
            bad.join(", ")
        )
    }
}

/// The program and params: a checkpoint's (a `.safetensors` or `.json` file), or a script's initial ones.
pub fn load_source(source: &str) -> Result<(Program, Vec<f32>)> {
    if is_checkpoint(source) {
        load_trained(Path::new(source))
    } else {
        let program = crate::script::load(source)?;
        let params = program.param_values.clone();
        Ok((program, params))
    }
}

/// Whether `source` names a checkpoint (a `.safetensors` or `.json` file) rather than a script.
pub fn is_checkpoint(source: &str) -> bool {
    source.ends_with(".safetensors") || source.ends_with(".json")
}
