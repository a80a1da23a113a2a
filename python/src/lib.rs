//! nerfjit from Python: the extension module `nerfjit._nerfjit`, which the package `nerfjit` re-exports.
//!
//! Conversions only: a `Script` is a compiled program with its params, whose functions run as JIT kernels
//! on numpy arrays (values, gradients, vector-Jacobian products), and `run` runs a script's blocks as
//! `nerfjit run` does. Every kernel runs with the GIL released, over the machine's cores; compilation and
//! runs happen on a thread with the command line's deep stack.

use std::borrow::Cow;
use std::collections::HashMap;
use std::ops::Range;
use std::path::PathBuf;
use std::sync::{mpsc, Arc, Mutex};
use std::time::Duration;

use nerfjit::commands::render_views::{FieldViews, ViewArgs};
use nerfjit::failure::Failure;
use nerfjit::training::data_source::{scored_views, ScoredViews};
use nerfjit_dsl::{kernel_graphs, Program, Type};
use nerfjit_jit::{Kernel, Options};
use numpy::ndarray::{Array2, Array3, ShapeBuilder};
use numpy::{AllowTypeChange, IntoPyArray, PyArrayLikeDyn, PyArrayMethods, PyUntypedArrayMethods};
use pyo3::create_exception;
use pyo3::exceptions::{PyKeyError, PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use rayon::prelude::*;

create_exception!(
    nerfjit,
    ScriptError,
    PyValueError,
    "A script that does not compile; the message is the diagnostic: line, column, caret and hint."
);
create_exception!(
    nerfjit,
    NerfjitError,
    PyRuntimeError,
    "Anything else nerfjit refuses or fails at: a missing file, a bad argument, a run that failed."
);

/// The Python exception for `failure`.
fn to_py(failure: Failure) -> PyErr {
    match failure {
        Failure::Script(report) => ScriptError::new_err(report.to_string()),
        other => NerfjitError::new_err(other.to_string()),
    }
}

/// Runs `work` on a thread with the command line's stack (deep expressions recurse deeply in the
/// compiler's passes).
fn on_work_stack<T: Send>(work: impl FnOnce() -> T + Send) -> T {
    std::thread::scope(|scope| {
        let thread = std::thread::Builder::new()
            .stack_size(nerfjit::WORK_STACK_BYTES)
            .spawn_scoped(scope, work)
            .expect("a thread for the work");
        thread
            .join()
            .unwrap_or_else(|panic| std::panic::resume_unwind(panic))
    })
}

/// What a kernel of a function computes.
#[derive(Clone, Copy, Debug, Hash, PartialEq, Eq)]
enum Kind {
    /// The values.
    Value,
    /// The values, then each output's gradient with respect to the inputs.
    Gradient,
    /// Inputs and one cotangent per output → the values, the inputs' cotangents; the params' as reductions.
    Vjp,
}

/// A compiled kernel of one function and its shape.
struct Compiled {
    kernel: Kernel,
    /// Scalars the function reads per point.
    inputs: usize,
    /// Scalars it returns per point.
    outputs: usize,
    /// Whether it returns one scalar (`f32`), not a vector.
    scalar: bool,
}

/// What fills the input columns of points start..end (`fill(start, end, columns)`).
type FillColumns<'a> = dyn Fn(usize, usize, &mut [Vec<f32>]) + Sync + 'a;

/// Where a kernel's input columns come from: numpy's memory itself (column-major points), or copies that
/// each chunk makes of its rows.
enum Inputs<'a> {
    Columns(Vec<&'a [f32]>),
    Filled(&'a FillColumns<'a>),
}

/// Points per call of a kernel; the calls run on every core.
const CHUNK: usize = 4096;

impl Compiled {
    /// Runs the kernel on n points over every core, reading its input columns from `inputs`: for each of
    /// `ranges` (of output indices) a column-major (n, range) array of those outputs, which the kernel writes
    /// in place, and the reductions summed over the points.
    fn run(
        &self,
        n: usize,
        inputs: &Inputs,
        params: &[f32],
        ranges: &[Range<usize>],
    ) -> (Vec<Vec<f32>>, Vec<f32>) {
        let k = &self.kernel;
        let chunks = n.div_ceil(CHUNK);
        let mut results: Vec<Vec<f32>> = ranges.iter().map(|r| vec![0.0f32; n * r.len()]).collect();
        // Each chunk's part of each output column that a result holds, by output index.
        let mut parts: Vec<Vec<Option<&mut [f32]>>> = (0..chunks)
            .map(|_| (0..k.n_outputs).map(|_| None).collect())
            .collect();
        for (result, range) in results.iter_mut().zip(ranges) {
            for (column, output) in result.chunks_mut(n.max(1)).zip(range.clone()) {
                for (c, part) in column.chunks_mut(CHUNK).enumerate() {
                    parts[c][output] = Some(part);
                }
            }
        }
        let chunk = |(c, mut columns): (usize, Vec<Option<&mut [f32]>>)| -> Vec<f32> {
            let (start, end) = (c * CHUNK, ((c + 1) * CHUNK).min(n));
            let len = end - start;
            let filled: Vec<Vec<f32>>;
            let ins: Vec<&[f32]> = match inputs {
                Inputs::Columns(columns) => columns.iter().map(|col| &col[start..end]).collect(),
                Inputs::Filled(fill) => {
                    let mut columns = vec![vec![0.0f32; len]; k.n_inputs];
                    fill(start, end, &mut columns);
                    filled = columns;
                    filled.iter().map(Vec::as_slice).collect()
                }
            };
            // Outputs no result holds go to scratch columns.
            let mut scratch = vec![vec![0.0f32; len]; columns.iter().filter(|c| c.is_none()).count()];
            let mut spare = scratch.iter_mut();
            let mut outs: Vec<&mut [f32]> = columns
                .iter_mut()
                .map(|c| match c.take() {
                    Some(part) => part,
                    None => spare.next().expect("a scratch column").as_mut_slice(),
                })
                .collect();
            let mut reductions = vec![0.0f32; k.n_reductions];
            k.eval(len, &ins, &mut outs, params, &mut reductions);
            reductions
        };
        // One chunk runs on the calling thread: a call on a few points costs no thread hand-off.
        let sums: Vec<Vec<f32>> = match parts.len() {
            0 | 1 => parts.into_iter().enumerate().map(chunk).collect(),
            _ => parts.into_par_iter().enumerate().map(chunk).collect(),
        };
        let mut reductions = vec![0.0f32; k.n_reductions];
        for part in sums {
            for (total, x) in reductions.iter_mut().zip(part) {
                *total += x;
            }
        }
        (results, reductions)
    }
}

/// The box a mesh is extracted in: `r` for [−r, r]³, or its low and high corners.
#[derive(FromPyObject)]
enum Bounds {
    Radius(f32),
    Corners([f32; 3], [f32; 3]),
}

/// An (n, 3) array of triples (vertices, triangles).
fn rows_of<T: Copy>(triples: &[[T; 3]]) -> Array2<T> {
    Array2::from_shape_fn((triples.len(), 3), |(i, k)| triples[i][k])
}

/// The numpy shape of a param of type `ty`: a scalar, a vector, a matrix, or the flat values of networks and
/// grid tables.
fn param_shape(ty: &Type) -> Vec<usize> {
    match ty {
        Type::F32 => vec![],
        Type::Vec(n) => vec![*n],
        Type::Mat(r, c) => vec![*r, *c],
        other => vec![other.scalars()],
    }
}

/// The params of `program` as a dict of numpy arrays of their shapes, their values read from `flat` (the
/// params' values, or their gradients).
fn param_dict<'py>(py: Python<'py>, program: &Program, flat: &[f32]) -> PyResult<Bound<'py, PyDict>> {
    let dict = PyDict::new(py);
    for p in &program.params {
        let values = flat[p.offset..p.offset + p.ty.scalars()].to_vec();
        dict.set_item(&p.name, values.into_pyarray(py).reshape(param_shape(&p.ty))?)?;
    }
    Ok(dict)
}

/// A function's values at n points from their row-major array: (n,) for an `f32` result, else (n, outputs).
fn values_array<'py>(
    py: Python<'py>,
    compiled: &Compiled,
    n: usize,
    values: Vec<f32>,
) -> PyResult<Bound<'py, PyAny>> {
    Ok(match compiled.scalar {
        true => values.into_pyarray(py).into_any(),
        false => columns_array(n, compiled.outputs, values)
            .into_pyarray(py)
            .into_any(),
    })
}

/// The (n, width) array whose columns lie one after the other in `columns` (numpy's Fortran order: no copy).
fn columns_array(n: usize, width: usize, columns: Vec<f32>) -> Array2<f32> {
    Array2::from_shape_vec((n, width).f(), columns).expect("width columns of n values")
}

/// What a kernel computed at n points: the row-major arrays of the outputs asked for, and its reductions.
struct Evaluated {
    compiled: Arc<Compiled>,
    n: usize,
    results: Vec<Vec<f32>>,
    reductions: Vec<f32>,
}

/// A compiled `.sdf` script: its functions run on numpy arrays, its params are numpy arrays.
///
/// `Script(source, set=[])` compiles a script file (a path that exists, or an example's name such as
/// `"torus"`) or a script's text, with `--set` overrides (`["radius=1.5", "train.steps=100"]`); errors
/// raise `ScriptError` with the diagnostic. Points are `(N, k)` arrays of any float type, k the scalars the
/// function reads (`p: vec3` → 3; `color(p, d)` → 6).
#[pyclass(module = "nerfjit", name = "Script")]
struct Script {
    program: Mutex<Program>,
    /// The params' values, shared with the kernels running on them (copied only when one is set while a
    /// kernel still holds them).
    params: Mutex<Arc<Vec<f32>>>,
    kernels: Mutex<HashMap<(String, Kind), Arc<Compiled>>>,
}

impl Script {
    /// The script of `program` with `params`.
    fn of(program: Program, params: Vec<f32>) -> Script {
        Script {
            program: Mutex::new(program),
            params: Mutex::new(Arc::new(params)),
            kernels: Mutex::new(HashMap::new()),
        }
    }

    /// The kernel of `kind` for function `name`, compiled on first use.
    fn kernel(&self, name: &str, kind: Kind) -> PyResult<Arc<Compiled>> {
        let key = (name.to_string(), kind);
        if let Some(k) = self.kernels.lock().expect("the kernel cache").get(&key) {
            return Ok(k.clone());
        }
        let program = self.program.lock().expect("the program");
        let n_params = program.n_params();
        let compiled = on_work_stack(|| -> Result<Compiled, Failure> {
            let lowered = program.lower(name).map_err(Failure::Script)?;
            let (inputs, outputs) = (lowered.graph.n_inputs as usize, lowered.graph.outputs.len());
            let graph = match kind {
                Kind::Value => kernel_graphs::value(&lowered),
                Kind::Gradient => kernel_graphs::with_gradient(&lowered),
                Kind::Vjp => kernel_graphs::vjp(&lowered, n_params),
            };
            let kernel =
                Kernel::compile(&graph, Options::default()).map_err(|e| Failure::Message(e.to_string()))?;
            Ok(Compiled {
                kernel,
                inputs,
                outputs,
                scalar: lowered.signature.output == Type::F32,
            })
        })
        .map_err(to_py)?;
        let compiled = Arc::new(compiled);
        self.kernels
            .lock()
            .expect("the kernel cache")
            .insert(key, compiled.clone());
        Ok(compiled)
    }

    /// Runs the `kind` kernel of function `name` at `points` (with the columns of `cotangent`, the shape of
    /// its values, after theirs when given), the GIL released: the outputs in `ranges`, each a row-major
    /// (N, range) array, and the reductions.
    fn evaluate(
        &self,
        py: Python<'_>,
        name: &str,
        kind: Kind,
        points: &PyArrayLikeDyn<f32, AllowTypeChange>,
        cotangent: Option<&PyArrayLikeDyn<f32, AllowTypeChange>>,
        ranges: impl Fn(&Compiled) -> Vec<Range<usize>>,
    ) -> PyResult<Evaluated> {
        let compiled = self.kernel(name, kind)?;
        let view = points.as_array();
        let shaped = match view.ndim() {
            1 if compiled.inputs == 1 => view.into_shape_with_order((points.len(), 1)).ok(),
            2 => view.into_dimensionality::<numpy::ndarray::Ix2>().ok(),
            _ => None,
        };
        let Some(view) = shaped.filter(|v| v.ncols() == compiled.inputs) else {
            return Err(PyValueError::new_err(format!(
                "{name} reads {} scalars per point: pass an array of shape (N, {}), not {:?}",
                compiled.inputs,
                compiled.inputs,
                points.shape()
            )));
        };
        let (n, width) = (view.nrows(), compiled.inputs);
        let m = compiled.outputs;
        let seeds = cotangent.map(|c| c.as_array());
        if let Some(seeds) = &seeds {
            if seeds.len() != n * m {
                let shape = match compiled.scalar {
                    true => format!("({n},)"),
                    false => format!("({n}, {m})"),
                };
                return Err(PyValueError::new_err(format!(
                    "the cotangent has the shape of {name}'s values, {shape}, not {:?}",
                    seeds.shape()
                )));
            }
        }
        let seeds: Option<Cow<[f32]>> = seeds.map(|s| match s.to_slice() {
            Some(flat) => Cow::Borrowed(flat),
            None => Cow::Owned(s.iter().copied().collect()),
        });
        // Each chunk transposes its own rows into the kernel's columns.
        let fill = |start: usize, end: usize, columns: &mut [Vec<f32>]| {
            match view.to_slice() {
                // Row-major (numpy's default): a plain transpose.
                Some(flat) => {
                    for (j, column) in columns.iter_mut().take(width).enumerate() {
                        for (i, x) in column.iter_mut().enumerate() {
                            *x = flat[(start + i) * width + j];
                        }
                    }
                }
                None => {
                    let rows = view.slice(numpy::ndarray::s![start..end, ..]);
                    for (i, row) in rows.rows().into_iter().enumerate() {
                        for (j, x) in row.iter().enumerate() {
                            columns[j][i] = *x;
                        }
                    }
                }
            }
            if let Some(seeds) = &seeds {
                for i in start..end {
                    for o in 0..m {
                        columns[width + o][i - start] = seeds[i * m + o];
                    }
                }
            }
        };
        // Column-major points (np.asfortranarray, or a (k, N) array's transpose) are read where they are.
        let columns: Option<Vec<&[f32]>> = match (view.t().to_slice(), &seeds) {
            (Some(flat), None) if n > 0 => Some(flat.chunks(n).collect()),
            _ => None,
        };
        let inputs = match columns {
            Some(columns) => Inputs::Columns(columns),
            None => Inputs::Filled(&fill),
        };
        let params = self.params.lock().expect("the params").clone();
        let wanted = ranges(&compiled);
        let (results, reductions) = py.detach(|| compiled.run(n, &inputs, &params, &wanted));
        Ok(Evaluated {
            compiled,
            n,
            results,
            reductions,
        })
    }
}

#[pymethods]
impl Script {
    #[new]
    #[pyo3(signature = (source, set = Vec::new()))]
    fn new(py: Python<'_>, source: String, set: Vec<String>) -> PyResult<Script> {
        let program = py
            .detach(|| {
                on_work_stack(|| {
                    let is_path =
                        std::path::Path::new(&source).is_file() || !source.contains(['\n', '(', '=']);
                    if is_path {
                        nerfjit::script::load_with(&source, &set)
                    } else {
                        nerfjit_dsl::compile_with("<text>", &source, &set).map_err(Failure::Script)
                    }
                })
            })
            .map_err(to_py)?;
        let params = program.param_values.clone();
        Ok(Script::of(program, params))
    }

    /// The script's own functions' signatures, e.g. `["fn sdf(p: vec3) -> f32"]`.
    #[getter]
    fn functions(&self) -> Vec<String> {
        let program = self.program.lock().expect("the program");
        program.functions().iter().map(ToString::to_string).collect()
    }

    /// The params by name, as numpy arrays (copies; set them with `set_param`).
    #[getter]
    fn params<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let values = self.params.lock().expect("the params");
        param_dict(py, &self.program.lock().expect("the program"), &values)
    }

    /// Sets param `name` to `value` (any array of its shape or its number of values).
    fn set_param(&self, name: &str, value: PyArrayLikeDyn<f32, AllowTypeChange>) -> PyResult<()> {
        let program = self.program.lock().expect("the program");
        let Some(p) = program.params.iter().find(|p| p.name == name) else {
            let names: Vec<&str> = program.params.iter().map(|p| p.name.as_str()).collect();
            return Err(PyKeyError::new_err(format!(
                "no param '{name}': the script's params are {}",
                names.join(", ")
            )));
        };
        let view = value.as_array();
        if view.len() != p.ty.scalars() {
            return Err(PyValueError::new_err(format!(
                "param '{name}' is {} ({} values), not an array of shape {:?}",
                p.ty,
                p.ty.scalars(),
                view.shape()
            )));
        }
        if let Some(bad) = view.iter().find(|x| !x.is_finite()) {
            return Err(PyValueError::new_err(format!(
                "param '{name}' would hold {bad}: values must be finite"
            )));
        }
        let mut values = self.params.lock().expect("the params");
        for (slot, x) in Arc::make_mut(&mut values)[p.offset..].iter_mut().zip(view.iter()) {
            *slot = *x;
        }
        Ok(())
    }

    /// Function `name` at `points`, by its JIT kernel: (N,) for a function returning `f32`, else (N, k).
    fn eval<'py>(
        &self,
        py: Python<'py>,
        name: &str,
        points: PyArrayLikeDyn<'py, f32, AllowTypeChange>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let values = |c: &Compiled| std::iter::once(0..c.outputs).collect();
        let Evaluated {
            compiled, n, results, ..
        } = self.evaluate(py, name, Kind::Value, &points, None, values)?;
        values_array(py, &compiled, n, results.into_iter().next().unwrap_or_default())
    }

    /// The gradient of function `name` with respect to its inputs at `points`: (N, k) for a function returning
    /// `f32`, else the Jacobian (N, outputs, k).
    fn grad<'py>(
        &self,
        py: Python<'py>,
        name: &str,
        points: PyArrayLikeDyn<'py, f32, AllowTypeChange>,
    ) -> PyResult<Bound<'py, PyAny>> {
        // The kernel's outputs: the m values, then output o's gradient in input j at m + o·k + j.
        let jacobian = |c: &Compiled| std::iter::once(c.outputs..c.outputs * (1 + c.inputs)).collect();
        let Evaluated {
            compiled, n, results, ..
        } = self.evaluate(py, name, Kind::Gradient, &points, None, jacobian)?;
        let (m, k) = (compiled.outputs, compiled.inputs);
        let columns = results.into_iter().next().unwrap_or_default();
        Ok(match compiled.scalar {
            true => columns_array(n, k, columns).into_pyarray(py).into_any(),
            // Column o·k + j is ∂outₒ/∂xⱼ: the (n, m, k) array of strides (1, k·n, n), in place.
            false => Array3::from_shape_vec((n, m, k).strides((1, k * n, n)), columns)
                .expect("m·k columns of n values")
                .into_pyarray(py)
                .into_any(),
        })
    }

    /// The marching-cubes mesh of the level `level` of function `function` (`fn(p: vec3) -> f32`) on
    /// `resolution`³ cells of `bounds` (r for [−r, r]³, or `((x0, y0, z0), (x1, y1, z1))`): `(vertices, faces)`,
    /// float32 (V, 3) and uint32 (F, 3), faces counter-clockwise seen from outside.
    #[pyo3(signature = (function = "sdf", resolution = 128, bounds = Bounds::Radius(1.0), level = 0.0))]
    fn mesh<'py>(
        &self,
        py: Python<'py>,
        function: &str,
        resolution: usize,
        bounds: Bounds,
        level: f32,
    ) -> PyResult<(Bound<'py, PyAny>, Bound<'py, PyAny>)> {
        let program = self.program.lock().expect("the program");
        let params = self.params.lock().expect("the params").clone();
        let corners = match bounds {
            Bounds::Radius(r) => ([-r; 3], [r; 3]),
            Bounds::Corners(lo, hi) => (lo, hi),
        };
        let cache = nerfjit_jit::KernelCache::new();
        let grid = (corners, resolution, level);
        let program = &*program;
        let mesh = py
            .detach(|| {
                on_work_stack(|| nerfjit::blocks::mesh::level_set(program, &params, function, grid, &cache))
            })
            .map_err(to_py)?;
        let vertices = rows_of(&mesh.vertices).into_pyarray(py).into_any();
        let faces = rows_of(&mesh.triangles).into_pyarray(py).into_any();
        Ok((vertices, faces))
    }

    /// The vector-Jacobian product of function `name` at `points` with `cotangent` (the shape of its values):
    /// `(values, d_points, d_params)`, d_points of the shape of the points and d_params a dict of arrays
    /// of the params' shapes, Σᵢ cotangentᵢ · ∂valueᵢ/∂θ.
    fn vjp<'py>(
        &self,
        py: Python<'py>,
        name: &str,
        points: PyArrayLikeDyn<'py, f32, AllowTypeChange>,
        cotangent: PyArrayLikeDyn<'py, f32, AllowTypeChange>,
    ) -> PyResult<(Bound<'py, PyAny>, Bound<'py, PyAny>, Bound<'py, PyDict>)> {
        // The kernel's outputs: the m values, then the k inputs' cotangents.
        let both = |c: &Compiled| vec![0..c.outputs, c.outputs..c.outputs + c.inputs];
        let Evaluated {
            compiled,
            n,
            results,
            reductions,
        } = self.evaluate(py, name, Kind::Vjp, &points, Some(&cotangent), both)?;
        let [values, d_points]: [Vec<f32>; 2] = results.try_into().expect("two results");
        let values = values_array(py, &compiled, n, values)?;
        let d_points = match points.ndim() {
            1 => d_points.into_pyarray(py).into_any(),
            _ => columns_array(n, compiled.inputs, d_points)
                .into_pyarray(py)
                .into_any(),
        };
        let d_params = param_dict(py, &self.program.lock().expect("the program"), &reductions)?;
        Ok((values, d_points, d_params))
    }
}

/// A trained field: a checkpoint (or a script with its initial params) whose volume renders into numpy
/// images as `nerfjit render` renders it, and whose functions and params are its `script`'s.
#[pyclass(module = "nerfjit", name = "Field")]
struct Field {
    /// The checkpoint or script, and how to render it.
    source: String,
    near: Option<f32>,
    far: Option<f32>,
    samples: Option<usize>,
    background: Option<[f32; 3]>,
    exact: bool,
    /// Its volume, compiled at the first render (a field without one, such as a neural SDF, has only its
    /// script).
    views: Mutex<Option<Arc<FieldViews>>>,
    script: Py<Script>,
}

impl Field {
    /// The volume renderer, compiled on first use.
    fn views(&self, py: Python<'_>) -> PyResult<Arc<FieldViews>> {
        let mut views = self.views.lock().expect("the field's renderer");
        if let Some(v) = views.as_ref() {
            return Ok(v.clone());
        }
        let args = ViewArgs {
            source: &self.source,
            size: None,
            near: self.near,
            far: self.far,
            samples: self.samples,
            background: self.background,
            importance: None,
            exact: self.exact,
        };
        let opened = Arc::new(
            py.detach(|| on_work_stack(|| FieldViews::open(&args)))
                .map_err(to_py)?,
        );
        *views = Some(opened.clone());
        Ok(opened)
    }
}

#[pymethods]
impl Field {
    /// The field's script, with the trained params: its functions on numpy arrays, its meshes, its params.
    #[getter]
    fn script(&self, py: Python<'_>) -> Py<Script> {
        self.script.clone_ref(py)
    }

    /// The trained params by name, as numpy arrays (copies).
    #[getter]
    fn params<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        self.script.borrow(py).params(py)
    }

    /// The near and far depths, samples per ray and background its volume renders with.
    #[getter]
    fn rendering(&self, py: Python<'_>) -> PyResult<(f32, f32, usize, [f32; 3])> {
        let r = self.views(py)?.rendering;
        Ok((r.near, r.far, r.samples, r.background))
    }

    /// The view of a camera: `c2w` its 4×4 (or 3×4) camera-to-world matrix in the OpenGL / Blender
    /// convention of `transforms.json` (looking down −z, +y up), `focal` its focal length in pixels (or
    /// `(fx, fy)`), `size` the image's side (or `(width, height)`), `principal` the principal point in
    /// pixels (the image's center by default). Returns `(image, depth, opacity)`: (H, W, 3) colour composited
    /// on the background, (H, W) expected depth Σ wᵢtᵢ and (H, W) opacity Σ wᵢ, float32.
    #[pyo3(signature = (c2w, focal, size, principal = None))]
    fn render<'py>(
        &self,
        py: Python<'py>,
        c2w: PyArrayLikeDyn<'py, f32, AllowTypeChange>,
        focal: Pair,
        size: Size,
        principal: Option<(f32, f32)>,
    ) -> PyResult<(Bound<'py, PyAny>, Bound<'py, PyAny>, Bound<'py, PyAny>)> {
        let matrix = c2w.as_array();
        if !matches!(matrix.shape(), [3, 4] | [4, 4]) {
            return Err(PyValueError::new_err(format!(
                "c2w is a 4×4 or 3×4 camera-to-world matrix, not an array of shape {:?}",
                matrix.shape()
            )));
        }
        let at = |r: usize, c: usize| {
            if r < 3 {
                matrix[[r, c]]
            } else {
                [0.0, 0.0, 0.0, 1.0][c]
            }
        };
        let c2w = glam::Mat4::from_cols_array_2d(&std::array::from_fn(|c| std::array::from_fn(|r| at(r, c))));
        let (width, height) = match size {
            Size::Side(side) => (side, side),
            Size::Sides(w, h) => (w, h),
        };
        if !(1..=16384).contains(&width) || !(1..=16384).contains(&height) {
            return Err(PyValueError::new_err(format!(
                "an image of {width}×{height}: each side is 1 to 16384"
            )));
        }
        let (fx, fy) = match focal {
            Pair::One(f) => (f, f),
            Pair::Two(fx, fy) => (fx, fy),
        };
        let (cx, cy) = principal.unwrap_or((0.5 * width as f32, 0.5 * height as f32));
        let intrinsics = nerfjit_runtime::PixelIntrinsics { fx, fy, cx, cy };
        let camera = nerfjit_runtime::Camera::from_pixels(c2w, intrinsics, width, height)
            .map_err(|e| PyValueError::new_err(e.to_string()))?;
        let views = self.views(py)?;
        let frame = py
            .detach(|| views.render(&camera, width, height))
            .map_err(to_py)?;
        let (h, w) = (height as usize, width as usize);
        let image = numpy::ndarray::Array3::from_shape_fn((h, w, 3), |(r, c, k)| frame.rgb[r * w + c][k]);
        let depth = Array2::from_shape_vec((h, w), frame.depth).expect("a depth per pixel");
        let opacity = Array2::from_shape_vec((h, w), frame.opacity).expect("an opacity per pixel");
        Ok((
            image.into_pyarray(py).into_any(),
            depth.into_pyarray(py).into_any(),
            opacity.into_pyarray(py).into_any(),
        ))
    }
}

/// A number, or two.
#[derive(FromPyObject)]
enum Pair {
    One(f32),
    Two(f32, f32),
}

/// An image's side, or its width and height.
#[derive(FromPyObject)]
enum Size {
    Side(u32),
    Sides(u32, u32),
}

/// Opens a trained field: a checkpoint written by `train` (`.safetensors` or `.json`), or a script with its
/// initial params. `near`, `far`, `samples` and `background` (`"black"` or `"white"`) override what its
/// train block renders with; `exact` evaluates every sample (no occupancy grid or early termination).
#[pyfunction]
#[pyo3(signature = (source, *, near = None, far = None, samples = None, background = None, exact = false))]
fn load(
    py: Python<'_>,
    source: String,
    near: Option<f32>,
    far: Option<f32>,
    samples: Option<usize>,
    background: Option<String>,
    exact: bool,
) -> PyResult<Field> {
    let background = match background.as_deref() {
        None => None,
        Some("black") => Some([0.0; 3]),
        Some("white") => Some([1.0; 3]),
        Some(other) => {
            return Err(PyValueError::new_err(format!(
                "background '{other}': black or white"
            )))
        }
    };
    if samples.is_some_and(|n| !(1..=4096).contains(&n)) {
        return Err(PyValueError::new_err("samples is 1 to 4096 per ray"));
    }
    let (program, params) = py
        .detach(|| on_work_stack(|| nerfjit::commands::render_views::load(&source)))
        .map_err(to_py)?;
    let script = Py::new(py, Script::of(program, params))?;
    Ok(Field {
        source,
        near,
        far,
        samples,
        background,
        exact,
        views: Mutex::new(None),
        script,
    })
}

/// The views of a data set: a camera file or data folder read as `nerfjit eval-views --cameras` reads one
/// (its layout, or `format`; every frame, at about `width` pixels across, composited on `background`), or a
/// reader written as in a script (`llff("fern", downscale: 8)`). A dict of numpy arrays: `images` (N, H, W,
/// 3), `c2w` (N, 4, 4) in the OpenGL / Blender convention, `intrinsics` (N, 4) as fx, fy, cx, cy in pixels,
/// `masks` (N, H, W) where the data has object masks (else None), and `read_as`, how it was read.
#[pyfunction]
#[pyo3(signature = (path, *, format = None, width = None, background = None))]
fn load_views<'py>(
    py: Python<'py>,
    path: PathBuf,
    format: Option<String>,
    width: Option<u32>,
    background: Option<String>,
) -> PyResult<Bound<'py, PyDict>> {
    let format = match format.as_deref() {
        None => None,
        Some(name) => Some(nerfjit_runtime::Layout::parse(name).ok_or_else(|| {
            PyValueError::new_err(format!(
                "format '{name}': dtu, llff, nerfstudio, colmap or blender"
            ))
        })?),
    };
    let background = match background.as_deref() {
        None | Some("black") => [0.0; 3],
        Some("white") => [1.0; 3],
        Some(other) => {
            return Err(PyValueError::new_err(format!(
                "background '{other}': black or white"
            )))
        }
    };
    if width.is_some_and(|w| !(1..=16384).contains(&w)) {
        return Err(PyValueError::new_err("width is 1 to 16384 pixels"));
    }
    let request = ScoredViews {
        cameras: &path,
        format,
        width,
        background,
        trained: None,
    };
    let read = py
        .detach(|| on_work_stack(|| scored_views(&request)))
        .map_err(to_py)?;
    let views = read.views;
    let (n, w, h) = (views.len(), views.width as usize, views.height as usize);
    let images = numpy::ndarray::Array4::from_shape_fn((n, h, w, 3), |(i, r, c, k)| {
        views.images[i].pixels[r * w + c][k]
    });
    let c2w = Array3::from_shape_fn((n, 4, 4), |(i, r, c)| views.cameras[i].c2w().col(c)[r]);
    let intrinsics = Array2::from_shape_fn((n, 4), |(i, k)| {
        let p = views.cameras[i].pixel_intrinsics(views.width, views.height);
        [p.fx, p.fy, p.cx, p.cy][k]
    });
    let dict = PyDict::new(py);
    dict.set_item("images", images.into_pyarray(py))?;
    dict.set_item("c2w", c2w.into_pyarray(py))?;
    dict.set_item("intrinsics", intrinsics.into_pyarray(py))?;
    match &views.masks {
        Some(masks) => {
            let masks = Array3::from_shape_fn((n, h, w), |(i, r, c)| masks[i][r * w + c]);
            dict.set_item("masks", masks.into_pyarray(py))?
        }
        None => dict.set_item("masks", py.None())?,
    }
    dict.set_item("read_as", read.how)?;
    Ok(dict)
}

/// Runs the blocks of the script at `script` (a path, or an example's name) as `nerfjit run` does, with
/// `set` overrides, writing into `out` (default: the working folder), resuming its checkpoint when
/// `resume`. Ctrl-C stops training at the end of its step with its checkpoint written, then raises
/// `KeyboardInterrupt`.
#[pyfunction]
#[pyo3(signature = (script, *, set = Vec::new(), out = None, resume = false))]
fn run(py: Python<'_>, script: String, set: Vec<String>, out: Option<PathBuf>, resume: bool) -> PyResult<()> {
    let (done, finished) = mpsc::channel();
    let worker = std::thread::Builder::new()
        .stack_size(nerfjit::WORK_STACK_BYTES)
        .spawn(move || {
            let result = nerfjit::commands::run::run(&script, &set, out.as_deref(), resume, None);
            let _ = done.send(());
            result
        })
        .map_err(|e| NerfjitError::new_err(format!("cannot start the run: {e}")))?;
    let mut interrupted = None;
    let mut finished = finished;
    loop {
        let (receiver, ended) = py.detach(move || {
            let ended = finished.recv_timeout(Duration::from_millis(100)).is_ok();
            (finished, ended)
        });
        finished = receiver;
        if ended {
            break;
        }
        if let Err(signal) = py.check_signals() {
            interrupted.get_or_insert(signal);
        }
        if interrupted.is_some() {
            nerfjit::interrupt::request_stop();
        }
    }
    let result = worker
        .join()
        .unwrap_or_else(|panic| std::panic::resume_unwind(panic));
    match (interrupted, result) {
        (Some(signal), Err(Failure::Interrupted(message))) => {
            nerfjit::note(&message);
            Err(signal)
        }
        (Some(signal), _) => Err(signal),
        (None, result) => result.map_err(to_py),
    }
}

/// The extension module: `Script`, `run` and the exceptions.
#[pymodule]
fn _nerfjit(module: &Bound<'_, PyModule>) -> PyResult<()> {
    module.add_class::<Script>()?;
    module.add_class::<Field>()?;
    module.add_function(wrap_pyfunction!(run, module)?)?;
    module.add_function(wrap_pyfunction!(load, module)?)?;
    module.add_function(wrap_pyfunction!(load_views, module)?)?;
    module.add("ScriptError", module.py().get_type::<ScriptError>())?;
    module.add("NerfjitError", module.py().get_type::<NerfjitError>())?;
    Ok(())
}
