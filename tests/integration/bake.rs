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

/// `eval-views SOURCE` in `dir` on the four views of the box at 40² (`cams.json`): its mean PSNR.
fn psnr_on_the_four_views(dir: &std::path::Path, source: &str) -> f64 {
    let json = format!("{source}.json");
    let args = [
        "eval-views",
        source,
        "--cameras",
        "cams.json",
        "--size",
        "40",
        "--json",
        &json,
    ];
    let (ok, _, err) = run(dir, &args);
    assert!(ok, "{source}: {err}");
    mean_psnr(&dir.join(json))
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
    let (field, baked) = (
        psnr_on_the_four_views(&dir, "train.ckpt.safetensors"),
        psnr_on_the_four_views(&dir, "box.bake"),
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
    let tuned = psnr_on_the_four_views(&dir, "tuned.bake");
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

    // Without --size, from the views the field trained on (40² here), the views baked are half as wide;
    // from other cameras, 400².
    let (ok, out, err) = run(&dir, &["bake", "train.ckpt.safetensors", "--out", "half.bake"]);
    assert!(ok, "{err}");
    assert!(
        out.contains("views of 20×20") && out.contains("training views of 40×40 loaded"),
        "{out}"
    );
    let own = [
        "bake",
        "train.ckpt.safetensors",
        "--cameras",
        "cams.json",
        "--out",
        "own.bake",
    ];
    let (ok, out, err) = run(&dir, &own);
    assert!(ok && out.contains("views of 400×400"), "{out}{err}");
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
        &["export", "junk.bake", "--format", "glb", "--out", "x.glb"][..],
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

/// The cells' sides a bake's summary states ("(cells: 800 of 0.0205, 120 of 0.0410)"), finest first.
fn cell_sides(summary: &str) -> Vec<f64> {
    let list = summary
        .split_once("(cells: ")
        .and_then(|(_, rest)| rest.split_once(')'))
        .unwrap_or_else(|| panic!("no cells in {summary}"))
        .0;
    list.split(", ")
        .map(|level| {
            level
                .split_once(" of ")
                .and_then(|(_, side)| side.parse().ok())
                .unwrap_or_else(|| panic!("'{level}' in {summary}"))
        })
        .collect()
}

/// `eval-views SOURCE --json JSON` in `dir` (the views the checkpoint's training held out): its report.
fn held_out_scores(dir: &std::path::Path, source: &str, json: &str) -> serde_json::Value {
    let (ok, _, err) = run(dir, &["eval-views", source, "--json", json]);
    assert!(ok, "{source}: {err}");
    serde_json::from_str(&std::fs::read_to_string(dir.join(json)).unwrap()).unwrap()
}

/// A surface field (the box's VolSDF density, at its true params) on a DTU scan with object masks: the bake
/// sees it from the six views its training read (views 0 and 4 held out), eval-views scores the bake on the
/// held-out views as it scores the field, whole and inside the masks, and fine-tuning against the six
/// views' masked images brings the object's inside closer.
#[test]
fn a_surface_field_on_a_dtu_scan_bakes_and_scores_inside_its_masks() {
    let dir = scratch("dtu_surface");
    crate::captures::write_dtu_scan(&dir, 1.0);
    crate::captures::train_truth(&dir, "dtu(\".\", masks: true)");
    let field = held_out_scores(&dir, "train.ckpt.safetensors", "field.json");
    let mut scores = Vec::new();
    for (tune, bake) in [("0", "scan.bake"), ("5", "tuned.bake")] {
        let args = [
            "bake",
            "train.ckpt.safetensors",
            "--size",
            "48",
            "--tune",
            tune,
            "--out",
            bake,
        ];
        let (ok, out, err) = run(&dir, &args);
        assert!(ok && out.contains("of 6 views of 48×32"), "{out}{err}");
        let baked = held_out_scores(&dir, bake, &format!("{bake}.json"));
        assert_eq!(baked["protocol"], field["protocol"]);
        scores.push(baked);
    }
    let masked = |s: &serde_json::Value| s["mean_masked_psnr"].as_f64().unwrap();
    let whole = |s: &serde_json::Value| s["mean_psnr"].as_f64().unwrap();
    let [baked, tuned] = [&scores[0], &scores[1]];
    eprintln!(
        "box on a DTU scan: the field {:.2} dB ({:.2} inside the masks), its bake {:.2} ({:.2}), tuned 5 s {:.2} ({:.2})",
        whole(&field),
        masked(&field),
        whole(baked),
        masked(baked),
        whole(tuned),
        masked(tuned)
    );
    assert!(whole(baked) > 24.0 && masked(baked) > 15.0, "{baked}");
    assert!(masked(tuned) > masked(baked) + 6.0, "{tuned}");
}

/// A capture whose background is part of the scene (a ball inside a shell 30 units away, seen from inside
/// the shell; a grid over contracted space): the shell, ten times farther than the ball, is merged into
/// cells eight or more times wider, and the bake, whose splats surround every camera, is drawn and scored
/// like the field on the views its training held out (every 5th, left out of the bake).
#[test]
fn a_contracted_scene_bakes_its_far_background_into_coarser_splats_around_the_cameras() {
    let dir = scratch("unbounded");
    crate::captures::write_unbounded_scene(&dir);
    let trainer = crate::captures::UNBOUNDED_TRAINER
        .replace("STEPS", "300")
        .replace("checkpoint: none", "checkpoint: \"train.ckpt.safetensors\"");
    std::fs::write(dir.join("train.sdf"), trainer).unwrap();
    let (ok, _, err) = run(&dir, &["run", "train.sdf"]);
    assert!(ok, "{err}");
    let args = [
        "bake",
        "train.ckpt.safetensors",
        "--size",
        "32",
        "--out",
        "scene.bake",
    ];
    let (ok, out, err) = run(&dir, &args);
    assert!(ok && out.contains("of 28 views of 32×32"), "{out}{err}");
    let sides = cell_sides(&out);
    assert!(sides[sides.len() - 1] >= 8.0 * sides[0], "{out}");
    let field = held_out_scores(&dir, "train.ckpt.safetensors", "field.json");
    let baked = held_out_scores(&dir, "scene.bake", "bake.json");
    let psnr = |s: &serde_json::Value| s["mean_psnr"].as_f64().unwrap();
    eprintln!(
        "unbounded scene: the field {:.2} dB, its bake {:.2} dB ({out})",
        psnr(&field),
        psnr(&baked)
    );
    assert!(psnr(&baked) > psnr(&field) - 1.5, "{out}");
}

/// `count` round splats of standard deviation `scale` spread evenly over a sphere of `radius` (a Fibonacci
/// lattice), red above z = 0 and blue below.
fn shell_of_splats(count: usize, radius: f32, scale: f32) -> nerfjit_runtime::splats::Splats {
    let mut splats = nerfjit_runtime::splats::Splats::default();
    let golden = std::f32::consts::PI * (3.0 - 5f32.sqrt());
    for i in 0..count {
        let z = 1.0 - 2.0 * (i as f32 + 0.5) / count as f32;
        let (r, phi) = ((1.0 - z * z).sqrt(), golden * i as f32);
        splats
            .positions
            .push([radius * r * phi.cos(), radius * r * phi.sin(), radius * z]);
        splats
            .colors
            .push(if z > 0.0 { [0.9, 0.1, 0.1] } else { [0.1, 0.1, 0.9] });
        splats.opacities.push(0.9);
        splats.scales.push([scale; 3]);
        splats.rotations.push([1.0, 0.0, 0.0, 0.0]);
    }
    splats
}

/// A bake of a shell of splats (radius 1, red above z = 0, blue below) exported as glTF: the `gltf` crate
/// reads one closed surface just outside the shell (within the splats' reach; the inner wall filled), and
/// the texture red on the upper half and blue on the lower one; bad options are refused with what is wrong.
#[test]
fn a_bake_exports_as_a_textured_gltf_of_its_splats_surface() {
    let dir = scratch("glb");
    let bake = nerfjit::bake_file::Bake {
        splats: shell_of_splats(3000, 1.0, 0.04),
        background: [1.0; 3],
        source: "nowhere.ckpt.safetensors".into(),
    };
    nerfjit::bake_file::write(&dir.join("shell.bake"), &bake).unwrap();
    let (ok, out, err) = run(
        &dir,
        &["export", "shell.bake", "--format", "glb", "--out", "shell.glb"],
    );
    assert!(
        ok && out.contains("3000 of 3000 splats") && out.contains("(closed)"),
        "{out}{err}"
    );

    let crate::common::TexturedGlb {
        positions,
        normals,
        uvs,
        indices,
        texture,
    } = crate::common::read_textured_glb(&dir.join("shell.glb"));
    assert!(indices.len() > 3 * 2000, "{} triangles", indices.len() / 3);
    // Outside the shell, within the reach of its splats (σ = 0.04, widened by half a cell), facing out.
    for (p, n) in positions.iter().zip(&normals) {
        assert!(
            (1.0..1.2).contains(&p.length()),
            "a vertex at {p}, {} from the center",
            p.length()
        );
        assert!(p.normalize().dot(*n) > 0.8, "{p}: normal {n}");
    }
    let size = glam::Vec2::new(texture.width() as f32, texture.height() as f32);
    let (mut red, mut blue) = (0, 0);
    for t in indices.chunks_exact(3) {
        let (p, uv) = ([0, 1, 2].map(|k| positions[t[k]]), [0, 1, 2].map(|k| uvs[t[k]]));
        let (center, uv) = ((p[0] + p[1] + p[2]) / 3.0, (uv[0] + uv[1] + uv[2]) / 3.0);
        let texel = (uv * size).floor();
        let [r, _, b] = texture.get_pixel(texel.x as u32, texel.y as u32).0;
        if center.z > 0.15 {
            assert!(r > 215 && b < 40, "red above: {center} is {:?}", [r, b]);
            red += 1;
        } else if center.z < -0.15 {
            assert!(b > 215 && r < 40, "blue below: {center} is {:?}", [r, b]);
            blue += 1;
        }
    }
    assert!(red > 1000 && blue > 1000, "{red} red, {blue} blue");

    for (extra, want) in [
        (&["--level", "50"][..], "no surface at level 50"),
        (&["--level", "-1"][..], "must be above 0"),
        (&["--res", "1"][..], "use 2 to 1024"),
        (&["--bounds", "1,1"][..], "--bounds takes"),
        (&["--texels", "1"][..], "use 2 to 64"),
    ] {
        let mut args = vec!["export", "shell.bake", "--format", "glb", "--out", "x.glb"];
        args.extend(extra);
        let (ok, _, err) = run(&dir, &args);
        assert!(!ok && err.contains(want), "{extra:?}: {err}");
        assert!(!dir.join("x.glb").exists());
    }
    let (ok, _, err) = run(
        &dir,
        &["export", "shell.bake", "--format", "glb", "--out", "x.ply"],
    );
    assert!(!ok && err.contains("writes a .glb file"), "{err}");
    let (ok, _, err) = run(
        &dir,
        &[
            "export",
            "shell.bake",
            "--format",
            "splat-ply",
            "--out",
            "x.ply",
            "--res",
            "64",
        ],
    );
    assert!(!ok && err.contains("are for --format glb"), "{err}");
    let empty = nerfjit::bake_file::Bake {
        splats: Default::default(),
        ..bake
    };
    nerfjit::bake_file::write(&dir.join("empty.bake"), &empty).unwrap();
    let (ok, _, err) = run(
        &dir,
        &["export", "empty.bake", "--format", "glb", "--out", "x.glb"],
    );
    assert!(!ok && err.contains("no splats"), "{err}");
}

/// A script's `bake { }` block after its `train` block bakes the params as trained, as `nerfjit bake` bakes
/// the run's checkpoint with the same options (the same splats), records the script it was baked from, and
/// the bake is scored and rendered like one of the command's; with `tune`, it is fine-tuned as `--tune` does.
#[test]
fn a_bake_block_bakes_the_trained_field_as_the_command_bakes_its_checkpoint() {
    let dir = scratch("block");
    make_views(&dir);
    let script = trainer_with(400, "")
        + "bake { out: \"block.bake\", size: 80 }\n\
           bake { out: \"tuned.bake\", size: 80, tune: 2, sh_degree: 0 }\n";
    std::fs::write(dir.join("train.sdf"), script).unwrap();
    let (ok, out, err) = run(&dir, &["run", "train.sdf"]);
    assert!(ok, "{err}");
    assert!(out.contains("of 4 views of 80×80"), "{out}");
    assert!(out.contains("tuning pass 1: 4 views"), "{out}");

    // The bake records the checkpoint the train block wrote: the script as it ran, `--set` overrides
    // included, whose data and protocol score it.
    let block = nerfjit::bake_file::read(&dir.join("block.bake")).unwrap();
    assert!(block.splats.len() > 100, "{} splats", block.splats.len());
    assert_eq!(
        std::fs::canonicalize(&block.source).unwrap(),
        std::fs::canonicalize(dir.join("train.ckpt.safetensors")).unwrap()
    );
    let command = [
        "bake",
        "train.ckpt.safetensors",
        "--size",
        "80",
        "--out",
        "command.bake",
    ];
    let (ok, _, err) = run(&dir, &command);
    assert!(ok, "{err}");
    let from_checkpoint = nerfjit::bake_file::read(&dir.join("command.bake")).unwrap();
    assert!(from_checkpoint.splats == block.splats && from_checkpoint.background == block.background);

    let tuned = nerfjit::bake_file::read(&dir.join("tuned.bake")).unwrap();
    assert!(tuned.splats.sh.is_empty() && !tuned.splats.is_empty());
    let scores = ["block.bake", "tuned.bake"].map(|bake| psnr_on_the_four_views(&dir, bake));
    eprintln!(
        "box at 40²: the block's bake {:.2} dB, tuned 2 s {:.2} dB",
        scores[0], scores[1]
    );
    // As the command's bake of the checkpoint (above): 26.5 dB untuned.
    assert!(scores[0] > 24.0 && scores[1] > scores[0], "{scores:?}");
    let render = [
        "render",
        "block.bake",
        "--cameras",
        "cams.json",
        "--size",
        "40",
        "--out",
        "views",
    ];
    let (ok, out, err) = run(&dir, &render);
    let splats = format!("{} splats", block.splats.len());
    assert!(ok && out.contains(&splats), "{out}{err}");
    assert!(dir.join("views/view_003.png").exists());
}

/// `nerfjit check` of a script with bad `bake` blocks: each mistake at its line and column, with a caret
/// under it and a hint; a script without a `train` block is refused before anything runs.
#[test]
fn bad_bake_blocks_are_refused_at_their_settings() {
    let dir = scratch("bad_block");
    let lines = [
        "bake { out: \"a.bake\", tune: -1, sh_degree: 2, tnue: 3 }",
        "bake { tune: 1 }",
        "bake { out: \"a.ply\" }",
    ];
    let script = trainer_with(5, "") + &lines.join("\n") + "\n";
    let first = script.lines().count() - lines.len() + 1;
    std::fs::write(dir.join("bad.sdf"), &script).unwrap();
    let (ok, _, err) = run(&dir, &["check", "bad.sdf"]);
    assert!(!ok, "{err}");
    for (line, what, message, hint) in [
        (0, "-1", "-1 is out of range", "expected a number from 0 to 1e6"),
        (
            0,
            "2,",
            "2 is out of range",
            "expected a whole number from 0 to 1",
        ),
        (
            0,
            "tnue",
            "unknown setting 'tnue' in 'bake' block",
            "did you mean 'tune'?",
        ),
        (
            1,
            "bake",
            "the bake block needs 'out'",
            "add e.g. out: \"scene.bake\"",
        ),
        (
            2,
            "\"a.ply\"",
            "cannot write 'a.ply': unknown format",
            "use a file ending in .bake",
        ),
    ] {
        let text = lines[line];
        let column = text.find(what).unwrap() + 1;
        let at = format!("bad.sdf:{}:{column}", first + line);
        let caret = format!("{text}\n  | {}^", " ".repeat(column - 1));
        assert!(
            err.contains(&at) && err.contains(message) && err.contains(&format!("hint: {hint}")),
            "{at} {message}: {err}"
        );
        assert!(err.contains(&caret), "{caret}: {err}");
    }

    std::fs::write(
        dir.join("untrained.sdf"),
        format!(
            "const center = [0, 0, 0]\nconst sides = [1, 1, 1]\n{}bake {{ out: \"a.bake\" }}\n",
            crate::common::FIELD
        ),
    )
    .unwrap();
    let (ok, _, err) = run(&dir, &["check", "untrained.sdf"]);
    assert!(ok, "the settings are right: {err}");
    let (ok, _, err) = run(&dir, &["run", "untrained.sdf"]);
    assert!(
        !ok && err.contains("untrained.sdf:5:1") && err.contains("this script has no train block"),
        "{err}"
    );
    assert!(!dir.join("a.bake").exists());
}

/// A portrait capture (a view twice as tall as wide) of a scene that fills it (the box inside a shell): the bake
/// sees the training view whole, in its own shape and a little beyond, so that its splats draw the view's top
/// and bottom too. (Baked from square views, as bakes were until 2026-12-07, the top and bottom quarters were
/// left black: a mean error of 0.80 and 0.88 there, against 0.06 and 0.01 now.)
#[test]
fn a_portrait_capture_bakes_its_views_whole() {
    let dir = scratch("portrait");
    let camera = r#"{"image": "view_000.png", "focal": 1.0, "principal_point": [0, 0], "eye": [-2.5, 0.3, 0.0],
        "scene_center": [0, 0, 0], "up": [0, 1, 0]}"#;
    let cameras = format!(r#"{{"image_size": [64, 32], "cameras": [{camera}]}}"#);
    std::fs::write(dir.join("cams.json"), cameras).unwrap();
    let field = "fn opacity(p: vec3) -> f32 = opacity_laplace(min(box(p - center, sides), 2.9 - length(p)), \
                 alpha: 1.0, beta: 0.05)\n\
                 fn color(p: vec3) -> vec3 = clamp(abs(p - center), 0.02, 0.98)\n";
    let truth = format!(
        "const center = [0.2, -0.1, 0.1]\nconst sides = [1.2, 0.8, 1.0]\n{field}\
         render volume {{ camera: cameras(\"cams.json\"), size: [32, 64], near: 0, far: 6, samples: 64, out: \"view_000.png\" }}\n"
    );
    std::fs::write(dir.join("truth.sdf"), truth).unwrap();
    let (ok, _, err) = run(&dir, &["run", "truth.sdf"]);
    assert!(ok, "{err}");
    // The field at the truth's params (one step at a negligible rate).
    let trainer = format!(
        "param center: vec3 = [0.2, -0.1, 0.1]\nparam sides: vec3 = [1.2, 0.8, 1.0]\n{field}\
         train {{ data: views(\"cams.json\"), near: 0, far: 6, samples: 64, steps: 1, batch: 64, lr: 1e-6 }}\n"
    );
    std::fs::write(dir.join("train.sdf"), trainer).unwrap();
    let (ok, _, err) = run(&dir, &["run", "train.sdf"]);
    assert!(ok, "{err}");
    let bake = [
        "bake",
        "train.ckpt.safetensors",
        "--size",
        "64",
        "--out",
        "portrait.bake",
    ];
    let (ok, out, err) = run(&dir, &bake);
    assert!(
        ok && out.contains("of 1 views of 32×64 (and 8 pixels beyond each side)"),
        "{out}{err}"
    );
    let render = [
        "render",
        "portrait.bake",
        "--cameras",
        "cams.json",
        "--size",
        "32",
        "--out",
        "drawn",
    ];
    let (ok, _, err) = run(&dir, &render);
    assert!(ok, "{err}");
    let pixels = |path: std::path::PathBuf| image::open(path).unwrap().to_rgb32f();
    let (truth, drawn) = (
        pixels(dir.join("view_000.png")),
        pixels(dir.join("drawn/view.png")),
    );
    assert_eq!(drawn.dimensions(), (32, 64));
    // The mean absolute error of rows `rows` of the bake's picture against the truth's.
    let error = |rows: std::ops::Range<u32>| {
        let n = rows.len() as f32 * 32.0 * 3.0;
        let sum: f32 = rows
            .flat_map(|y| (0..32).map(move |x| (x, y)))
            .map(|(x, y)| {
                let (t, d) = (truth.get_pixel(x, y).0, drawn.get_pixel(x, y).0);
                (0..3).map(|c| (t[c] - d[c]).abs()).sum::<f32>()
            })
            .sum();
        sum / n
    };
    let (top, middle, bottom) = (error(0..12), error(12..52), error(52..64));
    eprintln!("portrait bake: mean error {top:.3} in the top rows, {middle:.3} in the middle, {bottom:.3} at the bottom");
    assert!(
        top < 0.2 && bottom < 0.2 && middle < 0.2,
        "{top} {middle} {bottom}"
    );
}
