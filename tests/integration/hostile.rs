//! Issue 16's hostile-input suite: generated scripts, data files and command lines of the classes the
//! issue lists (long and deep expressions, sizes that would exhaust memory, non-finite values, endless or
//! lying files, absurd flags), each run by the real binary under an address-space cap (`ulimit -v`) and a
//! time limit. Every case must end in seconds with a clear error: exit status 1 or 2, a message holding
//! the expected words and no longer than a screenful or two, and no panic, abort or signal. The few cases
//! that are no error (resuming a run that is already complete) must instead exit 0 with their message and
//! leave every file they were given as it was. Issue 56 added the last classes found: rows that take no
//! bytes, inlining that multiplies, decoders' own buffers, endless point streams, NaN initializers,
//! output-less blocks, negative seeds and errors pointing to the wrong place.

use std::fmt::Write as _;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// The address-space cap of every run, in KiB (`ulimit -v`): 4 GiB.
const ADDRESS_SPACE_KIB: u64 = 4 << 20;
/// The most time a case may take.
const TIME_LIMIT: Duration = Duration::from_secs(10);
/// The most standard error a case may print (a long line must not be echoed whole).
const MAX_STDERR_BYTES: usize = 16 << 10;

/// One hostile input: the files it needs, the arguments, and words its error must hold.
struct Case {
    class: &'static str,
    name: &'static str,
    files: Vec<(&'static str, Vec<u8>)>,
    args: Vec<String>,
    expect: &'static str,
    /// The address-space cap (`ulimit -v`) in KiB.
    address_space_kib: u64,
    /// Whether the case is no error: exit status 0, the expected words on standard output or error, and
    /// its files unchanged.
    succeeds: bool,
}

fn case(class: &'static str, name: &'static str, args: &[&str], expect: &'static str) -> Case {
    Case {
        class,
        name,
        files: Vec::new(),
        args: args.iter().map(|a| a.to_string()).collect(),
        expect,
        address_space_kib: ADDRESS_SPACE_KIB,
        succeeds: false,
    }
}

impl Case {
    /// The case run under an address-space cap of `kib` KiB instead.
    fn under(mut self, kib: u64) -> Case {
        self.address_space_kib = kib;
        self
    }

    /// The case as one that must succeed, keeping its files.
    fn succeeding(mut self) -> Case {
        self.succeeds = true;
        self
    }

    fn file(mut self, name: &'static str, bytes: impl Into<Vec<u8>>) -> Case {
        self.files.push((name, bytes.into()));
        self
    }

    /// A case that checks `script` (written as `s.sdf`).
    fn script(class: &'static str, name: &'static str, script: String, expect: &'static str) -> Case {
        case(class, name, &["check", "s.sdf"], expect).file("s.sdf", script)
    }
}

/// A sphere whose radius adds `expr` (an f32 expression in `p`).
fn sphere_plus(expr: &str) -> String {
    format!("fn sdf(p: vec3) -> f32 = length(p) - 1.0 + {expr}\n")
}

fn script_cases() -> Vec<Case> {
    let s = "scripts";
    vec![
        Case::script(
            s,
            "params beyond the memory limit",
            "param w: mat<65536, 65536> = kaiming(seed: 1)\nparam u: mat<65536, 65536> = kaiming(seed: 2)\n\
             fn sdf(p: vec3) -> f32 = length(p) - 1.0 + w[0][0] + u[0][0]\n"
                .into(),
            "more than the memory limit",
        ),
        Case::script(
            s,
            "a hash table beyond its limit",
            "param g: hashgrid<3, levels: 16, features: 2, log2_size: 40, base: 16, finest: 2048> = uniform(-1e-4, 1e-4, seed: 1)\n"
                .into(),
            "log2_size",
        ),
        Case::script(
            s,
            "a dense grid of 2 TiB",
            "param v: grid<3, res: 4096, features: 8> = uniform(-1e-4, 1e-4, seed: 1)\n".into(),
            "needs 549755813888 floats",
        ),
        Case::script(s, "a matrix dimension of 10^6", "param w: mat<1000000, 3> = 0\n".into(), "dimension"),
        Case::script(
            s,
            "a sum of 100,000 terms",
            sphere_plus(&vec!["p.x"; 100_000].join(" + ")),
            "chained operations",
        ),
        Case::script(
            s,
            "100,000 nested parentheses",
            sphere_plus(&format!("{}p.x{}", "(".repeat(100_000), ")".repeat(100_000))),
            "nest",
        ),
        Case::script(
            s,
            "a chain of 100,000 swizzles",
            sphere_plus(&format!("p{}.x", ".xyz".repeat(100_000))),
            "chained operations",
        ),
        Case::script(
            s,
            "a chain of 100,000 indexings",
            sphere_plus(&format!("p{}", "[0]".repeat(100_000))),
            "chained operations",
        ),
        Case::script(s, "100,000 unary minuses", sphere_plus(&format!("{}p.x", "-".repeat(100_000))), "nest"),
        Case::script(
            s,
            "100 functions calling each other",
            (1..100)
                .map(|i| format!("fn f{i}(x: f32) -> f32 = f{}(x) + 1.0\n", i - 1))
                .chain(["fn f0(x: f32) -> f32 = x\nfn sdf(p: vec3) -> f32 = f99(p.x)\n".to_string()])
                .collect(),
            "64",
        ),
        Case::script(s, "a literal beyond f32", sphere_plus("1e39"), "3.4028235e38"),
        Case::script(s, "a NaN const", format!("const a = 0 / 0\n{}", sphere_plus("a")), "finite"),
        Case::script(
            s,
            "an infinite param value",
            format!("param a: f32 = 1e38 * 10\n{}", sphere_plus("a")),
            "finite",
        ),
        Case::script(
            s,
            "a NaN block setting",
            format!("{}render sphere_trace {{ size: 0 / 0, out: \"a.png\" }}\n", sphere_plus("0.0")),
            "finite",
        ),
        Case::script(
            s,
            "a 200,000-character unknown name",
            sphere_plus(&format!("lenght{}(p)", "x".repeat(200_000))),
            "unknown function",
        ),
        Case::script(
            s,
            "an error at the end of a 1 MB line",
            sphere_plus(&format!("{}0.0 + lenght(p)", " ".repeat(1 << 20))),
            "unknown function 'lenght'",
        ),
        Case::script(
            s,
            "10,000 functions with an error each",
            (0..10_000).map(|i| format!("fn f{i}(x: f32) -> f32 = lenght(x)\n")).collect(),
            "more errors",
        ),
        case(s, "a script that never ends", &["check", "/dev/zero"], "longer than the 4194304 bytes"),
        case(s, "a 5 MB script", &["check", "big.sdf"], "longer than the 4194304 bytes")
            .file("big.sdf", format!("{}\n{}", sphere_plus("0.0"), "//".repeat(5 << 19))),
        case(
            s,
            "--set of 50,000 terms",
            &["run", "s.sdf", "--set", &format!("k={}", vec!["1"; 50_000].join("+"))],
            "chained operations",
        )
        .file("s.sdf", format!("const k = 1\n{}", sphere_plus("k"))),
        case(s, "--set of NaN", &["run", "s.sdf", "--set", "k=0/0"], "finite")
            .file("s.sdf", format!("const k = 1\n{}", sphere_plus("k"))),
        Case::script(
            s,
            "300 functions each inlining 2^19 calls",
            std::iter::once("fn f0(x: f32) -> f32 = sin(x) * 2.0 + cos(x) * 3.0 + x * x\n".to_string())
                .chain((1..20).map(|i| format!("fn f{i}(x: f32) -> f32 = f{}(x) + f{}(x)\n", i - 1, i - 1)))
                .chain((0..300).map(|k| format!("fn g{k}(x: f32) -> f32 = f19(x) + f18(x) + {k}.0\n")))
                .collect(),
            "together may take 4000000 expression steps",
        ),
        case(
            s,
            "a function of 400,000 IR nodes to mesh",
            &["mesh", "s.sdf", "--res", "16", "--out", "m.ply"],
            "262144 IR nodes",
        )
        .file("s.sdf", multiplying_sdf(9)),
        Case::script(
            s,
            "an initializer of fan_in 0",
            format!("param w: mat<2, 3> = kaiming(fan_in: 0, seed: 1)\n{}", sphere_plus("w[0][0]")),
            "fan_in is 0, not a whole number from 1",
        ),
        Case::script(
            s,
            "a negative seed",
            format!("param w: mat<2, 3> = uniform(-1, 1, seed: -1)\n{}", sphere_plus("w[0][0]")),
            "seed is -1, not a whole number from 0",
        ),
        Case::script(
            s,
            "a NaN const in a block setting",
            format!("const a = 0 / 0\n{}render sphere_trace {{ size: a, out: \"a.png\" }}\n", sphere_plus("0.0")),
            "setting 'size' is not finite: it uses const 'a'",
        ),
        case(s, "a block naming a missing function", &["run", "s.sdf"], "s.sdf:3:46")
            .file("s.sdf", fit("c.xyz").replace("steps: 5", "function: \"sdff\", steps: 5"))
            .file("c.xyz", SIX_POINTS),
        case(s, "a viz block drawing nothing", &["run", "s.sdf"], "draws nothing").file(
            "s.sdf",
            format!(
                "{}viz {{ camera: look_at(eye: [0, 0, -4], at: [0, 0, 0], up: [0, 1, 0]), near: 1, far: 6 }}\n",
                sphere_plus("0.0")
            ),
        ),
    ]
}

/// A sphere plus `f{depth}(p.x)`, where f0 sums 400 distinct terms and each f_i calls f_{i−1} twice with
/// other arguments: inlining makes 400·2^depth nodes that hash-consing cannot merge.
fn multiplying_sdf(depth: usize) -> String {
    let terms: Vec<String> = (0..400).map(|i| format!("x * {i}.5")).collect();
    std::iter::once(format!("fn f0(x: f32) -> f32 = {}\n", terms.join(" + ")))
        .chain(
            (1..=depth).map(|i| format!("fn f{i}(x: f32) -> f32 = f{0}(x + 0.1) * f{0}(x - 0.2)\n", i - 1)),
        )
        .chain([sphere_plus(&format!("f{depth}(p.x)"))])
        .collect()
}

/// Six points on the unit sphere, as an `.xyz` file.
const SIX_POINTS: &str = "0 0 1\n1 0 0\n0 1 0\n0 0 -1\n-1 0 0\n0 -1 0\n";

/// A PNG header declaring a `side`×`side` image of PNG color type `color` (0 gray, 6 RGBA), followed by
/// a few bytes of data.
fn png_bomb(side: u32, color: u8) -> Vec<u8> {
    fn chunk(out: &mut Vec<u8>, kind: &[u8; 4], data: &[u8]) {
        out.extend((data.len() as u32).to_be_bytes());
        out.extend(kind);
        out.extend(data);
        out.extend(crc32(&[kind.as_slice(), data].concat()).to_be_bytes());
    }
    let mut header = Vec::new();
    header.extend(side.to_be_bytes());
    header.extend(side.to_be_bytes());
    header.extend([8, color, 0, 0, 0]);
    let mut png = b"\x89PNG\r\n\x1a\n".to_vec();
    chunk(&mut png, b"IHDR", &header);
    chunk(&mut png, b"IDAT", &[0x78, 0x9c, 0x63, 0, 0, 0, 1, 0, 1]);
    chunk(&mut png, b"IEND", &[]);
    png
}

/// A valid, all-black grayscale PNG of `side`×`side` pixels (it compresses about a thousandfold).
fn black_png(side: u32) -> Vec<u8> {
    let mut png = std::io::Cursor::new(Vec::new());
    image::GrayImage::new(side, side)
        .write_to(&mut png, image::ImageFormat::Png)
        .unwrap();
    png.into_inner()
}

/// The CRC-32 of PNG chunks.
fn crc32(bytes: &[u8]) -> u32 {
    let mut crc = !0u32;
    for &b in bytes {
        crc ^= u32::from(b);
        for _ in 0..8 {
            crc = if crc & 1 == 1 {
                (crc >> 1) ^ 0xedb8_8320
            } else {
                crc >> 1
            };
        }
    }
    !crc
}

/// A `.npy` header for float32 data of `shape`, followed by `data_bytes` zero bytes.
fn npy(shape: &str, data_bytes: usize) -> Vec<u8> {
    let mut header = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': {shape}, }}");
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend((header.len() as u16).to_le_bytes());
    out.extend(header.as_bytes());
    out.extend(vec![0u8; data_bytes]);
    out
}

/// A script fitting an SDF to the point cloud `file`.
fn fit(file: &str) -> String {
    format!(
        "param r: vec<1> = [0.5]\nfn sdf(p: vec3) -> f32 = length(p) - r[0]\n\
         train sdf {{ data: points(\"{file}\"), steps: 5, batch: 6, random: 6, checkpoint: none }}\n"
    )
}

fn data_cases() -> Vec<Case> {
    let d = "data";
    let blender = r#"{"camera_angle_x": 0.69, "frames": [{"file_path": "./r_0",
        "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]}]}"#;
    let nerf = "param c: vec3 = [0, 0, 0]\n\
                fn opacity(p: vec3) -> f32 = opacity_laplace(length(p - c) - 1.0, alpha: 1.0, beta: 0.05)\n\
                fn color(p: vec3) -> vec3 = [0.5, 0.5, 0.5]\n\
                train { data: blender(\"t.json\"), near: 2, far: 6, samples: 8, steps: 5, batch: 64, checkpoint: none }\n";
    let frame = r#"{"file_path": "./r_0", "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]}"#;
    let hundred_frames = format!(
        r#"{{"camera_angle_x": 0.69, "frames": [{}]}}"#,
        vec![frame; 100].join(", ")
    );
    let deep_json = format!("{}{}", "[".repeat(100_000), "]".repeat(100_000));
    vec![
        case(
            d,
            "a PNG declaring 60000×60000 pixels",
            &["run", "s.sdf"],
            "r_0.png",
        )
        .file("s.sdf", nerf)
        .file("t.json", blender)
        .file("r_0.png", png_bomb(60_000, 6)),
        case(
            d,
            "a capture of 100000×100000 images",
            &["run", "s.sdf"],
            "would need 111.8 GiB",
        )
        .file(
            "s.sdf",
            nerf.replace("blender(\"t.json\")", "nerfstudio(\"t.json\", normalize: false)"),
        )
        .file(
            "t.json",
            r#"{"camera_model": "PINHOLE", "fl_x": 5e4, "fl_y": 5e4, "cx": 5e4, "cy": 5e4, "w": 100000,
                    "h": 100000, "frames": [{"file_path": "a.png",
                    "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]}]}"#,
        ),
        case(
            d,
            "100 views beyond --max-memory 1M",
            &["--max-memory", "1M", "run", "s.sdf"],
            "100 views of 128×128",
        )
        .file(
            "s.sdf",
            nerf.replace("blender(\"t.json\")", "blender(\"t.json\", size: 128)"),
        )
        .file("t.json", hundred_frames),
        case(d, "camera JSON nested 100,000 deep", &["run", "s.sdf"], "t.json")
            .file("s.sdf", nerf)
            .file("t.json", deep_json.clone()),
        case(d, "a .npy declaring 10^15 points", &["run", "s.sdf"], "cloud.npy")
            .file("s.sdf", fit("cloud.npy"))
            .file("cloud.npy", npy("(1000000000000000, 3)", 64)),
        case(d, "a .npy shape that overflows", &["run", "s.sdf"], "too large")
            .file("s.sdf", fit("cloud.npy"))
            .file(
                "cloud.npy",
                npy("(4611686018427387904, 4611686018427387904, 3)", 64),
            ),
        case(
            d,
            "a PLY declaring 10^12 vertices",
            &["run", "s.sdf"],
            "cloud.ply",
        )
        .file("s.sdf", fit("cloud.ply"))
        .file(
            "cloud.ply",
            "ply\nformat binary_little_endian 1.0\nelement vertex 1000000000000\n\
                 property float x\nproperty float y\nproperty float z\nend_header\n\0\0\0\0",
        ),
        case(d, "an .xyz point that is NaN", &["run", "s.sdf"], "cloud.xyz")
            .file("s.sdf", fit("cloud.xyz"))
            .file("cloud.xyz", "0 0 1\n1 0 0\nnan 0 0\n"),
        case(d, "a point file that never ends", &["run", "s.sdf"], "/dev/zero")
            .file("s.sdf", fit("/dev/zero")),
        case(
            d,
            "a checkpoint whose header claims 2^60 bytes",
            &["mesh", "c.safetensors", "--out", "m.ply"],
            "c.safetensors",
        )
        .file(
            "c.safetensors",
            [(1u64 << 60).to_le_bytes().as_slice(), b"{}"].concat(),
        ),
        case(
            d,
            "a checkpoint of JSON nested 100,000 deep",
            &["mesh", "c.ckpt.json", "--out", "m.ply"],
            "c.ckpt.json",
        )
        .file("c.ckpt.json", deep_json),
        case(d, "a .vm model of garbage", &["import", "m.vm"], "m.vm")
            .file("m.vm", "_0 var-x\n_1 frobnicate _0\n"),
        case(
            d,
            "a PLY element of 2^64 - 1 rows without properties",
            &["run", "s.sdf"],
            "element 'junk' declares 18446744073709551615 rows but no properties",
        )
        .file("s.sdf", fit("cloud.ply"))
        .file(
            "cloud.ply",
            [
                b"ply\nformat binary_little_endian 1.0\nelement junk 18446744073709551615\n\
                  element vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
                    .as_slice(),
                &[0; 12],
            ]
            .concat(),
        ),
        case(
            d,
            "a grayscale PNG declaring 20000×20000 pixels",
            &["run", "s.sdf"],
            "r_0.png: the image declares 20000×20000 pixels",
        )
        .file(
            "s.sdf",
            nerf.replace("blender(\"t.json\")", "blender(\"t.json\", size: 64)"),
        )
        .file("t.json", blender)
        .file("r_0.png", png_bomb(20_000, 0)),
        case(
            d,
            "a 4000×4000 PNG to decode beyond --max-memory 256M",
            &["--max-memory", "256M", "run", "s.sdf"],
            "decoding its 4000×4000 pixels would need",
        )
        .file(
            "s.sdf",
            nerf.replace("blender(\"t.json\")", "blender(\"t.json\", size: 64)"),
        )
        .file("t.json", blender)
        .file("r_0.png", black_png(4000)),
        case(
            d,
            "a checkpoint whose script no longer compiles",
            &["mesh", "c.ckpt.json", "--out", "m.ply"],
            "in the copy of 's.sdf' embedded in checkpoint 'c.ckpt.json'",
        )
        .file(
            "c.ckpt.json",
            checkpoint(
                "param r: vec<1> = [0.5]\nfn sdf(p: vec3) -> f32 = lenght(p) - r[0]\n",
                5,
            ),
        ),
        case(
            d,
            "--resume of a finished run",
            &["run", "s.sdf", "--resume"],
            "the run is already complete: 'c.ckpt.json' holds all 5 steps",
        )
        .succeeding()
        .file("s.sdf", finished_fit())
        .file("c.xyz", SIX_POINTS)
        .file("c.ckpt.json", checkpoint(&finished_fit(), 5))
        .file("sum.json", "{\"final_loss\": 0.25}\n"),
    ]
}

/// A fit of 5 steps to `c.xyz` with a checkpoint and a summary.
fn finished_fit() -> String {
    fit("c.xyz").replace(
        "checkpoint: none",
        "checkpoint: \"c.ckpt.json\", summary: \"sum.json\"",
    )
}

/// A JSON checkpoint at `step` of `script`, whose one param is `r: vec<1>`.
fn checkpoint(script: &str, step: u32) -> String {
    serde_json::json!({
        "format": "nerfjit-checkpoint-1",
        "script": { "name": "s.sdf", "source": script, "overrides": [] },
        "step": step,
        "params": [0.5],
        "adam": [step, 0.0, 0.0],
    })
    .to_string()
}

fn command_line_cases() -> Vec<Case> {
    let c = "command line";
    let torus = "examples/torus.sdf";
    // 1M params: 4 MiB of values fit in 8 MiB, their training state (16 bytes each) does not.
    let million = "param v: grid<3, res: 100, features: 1> = uniform(-1e-4, 1e-4, seed: 1)\n\
                   fn sdf(p: vec3) -> f32 = length(p) - 1.0 + grid(v, p)[0]\n\
                   train sdf { data: points(\"c.xyz\"), steps: 5, batch: 6, random: 6, checkpoint: none }\n";
    vec![
        case(
            c,
            "--threads 1000000",
            &["--threads", "1000000", "check", torus],
            "threads per core",
        ),
        case(
            c,
            "--max-memory 12X",
            &["--max-memory", "12X", "check", torus],
            "unknown unit",
        ),
        case(
            c,
            "--max-memory 0",
            &["--max-memory", "0", "check", torus],
            "1 byte",
        ),
        case(
            c,
            "params beyond --max-memory 1M",
            &["--max-memory", "1M", "check", "examples/instant_lego.sdf"],
            "'encoding'",
        ),
        case(
            c,
            "training state beyond --max-memory 8M",
            &["--max-memory", "8M", "run", "s.sdf"],
            "training 1000000 params",
        )
        .file("s.sdf", million)
        .file("c.xyz", SIX_POINTS),
        case(
            c,
            "mesh --res 100000",
            &["mesh", torus, "--res", "100000", "--out", "m.ply"],
            "2048",
        ),
        case(
            c,
            "render --size 60000",
            &["render", torus, "--size", "60000", "--out", "r.png"],
            "1..=4096",
        ),
        case(
            c,
            "a camera path of 10^9 frames",
            &[
                "render",
                torus,
                "--path",
                "orbit(frames: 1000000000)",
                "--out",
                "r.gif",
            ],
            "frames",
        ),
        case(c, "ulimit -v of 1 GB", &["run", torus], "ulimit -v").under(1_000_000),
        case(
            c,
            "a script that does not exist",
            &["run", "nowhere.sdf"],
            "nowhere.sdf",
        ),
        case(
            c,
            "eval --points /dev/zero",
            &["eval", torus, "sdf", "--points", "/dev/zero"],
            "/dev/zero:1: the line is longer than 1048576 bytes",
        ),
    ]
}

/// Runs `case` in `dir` under the caps; the problem found, if any.
fn run(case: &Case, dir: &Path) -> Option<String> {
    for (name, bytes) in &case.files {
        std::fs::write(dir.join(name), bytes).unwrap();
    }
    let repo = env!("CARGO_MANIFEST_DIR");
    let args: Vec<String> = case
        .args
        .iter()
        .map(|a| a.replace("examples/", &format!("{repo}/examples/")))
        .collect();
    let start = Instant::now();
    let mut child = Command::new("sh")
        .arg("-c")
        .arg(format!(
            "ulimit -v {} && exec \"$0\" \"$@\"",
            case.address_space_kib
        ))
        .arg(env!("CARGO_BIN_EXE_nerfjit"))
        .args(&args)
        .current_dir(dir)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("starts");
    let (stdout, stderr) = (child.stdout.take().unwrap(), child.stderr.take().unwrap());
    let out_reader = std::thread::spawn(move || std::io::read_to_string(stdout).unwrap_or_default());
    let reader = std::thread::spawn(move || std::io::read_to_string(stderr).unwrap_or_default());
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        if start.elapsed() > TIME_LIMIT {
            child.kill().ok();
            child.wait().ok();
            return Some(format!("still running after {} s", TIME_LIMIT.as_secs()));
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    let seconds = start.elapsed().as_secs_f64();
    let err = reader.join().unwrap();
    let out = out_reader.join().unwrap();
    let head: String = err.chars().take(600).collect();
    if case.succeeds {
        return succeeded(case, dir, status, &format!("{out}{err}"))
            .map(|p| format!("{p} after {seconds:.2} s: {head}"));
    }
    let problem = match status.code() {
        None => Some(format!("killed by a signal ({status})")),
        Some(0) => Some("succeeded".to_string()),
        Some(1 | 2)
            if ["panicked", "overflowed its stack", "memory allocation of"]
                .iter()
                .any(|w| err.contains(w)) =>
        {
            Some("crashed".to_string())
        }
        Some(1 | 2) if err.len() > MAX_STDERR_BYTES => Some(format!("printed {} bytes of errors", err.len())),
        Some(1 | 2) if !err.contains(case.expect) => Some(format!("the message lacks '{}'", case.expect)),
        Some(1 | 2) => None,
        Some(code) => Some(format!("exit status {code}")),
    };
    problem.map(|p| format!("{p} after {seconds:.2} s: {head}"))
}

/// The problem, if any, of `case` (one that must succeed) run in `dir`: it ended with `status`, printing
/// `output`.
fn succeeded(case: &Case, dir: &Path, status: std::process::ExitStatus, output: &str) -> Option<String> {
    if status.code() != Some(0) {
        return Some(format!("failed ({status})"));
    }
    if !output.contains(case.expect) {
        return Some(format!("the output lacks '{}'", case.expect));
    }
    let changed = case
        .files
        .iter()
        .find(|(name, bytes)| std::fs::read(dir.join(name)).ok().as_ref() != Some(bytes));
    changed.map(|(name, _)| format!("changed or removed {name}"))
}

#[test]
fn hostile_inputs_end_in_clear_errors_within_the_caps() {
    let root = std::env::temp_dir().join(format!("nerfjit-hostile-{}", std::process::id()));
    let classes = [
        ("scripts", script_cases()),
        ("data", data_cases()),
        ("command line", command_line_cases()),
    ];
    let mut failures = String::new();
    let mut counts = Vec::new();
    for (class, cases) in &classes {
        for (i, case) in cases.iter().enumerate() {
            assert_eq!(&case.class, class);
            let dir = root.join(format!("{}-{i}", class.replace(' ', "-")));
            std::fs::create_dir_all(&dir).unwrap();
            if let Some(problem) = run(case, &dir) {
                writeln!(failures, "[{class}] {}: {problem}\n", case.name).unwrap();
            }
        }
        counts.push(format!("{} {class}", cases.len()));
    }
    std::fs::remove_dir_all(&root).ok();
    let total: usize = classes.iter().map(|(_, c)| c.len()).sum();
    println!(
        "hostile inputs: {total} cases ({}), under ulimit -v {ADDRESS_SPACE_KIB} KiB unless the case says",
        counts.join(", ")
    );
    assert!(
        failures.is_empty(),
        "hostile inputs that did not end in a clear error:\n{failures}"
    );
}
