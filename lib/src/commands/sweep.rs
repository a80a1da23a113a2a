//! `nerfjit sweep`: runs a script once for every combination of the values given to its consts and block
//! settings (a grid search), one run after another, each in its own folder, and writes one table of every
//! run's final metrics (`sweep.json` and `sweep.md`).
//!
//! Each run is exactly `nerfjit run SCRIPT --out FOLDER --set NAME=VALUE ...`; its metrics are the last
//! value of each column of its training blocks' metrics logs (loss, PSNR, validation PSNR and SSIM, ...).
//! Every combination is checked (the script compiled with its overrides) before the first run starts.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use crate::commands::run::{open, run_session};
use crate::failure::{Failure, Result};
use crate::observe::ProgressBars;

/// One axis of the grid: a const or block setting (as `--set` names it) and the values it takes.
#[derive(Clone, Debug, PartialEq)]
pub struct Axis {
    /// The name, e.g. `beta` or `train.lr`.
    pub name: String,
    /// The values, each as a script would write it.
    pub values: Vec<String>,
}

/// Parses `NAME=[v1, v2, ...]` (or `NAME=v`, one value) into an axis. Values are split at the commas of the
/// list's top level, so a value may itself hold lists, calls and strings
/// (`train.data=[blender("a.json", views: 20), blender("a.json", views: 5)]`).
pub fn parse_axis(text: &str) -> std::result::Result<Axis, String> {
    let (name, value) = text
        .split_once('=')
        .ok_or_else(|| format!("'{text}' is not NAME=[VALUE, ...] (e.g. 'train.lr=[1e-3, 1e-2]')"))?;
    let name = name.trim();
    if name.is_empty() {
        return Err(format!("'{text}' names nothing before '='"));
    }
    let value = value.trim();
    let values = match value.strip_prefix('[').and_then(|v| v.strip_suffix(']')) {
        Some(list) => split_top_level(list)?,
        None => vec![value.to_string()],
    };
    if values.iter().any(String::is_empty) {
        return Err(format!("'{text}' has an empty value"));
    }
    Ok(Axis {
        name: name.to_string(),
        values,
    })
}

/// The items of a comma-separated list, split only where no bracket, parenthesis, brace or string is open.
fn split_top_level(list: &str) -> std::result::Result<Vec<String>, String> {
    let (mut items, mut current, mut depth, mut quoted) = (Vec::new(), String::new(), 0i32, false);
    for c in list.chars() {
        match c {
            '"' => quoted = !quoted,
            '[' | '(' | '{' if !quoted => depth += 1,
            ']' | ')' | '}' if !quoted => depth -= 1,
            ',' if !quoted && depth == 0 => {
                items.push(current.trim().to_string());
                current.clear();
                continue;
            }
            _ => {}
        }
        if depth < 0 {
            return Err(format!("'[{list}]' closes a bracket it did not open"));
        }
        current.push(c);
    }
    if quoted || depth != 0 {
        return Err(format!("'[{list}]' leaves a string or bracket open"));
    }
    items.push(current.trim().to_string());
    Ok(items)
}

/// Every combination of the axes' values, as `--set` overrides, the last axis varying fastest.
pub fn combinations(axes: &[Axis]) -> Vec<Vec<String>> {
    axes.iter().fold(vec![Vec::new()], |runs, axis| {
        runs.iter()
            .flat_map(|run| {
                axis.values.iter().map(move |v| {
                    let mut next = run.clone();
                    next.push(format!("{}={v}", axis.name));
                    next
                })
            })
            .collect()
    })
}

/// The most runs one sweep may have.
pub const MAX_RUNS: usize = 10_000;

/// Runs `script` for every combination of `axes` (an axis of one value sets it in every run), each in
/// `out/run_NNN/`, and
/// writes `out/sweep.json` and `out/sweep.md`; returns the table. A failed run is reported in the table and
/// the sweep goes on; Ctrl-C stops it after writing the table of the runs so far. In an MPI job the ranks
/// share the runs (each run on one rank, by itself) and rank 0 writes the table.
pub fn sweep(script: &str, axes: &[Axis], out: &Path, bars: &dyn ProgressBars) -> Result<String> {
    let runs = combinations(axes);
    if runs.len() > MAX_RUNS {
        return Err(Failure::Message(format!(
            "the sweep has {} runs, more than {MAX_RUNS}: give fewer values",
            runs.len()
        )));
    }
    // Every combination must check before hours go into the first runs.
    for run in &runs {
        open(script, run, None).map_err(|e| {
            Failure::Message(format!(
                "the sweep's run with {} does not check:\n{e}",
                run.join(" ")
            ))
        })?;
    }
    std::fs::create_dir_all(out)
        .map_err(|e| Failure::Message(format!("cannot create '{}': {e}", out.display())))?;
    // In an MPI job each rank takes every size-th run and runs it by itself; rank 0 gathers the rows.
    let job = crate::cluster::job();
    let mut mine = Vec::new();
    let mut stopped = None;
    for i in crate::cluster::share(runs.len(), job.rank(), job.size()) {
        let (run, folder) = (&runs[i], out.join(format!("run_{i:03}")));
        let start = Instant::now();
        let outcome = crate::cluster::alone(|| {
            crate::console::emit(&format!(
                "run {}/{} in {}: {}\n",
                i + 1,
                runs.len(),
                folder.display(),
                run.join(" ")
            ));
            open(script, run, Some(&folder))
                .and_then(|mut session| run_session(&mut session, false, bars, None))
        });
        let seconds = start.elapsed().as_secs_f64();
        let status = match &outcome {
            Ok(()) => "done".to_string(),
            Err(e) => e.to_string().trim().to_string(),
        };
        mine.push(serde_json::json!({
            "run": i,
            "folder": folder.display().to_string(),
            "settings": axes.iter().zip(run).map(|(a, o)| (a.name.clone(), serde_json::json!(o[a.name.len() + 1..])))
                .collect::<serde_json::Map<_, _>>(),
            "status": status,
            "seconds": seconds,
            "metrics": final_metrics(&folder),
        }));
        if let Err(Failure::Interrupted(m)) = outcome {
            stopped = Some(m);
            break;
        }
    }
    let sent = serde_json::json!({ "rows": mine, "stopped": stopped });
    let Some(every_rank) = job.gather(sent.to_string().as_bytes()) else {
        return stopped.map_or(Ok(String::new()), |m| Err(Failure::Interrupted(m)));
    };
    let mut results = Vec::new();
    for bytes in every_rank {
        let mut got: serde_json::Value = serde_json::from_slice(&bytes)
            .map_err(|e| Failure::Message(format!("a rank's rows of the sweep do not read: {e}")))?;
        if let Some(rows) = got["rows"].as_array_mut() {
            results.append(rows);
        }
        if let Some(m) = got["stopped"].as_str() {
            stopped.get_or_insert_with(|| m.to_string());
        }
    }
    results.sort_by_key(|row| row["run"].as_u64());
    let table = markdown(axes, &results);
    let json = serde_json::json!({ "script": script, "runs": results });
    write(
        &out.join("sweep.json"),
        &serde_json::to_string_pretty(&json).unwrap_or_default(),
    )?;
    write(&out.join("sweep.md"), &table)?;
    match stopped {
        Some(m) => Err(Failure::Interrupted(format!(
            "{m}; the sweep's table of the runs so far is in {}",
            out.join("sweep.md").display()
        ))),
        None => Ok(table),
    }
}

fn write(path: &Path, text: &str) -> Result<()> {
    Ok(nerfjit_runtime::write_whole(path, text.as_bytes())?)
}

/// The last value of each column of every metrics log (`*.metrics.jsonl`) in `folder`, the columns named
/// after the log's file when there are several.
fn final_metrics(folder: &Path) -> serde_json::Map<String, serde_json::Value> {
    let mut logs: Vec<PathBuf> = std::fs::read_dir(folder)
        .map(|entries| entries.filter_map(|e| e.ok().map(|e| e.path())).collect())
        .unwrap_or_default();
    logs.retain(|p| p.to_string_lossy().ends_with(".metrics.jsonl"));
    logs.sort();
    let mut metrics = serde_json::Map::new();
    for log in &logs {
        let prefix = match logs.len() {
            1 => String::new(),
            _ => {
                log.file_name()
                    .unwrap_or_default()
                    .to_string_lossy()
                    .replace(".metrics.jsonl", "")
                    + "."
            }
        };
        let text = std::fs::read_to_string(log).unwrap_or_default();
        for record in text
            .lines()
            .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        {
            if let Some(fields) = record.as_object() {
                for (k, v) in fields {
                    metrics.insert(format!("{prefix}{k}"), v.clone());
                }
            }
        }
    }
    metrics
}

/// The runs as a Markdown table: the settings, the status, the seconds and every metric any run has.
fn markdown(axes: &[Axis], results: &[serde_json::Value]) -> String {
    // A column's metric, without the name of its log when the run has several.
    let metric = |c: &str| c.rsplit('.').next().unwrap_or(c).to_string();
    let mut columns: Vec<String> = Vec::new();
    for r in results {
        for k in r["metrics"].as_object().into_iter().flat_map(|m| m.keys()) {
            if !columns.contains(k) && !["train_seconds", "lr"].contains(&metric(k).as_str()) {
                columns.push(k.clone());
            }
        }
    }
    // The step first, then the losses and scores in the order of the metrics log.
    let order = <crate::blocks::train::VolumeRecord as crate::training::metrics_log::LogRecord>::COLUMNS;
    let rank = |c: &String| order.iter().position(|o| metric(c) == *o).unwrap_or(order.len());
    columns.sort_by_key(|c| (c.rsplit_once('.').map(|(log, _)| log.to_string()), rank(c)));
    let mut text = String::from("| run |");
    for a in axes {
        let _ = write!(text, " {} |", a.name);
    }
    for c in &columns {
        let _ = write!(text, " {c} |");
    }
    text.push_str(" seconds | status |\n|---|");
    text.push_str(&"---|".repeat(axes.len() + columns.len() + 2));
    text.push('\n');
    for r in results {
        let _ = write!(text, "| {} |", r["run"]);
        for a in axes {
            let _ = write!(text, " `{}` |", r["settings"][&a.name].as_str().unwrap_or(""));
        }
        for c in &columns {
            let cell = match &r["metrics"][c] {
                serde_json::Value::Number(n) if n.is_f64() => short(n.as_f64().unwrap_or(f64::NAN)),
                serde_json::Value::Null => String::new(),
                v => v.to_string(),
            };
            let _ = write!(text, " {cell} |");
        }
        let status = r["status"]
            .as_str()
            .unwrap_or("")
            .lines()
            .next()
            .unwrap_or("")
            .replace('|', "/");
        let _ = writeln!(text, " {:.1} | {status} |", r["seconds"].as_f64().unwrap_or(0.0));
    }
    text
}

/// `x` with four significant digits (small losses in scientific notation).
fn short(x: f64) -> String {
    if x != 0.0 && x.abs() < 1e-2 {
        format!("{x:.3e}")
    } else {
        format!("{x:.4}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn axes_split_at_the_top_level_only() {
        let axis = parse_axis(r#"train.data=[blender("a, b.json", views: 20), views("c.json")]"#).unwrap();
        assert_eq!(axis.name, "train.data");
        assert_eq!(
            axis.values,
            [r#"blender("a, b.json", views: 20)"#, r#"views("c.json")"#]
        );
        assert_eq!(
            parse_axis("beta = [0.01, 0.05,0.1]").unwrap().values,
            ["0.01", "0.05", "0.1"]
        );
        assert_eq!(
            parse_axis("c=[[1, 2, 3], [4, 5, 6]]").unwrap().values,
            ["[1, 2, 3]", "[4, 5, 6]"]
        );
        assert_eq!(parse_axis("train.steps=200").unwrap().values, ["200"]);
        for bad in [
            "beta",
            "=[1]",
            "beta=[1, ]",
            "beta=[(1, 2]",
            "beta=[\"a]",
            "beta=[1)]",
        ] {
            assert!(parse_axis(bad).is_err(), "{bad} should be refused");
        }
    }

    #[test]
    fn combinations_cover_the_grid_with_the_last_axis_fastest() {
        let axes = [
            parse_axis("a=[1, 2]").unwrap(),
            parse_axis("b=[x, y, z]").unwrap(),
        ];
        let runs = combinations(&axes);
        assert_eq!(runs.len(), 6);
        assert_eq!(runs[0], ["a=1", "b=x"]);
        assert_eq!(runs[1], ["a=1", "b=y"]);
        assert_eq!(runs[5], ["a=2", "b=z"]);
        assert_eq!(combinations(&[]), vec![Vec::<String>::new()]);
    }
}
