//! `nerfjit bench`: the benchmark workloads of `shared/bench/WORKLOADS.md`, timed after warm-up, medians of
//! several repetitions, JIT compile time reported separately.

use std::path::Path;
use std::time::Instant;

use nerfjit_dsl::{kernel_graphs, Type};
use nerfjit_jit::profile::{self, Phase};
use nerfjit_jit::{Kernel, Options, Precision};
use nerfjit_runtime::surfaces::marching::{extract, extract_pruned, Pruning};
use nerfjit_runtime::{on_pool, render_frames, sphere_trace_into, Quantize, Rng, Shading};

use nerfjit::blocks::sphere_trace::SphereTracePlan;
use nerfjit::failure::{Failure, Result};
use nerfjit::script;
use nerfjit::settings::block::first_block;
use nerfjit::settings::schema::Kind;
use nerfjit_field::JitFn;

mod frames;
mod quality;
pub mod roofline;

/// A benchmark workload.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Workload {
    /// W7: the 20-primitive scene's distance (and distance + gradient) at 1,048,576 random points.
    W7,
    /// W1: the course's torus, 20 sphere-traced 256×256 frames.
    W1,
    /// W2: the course's box volume, 20 frames of 256×256 with 64 samples.
    W2,
    /// W3: training steps of the box recovery (needs ../shared/data/assignment3).
    W3,
    /// W4: training steps of the course's NeRF on lego (needs ../shared/data/lego), and one 128×128 view.
    W4,
    /// W5: training steps of the course's neural SDF on the bunny (needs ../shared/data/assignment3).
    W5,
    /// W6: training steps of the course's VolSDF on lego (needs ../shared/data/lego).
    W6,
    /// W8: hash-grid training steps of `instant_lego.sdf` (needs ../shared/data/lego): its recipe (2^14
    /// entries per hashed level, 1024 rays × 128 samples a step, the occupancy grid from step 50), and
    /// instant-ngp's table of 2^19 entries with 4096 rays a step; each with its roofline (the step's phases
    /// against the machine's FMA, random-access and memory rates, measured in the same sitting).
    W8,
    /// Marching cubes of W7's 20-primitive scene at 512³ over [-4, 4]³: every grid point evaluated, and only
    /// the blocks that interval bounds leave near the surface (the same mesh, checked).
    Mesh,
    /// A large f-rep model (by default a generated city of 288 boxes, ~8,000 operations in the `.vm`
    /// format; `--scene MODEL.vm` for another, such as fidget's published models): JIT compile time of its
    /// value, gradient and bounds kernels, a 512³ interval-pruned mesh, sphere-traced 256² and 1024² frames.
    Large,
    /// The dense-layer products alone: GFLOP/s of the 128 × 128 forward product and weight gradient on
    /// tiles of points, on one thread and on all threads.
    Dense,
    /// The hash-grid encoding alone (16 levels × 2 features, lego's 2^14 and instant-ngp's 2^19 entries a
    /// level): ns a point of its read and its scatter on one thread, over batches of 128 (a tile of the
    /// kernels), 1,024 and 8,192 uniformly random points, the levels the outer loop of each batch.
    Grid,
    /// Quality: each shipped recipe trained on each data set of ../shared/data for `--minutes`, one
    /// after the other; one table of held-out PSNR / SSIM, speed and occupied cells.
    Quality,
    /// Frames: renders of a trained checkpoint (`--scene CKPT`, e.g. `instant_lego_full.ckpt.safetensors`)
    /// at 800×800 and 400×400 from the views its training holds out (else its script's camera path), as
    /// `nerfjit render` makes them.
    Frames,
}

fn median(mut xs: Vec<f64>) -> f64 {
    xs.sort_by(f64::total_cmp);
    xs[xs.len() / 2]
}

fn time_reps(reps: usize, mut f: impl FnMut()) -> f64 {
    f();
    median(
        (0..reps.max(1))
            .map(|_| {
                let t = Instant::now();
                f();
                t.elapsed().as_secs_f64()
            })
            .collect(),
    )
}

/// Runs a workload and prints its figures; the networks of W4, W5, W6 and W8 multiply in `products`; W7
/// evaluates the `sdf` of `scene` when given (the 20-primitive scene otherwise), `large` imports the
/// model `scene` names (the generated city otherwise), and `quality` trains each recipe for `minutes`.
pub fn run(
    workload: Workload,
    reps: usize,
    threads: Option<usize>,
    products: Precision,
    scene: Option<&str>,
    minutes: f64,
) -> Result<()> {
    if scene.is_some() && !matches!(workload, Workload::W7 | Workload::Large | Workload::Frames) {
        return Err(Failure::Message(
            "'--scene' applies to w7 (the script whose sdf is evaluated at W7's points), large (the model) and frames (the checkpoint)"
                .into(),
        ));
    }
    match workload {
        Workload::W7 => w7(reps, threads, scene.unwrap_or(W7_SCENE)),
        Workload::W1 => w1(reps),
        Workload::W2 => w2(reps),
        Workload::W3 => w3(reps),
        Workload::W4 => w4(reps, products),
        Workload::W5 => w5(reps, products),
        Workload::W6 => w6(reps, products),
        Workload::W8 => w8(reps, products),
        Workload::Mesh => mesh(reps),
        Workload::Large => large(reps, scene.map(Path::new)),
        Workload::Dense => dense(reps, threads),
        Workload::Grid => grid(reps),
        Workload::Quality => quality::quality(minutes),
        Workload::Frames => frames::frames(reps, scene.map(Path::new)),
    }
}

/// W7's scene: 8 spheres, 6 boxes and 6 tori joined by `min`.
const W7_SCENE: &str = "examples/complex_scene.sdf";

fn w7(reps: usize, threads: Option<usize>, scene: &str) -> Result<()> {
    const N: usize = 1 << 20;
    let program = script::load(scene)?;
    nerfjit_field::check_signature(&program, "sdf", &[&[Type::Vec(3)]], &Type::F32)?;
    let f = program.lower("sdf")?;
    let mut rng = Rng::new(7);
    let cols: Vec<Vec<f32>> = (0..3)
        .map(|_| (0..N).map(|_| rng.next_f32() * 8.0 - 4.0).collect())
        .collect();
    let ins: Vec<&[f32]> = cols.iter().map(Vec::as_slice).collect();
    nerfjit::emit(&(format!("W7 sdf_eval: {N} points, the sdf of {scene}, median of {reps}") + "\n"));
    let max_threads = threads.unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    for (label, graph) in [
        ("distance", kernel_graphs::value(&f)),
        ("distance+gradient", kernel_graphs::with_gradient(&f)),
    ] {
        let kernel = Kernel::compile(&graph, Options::default())?;
        let mut outs = vec![vec![0.0f32; N]; kernel.n_outputs];
        for t in [1, max_threads] {
            let seconds = time_reps(reps, || {
                let mut refs: Vec<&mut [f32]> = outs.iter_mut().map(Vec::as_mut_slice).collect();
                kernel.eval_parallel(N, &ins, &mut refs, &program.param_values, &mut [], t);
            });
            nerfjit::emit(
                &(format!(
                "  {label:<18} {t} thread{}: {:6.2} ns/point   (JIT compile {:.1} ms, {} IR nodes, {} bytes)",
                if t == 1 { " " } else { "s" },
                seconds * 1e9 / N as f64,
                kernel.stats().seconds * 1e3,
                kernel.stats().nodes,
                kernel.stats().code_bytes
            ) + "\n"),
            );
            if t == max_threads {
                break;
            }
        }
    }
    Ok(())
}

/// The value, gradient and bounds kernels of a benchmark script's `sdf`.
fn mesh_kernels(compiler: &nerfjit_field::Compiler) -> Result<(JitFn, JitFn, JitFn)> {
    let kernels = nerfjit::blocks::mesh::MeshKernels::compile(compiler, "sdf", true)?;
    let bounds = kernels
        .bounds
        .ok_or_else(|| Failure::Message("the script's interval bounds are constant".into()))?;
    Ok((kernels.value, kernels.gradient, bounds))
}

fn mesh(reps: usize) -> Result<()> {
    const RESOLUTION: usize = 512;
    let program = script::load(W7_SCENE)?;
    let cache = nerfjit_jit::KernelCache::new();
    let compiler = nerfjit_field::Compiler {
        program: &program,
        params: &program.param_values,
        cache: &cache,
    };
    let t = Instant::now();
    let (value, gradient, bounds_of) = mesh_kernels(&compiler)?;
    let compile_s = t.elapsed().as_secs_f64();
    let grid = ([-4.0; 3], [4.0; 3]);
    let mut brute = None;
    let brute_s = time_reps(reps, || {
        brute = Some(extract(&value, Some(&gradient), grid, RESOLUTION, 0.0).expect("a finite field meshes"));
    });
    let mut pruned = None;
    let pruned_s = time_reps(reps, || {
        pruned = Some(
            extract_pruned(&value, Some(&gradient), &bounds_of, None, grid, RESOLUTION, 0.0)
                .expect("a finite field meshes"),
        );
    });
    let mut specialized = None;
    let specialized_s = time_reps(reps, || {
        specialized = Some(specialized_mesh(
            &compiler, &value, &gradient, &bounds_of, grid, RESOLUTION,
        ));
    });
    let brute = brute.expect("timed");
    let (pruned, pruning) = pruned.expect("timed");
    let (specialized, regions) = specialized.expect("timed");
    let same = |m: &nerfjit_runtime::Mesh| m.vertices == brute.vertices && m.triangles == brute.triangles;
    let verdict = |m| if same(m) { "the same mesh" } else { "MESHES DIFFER" };
    nerfjit::emit(&format!(
        "mesh: W7 scene at {RESOLUTION}³ cells, median of {reps}\n  every grid point   {:7.3} s\n  interval-pruned    {:7.3} s   ({:.3}× brute force; {:.2}% of the points evaluated, {} boxes bounded; kernels compiled in {:.1} ms): {}\n  and specialized    {:7.3} s   ({:.3}× brute force; {} of {} regions restricted, the restrictions within the time): {}\n  {} triangles\n",
        brute_s,
        pruned_s,
        pruned_s / brute_s,
        100.0 * pruning.points_evaluated as f64 / pruning.points as f64,
        pruning.boxes,
        compile_s * 1e3,
        verdict(&pruned),
        specialized_s,
        specialized_s / brute_s,
        regions.regions_specialized,
        regions.regions,
        verdict(&specialized),
        brute.triangles.len(),
    ));
    if !same(&pruned) || !same(&specialized) {
        return Err(Failure::Message(
            "a pruned mesh differs from the brute-force mesh".into(),
        ));
    }
    Ok(())
}

/// The pruned mesh of a script's `sdf` with its regions specialized (the specialization is part of the
/// time).
fn specialized_mesh(
    compiler: &nerfjit_field::Compiler,
    value: &JitFn,
    gradient: &JitFn,
    bounds_of: &JitFn,
    grid: ([f32; 3], [f32; 3]),
    resolution: usize,
) -> (nerfjit_runtime::Mesh, Pruning) {
    let specializer = compiler
        .specializer("sdf", &[Type::Vec(3)], &Type::F32)
        .expect("the benchmark's sdf is checked");
    extract_pruned(
        value,
        Some(gradient),
        bounds_of,
        Some(&specializer),
        grid,
        resolution,
        0.0,
    )
    .expect("a finite field meshes")
}

/// `large` on the model file `model` (`.vm`), or on the generated city of 288 boxes.
fn large(reps: usize, model: Option<&Path>) -> Result<()> {
    let (script, name) = match model {
        Some(path) => {
            let imported = nerfjit::commands::import::script_of(path)?;
            (imported.script, imported.name)
        }
        None => (
            nerfjit::commands::import::convert(&nerfjit::city_model::city(), "city.vm")
                .map_err(Failure::Message)?,
            "a city of 288 boxes".to_string(),
        ),
    };
    let program = nerfjit_dsl::compile(&format!("{name} (imported)"), &script)?;
    let f = program.lower("sdf")?;
    let ops = nerfjit::commands::import::operations(&script);
    nerfjit::emit(&format!(
        "large: {name}, {ops} operations in the .vm format, median of {reps}\n"
    ));
    for (label, graph) in [
        ("value", kernel_graphs::value(&f)),
        ("value+gradient", kernel_graphs::with_gradient(&f)),
        ("bounds", kernel_graphs::interval(&f)),
    ] {
        let seconds = time_reps(reps.min(3), || {
            Kernel::compile(&graph, Options::default()).expect("an imported model compiles");
        });
        nerfjit::emit(&format!(
            "  JIT compile {label:<15} {:7.3} s ({} IR nodes)\n",
            seconds,
            graph.compact().len()
        ));
    }
    let cache = nerfjit_jit::KernelCache::new();
    let compiler = nerfjit_field::Compiler {
        program: &program,
        params: &program.param_values,
        cache: &cache,
    };
    let (value, gradient, bounds_of) = mesh_kernels(&compiler)?;
    // One run: tens of seconds.
    let t = Instant::now();
    let grid = ([-1.0; 3], [1.0; 3]);
    let (pruned, pruning) = extract_pruned(&value, Some(&gradient), &bounds_of, None, grid, 512, 0.0)?;
    let mesh_s = t.elapsed().as_secs_f64();
    nerfjit::emit(&format!(
        "  mesh at 512³, interval-pruned, one run {:7.3} s (field evaluations {:.2}% of the grid's points)\n",
        mesh_s,
        100.0 * pruning.points_evaluated as f64 / pruning.points as f64
    ));
    let t = Instant::now();
    let (specialized, regions) = specialized_mesh(&compiler, &value, &gradient, &bounds_of, grid, 512);
    let specialized_s = t.elapsed().as_secs_f64();
    let same = specialized.vertices == pruned.vertices && specialized.triangles == pruned.triangles;
    nerfjit::emit(&format!(
        "  and specialized, one run             {:7.3} s ({} of {} regions restricted, the restrictions within the time): {}\n",
        specialized_s,
        regions.regions_specialized,
        regions.regions,
        if same { "the same mesh" } else { "MESHES DIFFER" }
    ));
    let plan = SphereTracePlan::new(first_block(&program, Kind::SphereTrace, ".")?)?;
    let fields = plan.compile_fields(&compiler)?;
    let sdf = fields.traced_sdf();
    let shading = Shading::Lambert {
        gradient: &gradient,
        light_dir: glam::Vec3::new(-0.5, 1.0, -0.8),
        albedo: [0.85, 0.75, 0.6],
    };
    let (w, h) = plan.size;
    let trace = |sdf: &dyn nerfjit_runtime::BatchFn, (w, h): (u32, u32)| {
        let mut frame = nerfjit_runtime::Frame::empty();
        let seconds = time_reps(reps.min(3), || {
            sphere_trace_into(&plan.cameras[0], w, h, sdf, &shading, &plan.trace, &mut frame)
                .expect("validated settings render");
        });
        (seconds, frame)
    };
    let ((trace_s, skipped), (plain_s, plain)) = (trace(&sdf, (w, h)), trace(&fields.sdf, (w, h)));
    let hits_differ = skipped.hit.iter().zip(&plain.hit).filter(|(a, b)| a != b).count();
    let depth_differs = skipped
        .depth
        .iter()
        .zip(&plain.depth)
        .filter(|(a, b)| a.is_finite() && b.is_finite())
        .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
    nerfjit::emit(&format!(
        "  sphere trace one {w}×{h} frame {:7.3} s ({:.2} M rays/s; {:.3} s without skipping the space its bounds prove empty: {hits_differ} hits differ, depths by {depth_differs:.1e} at most)\n",
        trace_s,
        f64::from(w * h) / trace_s / 1e6,
        plain_s
    ));
    // Large models are to trace at 1024² in seconds: one frame at that size.
    let (big_s, _) = trace(&sdf, (1024, 1024));
    nerfjit::emit(&format!(
        "  sphere trace one 1024×1024 frame {:7.3} s ({:.2} M rays/s)\n",
        big_s,
        1024.0 * 1024.0 / big_s / 1e6
    ));
    Ok(())
}

/// Plain sphere tracing of the torus in f64, one ray at a time: the reference for W1's output.
fn reference_torus_frame(plan: &SphereTracePlan, camera: usize) -> Vec<[f32; 3]> {
    let (w, h) = plan.size;
    let cam = &plan.cameras[camera];
    let s = &plan.trace;
    let sdf = |p: [f64; 3]| ((p[0].hypot(p[1]) - 1.0).hypot(p[2])) - 0.25;
    let mut out = Vec::with_capacity((w * h) as usize);
    for row in 0..h {
        for col in 0..w {
            let (o, d) = cam.ray(row, col, w, h);
            let (o, d) = (o.as_dvec3(), d.as_dvec3());
            let mut t = f64::from(s.near);
            let mut color = s.background;
            for _ in 0..s.max_steps {
                let p = o + t * d;
                let dist = sdf(p.to_array());
                if dist < f64::from(s.eps) {
                    color = p.to_array().map(|c| c.abs().clamp(0.02, 0.98) as f32);
                    break;
                }
                t += dist;
                if t > f64::from(s.far) {
                    break;
                }
            }
            out.push(color);
        }
    }
    out
}

fn w1(reps: usize) -> Result<()> {
    let program = script::load("examples/torus.sdf")?;
    let plan = SphereTracePlan::new(first_block(&program, Kind::SphereTrace, ".")?)?;
    let cache = nerfjit_jit::KernelCache::new();
    let t = Instant::now();
    let compiler = nerfjit_field::Compiler {
        program: &program,
        params: &program.param_values,
        cache: &cache,
    };
    let fields = plan.compile_fields(&compiler)?;
    let compile_s = t.elapsed().as_secs_f64();
    let sdf = fields.traced_sdf();
    let color = fields
        .color
        .as_ref()
        .ok_or_else(|| Failure::Message("torus.sdf must shade with color".into()))?;
    let shading = Shading::Color {
        color,
        gradient: None,
    };
    let (w, h) = plan.size;
    let mut frame = nerfjit_runtime::Frame::empty();
    // Frame after frame from a thread of the pool, as `render_frames` traces them.
    let seconds = time_reps(reps, || {
        on_pool(|| {
            for camera in &plan.cameras {
                sphere_trace_into(camera, w, h, &sdf, &shading, &plan.trace, &mut frame)
                    .expect("validated settings render");
            }
        })
    });
    let frames = render_frames(&plan.cameras, w, h, &sdf, &shading, &plan.trace, None)?;
    let per_frame = seconds / plan.cameras.len() as f64;
    // Frames are rendered into one reused frame buffer, as a viewer would; `run` keeps every frame.
    let mut diff = 0.0f64;
    for (i, frame) in frames.iter().enumerate() {
        let reference = reference_torus_frame(&plan, i);
        let byte = |x: f32| f64::from((x.clamp(0.0, 1.0) * 255.0) as u8);
        diff += frame
            .rgb
            .iter()
            .zip(&reference)
            .map(|(a, b)| (0..3).map(|c| (byte(a[c]) - byte(b[c])).abs()).sum::<f64>())
            .sum::<f64>();
    }
    let mean_diff = diff / (frames.len() as f64 * f64::from(w * h) * 3.0);
    nerfjit::emit(
        &(format!(
            "W1 sphere_trace_torus: {} frames of {w}×{h}, median of {reps}",
            frames.len()
        ) + "\n"),
    );
    nerfjit::emit(
        &(format!(
            "  {:.3} ms/frame, {:.1} M rays/s (JIT compile {:.1} ms)",
            per_frame * 1e3,
            f64::from(w * h) / per_frame / 1e6,
            compile_s * 1e3
        ) + "\n"),
    );
    nerfjit::emit(
        &(format!("  mean |difference| from plain f64 sphere tracing: {mean_diff:.4} of 255 per channel")
            + "\n"),
    );
    Ok(())
}

/// The first block of `kind` in a benchmark script, with outputs going to the temporary folder.
fn w2(reps: usize) -> Result<()> {
    let program = script::load("examples/box.sdf")?;
    let plan = nerfjit::blocks::volume::VolumePlan::new(first_block(&program, Kind::Volume, ".")?)?;
    let cache = nerfjit_jit::KernelCache::new();
    let t = Instant::now();
    let field = nerfjit_field::VolumeField::compile(&program, &cache, Precision::F32)?;
    let compile_s = t.elapsed().as_secs_f64();
    let (forward, _) = field.bind(&program.param_values);
    let settings = plan.settings(&field);
    let (w, h) = plan.size;
    let seconds = time_reps(reps, || {
        for camera in &plan.cameras {
            nerfjit_runtime::render_volume(camera, w, h, &forward, &settings)
                .expect("validated settings render");
        }
    });
    nerfjit::emit(
        &(format!(
            "W2 volume_render_box: {} frames of {w}×{h}×{} samples, median of {reps}",
            plan.cameras.len(),
            plan.samples
        ) + "\n"),
    );
    nerfjit::emit(
        &(format!(
        "  {:.2} ms/frame, {:.1} M samples/s (exact composite: no early termination; JIT compile {:.1} ms)",
        1e3 * seconds / plan.cameras.len() as f64,
        (plan.cameras.len() * (w * h) as usize * plan.samples) as f64 / seconds / 1e6,
        compile_s * 1e3
    ) + "\n"),
    );
    // Empty-space skipping: an occupancy grid over the box (half-side 0.875) and its falloff, probed as
    // any field's is, and from the script's interval bounds as `render volume` builds it.
    let (bounds, resolution, threshold) = (([-1.25; 3], [1.25; 3]), 64, 1e-4);
    let probed = || {
        nerfjit_runtime::OccupancyGrid::build(
            &field.bind_density(&program.param_values),
            bounds,
            resolution,
            settings.mode,
            threshold,
        )
    };
    let from_bounds = || {
        field.occupancy_grid(
            &program,
            &program.param_values,
            &cache,
            (bounds, resolution, threshold, nerfjit_runtime::GridSpace::Scene),
            false,
        )
    };
    nerfjit::emit(&format!(
        "W2 {w}×{h}×{}: exact: {:.2} ms/frame\n",
        plan.samples,
        1e3 * seconds / plan.cameras.len() as f64
    ));
    for (label, grid) in [
        ("probed", w2_grid(probed)?),
        ("from interval bounds", w2_grid(from_bounds)?),
    ] {
        let (grid, grid_ms) = grid;
        let render_grid =
            |camera| nerfjit_runtime::render_volume_with(camera, w, h, &forward, &settings, Some(&grid));
        let grid_seconds = time_reps(reps, || {
            for camera in &plan.cameras {
                render_grid(camera).expect("validated settings render");
            }
        });
        // Error of the grid render in 8-bit color steps, over every channel of every frame.
        let (mut max_err, mut sum_err, mut count) = (0u8, 0u64, 0u64);
        for camera in &plan.cameras {
            let exact = nerfjit_runtime::render_volume(camera, w, h, &forward, &settings)?;
            let fast = render_grid(camera)?;
            for (a, b) in exact.rgb.iter().flatten().zip(fast.rgb.iter().flatten()) {
                let err = Quantize::Round.byte(*a).abs_diff(Quantize::Round.byte(*b));
                (max_err, sum_err, count) = (max_err.max(err), sum_err + err as u64, count + 1);
            }
        }
        nerfjit::emit(&format!(
            "  with an occupancy grid {label}: {:.2} ms/frame (grid built in {grid_ms:.1} ms, {:.1}% of {resolution}³ cells occupied), max |Δ| {max_err}/255, mean {:.4}/255\n",
            1e3 * grid_seconds / plan.cameras.len() as f64,
            100.0 * grid.occupancy(),
            sum_err as f64 / count as f64
        ));
    }
    Ok(())
}

/// An occupancy grid and the milliseconds it took to build (the best of three builds).
fn w2_grid<E>(
    build: impl Fn() -> std::result::Result<nerfjit_runtime::OccupancyGrid, E>,
) -> Result<(nerfjit_runtime::OccupancyGrid, f64)>
where
    Failure: From<E>,
{
    let mut best = f64::INFINITY;
    let mut grid = None;
    for _ in 0..3 {
        let t = Instant::now();
        grid = Some(build()?);
        best = best.min(t.elapsed().as_secs_f64() * 1e3);
    }
    Ok((grid.expect("built"), best))
}

fn w3(reps: usize) -> Result<()> {
    let program = script::load("examples/train_box.sdf")?;
    let plan = nerfjit::blocks::train::TrainPlan::new(first_block(&program, Kind::Train, "examples")?)?;
    let steps = 50 * reps.max(1);
    let mut params = program.param_values.clone();
    let t = Instant::now();
    let summary = plan.run_steps(&program, &mut params, steps as u32)?;
    let seconds = t.elapsed().as_secs_f64();
    nerfjit::emit(
        &(format!("W3 train_box: {steps} steps of 4096 rays × 64 samples (forward, backward, Adam)") + "\n"),
    );
    nerfjit::emit(
        &(format!(
            "  {:.2} ms/step including JIT compile and data loading ({summary})",
            1e3 * seconds / steps as f64
        ) + "\n"),
    );
    Ok(())
}

/// GFLOP/s of a product of `flops`: `make` builds one thread's operands and returns the product, which
/// runs `per_thread` times on each of `threads` threads.
fn gflops(
    reps: usize,
    threads: usize,
    per_thread: usize,
    flops: f64,
    make: &(dyn Fn() -> Box<dyn FnMut()> + Sync),
) -> f64 {
    let seconds = time_reps(reps, || {
        std::thread::scope(|s| {
            for _ in 0..threads {
                s.spawn(|| {
                    let mut f = make();
                    (0..per_thread).for_each(|_| f());
                });
            }
        });
    });
    flops * (threads * per_thread) as f64 / seconds / 1e9
}

fn dense(reps: usize, threads: Option<usize>) -> Result<()> {
    use nerfjit_jit::bf16;
    use nerfjit_jit::gemm::{self, COLUMN, TILE};
    const WIDTH: usize = 128;
    const PER_THREAD: usize = 4000;
    let all = threads.unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    // Columns of one 64-byte aligned block, COLUMN floats apart, as the tiled kernels' arena lays them out.
    let columns = |n: usize| -> (Vec<f32>, usize) {
        let v: Vec<f32> = (0..n * COLUMN + 16).map(|i| 0.01 * (i / COLUMN) as f32).collect();
        let skip = v.as_ptr().align_offset(64);
        (v, skip)
    };
    let pointers = |(v, skip): &mut (Vec<f32>, usize), n: usize| -> Vec<*mut f32> {
        // SAFETY: column c lies inside the buffer (n·COLUMN + 16 floats, skip < 16).
        (0..n)
            .map(|c| unsafe { v.as_mut_ptr().add(*skip + c * COLUMN) })
            .collect()
    };
    let product = move |precision: Precision| -> Box<dyn FnMut()> {
        let w: Vec<f32> = (0..WIDTH * WIDTH)
            .map(|i| ((i * 7919) % 201) as f32 / 100.0 - 1.0)
            .collect();
        let w_bf16 = bf16::Bf16Matrix::new(&w, WIDTH, WIDTH);
        let mut x = columns(WIDTH);
        let mut y = columns(WIDTH);
        let xp: Vec<*const f32> = pointers(&mut x, WIDTH)
            .into_iter()
            .map(|p| p as *const f32)
            .collect();
        let yp = pointers(&mut y, WIDTH);
        let mut scratch = bf16::Bf16Scratch::default();
        Box::new(move || {
            // SAFETY: every column holds TILE floats; x and y are separate buffers.
            unsafe {
                match precision {
                    Precision::F32 => gemm::matmul(&w, &xp, &yp, TILE),
                    Precision::Bf16 => bf16::matmul(&w_bf16, &xp, &yp, TILE, &mut scratch),
                }
            };
            std::hint::black_box(&mut y);
        })
    };
    let grad = move |precision: Precision| -> Box<dyn FnMut()> {
        let mut l = columns(WIDTH);
        let mut r = columns(WIDTH);
        let lp: Vec<*const f32> = pointers(&mut l, WIDTH)
            .into_iter()
            .map(|p| p as *const f32)
            .collect();
        let rp: Vec<*const f32> = pointers(&mut r, WIDTH)
            .into_iter()
            .map(|p| p as *const f32)
            .collect();
        let mut g = vec![0.0f32; WIDTH * gemm::padded(WIDTH)];
        let (mut scratch, mut scratch_bf16) = (Vec::new(), bf16::Bf16Scratch::default());
        Box::new(move || {
            // SAFETY: every column holds TILE floats.
            unsafe {
                match precision {
                    Precision::F32 => gemm::outer(&lp, &rp, TILE, &mut g, &mut scratch),
                    Precision::Bf16 => bf16::outer(&lp, &rp, TILE, &mut g, &mut scratch_bf16),
                }
            };
            std::hint::black_box((&l, &r, &g));
        })
    };
    let flops = (2 * WIDTH * WIDTH * TILE) as f64;
    let run = |name: &str, make: &(dyn Fn() -> Box<dyn FnMut()> + Sync)| {
        let one = gflops(reps, 1, PER_THREAD, flops, make);
        let many = gflops(reps, all, PER_THREAD, flops, make);
        nerfjit::emit(
            &(format!("dense {name} {WIDTH}×{WIDTH} × {TILE} points ({:?}): {one:.1} GFLOP/s on 1 thread, {many:.1} GFLOP/s on {all}", gemm::Backend::best())
                + "\n"),
        );
    };
    let unit = bf16::Unit::best().name();
    run("forward product (W·x)", &|| product(Precision::F32));
    run(&format!("bf16 product (W·x, {unit})"), &|| {
        product(Precision::Bf16)
    });
    run("weight gradient (Σ ȳ ⊗ x)", &|| grad(Precision::F32));
    run(&format!("bf16 weight gradient (Σ ȳ ⊗ x, {unit})"), &|| {
        grad(Precision::Bf16)
    });
    Ok(())
}

fn grid(reps: usize) -> Result<()> {
    use nerfjit_dsl::ir::{GridRead, GridSpec, V};
    use nerfjit_jit::grid_encoding::GridPlan;
    const POINTS: usize = 1 << 18;
    const FEATURES: usize = 2;
    const LEVELS: usize = 16;
    let mut rng = Rng::new(7);
    let coordinates: Vec<Vec<f32>> = (0..3)
        .map(|_| (0..POINTS).map(|_| 3.0 * rng.next_f32() - 1.5).collect())
        .collect();
    let cotangents: Vec<Vec<f32>> = (0..LEVELS * FEATURES)
        .map(|j| (0..POINTS).map(|t| 0.1 + 0.01 * ((t + j) % 97) as f32).collect())
        .collect();
    for log2_size in [14, 19] {
        let plan = GridPlan::new(&GridRead {
            spec: GridSpec {
                table: 0,
                levels: LEVELS as u32,
                features: FEATURES as u32,
                log2_size,
                base: 16,
                finest: 2048,
                extent: 1.5f32.to_bits(),
            },
            p: [V(0), V(1), V(2)],
            deriv: 0,
        });
        let params: Vec<f32> = (0..plan.params_end()).map(|i| 1e-4 * (i % 13) as f32).collect();
        let mut grads = vec![0.0f32; plan.params_end()];
        let mut line = format!("grid 2^{log2_size} entries a level, ns a point (1 thread):");
        for batch in [128, 1024, 8192] {
            let mut out = vec![vec![0.0f32; batch]; LEVELS * FEATURES];
            let read = time_reps(reps, || {
                for start in (0..POINTS).step_by(batch) {
                    let p = [0, 1, 2].map(|a| coordinates[a][start..].as_ptr());
                    let columns: Vec<*mut f32> = out.iter_mut().map(|c| c.as_mut_ptr()).collect();
                    // SAFETY: every point column holds POINTS ≥ start + batch floats, every output column
                    // batch floats.
                    unsafe { plan.read(p, &columns, &params, batch) };
                }
                std::hint::black_box(&out);
            });
            let scatter = time_reps(reps, || {
                for start in (0..POINTS).step_by(batch) {
                    let p = [0, 1, 2].map(|a| coordinates[a][start..].as_ptr());
                    let cot: Vec<*const f32> = cotangents.iter().map(|c| c[start..].as_ptr()).collect();
                    // SAFETY: every column holds POINTS ≥ start + batch floats.
                    unsafe { plan.scatter(p, &cot, &mut grads, batch) };
                }
                std::hint::black_box(&grads);
            });
            let ns = |seconds: f64| seconds * 1e9 / POINTS as f64;
            line += &format!(
                " batches of {batch}: read {:.0}, scatter {:.0};",
                ns(read),
                ns(scatter)
            );
        }
        nerfjit::emit(&format!("{}\n", line.trim_end_matches(';')));
    }
    Ok(())
}

/// Runs `steps` steps of the first `train` block of `script`, every sample evaluated; returns the summary
/// line.
fn volume_training(script: &str, steps: u32, products: Precision) -> Result<String> {
    let program = script::load_with(script, &[products_override("train", products)])?;
    let plan =
        nerfjit::blocks::train::TrainPlan::new(first_block(&program, Kind::Train, "examples")?)?.exact();
    let mut params = program.param_values.clone();
    profiled(|| plan.run_steps(&program, &mut params, steps))
}

/// The summary of training steps run by `train`, and where their time went.
fn profiled(train: impl FnOnce() -> Result<String>) -> Result<String> {
    profile::take();
    profile::enable(true);
    let summary = train();
    profile::enable(false);
    Ok(format!("{}\n  {}", summary?, time_shares(&profile::take())))
}

/// The `--set` override of a block's `products`.
fn products_override(block: &str, products: Precision) -> String {
    format!("{block}.products={}", products.name())
}

fn w4(reps: usize, products: Precision) -> Result<()> {
    let steps = 10 * reps.max(1) as u32;
    let summary = volume_training("examples/nerf_lego.sdf", steps, products)?;
    nerfjit::emit(&format!(
        "W4 nerf_lego: {steps} steps of 1024 rays × 128 samples ({products:?} products): {summary}\n"
    ));
    let program = script::load("examples/nerf_lego.sdf")?;
    let cache = nerfjit_jit::KernelCache::new();
    let field = nerfjit_field::VolumeField::compile(&program, &cache, products)?;
    let (forward, _) = field.bind(&program.param_values);
    let settings = nerfjit_runtime::VolumeSettings {
        near: 2.0,
        far: 6.0,
        samples: 128,
        mode: field.mode,
        background: Some([0.0; 3]),
        early_termination: None,
        spacing: nerfjit_runtime::DepthSpacing::Linear,
    };
    let set = nerfjit_runtime::load_blender_cameras(Path::new("../shared/data/lego/transforms_val.json"))?;
    let camera = set.cameras[0];
    let seconds = time_reps(reps, || {
        let frame = nerfjit_runtime::render_volume(&camera, 128, 128, &forward, &settings);
        std::hint::black_box(frame.is_ok());
    });
    nerfjit::emit(&format!(
        "W4 render: one 128×128 view, 128 samples per ray ({products:?} products): {seconds:.2} s/view\n"
    ));
    Ok(())
}

/// W8 with its roofline: for each table size, the machine's rates (for its grid levels' sizes and its
/// model's) measured before and after the steps, the better of each kept, and the steps' phases set
/// against them.
fn w8(reps: usize, products: Precision) -> Result<()> {
    let steps = 200 * reps.max(1) as u32;
    let (name, source) = script::read("examples/instant_lego.sdf")?;
    for (label, table, batch) in [("the example's", 14, 1024), ("instant-ngp's", 19, 4096)] {
        let source = source.replace("log2_size: 14", &format!("log2_size: {table}"));
        // 128 samples a ray whatever the example ships with, so that W8 stays the workload its log measured.
        let overrides = [
            format!("train.batch={batch}"),
            "train.samples=128".to_string(),
            products_override("train", products),
        ];
        let program = nerfjit_dsl::compile_with(&name, &source, &overrides).map_err(Failure::Script)?;
        let plan = nerfjit::blocks::train::TrainPlan::new(first_block(&program, Kind::Train, "examples")?)?;
        let mut params = program.param_values.clone();
        let levels: Vec<usize> = program
            .params
            .iter()
            .filter_map(|p| match &p.ty {
                Type::Grid(shape) => Some(shape),
                _ => None,
            })
            .flat_map(|g| {
                let g = &g.layout;
                (0..g.levels).map(|l| (g.level_size(l) * u64::from(g.features) * 4) as usize)
            })
            .collect();
        // The machine's rates before and after the steps, the better of each kept.
        let before = roofline::Rates::measure(&levels, params.len(), 5, products);
        profile::take();
        profile::enable(true);
        let summary = plan.run_steps(&program, &mut params, steps);
        profile::enable(false);
        let times = profile::take();
        let rates = roofline::Rates::measure(&levels, params.len(), 5, products).best(&before);
        nerfjit::emit(&format!(
            "W8 instant_lego, {label} table (2^{table} entries per hashed level), {steps} steps of {batch} rays × 128 samples (occupancy grid from step 50, {products:?} products): {}\n  {}\n{}\n",
            summary?,
            rates.describe(),
            roofline::table(&times, &rates, rayon::current_num_threads()),
        ));
    }
    Ok(())
}

/// Each phase's share of the training steps' time on all threads (wall time × threads), and the rest:
/// sampling, compositing, occupancy updates, gradient sums and idle threads.
fn time_shares(times: &profile::Times) -> String {
    let total = times.seconds(Phase::Steps) * rayon::current_num_threads() as f64;
    let mut parts: Vec<String> = Vec::new();
    let mut accounted = 0.0;
    for phase in Phase::ALL.into_iter().filter(|&p| p != Phase::Steps) {
        let share = times.seconds(phase) / total;
        accounted += share;
        parts.push(format!("{} {:.1}%", phase.name(), 100.0 * share));
    }
    parts.push(format!("the rest {:.1}%", 100.0 * (1.0 - accounted)));
    format!(
        "time on {} threads: {}",
        rayon::current_num_threads(),
        parts.join(", ")
    )
}

fn w5(reps: usize, products: Precision) -> Result<()> {
    let program = script::load_with(
        "examples/neural_sdf_bunny.sdf",
        &[products_override("train", products)],
    )?;
    let plan =
        nerfjit::blocks::train_sdf::TrainSdfPlan::new(first_block(&program, Kind::TrainSdf, "examples")?)?;
    let steps = 20 * reps.max(1) as u32;
    let mut params = program.param_values.clone();
    let summary = profiled(|| plan.run_steps(&program, &mut params, steps))?;
    nerfjit::emit(&format!(
        "W5 neural_sdf_bunny: {steps} steps of 4096 + 4096 points ({products:?} products): {summary}\n"
    ));
    Ok(())
}

fn w6(reps: usize, products: Precision) -> Result<()> {
    let steps = 10 * reps.max(1) as u32;
    let summary = volume_training("examples/volsdf_lego.sdf", steps, products)?;
    nerfjit::emit(&format!(
        "W6 volsdf_lego: {steps} steps of 1024 rays × 128 samples + eikonal ({products:?} products): {summary}\n"
    ));
    Ok(())
}
