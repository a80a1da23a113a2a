//! One conformance suite for every way a script function is evaluated: the f64 interpreter (through the
//! runtime's [`BatchFn`], like the others), the JIT kernel (plain for elementwise functions, tiled for
//! dense layers and grid reads), the tape that meshes of large models run, and the fused sphere tracer.
//! Each backend evaluates the shipped examples' functions at the same random points and must agree with
//! the interpreter; the fused tracer must trace the images the interpreter traces step by step.

use nerfjit_dsl::ir::Graph;
use nerfjit_dsl::{interp, kernel_graphs, Program, Type};
use nerfjit_jit::{KernelCache, Tape};
use nerfjit_runtime::surfaces::sphere_trace::{sphere_trace, Shading, TraceSettings};
use nerfjit_runtime::{BatchFn, Camera, ClosureFn, Rng};

use nerfjit_field::{Compiler, Kind, TapeFn};

/// The functions of the shipped examples the suite evaluates: elementwise SDFs and colors, CSG,
/// dense layers, hash grids with spherical harmonics.
const FUNCTIONS: &[(&str, &str)] = &[
    ("examples/torus.sdf", "sdf"),
    ("examples/torus.sdf", "color"),
    ("examples/complex_scene.sdf", "sdf"),
    ("examples/nerf_lego_small.sdf", "density"),
    ("examples/nerf_lego_small.sdf", "color"),
    ("examples/instant_lego.sdf", "density"),
    ("examples/instant_lego.sdf", "color"),
    ("examples/instant_bunny.sdf", "sdf"),
    ("examples/instant_volsdf_lego.sdf", "density"),
];

/// A way to evaluate a function of a program.
trait Backend {
    /// The function `name` of `program` (its value graph `graph`) as a batch function, or `None` where
    /// this backend does not take it.
    fn build(program: &Program, name: &str, graph: &Graph) -> Option<Box<dyn BatchFn>>;
}

/// The reference: [`interp::eval_point`] in f64, one point at a time, rounded to f32.
struct Interpreter;

/// A value graph run by the interpreter.
struct Interpreted {
    graph: Graph,
    params: Vec<f64>,
}

impl BatchFn for Interpreted {
    fn n_inputs(&self) -> usize {
        self.graph.n_inputs as usize
    }

    fn n_outputs(&self) -> usize {
        self.graph.outputs.len()
    }

    fn eval(&self, n: usize, inputs: &[&[f32]], outputs: &mut [&mut [f32]]) {
        let mut point = vec![0.0; inputs.len()];
        for i in 0..n {
            for (x, column) in point.iter_mut().zip(inputs) {
                *x = f64::from(column[i]);
            }
            let values = interp::eval_point(&self.graph, &point, &self.params).outputs;
            for (column, v) in outputs.iter_mut().zip(values) {
                column[i] = v as f32;
            }
        }
    }
}

impl Backend for Interpreter {
    fn build(program: &Program, _name: &str, graph: &Graph) -> Option<Box<dyn BatchFn>> {
        Some(Box::new(Interpreted {
            graph: graph.clone(),
            params: program.param_values.iter().map(|&x| f64::from(x)).collect(),
        }))
    }
}

/// The JIT kernel the fields run on (tiled when the function has dense layers or grid reads).
struct JitKernel;

impl Backend for JitKernel {
    fn build(program: &Program, name: &str, _graph: &Graph) -> Option<Box<dyn BatchFn>> {
        let cache = KernelCache::new();
        let compiler = Compiler {
            program,
            params: &program.param_values,
            cache: &cache,
        };
        let signature = program.lower(name).expect("lowers").signature;
        let inputs: Vec<Type> = signature.inputs.into_iter().map(|(_, ty)| ty).collect();
        let field = compiler
            .function(name, &inputs, &signature.output, Kind::Value)
            .expect("compiles");
        Some(Box::new(field))
    }
}

/// The tape interpreter of meshes of large models (elementwise functions whose ops it takes).
struct TapeBackend;

impl Backend for TapeBackend {
    fn build(program: &Program, _name: &str, graph: &Graph) -> Option<Box<dyn BatchFn>> {
        let tape = Tape::new(graph, &program.param_values).ok()?;
        Some(Box::new(TapeFn(tape)))
    }
}

/// `n` random points in [−1.5, 1.5]³, each followed by a unit direction when `inputs` is 6.
fn points(inputs: usize, n: usize) -> Vec<Vec<f32>> {
    let mut rng = Rng::new(11);
    let mut columns = vec![Vec::with_capacity(n); inputs];
    for _ in 0..n {
        let mut point: Vec<f32> = (0..inputs).map(|_| 3.0 * rng.next_f32() - 1.5).collect();
        if inputs == 6 {
            let d = &mut point[3..];
            let norm = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-3);
            d.iter_mut().for_each(|x| *x /= norm);
        }
        for (column, x) in columns.iter_mut().zip(point) {
            column.push(x);
        }
    }
    columns
}

/// `field`'s outputs at `points`, output by output.
fn outputs(field: &dyn BatchFn, points: &[Vec<f32>]) -> Vec<Vec<f32>> {
    let ins: Vec<&[f32]> = points.iter().map(Vec::as_slice).collect();
    field.eval_columns(&ins)
}

/// Checks backend `B` against the interpreter on every function it takes; returns how many it took
/// and how many of those the JIT runs tiled.
fn conforms<B: Backend>() -> (usize, usize) {
    let (mut taken, mut tiled) = (0, 0);
    for &(path, name) in FUNCTIONS {
        let program = crate::script::load(path).expect("a shipped example");
        let graph = kernel_graphs::value(&program.lower(name).expect("lowers"));
        let Some(field) = B::build(&program, name, &graph) else {
            continue;
        };
        taken += 1;
        tiled += usize::from(graph.needs_tiles());
        let reference = Interpreter::build(&program, name, &graph).expect("the interpreter takes all");
        let points = points(graph.n_inputs as usize, 500);
        let (got, want) = (
            outputs(field.as_ref(), &points),
            outputs(reference.as_ref(), &points),
        );
        for (o, (got, want)) in got.iter().zip(&want).enumerate() {
            for (i, (&g, &w)) in got.iter().zip(want).enumerate() {
                let close = (g - w).abs() <= 2e-4 * (1.0 + w.abs()) || (g.is_nan() && w.is_nan());
                assert!(
                    close,
                    "{path} {name}, output {o} at point {i}: {g} where the interpreter gives {w}"
                );
            }
        }
    }
    (taken, tiled)
}

#[test]
fn the_jit_kernels_plain_and_tiled_agree_with_the_interpreter() {
    let (taken, tiled) = conforms::<JitKernel>();
    assert_eq!(taken, FUNCTIONS.len());
    assert!((1..taken).contains(&tiled), "{tiled} of {taken} tiled");
}

#[test]
fn the_tape_agrees_with_the_interpreter_on_the_functions_it_takes() {
    let (taken, tiled) = conforms::<TapeBackend>();
    assert!(taken >= 3, "the tape took {taken} functions");
    assert_eq!(tiled, 0);
}

/// The fused sphere tracer (a whole ray in one native loop) traces the image that the interpreter's SDF
/// traces step by step, for every elementwise SDF of the suite.
#[test]
fn the_fused_sphere_tracer_traces_what_the_interpreter_traces() {
    let camera = Camera::look_at(
        glam::Vec3::new(0.3, 1.2, 3.0),
        glam::Vec3::ZERO,
        glam::Vec3::Y,
        glam::Vec2::splat(1.2),
        glam::Vec2::ZERO,
    )
    .expect("a camera");
    let white = ClosureFn::new(3, 3, |_, out| out.fill(1.0));
    let shading = Shading::Color {
        color: &white,
        gradient: None,
    };
    let settings = TraceSettings {
        far: 20.0,
        eps: 1e-4,
        max_steps: 128,
        ..TraceSettings::default()
    };
    let mut traced = 0;
    for &(path, name) in FUNCTIONS.iter().filter(|(_, name)| *name == "sdf") {
        let program = crate::script::load(path).expect("a shipped example");
        let graph = kernel_graphs::value(&program.lower(name).expect("lowers"));
        if graph.needs_tiles() {
            continue;
        }
        let cache = KernelCache::new();
        let compiler = Compiler {
            program: &program,
            params: &program.param_values,
            cache: &cache,
        };
        let fused = compiler
            .function(name, &[Type::Vec(3)], &Type::F32, Kind::Sdf)
            .expect("compiles");
        assert!(fused.as_marcher().is_some(), "{path}: no fused tracer");
        let reference = Interpreter::build(&program, name, &graph).expect("the interpreter takes all");
        let (a, b) = (
            sphere_trace(&camera, 48, 48, &fused, &shading, &settings).expect("traces"),
            sphere_trace(&camera, 48, 48, reference.as_ref(), &shading, &settings).expect("traces"),
        );
        let hits = a.hit.iter().filter(|&&h| h).count();
        assert!(hits > 48 * 48 / 20, "{path}: {hits} hits");
        let disagree = a.hit.iter().zip(&b.hit).filter(|(x, y)| x != y).count();
        assert!(
            disagree * 100 <= hits,
            "{path}: {disagree} rays of {hits} hits disagree"
        );
        for ((&ta, &tb), (&ha, &hb)) in a.depth.iter().zip(&b.depth).zip(a.hit.iter().zip(&b.hit)) {
            if ha && hb {
                assert!(
                    (ta - tb).abs() < 1e-3 * (1.0 + tb),
                    "{path}: hit at {ta} where the interpreter hits at {tb}"
                );
            }
        }
        traced += 1;
    }
    assert_eq!(traced, 2);
}
