//! `nerfjit bake` on a field trained here (the box of `common`): the bake is drawn and scored like the
//! field, exported as the 3D Gaussian splatting `.ply`, and bad bakes are refused with what is wrong.

use crate::common::{make_views, run, trainer_with};

fn scratch(name: &str) -> crate::common::Scratch {
    crate::common::scratch("bake", name)
}

/// The mean PSNR an `eval-views --json` report holds.
fn mean_psnr(path: &std::path::Path) -> f64 {
    let report: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
    report["mean_psnr"].as_f64().unwrap()
}

#[test]
fn a_trained_box_bakes_into_splats_drawn_and_scored_like_the_field() {
    let dir = scratch("box");
    make_views(&dir);
    std::fs::write(dir.join("train.sdf"), trainer_with(400, "")).unwrap();
    let (ok, _, err) = run(&dir, &["run", "train.sdf"]);
    assert!(ok, "{err}");
    let bake = [
        "bake",
        "train.ckpt.safetensors",
        "--cameras",
        "cams.json",
        "--size",
        "80",
        "--out",
        "box.bake",
    ];
    let (ok, out, err) = run(&dir, &bake);
    assert!(ok, "{err}");
    let splats: usize = out
        .split_whitespace()
        .nth(1)
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("{out}"));
    assert!(splats > 100, "{out}");

    // Scored on the same views at the same size as the field.
    for (source, json) in [
        ("train.ckpt.safetensors", "field.json"),
        ("box.bake", "bake.json"),
    ] {
        let args = [
            "eval-views",
            source,
            "--cameras",
            "cams.json",
            "--size",
            "40",
            "--json",
            json,
        ];
        let (ok, _, err) = run(&dir, &args);
        assert!(ok, "{source}: {err}");
    }
    let (field, baked) = (
        mean_psnr(&dir.join("field.json")),
        mean_psnr(&dir.join("bake.json")),
    );
    eprintln!("box at 40²: the field {field:.2} dB, its bake of {splats} splats {baked:.2} dB");
    // The field renders its own views of the box almost exactly (above 60 dB); the bake, without fine-tuning,
    // blurs the box's edges by its splats' width (26.5 dB when written).
    assert!(baked > 24.0, "field {field:.2} dB, bake {baked:.2} dB");

    // Fine-tuned against the views the field trained on (the same four views it is scored on here), the
    // splats take their edges back: 26.8 → 55.6 dB after 5 s when written.
    let mut tuned_bake = bake.to_vec();
    tuned_bake.extend(["--tune", "5"]);
    *tuned_bake.iter_mut().find(|a| **a == "box.bake").unwrap() = "tuned.bake";
    let (ok, out, err) = run(&dir, &tuned_bake);
    assert!(ok && out.contains("tuning pass 1: 4 views"), "{out}{err}");
    let args = [
        "eval-views",
        "tuned.bake",
        "--cameras",
        "cams.json",
        "--size",
        "40",
        "--json",
        "tuned.json",
    ];
    let (ok, _, err) = run(&dir, &args);
    assert!(ok, "{err}");
    let tuned = mean_psnr(&dir.join("tuned.json"));
    eprintln!("box at 40²: fine-tuned for 5 s, {tuned:.2} dB");
    assert!(
        tuned > 40.0 && tuned > baked + 10.0,
        "bake {baked:.2} dB, tuned {tuned:.2} dB"
    );

    // `compare` sets the field, its bake and the tuned bake side by side, each scored as eval-views scores it.
    let row = "box=train.ckpt.safetensors,box.bake,tuned.bake";
    let args = [
        "compare",
        "--cameras",
        "cams.json",
        "--size",
        "40",
        "--columns",
        "field,bake,tuned",
        "--row",
        row,
        "--out",
        "grid.png",
    ];
    let (ok, out, err) = run(&dir, &args);
    assert!(ok, "{err}");
    let shown = |column: &str| -> f64 {
        let at = out
            .find(&format!("{column}: "))
            .unwrap_or_else(|| panic!("{out}"))
            + column.len()
            + 2;
        out[at..]
            .split(' ')
            .next()
            .and_then(|x| x.parse().ok())
            .unwrap_or_else(|| panic!("{out}"))
    };
    assert!(
        shown("tuned") > shown("bake") + 10.0 && dir.join("grid.png").exists(),
        "{out}"
    );

    let (ok, out, err) = run(
        &dir,
        &[
            "render",
            "box.bake",
            "--cameras",
            "cams.json",
            "--size",
            "40",
            "--out",
            "views",
        ],
    );
    assert!(ok && out.contains(&format!("{splats} splats")), "{out}{err}");
    assert!(dir.join("views/view_003.png").exists());

    let (ok, _, err) = run(
        &dir,
        &["export", "box.bake", "--format", "splat-ply", "--out", "box.ply"],
    );
    assert!(ok, "{err}");
    let ply = std::fs::read(dir.join("box.ply")).unwrap();
    let header_end = ply.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
    let header = String::from_utf8_lossy(&ply[..header_end]);
    assert!(header.contains(&format!("element vertex {splats}\n")), "{header}");
    assert_eq!(ply.len() - header_end, splats * 17 * 4);
}

#[test]
fn bad_bakes_and_files_that_are_not_bakes_are_refused_with_what_is_wrong() {
    let dir = scratch("bad");
    make_views(&dir);
    std::fs::write(dir.join("train.sdf"), trainer_with(5, "")).unwrap();
    let (ok, _, err) = run(&dir, &["run", "train.sdf"]);
    assert!(ok, "{err}");
    let (ok, _, err) = run(
        &dir,
        &[
            "bake",
            "train.ckpt.safetensors",
            "--cameras",
            "cams.json",
            "--out",
            "x.ply",
        ],
    );
    assert!(!ok && err.contains("must end in .bake"), "{err}");
    let (ok, _, err) = run(
        &dir,
        &[
            "export",
            "train.ckpt.safetensors",
            "--format",
            "splat-ply",
            "--out",
            "x.ply",
        ],
    );
    assert!(!ok && err.contains("is not a baked scene"), "{err}");
    std::fs::write(dir.join("junk.bake"), b"\x10\0\0\0\0\0\0\0{\"a\": 1}").unwrap();
    for command in [
        &["eval-views", "junk.bake"][..],
        &["render", "junk.bake", "--out", "v"][..],
    ] {
        let (ok, _, err) = run(&dir, command);
        assert!(
            !ok && err.contains("'junk.bake' is not a baked scene"),
            "{command:?}: {err}"
        );
    }
    let (ok, _, err) = run(
        &dir,
        &["export", "junk.bake", "--format", "gltf", "--out", "x.glb"],
    );
    assert!(!ok && err.contains("not an export format"), "{err}");
    for seconds in ["-1", "nan", "soon"] {
        let tune = format!("--tune={seconds}");
        let (ok, _, err) = run(
            &dir,
            &["bake", "train.ckpt.safetensors", "--out", "x.bake", &tune],
        );
        assert!(
            !ok && err.contains("is not a number of seconds"),
            "{seconds}: {err}"
        );
    }
}
