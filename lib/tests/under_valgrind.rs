//! The JIT and the runtime write only their buffers in a training run. CI runs this test binary under
//! valgrind's memcheck (`.ci/run`): the box's views are rendered, three training steps of the box
//! (elementwise kernels), two of a small network (tiled kernels whose backward passes read the arenas
//! their forward passes kept) and two of a hash grid (its scatters held back and added level by level) run
//! in this process, and valgrind reports no error. Valgrind's virtual CPU has
//! no AVX-512, so CI builds this binary for x86-64-v3 and the AVX2 paths run.

use std::path::{Path, PathBuf};

const CAMERAS: &str = r#"{
  "image_size": [24, 24],
  "cameras": [
    {"image": "view_000.png", "focal": 1.0, "principal_point": [0, 0], "eye": [-2.5, 0.3, 0.0], "scene_center": [0, 0, 0], "up": [0, 1, 0]},
    {"image": "view_001.png", "focal": 1.0, "principal_point": [0, 0], "eye": [0.0, -0.4, -2.5], "scene_center": [0, 0, 0], "up": [0, 1, 0]}
  ]
}"#;

const FIELD: &str =
    "fn opacity(p: vec3) -> f32 = opacity_laplace(box(p - center, sides), alpha: 1.0, beta: 0.05)\n\
                     fn color(p: vec3) -> vec3 = clamp(abs(p - center), 0.02, 0.98)\n";

/// Writes `source` as `dir/name` and runs it as `nerfjit run` would.
fn run(dir: &Path, name: &str, source: &str) {
    let path = dir.join(name);
    std::fs::write(&path, source).unwrap();
    let path = path.display().to_string();
    if let Err(e) = nerfjit::commands::run::run(&path, &[], Some(dir), false, None) {
        panic!("{name}: {e}");
    }
}

/// A script training two steps of the network `h` (4 outputs: density and colour) defined in `body`.
fn network(body: &str, samples: u32, batch: u32, summary: &str) -> String {
    format!(
        "{body}fn density(p: vec3) -> f32 = softplus(h(p)[0])\n\
         fn color(p: vec3) -> vec3 = sigmoid([h(p)[1], h(p)[2], h(p)[3]])\n\
         train {{ data: views(\"cams.json\"), near: 0, far: 5, samples: {samples}, steps: 2, batch: {batch}, \
         lr: 0.01, summary: \"{summary}\" }}\n"
    )
}

fn scratch() -> PathBuf {
    let dir = std::env::temp_dir().join(format!("nerfjit-valgrind-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

#[test]
#[ignore = "run by .ci/run under valgrind: cargo test --release -p nerfjit --test under_valgrind -- --ignored"]
fn training_steps_under_valgrind_make_no_memory_errors() {
    let dir = scratch();
    std::fs::write(dir.join("cams.json"), CAMERAS).unwrap();
    let truth = format!(
        "const center = [0.2, -0.1, 0.1]\nconst sides = [1.2, 0.8, 1.0]\n{FIELD}\
         render volume {{ camera: cameras(\"cams.json\"), size: 24, near: 0, far: 5, samples: 48, out: \"view.png\" }}\n"
    );
    run(&dir, "truth.sdf", &truth);
    assert!(dir.join("view_001.png").exists());

    let trainer = format!(
        "param center: vec3 = [0, 0, 0]\nparam sides: vec3 = [1.0, 1.0, 1.0]\n{FIELD}\
         train {{ data: views(\"cams.json\"), near: 0, far: 5, samples: 48, steps: 3, batch: 400, lr: 0.01, \
         summary: \"box.json\" }}\n"
    );
    run(&dir, "box.sdf", &trainer);
    assert!(dir.join("box.json").exists());

    let net =
        "param w1: mat<16, 3> = linear_init(seed: 1)\nparam b1: vec<16> = linear_init(fan_in: 3, seed: 2)\n\
               param w2: mat<4, 16> = linear_init(seed: 3)\n\
               fn h(p: vec3) -> vec<4> = dense(w2, relu(dense(w1, b1, p)))\n";
    run(&dir, "net.sdf", &network(net, 48, 64, "net.json"));
    assert!(dir.join("net.json").exists());

    // A hash grid, whose backward passes hold their scatters back for the step to add level by level (two
    // tasks: 512 rays of 96 samples are two chunks of points).
    let grid = "param table: hashgrid<3, levels: 4, features: 2, log2_size: 9, base: 4, finest: 32, bounds: 1.5> = \
                uniform(-0.1, 0.1, seed: 1)\nparam w1: mat<8, 8> = kaiming(seed: 2)\nparam w2: mat<4, 8> = kaiming(seed: 3)\n\
                fn h(p: vec3) -> vec<4> = dense(w2, relu(dense(w1, hashgrid(table, p))))\n";
    run(&dir, "grid.sdf", &network(grid, 96, 512, "grid.json"));
    assert!(dir.join("grid.json").exists());
    std::fs::remove_dir_all(&dir).unwrap();
}
