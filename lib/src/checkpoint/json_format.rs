//! The JSON checkpoint format (`nerfjit-checkpoint-1`): readable text, written when a checkpoint's file
//! name ends in `.json`, and the format of checkpoints written before the binary one.

use nerfjit_runtime::Adam;

use super::{Saved, Script};
use crate::failure::Result;

/// The checkpoint as JSON text (`run_fraction` only where known).
pub fn encode(script: &Script, step: u32, params: &[f32], adam: &Adam, run_fraction: Option<f64>) -> String {
    let mut json = serde_json::json!({
        "format": "nerfjit-checkpoint-1",
        "script": { "name": script.name, "source": script.source, "overrides": script.overrides },
        "step": step,
        "params": params,
        "adam": adam.state(),
    });
    if let Some(fraction) = run_fraction {
        json["run_fraction"] = fraction.into();
    }
    json.to_string()
}

/// Reads a JSON checkpoint's text; `bad` words an error about it.
pub fn decode(text: &str, bad: &dyn Fn(&str) -> crate::failure::Failure) -> Result<Saved> {
    let json: serde_json::Value =
        serde_json::from_str(text).map_err(|e| bad(&format!("invalid JSON ({e})")))?;
    let (Some(name), Some(source)) = (json["script"]["name"].as_str(), json["script"]["source"].as_str())
    else {
        return Err(bad("it holds no script"));
    };
    let overrides: Vec<String> = json["script"]["overrides"]
        .as_array()
        .map(|a| a.iter().filter_map(|v| v.as_str().map(str::to_string)).collect())
        .unwrap_or_default();
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
    let state = floats("adam")?;
    let adam = Adam::from_state(params.len(), 0.0, &state).map_err(|e| bad(&e.to_string()))?;
    let run_fraction = match json.get("run_fraction") {
        None => None,
        Some(f) => Some(
            f.as_f64()
                .filter(|f| (0.0..=1.0).contains(f))
                .ok_or_else(|| bad("its 'run_fraction' is not a number from 0 to 1"))?,
        ),
    };
    Ok(Saved {
        script: Script {
            name: name.to_string(),
            source: source.to_string(),
            overrides,
        },
        step,
        params,
        adam,
        run_fraction,
    })
}
