//! `nerfjit bench quality`: trains each shipped recipe on each data set of `../shared/data` for a given
//! time, one run after the other, and prints one table of the held-out scores (by each data set's
//! protocol) against training time, with the speed and the occupancy grid's share of occupied cells. Each
//! run is this binary's own `nerfjit run` of the example in a folder of its own under
//! `target/bench-quality` (its output in `run.log` there), so that a run is exactly what a user gets.

use std::path::{Path, PathBuf};
use std::process::Command;

use nerfjit::failure::{Failure, Result};

/// A recipe on a data set.
struct Run {
    /// The data set, as the table names it.
    scene: &'static str,
    /// The example (as `nerfjit run` takes it by name).
    example: &'static str,
    /// A file the data set must hold, under `../shared/data`.
    needs: &'static str,
    /// The data set's protocol, as the table states it.
    protocol: &'static str,
}

/// The recipes and the data sets they run on.
const RUNS: [Run; 4] = [
    Run {
        scene: "lego",
        example: "instant_lego",
        needs: "lego/transforms_train.json",
        protocol: "128², 10 val views on white",
    },
    Run {
        scene: "fern",
        example: "instant_llff",
        needs: "llff/fern/poses_bounds.npy",
        protocol: "504×378, every 8th view",
    },
    Run {
        scene: "DTU 24, masks",
        example: "instant_neus_dtu",
        needs: "dtu/scan24/cameras_sphere.npz",
        protocol: "400×300, every 8th view, inside masks",
    },
    Run {
        scene: "DTU 24, no masks",
        example: "instant_capture",
        needs: "dtu/scan24/cameras_sphere.npz",
        protocol: "400×300, every 8th view, whole images",
    },
];

/// Trains every recipe whose data is present for `minutes`, validating after 1 minute and at the end, and
/// prints the table (and writes it as JSON to `target/bench-quality/quality.json`).
pub fn quality(minutes: f64) -> Result<()> {
    if !(minutes.is_finite() && minutes > 0.0) {
        return Err(Failure::Message(format!(
            "--minutes {minutes}: give a positive number of minutes"
        )));
    }
    let exe =
        std::env::current_exe().map_err(|e| Failure::Message(format!("cannot find this binary: {e}")))?;
    let data = Path::new("../shared/data");
    let root = PathBuf::from("target/bench-quality");
    nerfjit::emit(&format!(
        "quality: each recipe for {minutes} minutes of training, held-out views by each data set's protocol\n\
         {:<17} {:<17} {:<38} {:>12} {:>12} {:>7} {:>9} {:>10} {:>9}\n",
        "data", "recipe", "protocol", "PSNR 1 min", "PSNR end", "SSIM", "ms/step", "samples/s", "occupied"
    ));
    let mut table = Vec::new();
    for run in &RUNS {
        if !data.join(run.needs).is_file() {
            nerfjit::emit(&format!(
                "{:<17} {:<17} skipped: {} is not here\n",
                run.scene,
                run.example,
                data.join(run.needs).display()
            ));
            continue;
        }
        let out = root.join(run.example).join(run.scene.replace([' ', ','], "_"));
        std::fs::create_dir_all(&out)
            .map_err(|e| Failure::Message(format!("cannot create {}: {e}", out.display())))?;
        let minutes_set = format!("train.minutes={minutes}");
        let marks = format!("train.val_minutes=[{}]", if minutes > 1.0 { "1" } else { "" });
        let log_path = out.join("run.log");
        let log = std::fs::File::create(&log_path)
            .map_err(|e| Failure::Message(format!("cannot create {}: {e}", log_path.display())))?;
        let log_too = log
            .try_clone()
            .map_err(|e| Failure::Message(format!("cannot write {}: {e}", log_path.display())))?;
        let status = Command::new(&exe)
            .args(["run", run.example, "--out"])
            .arg(&out)
            .args(["--set", &minutes_set, "--set", &marks])
            .stdout(log)
            .stderr(log_too)
            .status()
            .map_err(|e| Failure::Message(format!("cannot run {}: {e}", exe.display())))?;
        if !status.success() {
            return Err(Failure::Message(format!(
                "the run of {} on {} failed ({status}); its output is in {}",
                run.example,
                run.scene,
                log_path.display()
            )));
        }
        let summary_path = out.join(format!("{}.json", run.example));
        let text = std::fs::read_to_string(&summary_path)
            .map_err(|e| Failure::Message(format!("cannot read {}: {e}", summary_path.display())))?;
        let summary: serde_json::Value = serde_json::from_str(&text)
            .map_err(|e| Failure::Message(format!("{} is not JSON: {e}", summary_path.display())))?;
        let validations = summary["validation"].as_array().cloned().unwrap_or_default();
        // The PSNR of the protocol: inside the masks where the data has them.
        let psnr = |v: &serde_json::Value| v["val_masked_psnr"].as_f64().or(v["val_psnr"].as_f64());
        let after_one = validations
            .iter()
            .find(|v| {
                v["train_seconds"]
                    .as_f64()
                    .is_some_and(|s| s >= 60.0 && minutes > 1.0)
            })
            .and_then(psnr);
        let last = validations.last();
        let row = serde_json::json!({
            "data": run.scene, "recipe": run.example, "protocol": run.protocol, "minutes": minutes,
            "psnr_1_minute": after_one, "psnr_end": last.and_then(psnr),
            "ssim_end": last.and_then(|v| v["val_ssim"].as_f64()),
            "ms_per_step": summary["ms_per_step"], "samples_per_s": summary["samples_per_s"],
            "occupied_cells": summary["occupied_cells"],
        });
        let cell = |v: Option<f64>, digits: usize| v.map_or("—".to_string(), |v| format!("{v:.digits$}"));
        nerfjit::emit(&format!(
            "{:<17} {:<17} {:<38} {:>12} {:>12} {:>7} {:>9} {:>10} {:>9}\n",
            run.scene,
            run.example,
            run.protocol,
            cell(after_one, 2),
            cell(last.and_then(psnr), 2),
            cell(last.and_then(|v| v["val_ssim"].as_f64()), 3),
            cell(summary["ms_per_step"].as_f64(), 1),
            cell(summary["samples_per_s"].as_f64().map(|s| s / 1e6), 2) + " M",
            summary["occupied_cells"]
                .as_f64()
                .map_or("—".to_string(), |o| format!("{:.1}%", 100.0 * o)),
        ));
        table.push(row);
    }
    let path = root.join("quality.json");
    std::fs::create_dir_all(&root)
        .map_err(|e| Failure::Message(format!("cannot create {}: {e}", root.display())))?;
    std::fs::write(&path, serde_json::to_string_pretty(&table).unwrap_or_default())
        .map_err(|e| Failure::Message(format!("cannot write {}: {e}", path.display())))?;
    nerfjit::emit(&format!("→ {}\n", path.display()));
    Ok(())
}
