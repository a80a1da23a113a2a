//! Training checkpoints: params and optimizer state as JSON, written atomically (temporary file, then
//! rename) so that an interrupted write never replaces a good checkpoint.

use std::path::Path;

use nerfjit_dsl::Program;
use nerfjit_runtime::Adam;

use crate::failure::{Failure, Result};
use crate::train::AdamSettings;

/// A saved training state.
pub struct Checkpoint {
    /// Steps done.
    pub step: u32,
    /// Param values.
    pub params: Vec<f32>,
    /// The optimizer's state.
    pub adam: Vec<f32>,
}

/// Writes `text` to `path` atomically.
pub fn write_atomic(path: &Path, text: &str) -> Result<()> {
    let tmp = path.with_extension("tmp");
    let fail = |e: std::io::Error| Failure::Message(format!("cannot write '{}': {e}", path.display()));
    std::fs::write(&tmp, text).map_err(fail)?;
    std::fs::rename(&tmp, path).map_err(fail)
}

/// Saves a checkpoint, with the script it belongs to (so that `nerfjit render` and `eval-views` can use
/// the checkpoint alone).
pub fn write(path: &Path, program: &Program, step: u32, params: &[f32], adam: &[f32]) -> Result<()> {
    // The source map holds the prelude, the script, then each `--set` override.
    let files = &program.sources.files;
    let (name, source) = files
        .get(1)
        .map(|f| (f.name.as_str(), f.text.as_str()))
        .unwrap_or_default();
    let overrides: Vec<&str> = files.iter().skip(2).map(|f| f.text.as_str()).collect();
    let json = serde_json::json!({
        "format": "nerfjit-checkpoint-1",
        "script": { "name": name, "source": source, "overrides": overrides },
        "step": step,
        "params": params,
        "adam": adam,
    });
    write_atomic(path, &json.to_string())
}

/// The script a checkpoint was written by, and its params: the program is compiled again from the source
/// the checkpoint holds.
pub fn load_trained(path: &Path) -> Result<(Program, Vec<f32>)> {
    let (program, ck) = load(path)?;
    Ok((program, ck.params))
}

/// Reads a checkpoint (parsed once) and compiles the script it holds; its params must fit that script.
fn load(path: &Path) -> Result<(Program, Checkpoint)> {
    let bad = |why: &str| Failure::Message(format!("checkpoint '{}' is not usable: {why}", path.display()));
    let text = std::fs::read_to_string(path).map_err(|e| bad(&e.to_string()))?;
    let json: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| bad(&format!("invalid JSON ({e})")))?;
    let (Some(name), Some(source)) = (json["script"]["name"].as_str(), json["script"]["source"].as_str())
    else {
        return Err(bad("it holds no script"));
    };
    let overrides: Vec<String> = json["script"]["overrides"]
        .as_array()
        .map(|a| a.iter().filter_map(|v| v.as_str().map(str::to_string)).collect())
        .unwrap_or_default();
    let program = nerfjit_dsl::compile_with(name, source, &overrides).map_err(Failure::Script)?;
    let floats = |key: &str| -> Result<Vec<f32>> {
        json[key]
            .as_array()
            .ok_or_else(|| bad(&format!("no '{key}' array")))?
            .iter()
            .map(|v| {
                let x = v
                    .as_f64()
                    .ok_or_else(|| bad(&format!("'{key}' holds a non-number")))?
                    as f32;
                if x.is_finite() {
                    Ok(x)
                } else {
                    Err(bad(&format!(
                        "'{key}' holds {v}, beyond the range of a 32-bit float"
                    )))
                }
            })
            .collect()
    };
    let step = json["step"]
        .as_u64()
        .and_then(|s| u32::try_from(s).ok())
        .ok_or_else(|| bad("no 'step', or not a step count"))?;
    let params = floats("params")?;
    let n_params = program.n_params();
    if params.len() != n_params {
        return Err(bad(&format!(
            "it holds {} params but the script has {n_params}",
            params.len()
        )));
    }
    let ck = Checkpoint {
        step,
        params,
        adam: floats("adam")?,
    };
    Ok((program, ck))
}

/// Where training starts: params, optimizer and step from `checkpoint` when resuming and it exists
/// (refused if a script with other params wrote it), else fresh Adam at `lr` from step 0 (params
/// untouched); either way with the decay rates and ε of `settings`. Says on standard error what it
/// resumed, or that there was nothing to resume.
pub fn resume_or_start(
    program: &Program,
    checkpoint: Option<&Path>,
    resume: bool,
    params: &mut Vec<f32>,
    settings: AdamSettings,
    lr: impl Fn(u32) -> f32,
) -> Result<(Adam, u32)> {
    let n = params.len();
    let fresh = || Ok((configured(Adam::new(n, lr(0)), settings), 0));
    let path = match checkpoint {
        Some(path) if resume && path.exists() => path,
        Some(path) if resume => {
            eprintln!(
                "nothing to resume: no checkpoint at '{}' yet; starting at step 0",
                path.display()
            );
            return fresh();
        }
        None if resume => {
            eprintln!("nothing to resume: the training block writes no checkpoint; starting at step 0");
            return fresh();
        }
        _ => return fresh(),
    };
    let (written_by, ck) = load(path)?;
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
    *params = ck.params;
    let adam = Adam::from_state(n, lr(ck.step), &ck.adam)?;
    eprintln!("resuming from {} at step {}", path.display(), ck.step);
    Ok((configured(adam, settings), ck.step))
}

/// Each param of `program` as `name: type`.
fn param_layout(program: &Program) -> Vec<String> {
    program
        .params
        .iter()
        .map(|p| format!("{}: {}", p.name, p.ty))
        .collect()
}

/// `adam` with the decay rates and ε of `settings`.
fn configured(mut adam: Adam, settings: AdamSettings) -> Adam {
    adam.beta1 = settings.beta1;
    adam.beta2 = settings.beta2;
    adam.eps = settings.eps;
    adam
}

/// The error of a training run that produced a non-finite loss or gradient at `step`, saying whether a
/// good checkpoint was kept.
pub fn diverged(step: u32, loss: f32, checkpoint: Option<&Path>) -> Failure {
    let kept = match checkpoint {
        Some(p) if p.exists() => format!("the last good checkpoint is kept in '{}'", p.display()),
        _ => "no checkpoint was written".to_string(),
    };
    Failure::Message(format!(
        "training diverged at step {step}: the loss or a gradient is not finite (loss {loss}); {kept}"
    ))
}
