//! End-to-end tests of the `nerfjit` binary on scripts the tests write themselves and on the shipped examples.

use std::io::Write;
use std::path::Path;
use std::process::{Command, Output, Stdio};

fn nerfjit(args: &[&str], stdin: Option<&str>) -> Output {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_nerfjit"));
    cmd.args(args)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    let mut child = cmd.spawn().expect("nerfjit runs");
    if let Some(text) = stdin {
        child
            .stdin
            .take()
            .expect("stdin")
            .write_all(text.as_bytes())
            .expect("write stdin");
    }
    drop(child.stdin.take());
    child.wait_with_output().expect("nerfjit finishes")
}

fn text(o: &Output) -> (String, String) {
    (
        String::from_utf8_lossy(&o.stdout).into_owned(),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    )
}

fn scratch(name: &str) -> crate::common::Scratch {
    crate::common::scratch("test", name)
}

fn write(dir: &Path, file: &str, source: &str) -> String {
    let path = dir.join(file);
    std::fs::write(&path, source).expect("write script");
    path.display().to_string()
}

fn examples() -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(concat!(env!("CARGO_MANIFEST_DIR"), "/examples"))
        .expect("examples")
        .filter_map(|e| e.ok().map(|e| e.path().display().to_string()))
        .filter(|p| p.ends_with(".sdf"))
        .collect();
    v.sort();
    v
}

#[test]
fn check_passes_on_every_example() {
    let all = examples();
    assert!(all.len() >= 2);
    for ex in all {
        let out = nerfjit(&["check", &ex], None);
        let (stdout, stderr) = text(&out);
        assert!(out.status.success(), "{ex}: {stderr}");
        assert!(stdout.contains(": ok\n") && stdout.contains("fn "), "{stdout}");
    }
}

/// `nerfjit check` of a script `source` saved as `name`, which must fail: the script's path and stderr.
fn check_fails(name: &str, source: &str) -> (String, String) {
    let dir = scratch(name);
    let path = write(&dir, &format!("{name}.sdf"), source);
    let out = nerfjit(&["check", &path], None);
    assert!(!out.status.success());
    (path, text(&out).1)
}

#[test]
fn a_typo_gets_a_diagnostic_with_caret_and_hint() {
    let (path, stderr) = check_fails("typo", "fn sdf(p: vec3) -> f32 {\n    lenght(p) - 1.0\n}\n");
    assert!(stderr.contains(&format!("{path}:2:5")), "{stderr}");
    assert!(stderr.contains("    lenght(p) - 1.0\n  |     ^^^^^^"), "{stderr}");
    assert!(stderr.contains("hint: did you mean 'length'?"), "{stderr}");
}

#[test]
fn check_evaluates_block_settings_and_refuses_a_nan_at_its_place() {
    let (path, stderr) = check_fails(
        "nan",
        "fn sdf(p: vec3) -> f32 = length(p) - 1\nrender sphere_trace { size: 16, background: [0 / 0, 0, 0] }\n",
    );
    assert!(stderr.contains(&format!("{path}:2:46")), "{stderr}");
    assert!(
        stderr.contains("this value is NaN, not a finite 32-bit float"),
        "{stderr}"
    );
}

#[test]
fn check_refuses_a_misspelt_setting_and_an_unknown_block_without_running_them() {
    let (path, stderr) = check_fails(
        "misspelt",
        "fn sdf(p: vec3) -> f32 = length(p) - 1\nrender sphere_trace { size: 16, max_step: 10, out: \"a.png\" }\n",
    );
    assert!(stderr.contains(&format!("{path}:2:33")), "{stderr}");
    assert!(
        stderr.contains("unknown setting 'max_step' in 'render sphere_trace' block"),
        "{stderr}"
    );
    assert!(stderr.contains("hint: did you mean 'max_steps'?"), "{stderr}");
    let (path, stderr) = check_fails(
        "unknown_block",
        "fn sdf(p: vec3) -> f32 = length(p) - 1\nrender ray_march { size: 16 }\n",
    );
    assert!(stderr.contains(&format!("{path}:2:1")), "{stderr}");
    assert!(
        stderr.contains("there are no 'render ray_march' blocks"),
        "{stderr}"
    );
}

#[test]
fn check_refuses_values_out_of_their_range_and_reports_every_one() {
    let (path, stderr) = check_fails(
        "ranges",
        "fn sdf(p: vec3) -> f32 = length(p) - 1\n\
         train sdf { data: points(\"nowhere.npy\"), steps: 0, lr: 50, schedule: linear }\n\
         render volume { camera: surround(radius: 3, frames: 2), samples: 1000000, out: \"v.avi\" }\n",
    );
    assert!(stderr.contains(&format!("{path}:2:49")), "{stderr}");
    assert!(
        stderr.contains("hint: expected a whole number from 1 to 100000000"),
        "{stderr}"
    );
    assert!(
        stderr.contains("hint: expected a number from 1e-12 to 10"),
        "{stderr}"
    );
    assert!(
        stderr.contains("expected a schedule, found name 'linear'"),
        "{stderr}"
    );
    assert!(stderr.contains("1000000 is out of range"), "{stderr}");
    assert!(
        stderr.contains("cannot write 'v.avi': unknown format"),
        "{stderr}"
    );
    assert!(!stderr.contains("not found"), "check reads no files: {stderr}");
}

#[test]
fn settings_describes_each_kind_of_block() {
    let out = nerfjit(&["settings", "train", "sdf"], None);
    let (stdout, stderr) = text(&out);
    assert!(out.status.success(), "{stderr}");
    assert!(
        stdout.starts_with("train sdf { ... }: fits a signed distance function"),
        "{stdout}"
    );
    assert!(
        stdout.contains("  eikonal_weight     the eikonal term's weight; default 0.02\n"),
        "{stdout}"
    );
    let out = nerfjit(&["settings"], None);
    let stdout = text(&out).0;
    for kind in [
        "render sphere_trace",
        "render volume",
        "train",
        "train sdf",
        "mesh",
        "viz",
    ] {
        assert!(
            stdout.contains(&format!("\n{kind} {{ ... }}: ")) || stdout.starts_with(kind),
            "{kind}"
        );
    }
    let out = nerfjit(&["settings", "render", "march"], None);
    assert_eq!(out.status.code(), Some(1));
    assert!(
        text(&out)
            .1
            .contains("the kinds are: render sphere_trace, render volume"),
        "{}",
        text(&out).1
    );
}

fn parse_rows(s: &str) -> Vec<Vec<f64>> {
    s.lines()
        .map(|l| l.split(',').map(|x| x.parse().expect("number")).collect())
        .collect()
}

#[test]
fn eval_agrees_with_the_interpreter_and_finite_differences() {
    // Points off the cell faces of the grid encodings, where their gradients jump (and f32 and f64 may
    // round a point into different cells): round coordinates such as 0.3 or 0.9 lie on faces of some
    // levels of instant_bunny's hash grid, and ±1.5 on its bounds.
    let points = "0.3137,0.2071,0.1093\n-1.2113,0.5021,0.7077\n2.0,-1.0137,0.2573\n0.9129,0.1043,-0.2017\n1.4871,1.4933,1.4902\n";
    let surfaces: Vec<String> = examples()
        .into_iter()
        .filter(|e| std::fs::read_to_string(e).unwrap().contains("fn sdf("))
        .collect();
    assert!(surfaces.len() >= 3);
    for ex in surfaces {
        let jit = nerfjit(&["eval", &ex, "sdf", "--grad"], Some(points));
        let interp = nerfjit(&["eval", &ex, "sdf", "--grad", "--interp"], Some(points));
        assert!(
            jit.status.success() && interp.status.success(),
            "{}",
            text(&jit).1
        );
        let (a, b) = (parse_rows(&text(&jit).0), parse_rows(&text(&interp).0));
        assert_eq!(a.len(), 5);
        for (ra, rb) in a.iter().zip(&b) {
            assert_eq!(ra.len(), 4);
            for (x, y) in ra.iter().zip(rb) {
                assert!(
                    (x - y).abs() <= 1e-5 * (1.0 + y.abs()),
                    "{ex}: jit {ra:?} vs interpreter {rb:?}"
                );
            }
        }
        // The gradient against central differences of the interpreter's values (in f64, so a small step
        // that seldom straddles a grid encoding's cell face).
        let h = 1e-6;
        for (row, line) in b.iter().zip(points.lines()) {
            let p: Vec<f64> = line.split(',').map(|x| x.parse().unwrap()).collect();
            let mut shifted = String::new();
            for k in 0..3 {
                for s in [h, -h] {
                    let mut q = p.clone();
                    q[k] += s;
                    shifted += &format!("{},{},{}\n", q[0], q[1], q[2]);
                }
            }
            let vals = parse_rows(&text(&nerfjit(&["eval", &ex, "sdf", "--interp"], Some(&shifted))).0);
            for k in 0..3 {
                let fd = (vals[2 * k][0] - vals[2 * k + 1][0]) / (2.0 * h);
                assert!(
                    (fd - row[1 + k]).abs() < 1e-4,
                    "{ex} at {p:?}: d/d{k} {} vs {fd}",
                    row[1 + k]
                );
            }
        }
    }
}

#[test]
fn eval_reports_bad_points() {
    let out = nerfjit(&["eval", "examples/torus.sdf", "sdf"], Some("1,2\n"));
    assert!(!out.status.success());
    assert!(
        text(&out).1.contains("<stdin>:1: expected 3 numbers per row"),
        "{}",
        text(&out).1
    );
    let out = nerfjit(&["eval", "examples/torus.sdf", "sdf"], Some("1,x,2\n"));
    assert!(
        text(&out).1.contains("<stdin>:1: invalid float literal"),
        "{}",
        text(&out).1
    );
}

#[test]
fn run_writes_the_torus_gif() {
    let dir = scratch("torus");
    let out = nerfjit(
        &["run", "examples/torus.sdf", "--out", dir.to_str().unwrap()],
        None,
    );
    let (stdout, stderr) = text(&out);
    assert!(out.status.success(), "{stderr}");
    assert!(stdout.contains("rendered 20 frames of 256×256"), "{stdout}");
    let file = std::fs::File::open(dir.join("torus.gif")).expect("torus.gif written");
    let decoder = image::codecs::gif::GifDecoder::new(std::io::BufReader::new(file)).expect("a GIF");
    use image::AnimationDecoder;
    let frames = decoder.into_frames().collect_frames().expect("frames");
    assert_eq!(frames.len(), 20);
    let first = frames[0].buffer();
    assert_eq!(first.dimensions(), (256, 256));
    // The torus fills part of the image: some pixels are lit, the corners are background.
    let lit = first
        .pixels()
        .filter(|p| p[0] as u32 + p[1] as u32 + p[2] as u32 > 60)
        .count();
    assert!(lit > 2000 && lit < 40000, "{lit} lit pixels");
    assert_eq!(first.get_pixel(0, 0).0[..3], [0, 0, 0]);
}

/// A float32 `.npy` file's shape (from its header) and values.
fn read_npy_f32(path: &Path) -> (String, Vec<f32>) {
    let bytes = std::fs::read(path).expect("npy written");
    assert!(bytes.starts_with(b"\x93NUMPY\x01\x00"), "not a .npy file");
    let header_len = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
    let header = std::str::from_utf8(&bytes[10..10 + header_len]).unwrap();
    assert!(header.contains("'descr': '<f4'"), "{header}");
    let shape = header
        .split("'shape': ")
        .nth(1)
        .unwrap()
        .split(')')
        .next()
        .unwrap()
        .to_string()
        + ")";
    let values = bytes[10 + header_len..]
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    (shape, values)
}

#[test]
fn depth_is_written_as_float_npy_by_both_renderers() {
    let dir = scratch("depth_npy");
    // A unit sphere seen from 3 units away: the center pixel of a 33×21 image is on the axis, depth 2.
    let script = write(
        &dir,
        "depth.sdf",
        "fn sdf(p: vec3) -> f32 = length(p) - 1.0\n\
         fn color(p: vec3) -> vec3 = [0.5, 0.5, 0.5]\n\
         fn density(p: vec3) -> f32 = 200.0 * sigmoid(-50.0 * sdf(p))\n\
         render sphere_trace { camera: look_at(eye: [0, 0, -3]), size: [33, 21], near: 0, far: 6, out: \"a.png\", depth: \"a.npy\" }\n\
         render volume { camera: look_at(eye: [0, 0, -3]), size: [33, 21], near: 1, far: 5, samples: 256, out: \"b.png\", depth: \"b.npy\" }\n",
    );
    let out = nerfjit(&["run", &script, "--out", dir.to_str().unwrap()], None);
    assert!(out.status.success(), "{}", text(&out).1);
    let center = 10 * 33 + 16;
    let (shape, traced) = read_npy_f32(&dir.join("a.npy"));
    assert_eq!(shape, "(21, 33)");
    assert!((traced[center] - 2.0).abs() < 1e-3, "{}", traced[center]);
    assert!(traced[0].is_infinite(), "a corner misses: {}", traced[0]);
    let (shape, volume) = read_npy_f32(&dir.join("b.npy"));
    assert_eq!(shape, "(21, 33)");
    // The soft density starts absorbing a little before the surface.
    assert!((volume[center] - 2.0).abs() < 0.05, "{}", volume[center]);
    assert!(volume[0].is_infinite(), "a corner sees nothing: {}", volume[0]);
    // Depth images other than these formats are refused before any work.
    let bad = write(
        &dir,
        "bad.sdf",
        "fn sdf(p: vec3) -> f32 = length(p) - 1.0\n\
         render sphere_trace { camera: look_at(eye: [0, 0, -3]), out: \"a.png\", depth: \"a.exr\" }\n",
    );
    let out = nerfjit(&["run", &bad, "--out", dir.to_str().unwrap()], None);
    let (_, stderr) = text(&out);
    assert!(!out.status.success());
    assert!(
        stderr.contains("a.exr': unknown format") && stderr.contains(".npy"),
        "{stderr}"
    );
}

#[test]
fn run_rejects_bad_scripts_before_any_work() {
    let dir = scratch("bad");
    let cases = [
        ("fn color(p: vec3) -> vec3 = p\nrender sphere_trace { camera: orbit(radius: 3), out: \"a.gif\" }", "no function 'sdf'"),
        ("fn sdf(p: vec3) -> f32 = length(p) - 1.0\nrender sphere_trace { camera: orbit(radius: 3), out: \"a.gif\", sise: 4 }", "unknown setting 'sise' in 'render sphere_trace' block"),
        ("fn sdf(p: vec3) -> f32 = length(p) - 1.0\nrender sphere_trace { camera: orbit(radius: 3), out: \"a.gif\", size: \"big\" }", "expected a number, found string"),
        ("fn sdf(p: vec3) -> f32 = length(p) - 1.0\nrender sphere_trace { camera: orbit(radius: 3), out: \"missing/a.gif\" }", "folder 'missing' does not exist"),
        ("fn sdf(p: vec3) -> f32 = length(p) - 1.0\nrender sphere_trace { camera: orbit(radius: 3), out: \"a.gif\", size: 0 }", "0 is out of range"),
        ("fn sdf(p: vec3) -> f32 = length(p) - 1.0\nrender sphere_trace { camera: orbit(radius: 3), out: \"a.gif\", size: 100000 }", "100000 is out of range"),
        ("fn sdf(p: vec3) -> f32 = length(p) - 1.0\nrender sphere_trace { out: \"a.gif\" }", "the render sphere_trace block needs 'camera'"),
        ("fn sdf(p: vec2) -> f32 = length(p) - 1.0\nrender sphere_trace { camera: orbit(radius: 3), out: \"a.gif\" }", "'sdf' must be fn sdf(vec3) -> f32"),
        ("fn sdf(p: vec3) -> f32 = length(p) - 1.0\n", "nothing to run"),
        (
            "fn sdf(p: vec3) -> f32 = length(p) - 1.0\nrender sphere_trace { camera: orbit(radius: 3, frames: 1e9), out: \"a.gif\" }",
            "1000000000 frames is out of range",
        ),
        (
            "fn sdf(p: vec3) -> f32 = length(p) - 1.0\nrender sphere_trace { camera: orbit(radius: 3, frames: 5000), size: 8192, out: \"a.gif\" }",
            "more than the 134217728 kept in memory",
        ),
    ];
    for (i, (src, expected)) in cases.iter().enumerate() {
        let path = write(&dir, &format!("bad{i}.sdf"), src);
        let out = Command::new(env!("CARGO_BIN_EXE_nerfjit"))
            .args(["run", &path])
            .current_dir(&dir)
            .output()
            .expect("runs");
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "case {i} should fail");
        assert!(
            stderr.contains(expected),
            "case {i}: expected '{expected}' in:\n{stderr}"
        );
        assert!(!dir.join("a.gif").exists(), "case {i} wrote output");
    }
}

#[test]
fn ir_prints_both_irs() {
    let out = nerfjit(&["ir", "examples/torus.sdf", "sdf", "--kind", "grad"], None);
    let (stdout, _) = text(&out);
    assert!(out.status.success());
    assert!(stdout.contains("output 3 = v"), "{stdout}");
    assert!(
        stdout.contains("function u0:0(i64, i64, i64, i64, i64)") || stdout.contains("fadd"),
        "{stdout}"
    );
    assert!(stdout.contains("sqrt"));
    let out = nerfjit(
        &["ir", "examples/train_box.sdf", "opacity", "--kind", "vjp"],
        None,
    );
    let (stdout, stderr) = text(&out);
    assert!(out.status.success(), "{stderr}");
    assert!(
        stdout.contains("reduce 5 = sum v"),
        "six param gradients: {stdout}"
    );
    let out = nerfjit(
        &["ir", "examples/torus.sdf", "color", "--kind", "second-order"],
        None,
    );
    assert!(!out.status.success());
    assert!(text(&out).1.contains("for scalar functions"));
}

#[test]
fn mesh_writes_a_closed_torus() {
    let dir = scratch("mesh");
    let ply = dir.join("torus.ply");
    let gif = dir.join("torus.gif");
    let out = nerfjit(
        &[
            "mesh",
            "examples/torus.sdf",
            "--res",
            "48",
            "--bounds",
            "1.5",
            "--out",
            ply.to_str().unwrap(),
            "--gif",
            gif.to_str().unwrap(),
        ],
        None,
    );
    let (stdout, stderr) = text(&out);
    assert!(out.status.success(), "{stderr}");
    assert!(stdout.contains("triangles, closed"), "{stdout}");
    assert!(std::fs::metadata(&ply).unwrap().len() > 10_000);
    assert!(std::fs::metadata(&gif).unwrap().len() > 1_000);
    let out = nerfjit(&["mesh", "examples/torus.sdf", "--out", "x.off"], None);
    assert!(!out.status.success());
    assert!(text(&out).1.contains("use a .ply, .obj, .stl or .glb file"));
    let out = nerfjit(
        &["mesh", "examples/torus.sdf", "--bounds", "1,2", "--out", "x.ply"],
        None,
    );
    assert!(text(&out).1.contains("--bounds takes"));
}

#[test]
fn meshes_take_vertex_colors_and_write_stl() {
    let dir = scratch("mesh-colors");
    let mesh = |out: &Path, extra: &[&str]| {
        let mut args = vec!["mesh", "examples/torus.sdf", "--res", "32", "--bounds", "1.5"];
        args.extend(["--out", out.to_str().unwrap()]);
        args.extend(extra);
        nerfjit(&args, None)
    };
    // torus.sdf's color(p) = clamp(abs(p), 0.02, 0.98).
    let ply = dir.join("torus.ply");
    let out = mesh(&ply, &["--color", "color"]);
    let (stdout, stderr) = text(&out);
    assert!(out.status.success(), "{stderr}");
    assert!(stdout.contains("colored by 'color'"), "{stdout}");
    let bytes = std::fs::read(&ply).unwrap();
    let header_end = bytes.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
    let header = String::from_utf8_lossy(&bytes[..header_end]);
    assert!(
        header.contains("property uchar red\nproperty uchar green\nproperty uchar blue"),
        "{header}"
    );
    // Each vertex: 6 floats and 3 color bytes; its color is the clamped |p| of its position.
    let vertex = |k: usize| &bytes[header_end + 27 * k..header_end + 27 * (k + 1)];
    for k in 0..10 {
        let v = vertex(k);
        for axis in 0..3 {
            let p = f32::from_le_bytes(v[4 * axis..4 * axis + 4].try_into().unwrap());
            let want = (p.abs().clamp(0.02, 0.98) * 255.0).round();
            assert!(
                (f32::from(v[24 + axis]) - want).abs() <= 1.0,
                "vertex {k} axis {axis}: {p}"
            );
        }
    }
    let stl = dir.join("torus.stl");
    let out = mesh(&stl, &[]);
    assert!(out.status.success(), "{}", text(&out).1);
    let bytes = std::fs::read(&stl).unwrap();
    let count = u32::from_le_bytes(bytes[80..84].try_into().unwrap()) as usize;
    assert!(count > 1000 && bytes.len() == 84 + 50 * count);
    let out = mesh(&stl, &["--color", "color"]);
    assert!(text(&out).1.contains("STL has no vertex colors"));
    let out = mesh(&ply, &["--color", "sdf"]);
    assert!(
        text(&out).1.contains("'sdf' must be fn sdf(vec3) -> vec3"),
        "{}",
        text(&out).1
    );
    // A function the script lacks is named without pointing into the prelude.
    let out = mesh(&ply, &["--color", "paint"]);
    let stderr = text(&out).1;
    assert!(stderr.contains("no function 'paint' in the script"), "{stderr}");
    assert!(
        stderr.contains("hint: the script defines: sdf, color") && !stderr.contains("prelude"),
        "{stderr}"
    );
}

/// A textured glTF file of the torus: the `gltf` crate reads it, and every triangle's corners and a texel
/// inside each triangle (its texture finer than the vertices) hold torus.sdf's color(p) = clamp(abs(p), 0.02, 0.98)
/// at their points, and `--texels` sizes the texture.
#[test]
fn meshes_write_textured_gltf() {
    let dir = scratch("mesh-glb");
    let glb = dir.join("torus.glb");
    let mesh = |extra: &[&str]| {
        let mut args = vec!["mesh", "examples/torus.sdf", "--res", "32", "--bounds", "1.5"];
        args.extend(["--out", glb.to_str().unwrap()]);
        args.extend(extra);
        nerfjit(&args, None)
    };
    let out = mesh(&["--color", "color", "--texels", "5"]);
    let (stdout, stderr) = text(&out);
    assert!(out.status.success(), "{stderr}");
    assert!(
        stdout.contains("textured by 'color'") && stdout.contains("patches of 5²"),
        "{stdout}"
    );
    let crate::common::TexturedGlb {
        positions,
        uvs,
        indices,
        texture,
        ..
    } = crate::common::read_textured_glb(&glb);
    assert!(indices.len() > 3000 && uvs.len() == positions.len());
    // Patches of 5² texels.
    assert!(texture.width().is_multiple_of(5) && texture.height().is_multiple_of(5));
    let size = glam::Vec2::new(texture.width() as f32, texture.height() as f32);
    let color_at = |p: glam::Vec3, uv: glam::Vec2| {
        let texel = (uv * size).floor();
        let got = texture.get_pixel(texel.x as u32, texel.y as u32).0;
        let want = p.abs().clamp(glam::Vec3::splat(0.02), glam::Vec3::splat(0.98)) * 255.0;
        for c in 0..3 {
            assert!((f32::from(got[c]) - want[c]).abs() <= 1.0, "{p} at {uv}: {got:?}");
        }
    };
    for t in indices.chunks_exact(3) {
        let (p, uv) = ([0, 1, 2].map(|k| positions[t[k]]), [0, 1, 2].map(|k| uvs[t[k]]));
        for k in 0..3 {
            color_at(p[k], uv[k]);
        }
        // A texel a quarter of the way (4 texels a side) along two sides from the first corner.
        let (s, r) = (0.25, 0.25);
        color_at(
            p[0] + s * (p[1] - p[0]) + r * (p[2] - p[0]),
            uv[0] + s * (uv[1] - uv[0]) + r * (uv[2] - uv[0]),
        );
    }
    let out = mesh(&["--texels", "4"]);
    assert!(
        text(&out).1.contains("only a .glb file with colors"),
        "{}",
        text(&out).1
    );
    let out = mesh(&["--color", "color", "--texels", "1"]);
    assert!(text(&out).1.contains("use 2 to 64"), "{}", text(&out).1);
}

/// A union of spheres and a box in the text format of fidget and MPR (with a comment and a smooth term).
const VM_MODEL: &str = "# two spheres and a box\n\
    x var-x\ny var-y\nz var-z\nh const 0.5\nr const 0.35\n\
    xa sub x h\nxb add x h\nx2a square xa\nx2b square xb\ny2 square y\nz2 square z\n\
    yz add y2 z2\nsa add x2a yz\nsb add x2b yz\nla sqrt sa\nlb sqrt sb\nda sub la r\ndb sub lb r\n\
    ax abs x\nay abs y\naz abs z\nw const 0.2\nqx sub ax w\nqy sub ay h\nqz sub az w\n\
    m1 max qx qy\nbox max m1 qz\nu min da db\nout min u box\n";

#[test]
fn imported_models_mesh_the_same_with_and_without_interval_pruning() {
    let dir = scratch("import");
    let model = dir.join("spheres.vm");
    std::fs::write(&model, VM_MODEL).unwrap();
    let out = nerfjit(&["import", model.to_str().unwrap()], None);
    let (stdout, stderr) = text(&out);
    assert!(out.status.success(), "{stderr}");
    assert!(stdout.contains("imported 29 operations"), "{stdout}");
    let script = dir.join("spheres.sdf");
    let mut meshes = Vec::new();
    for flag in [None, Some("--no-prune")] {
        let ply = dir.join(format!("spheres{}.ply", flag.unwrap_or("")));
        let mut args = vec!["mesh", script.to_str().unwrap(), "--res", "96", "--bounds", "1.2"];
        args.extend(["--out", ply.to_str().unwrap()]);
        args.extend(flag);
        let out = nerfjit(&args, None);
        let (stdout, stderr) = text(&out);
        assert!(out.status.success(), "{stderr}");
        assert!(stdout.contains("closed"), "{stdout}");
        let pruned = stdout.contains("interval bounds of");
        assert_eq!(pruned, flag.is_none(), "{stdout}");
        meshes.push(std::fs::read(&ply).unwrap());
    }
    assert!(meshes[0].len() > 10_000);
    assert_eq!(
        meshes[0], meshes[1],
        "the pruned mesh differs from the brute-force one"
    );
    // A mistake in the model names its line.
    std::fs::write(&model, "x var-x\ny mul x q\n").unwrap();
    let out = nerfjit(&["import", model.to_str().unwrap()], None);
    assert!(!out.status.success());
    assert!(
        text(&out).1.contains("spheres.vm:2: 'q' is not defined"),
        "{}",
        text(&out).1
    );
}

#[test]
fn set_overrides_consts_and_block_settings() {
    let dir = scratch("set");
    let out = nerfjit(
        &[
            "run",
            "examples/box.sdf",
            "--out",
            dir.to_str().unwrap(),
            "--set",
            "render.size=[40, 24]",
            "--set",
            "sides=[1.0, 0.5, 1.5]",
            "--set",
            "render.camera=surround(radius: 3.0, frames: 2, up: y, focal: 1.0)",
        ],
        None,
    );
    let (stdout, stderr) = text(&out);
    assert!(out.status.success(), "{stderr}");
    assert!(
        stdout.contains("volume-rendered 2 frames of 40×24×64 samples"),
        "{stdout}"
    );
    let out = nerfjit(&["run", "examples/box.sdf", "--set", "sidez=1"], None);
    let (_, stderr) = text(&out);
    assert!(!out.status.success());
    assert!(
        stderr.contains("--> --set:1:1") && stderr.contains("did you mean 'sides'?"),
        "{stderr}"
    );
    let out = nerfjit(&["run", "examples/box.sdf", "--set", "render.size"], None);
    assert!(text(&out).1.contains("is not name=value"));
}

#[test]
fn render_and_eval_views_agree_on_a_blender_camera_file() {
    // Two cameras in the Blender convention (camera-to-world, looking down −Z), 4 units from the origin.
    let dir = scratch("views");
    let transforms = r#"{"camera_angle_x": 0.69, "frames": [
        {"file_path": "./view_000", "transform_matrix": [[1, 0, 0, 0], [0, 0, -1, -4], [0, 1, 0, 0], [0, 0, 0, 1]]},
        {"file_path": "./view_001", "transform_matrix": [[0, 0, 1, 4], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]]}]}"#;
    std::fs::write(dir.join("transforms.json"), transforms).unwrap();
    let script = write(
        &dir,
        "box.sdf",
        "fn density(p: vec3) -> f32 = volsdf_density(box(p, [1.2, 0.8, 1.0]), alpha: 20.0, beta: 0.05)\n\
         fn color(p: vec3) -> vec3 = clamp(abs(p) + 0.2, 0.0, 1.0)\n",
    );
    let cams = dir.join("transforms.json");
    let common = [
        "--cameras",
        cams.to_str().unwrap(),
        "--size",
        "24",
        "--samples",
        "64",
    ];
    let mut args = vec!["render", script.as_str()];
    args.extend(common);
    args.extend(["--out", dir.to_str().unwrap()]);
    let out = nerfjit(&args, None);
    assert!(out.status.success(), "{}", text(&out).1);
    assert!(text(&out).0.contains("rendered 2 views of 24×24"));
    // The renders are the ground truth of the same field: only 8-bit rounding separates them.
    let mut args = vec!["eval-views", script.as_str()];
    args.extend(common);
    let out = nerfjit(&args, None);
    let (stdout, stderr) = text(&out);
    assert!(out.status.success(), "{stderr}");
    let mean = stdout
        .lines()
        .find(|l| l.starts_with("mean"))
        .expect("a mean line");
    let psnr: f64 = mean.split_whitespace().nth(1).unwrap().parse().unwrap();
    assert!(psnr > 40.0, "{stdout}");
    // A different field scores clearly worse.
    let other = write(
        &dir,
        "other.sdf",
        "fn density(p: vec3) -> f32 = 0.0\nfn color(p: vec3) -> vec3 = [1, 1, 1]\n",
    );
    let mut args = vec!["eval-views", other.as_str()];
    args.extend(common);
    let (stdout, _) = text(&nerfjit(&args, None));
    let mean = stdout
        .lines()
        .find(|l| l.starts_with("mean"))
        .expect("a mean line");
    let worse: f64 = mean.split_whitespace().nth(1).unwrap().parse().unwrap();
    assert!(worse < 25.0, "{stdout}");

    // A script whose train block skips empty space and stops opaque rays renders with both by default;
    // the images stay near-exact (measured: 49.0 dB against the targets, 55.8 dB with --exact, where
    // 8-bit rounding alone allows about 59 dB).
    let skipping = write(
        &dir,
        "skipping.sdf",
        "fn density(p: vec3) -> f32 = volsdf_density(box(p, [1.2, 0.8, 1.0]), alpha: 20.0, beta: 0.05)\n\
         fn color(p: vec3) -> vec3 = clamp(abs(p) + 0.2, 0.0, 1.0)\n\
         train { data: blender(\"transforms.json\", size: 24), samples: 64, skip_empty: grid(bounds: 1.5, threshold: 0.01), \
         early_termination: 1e-4, checkpoint: none }\n",
    );
    let mean_of = |extra: &[&str], json: &Path| {
        let mut args = vec!["eval-views", skipping.as_str(), "--json", json.to_str().unwrap()];
        args.extend(common);
        args.extend(extra);
        let out = nerfjit(&args, None);
        assert!(out.status.success(), "{}", text(&out).1);
        let report: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(json).unwrap()).unwrap();
        report
    };
    let fast = mean_of(&[], &dir.join("fast.json"));
    let exact = mean_of(&["--exact"], &dir.join("exact.json"));
    assert_eq!(
        (
            fast["occupancy_grid"].as_bool(),
            exact["occupancy_grid"].as_bool()
        ),
        (Some(true), Some(false))
    );
    assert_eq!(fast["early_termination"], 1e-4f32 as f64);
    let (a, b) = (
        fast["mean_psnr"].as_f64().unwrap(),
        exact["mean_psnr"].as_f64().unwrap(),
    );
    assert!(a > 45.0 && b > 45.0, "{a} dB skipping, {b} dB exact");

    // Hierarchical sampling with the same field as its coarse field renders nearly the same images.
    let two_pass = write(
        &dir,
        "two_pass.sdf",
        "fn density(p: vec3) -> f32 = volsdf_density(box(p, [1.2, 0.8, 1.0]), alpha: 20.0, beta: 0.05)\n\
         fn color(p: vec3) -> vec3 = clamp(abs(p) + 0.2, 0.0, 1.0)\n\
         fn coarse_density(p: vec3) -> f32 = density(p)\n\
         fn coarse_color(p: vec3) -> vec3 = color(p)\n",
    );
    let mut args = vec!["eval-views", two_pass.as_str(), "--importance", "64"];
    args.extend(common);
    let (stdout, stderr) = text(&nerfjit(&args, None));
    let mean = stdout
        .lines()
        .find(|l| l.starts_with("mean"))
        .unwrap_or_else(|| panic!("{stderr}"));
    let hierarchical: f64 = mean.split_whitespace().nth(1).unwrap().parse().unwrap();
    assert!(hierarchical > 30.0, "{stdout}");
    // Without coarse functions, --importance is a clear error.
    let mut args = vec!["eval-views", script.as_str(), "--importance", "64"];
    args.extend(common);
    let out = nerfjit(&args, None);
    assert!(!out.status.success());
    assert!(text(&out).1.contains("coarse_density"), "{}", text(&out).1);

    // The comparison grid: one row, both fields, their PSNR printed and a PNG written.
    let grid = dir.join("grid.png");
    let row = format!("fields={script},{other}");
    let mut args = vec![
        "compare",
        "--columns",
        "box,empty",
        "--row",
        row.as_str(),
        "--out",
        grid.to_str().unwrap(),
    ];
    args.extend(common);
    let out = nerfjit(&args, None);
    let (stdout, stderr) = text(&out);
    assert!(out.status.success(), "{stderr}");
    let scores: Vec<f64> = stdout
        .lines()
        .next()
        .unwrap()
        .split(": ")
        .filter_map(|part| part.split(' ').next()?.parse().ok())
        .collect();
    assert!(
        scores.len() == 2 && scores[0] > 40.0 && scores[1] < 25.0,
        "{stdout}"
    );
    let png = image::open(&grid).expect("a PNG").to_rgb8();
    assert!(
        png.width() > 3 * 24 && png.height() > 24,
        "{}×{}",
        png.width(),
        png.height()
    );
}

#[test]
fn long_expressions_compile_up_to_the_limit_and_are_refused_beyond_it() {
    let dir = scratch("chains");
    let sum = |n: usize| vec!["p.x * 0.001"; n].join(" + ");
    // 4,000 terms: deeper than the main thread's stack would take through every pass; sphere traced.
    let long = write(
        &dir,
        "long.sdf",
        &format!(
            "fn sdf(p: vec3) -> f32 = length(p) - 1.0 + {}\nrender sphere_trace {{ camera: orbit(radius: 3, frames: 1), size: 8, out: \"long.png\" }}\n",
            sum(4_000)
        ),
    );
    let out = nerfjit(&["run", &long, "--out", &dir.display().to_string()], None);
    let (stdout, stderr) = text(&out);
    assert!(out.status.success(), "{stdout}{stderr}");
    assert!(dir.join("long.png").is_file());
    // 100,000 terms: refused with the place and a hint, at once.
    let huge = write(
        &dir,
        "huge.sdf",
        &format!("fn sdf(p: vec3) -> f32 =\n    {}\n", sum(100_000)),
    );
    let out = nerfjit(&["check", &huge], None);
    let (_, stderr) = text(&out);
    assert!(!out.status.success());
    assert!(stderr.contains("expression too long"), "{stderr}");
    assert!(stderr.contains("huge.sdf:2:"), "{stderr}");
    assert!(stderr.contains("split it with 'let'"), "{stderr}");
}

#[test]
fn absurd_thread_counts_are_refused() {
    let torus = concat!(env!("CARGO_MANIFEST_DIR"), "/examples/torus.sdf");
    let out = nerfjit(&["--threads", "100000", "check", torus], None);
    let (_, stderr) = text(&out);
    assert!(!out.status.success());
    assert!(stderr.contains("--threads 100000"), "{stderr}");
}

#[test]
fn optimizer_settings_are_checked_and_used() {
    let dir = scratch("optimizer");
    std::fs::write(
        dir.join("cloud.xyz"),
        "1 0 0\n0 1 0\n0 0 1\n-1 0 0\n0 -1 0\n0 0 -1\n",
    )
    .expect("cloud");
    let script = |optimizer: &str| {
        format!(
            "param r: vec<1> = [0.5]\nfn sdf(p: vec3) -> f32 = length(p) - r[0]\ntrain sdf {{\n    data: points(\"cloud.xyz\"),\n    steps: 200, batch: 6, random: 6, lr: 1e-2,\n    optimizer: {optimizer},\n}}\n"
        )
    };
    let bad = write(&dir, "bad.sdf", &script("adam(beta2: 1.5)"));
    let out = nerfjit(&["run", &bad, "--out", &dir.display().to_string()], None);
    let (_, stderr) = text(&out);
    assert!(!out.status.success());
    assert!(
        stderr.contains("bad.sdf:6:28") && stderr.contains("out of range"),
        "{stderr}"
    );
    let bad = write(&dir, "bad.sdf", &script("adam(sparse: yes)"));
    let out = nerfjit(&["run", &bad, "--out", &dir.display().to_string()], None);
    let (_, stderr) = text(&out);
    assert!(!out.status.success());
    assert!(
        stderr.contains("bad.sdf:6:29") && stderr.contains("'true' or 'false'"),
        "{stderr}"
    );
    let good = write(
        &dir,
        "good.sdf",
        &script("adam(beta2: 0.99, eps: 1e-15, sparse: true)"),
    );
    let out = nerfjit(&["run", &good, "--out", &dir.display().to_string()], None);
    let (stdout, stderr) = text(&out);
    assert!(out.status.success(), "{stdout}{stderr}");
    // The radius moves from 0.5 toward the unit sphere the points lie on.
    let r: f32 = stdout
        .split("r = [")
        .nth(1)
        .and_then(|rest| rest.split(']').next())
        .and_then(|v| v.parse().ok())
        .expect("the trained radius is printed");
    assert!(r > 0.9 && r < 1.1, "{stdout}");
}

#[test]
fn numbers_beyond_f32_are_refused_in_scripts_and_settings() {
    let dir = scratch("overflow");
    let script = write(
        &dir,
        "big.sdf",
        "param r: vec<1> = [1.0]\nfn sdf(p: vec3) -> f32 = length(p) - r[0] * 1e39\n",
    );
    let out = nerfjit(&["check", &script], None);
    let (_, stderr) = text(&out);
    assert!(!out.status.success());
    assert!(
        stderr.contains("big.sdf:2:45") && stderr.contains("32-bit float"),
        "{stderr}"
    );
    let torus = concat!(env!("CARGO_MANIFEST_DIR"), "/examples/torus.sdf");
    let out = nerfjit(
        &[
            "run",
            torus,
            "--out",
            &dir.display().to_string(),
            "--set",
            "render.size=1e40",
        ],
        None,
    );
    let (_, stderr) = text(&out);
    assert!(!out.status.success());
    assert!(
        stderr.contains("--set:1:13") && stderr.contains("32-bit float"),
        "{stderr}"
    );
}

#[test]
fn resume_refuses_another_scripts_checkpoint_and_says_when_there_is_nothing() {
    let dir = scratch("resume");
    std::fs::write(
        dir.join("cloud.xyz"),
        "1 0 0\n0 1 0\n0 0 1\n-1 0 0\n0 -1 0\n0 0 -1\n",
    )
    .expect("cloud");
    let script = |param: &str| {
        format!(
            "param {param}: vec<1> = [0.5]\nfn sdf(p: vec3) -> f32 = length(p) - {param}[0]\ntrain sdf {{\n    data: points(\"cloud.xyz\"),\n    steps: 20, batch: 6, random: 6,\n    checkpoint: \"fit.ckpt.json\",\n}}\n"
        )
    };
    let out_dir = dir.display().to_string();
    let first = write(&dir, "first.sdf", &script("r"));
    let out = nerfjit(&["run", &first, "--out", &out_dir, "--resume"], None);
    let (stdout, stderr) = text(&out);
    assert!(out.status.success(), "{stdout}{stderr}");
    assert!(stderr.contains("nothing to resume: no checkpoint at"), "{stderr}");
    assert!(dir.join("fit.ckpt.json").is_file());
    // Same number of params, other names: not this script's checkpoint.
    let other = write(&dir, "other.sdf", &script("radius"));
    let out = nerfjit(&["run", &other, "--out", &out_dir, "--resume"], None);
    let (_, stderr) = text(&out);
    assert!(!out.status.success());
    assert!(
        stderr.contains("written by a script with other params (r: vec<1>)"),
        "{stderr}"
    );
    // Its own script resumes from it.
    let out = nerfjit(&["run", &first, "--out", &out_dir, "--resume"], None);
    let (_, stderr) = text(&out);
    assert!(
        out.status.success() && stderr.contains("resuming from"),
        "{stderr}"
    );
}

#[test]
fn two_outputs_of_one_run_may_not_be_the_same_file() {
    let dir = scratch("same-output");
    for sub in ["a", "b"] {
        std::fs::create_dir_all(dir.join(sub)).expect("folder");
    }
    let block = |out: &str| {
        format!("render sphere_trace {{ camera: orbit(radius: 3, frames: 1), size: 8, out: \"{out}\" }}\n")
    };
    let source = format!(
        "fn sdf(p: vec3) -> f32 = length(p) - 1.0\n{}{}",
        block("a/x.png"),
        block("b/x.png")
    );
    let script = write(&dir, "twice.sdf", &source);
    // Different folders: two files.
    let run = |args: &[&str]| {
        Command::new(env!("CARGO_BIN_EXE_nerfjit"))
            .args(args)
            .current_dir(&dir)
            .output()
            .expect("nerfjit runs")
    };
    let out = run(&["run", &script]);
    assert!(out.status.success(), "{:?}", text(&out));
    // --out keeps only the names: the same file twice, refused before anything is written.
    let flat = dir.join("flat");
    let out = run(&["run", &script, "--out", &flat.display().to_string()]);
    let (_, stderr) = text(&out);
    assert!(!out.status.success());
    assert!(
        stderr.contains("is written twice: also by the setting at line 2"),
        "{stderr}"
    );
    assert!(stderr.contains("twice.sdf:3:"), "{stderr}");
    assert!(!flat.join("x.png").exists());
}

#[test]
fn completions_are_printed_for_each_shell() {
    for (shell, marker) in [
        ("bash", "_nerfjit()"),
        ("zsh", "#compdef nerfjit"),
        ("fish", "complete -c nerfjit"),
    ] {
        let out = nerfjit(&["completions", shell], None);
        let (stdout, stderr) = text(&out);
        assert!(out.status.success(), "{stderr}");
        assert!(
            stdout.contains(marker) && stdout.contains("eval-views"),
            "{shell}: {stdout}"
        );
    }
}

#[test]
fn data_check_reports_a_data_set_or_names_what_is_wrong() {
    let dir = scratch("data-check");
    crate::common::make_views(&dir);
    let (ok, report, err) = crate::common::run(&dir, &["data", "check", "."]);
    assert!(ok, "{err}");
    assert!(
        report.contains("./cams.json: course (PyTorch3D look-at) cameras"),
        "{report}"
    );
    assert!(
        report.contains("4 views, images 40×40 PNG (Rgb8), all present"),
        "{report}"
    );
    assert!(
        report.contains(
            "camera centers 2.47 to 2.54 from the origin, within [-2.50, -0.40, -2.50] to [1.80, 0.80, 0.00]"
        ),
        "{report}"
    );

    std::fs::remove_file(dir.join("view_002.png")).unwrap();
    let (ok, _, err) = crate::common::run(&dir, &["data", "check", "cams.json"]);
    assert!(!ok);
    assert!(
        err.contains("1 of the 4 images are missing: 'view_002.png'"),
        "{err}"
    );

    std::fs::write(dir.join("other.json"), "{\"views\": []}").unwrap();
    let (ok, _, err) = crate::common::run(&dir, &["data", "check", "other.json"]);
    assert!(
        !ok && err.contains("is neither a Blender transforms file"),
        "{err}"
    );
    let empty = scratch("data-check-empty");
    let (ok, _, err) = crate::common::run(&empty, &["data", "check", "."]);
    assert!(
        !ok && err.contains("holds no camera file: looked for transforms_train.json"),
        "{err}"
    );
}

#[test]
fn renders_of_a_field_that_is_nan_somewhere_or_too_steep_name_the_function_and_a_point() {
    let dir = scratch("nan-field");
    let camera = "camera: surround(radius: 4, frames: 2, up: z, focal: 1), size: 24";
    let cases = [
        (
            format!("fn sdf(p: vec3) -> f32 = length(p) - 1.0 + sqrt(p.x - 0.5)\nrender sphere_trace {{ {camera}, out: \"a.png\" }}\n"),
            "warning: 'sdf' is NaN at [",
        ),
        (
            format!("fn density(p: vec3) -> f32 = 10.0 * log(p.x)\nfn color(p: vec3) -> vec3 = [0.5, 0.5, 0.5]\n\
                     render volume {{ {camera}, near: 2, far: 6, samples: 16, out: \"b.png\" }}\n"),
            "warning: 'density' is NaN at [",
        ),
        (
            format!("fn density(p: vec3) -> f32 = 1.0\nfn color(p: vec3) -> vec3 = [0.5, 1.0 / (p.y - p.y), 0.5]\n\
                     render volume {{ {camera}, near: 2, far: 6, samples: 16, out: \"c.png\" }}\n"),
            "warning: 'color' is inf at [",
        ),
        (
            format!("fn sdf(p: vec3) -> f32 = length(p) - 1.0\nrender sphere_trace {{ {camera}, out: \"d.png\" }}\n"),
            "",
        ),
        // Ten times a distance: steeper than the tracer assumes, which names the bound to use; with it, quiet.
        (
            format!("fn sdf(p: vec3) -> f32 = 10.0 * (length(p) - 1.0)\nrender sphere_trace {{ {camera}, out: \"e.png\" }}\n"),
            "the tracer's lipschitz (1): sphere tracing steps through surfaces where the field is steeper than that; set `lipschitz: 11`",
        ),
        (
            format!("fn sdf(p: vec3) -> f32 = 10.0 * (length(p) - 1.0)\nrender sphere_trace {{ {camera}, lipschitz: 10, out: \"f.png\" }}\n"),
            "",
        ),
    ];
    for (i, (source, want)) in cases.iter().enumerate() {
        let script = write(&dir, &format!("s{i}.sdf"), source);
        let out = nerfjit(&["run", &script, "--out", &dir.display().to_string()], None);
        let (_, err) = text(&out);
        assert!(out.status.success(), "{err}");
        if want.is_empty() {
            assert!(!err.contains("warning"), "{err}");
        } else {
            assert!(err.contains(want), "case {i}: {err}");
        }
    }
}

#[test]
fn hierarchical_renders_skip_an_occupancy_grid_without_changing_the_picture() {
    let dir = scratch("hierarchical_grid");
    let script = "\
fn density(p: vec3) -> f32 = 30.0 * sigmoid(-40.0 * (length(p) - 0.6))
fn color(p: vec3) -> vec3 = clamp(0.5 + 0.5 * p, 0.0, 1.0)
fn coarse_density(p: vec3) -> f32 = 10.0 * sigmoid(-10.0 * (length(p) - 0.6))
fn coarse_color(p: vec3) -> vec3 = vec3(0.5)
render volume { camera: surround(radius: 3, frames: 1, up: z, focal: 1.5), size: 32, near: 1, far: 5,
                samples: 16, importance: 32, out: \"exact.png\" }
render volume { camera: surround(radius: 3, frames: 1, up: z, focal: 1.5), size: 32, near: 1, far: 5,
                samples: 16, importance: 32, skip_empty: grid(bounds: 1.5, resolution: 32), out: \"grid.png\" }
";
    let path = write(&dir, "hierarchical.sdf", script);
    let out = nerfjit(&["run", &path, "--out", dir.to_str().unwrap()], None);
    assert!(out.status.success(), "{}", text(&out).1);
    let exact = image::open(dir.join("exact.png")).unwrap().to_rgb8();
    let grid = image::open(dir.join("grid.png")).unwrap().to_rgb8();
    let worst = exact
        .pixels()
        .zip(grid.pixels())
        .flat_map(|(p, q)| (0..3).map(move |c| p[c].abs_diff(q[c])))
        .max();
    // The grid is the fine field's (density above 1e-4): the coarse field's wider halo outside it is
    // skipped, which moves a few importance samples, no pixel by more than a few levels.
    assert!(worst <= Some(3), "the grid changed a pixel by {worst:?}");
    let lit = exact.pixels().filter(|p| p[0] > 40).count();
    assert!(lit > 50, "the ball is missing: {lit} lit pixels");
}

#[test]
fn bench_w7_and_large_take_a_given_scene_and_other_workloads_refuse_one() {
    let torus = concat!(env!("CARGO_MANIFEST_DIR"), "/examples/torus.sdf");
    let out = nerfjit(
        &["bench", "w7", "--reps", "1", "--threads", "1", "--scene", torus],
        None,
    );
    let (stdout, stderr) = text(&out);
    assert!(out.status.success(), "{stderr}");
    assert!(stdout.contains(&format!("the sdf of {torus}")), "{stdout}");
    assert!(stdout.contains("distance+gradient"), "{stdout}");

    let dir = scratch("bench-scene");
    let no_sdf = write(&dir, "no_sdf.sdf", "fn f(p: vec3) -> f32 = length(p) - 1.0\n");
    let out = nerfjit(&["bench", "w7", "--reps", "1", "--scene", &no_sdf], None);
    let (_, stderr) = text(&out);
    assert!(!out.status.success() && stderr.contains("sdf"), "{stderr}");

    let vec4 = write(&dir, "vec4.sdf", "fn sdf(p: vec4) -> f32 = length(p) - 1.0\n");
    let out = nerfjit(&["bench", "w7", "--reps", "1", "--scene", &vec4], None);
    let (_, stderr) = text(&out);
    assert!(
        out.status.code() == Some(1) && stderr.contains("must be fn sdf(vec3) -> f32"),
        "{stderr}"
    );

    let out = nerfjit(&["bench", "w5", "--scene", torus], None);
    let (_, stderr) = text(&out);
    assert!(
        !out.status.success()
            && stderr.contains("'--scene' applies to w7 (")
            && stderr.contains("large (the model)")
            && stderr.contains("frames (the checkpoint)"),
        "{stderr}"
    );
    // `frames` renders a checkpoint: without one it says so.
    let out = nerfjit(&["bench", "frames"], None);
    let (_, stderr) = text(&out);
    assert!(
        out.status.code() == Some(1) && stderr.contains("give --scene CKPT"),
        "{stderr}"
    );

    // `large` takes a model in the `.vm` format; a missing one is named.
    let out = nerfjit(&["bench", "large", "--scene", "no-such-model.vm"], None);
    let (_, stderr) = text(&out);
    assert!(
        out.status.code() == Some(1) && stderr.contains("cannot read 'no-such-model.vm'"),
        "{stderr}"
    );
}

#[test]
fn bench_quality_skips_the_data_sets_that_are_not_there() {
    // Beside a folder with no ../shared/data, every recipe is skipped, and the table is empty.
    let scratch = scratch("quality");
    let dir = scratch.join("checkout");
    std::fs::create_dir_all(&dir).unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_nerfjit"))
        .args(["bench", "quality", "--minutes", "1"])
        .current_dir(&dir)
        .output()
        .unwrap();
    let (stdout, stderr) = text(&out);
    assert!(out.status.success(), "{stderr}");
    let report = stdout + &stderr;
    assert_eq!(report.matches("skipped: ../shared/data/").count(), 4, "{report}");
    let table = std::fs::read_to_string(dir.join("target/bench-quality/quality.json")).unwrap();
    assert_eq!(table.trim(), "[]");
    let out = Command::new(env!("CARGO_BIN_EXE_nerfjit"))
        .args(["bench", "quality", "--minutes", "0"])
        .current_dir(&dir)
        .output()
        .unwrap();
    assert!(!out.status.success() && text(&out).1.contains("give a positive number of minutes"));
}
