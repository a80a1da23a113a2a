//! `nerfjit.Script`: a compiled script whose functions run on numpy arrays (values, gradients, vector-Jacobian
//! products, meshes) and whose params are numpy arrays.

use std::borrow::Cow;
use std::collections::HashMap;
use std::ops::Range;
use std::sync::{Arc, Mutex};

use nerfjit::failure::Failure;
use nerfjit_dsl::{kernel_graphs, Program, Type};
use nerfjit_jit::{Kernel, Options};
use numpy::ndarray::{Array2, Array3, ShapeBuilder};
use numpy::{AllowTypeChange, IntoPyArray, PyArrayLikeDyn, PyArrayMethods, PyUntypedArrayMethods};
use pyo3::exceptions::{PyKeyError, PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::kernels::{Compiled, Inputs, Kind};
use crate::{on_work_stack, to_py};

/// The box a mesh is extracted in: `r` for [−r, r]³, or its low and high corners.
#[derive(FromPyObject)]
pub(crate) enum Bounds {
    Radius(f32),
    Corners([f32; 3], [f32; 3]),
}

/// `array` (any array-like of real numbers) as float32, refusing complex numbers rather than dropping their
/// imaginary parts; `what` names it in the error.
pub(crate) fn real<'py>(
    array: &Bound<'py, PyAny>,
    what: &str,
) -> PyResult<PyArrayLikeDyn<'py, f32, AllowTypeChange>> {
    if let Ok(dtype) = array.getattr("dtype") {
        if dtype.getattr("kind")?.extract::<String>()? == "c" {
            return Err(PyTypeError::new_err(format!(
                "{what} must be real numbers, not complex"
            )));
        }
    }
    array.extract()
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
pub(crate) fn param_dict<'py>(
    py: Python<'py>,
    program: &Program,
    flat: &[f32],
) -> PyResult<Bound<'py, PyDict>> {
    let dict = PyDict::new(py);
    for p in &program.params {
        let values = flat[p.offset..p.offset + p.ty.scalars()].to_vec();
        dict.set_item(&p.name, values.into_pyarray(py).reshape(param_shape(&p.ty))?)?;
    }
    Ok(dict)
}

/// A function's values at n points from their column-major array (one column per output): (n,) for an `f32` result, else (n, outputs).
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

/// The column-major (n, width) `columns` in the shape of `points`: (n,) for 1-D points.
fn like_points<'py>(
    py: Python<'py>,
    points: &PyArrayLikeDyn<f32, AllowTypeChange>,
    n: usize,
    width: usize,
    columns: Vec<f32>,
) -> Bound<'py, PyAny> {
    match points.ndim() {
        1 => columns.into_pyarray(py).into_any(),
        _ => columns_array(n, width, columns).into_pyarray(py).into_any(),
    }
}

/// The (n, width) array whose columns lie one after the other in `columns` (numpy's Fortran order: no copy).
fn columns_array(n: usize, width: usize, columns: Vec<f32>) -> Array2<f32> {
    Array2::from_shape_vec((n, width).f(), columns).expect("width columns of n values")
}

/// What a kernel computed at n points: the column-major arrays of the outputs asked for, and its reductions.
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
pub(crate) struct Script {
    program: Mutex<Program>,
    /// The params' values, shared with the kernels running on them (copied only when one is set while a
    /// kernel still holds them).
    params: Mutex<Arc<Vec<f32>>>,
    kernels: Mutex<HashMap<(String, Kind), Arc<Compiled>>>,
}

impl Script {
    /// The script of `program` with `params`.
    pub(crate) fn of(program: Program, params: Vec<f32>) -> Script {
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
                Kind::VjpBackward => kernel_graphs::vjp_backward(&lowered, n_params),
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

    /// Runs the `kind` kernel of function `name` at `points`, with the columns of `extras` after theirs
    /// (cotangents: each an (N, width) array, or (N,) for a width of 1, and its name), the GIL released:
    /// the outputs in `ranges`, each a column-major (N, range) array, and the reductions.
    fn evaluate(
        &self,
        py: Python<'_>,
        name: &str,
        kind: Kind,
        points: &PyArrayLikeDyn<f32, AllowTypeChange>,
        extras: &[(&PyArrayLikeDyn<f32, AllowTypeChange>, usize, &str)],
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
        let mut seeds: Vec<(Cow<[f32]>, usize)> = Vec::with_capacity(extras.len());
        for (array, columns, what) in extras {
            let array = array.as_array();
            if array.len() != n * columns {
                let shape = match columns {
                    1 => format!("({n},)"),
                    _ => format!("({n}, {columns})"),
                };
                return Err(PyValueError::new_err(format!(
                    "{what} has the shape {shape} here, not {:?}",
                    array.shape()
                )));
            }
            let flat = match array.to_slice() {
                Some(flat) => Cow::Borrowed(flat),
                None => Cow::Owned(array.iter().copied().collect()),
            };
            seeds.push((flat, *columns));
        }
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
            let mut first = width;
            for (seeds, m) in &seeds {
                for i in start..end {
                    for o in 0..*m {
                        columns[first + o][i - start] = seeds[i * m + o];
                    }
                }
                first += m;
            }
        };
        // Column-major points (np.asfortranarray, or a (k, N) array's transpose) are read where they are.
        let columns: Option<Vec<&[f32]>> = match view.t().to_slice() {
            Some(flat) if n > 0 && seeds.is_empty() => Some(flat.chunks(n).collect()),
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
    pub(crate) fn params<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let values = self.params.lock().expect("the params");
        param_dict(py, &self.program.lock().expect("the program"), &values)
    }

    /// Sets param `name` to `value` (any array of its shape or its number of values).
    fn set_param(&self, name: &str, value: &Bound<'_, PyAny>) -> PyResult<()> {
        let value = real(value, "a param's value")?;
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
        points: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let values = |c: &Compiled| std::iter::once(0..c.outputs).collect();
        let Evaluated {
            compiled, n, results, ..
        } = self.evaluate(py, name, Kind::Value, &real(points, "points")?, &[], values)?;
        values_array(py, &compiled, n, results.into_iter().next().unwrap_or_default())
    }

    /// The gradient of function `name` with respect to its inputs at `points`: (N, k) for a function returning
    /// `f32`, else the Jacobian (N, outputs, k).
    fn grad<'py>(
        &self,
        py: Python<'py>,
        name: &str,
        points: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyAny>> {
        // The kernel's outputs: the m values, then output o's gradient in input j at m + o·k + j.
        let jacobian = |c: &Compiled| std::iter::once(c.outputs..c.outputs * (1 + c.inputs)).collect();
        let Evaluated {
            compiled, n, results, ..
        } = self.evaluate(py, name, Kind::Gradient, &real(points, "points")?, &[], jacobian)?;
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
        points: &Bound<'py, PyAny>,
        cotangent: &Bound<'py, PyAny>,
    ) -> PyResult<(Bound<'py, PyAny>, Bound<'py, PyAny>, Bound<'py, PyDict>)> {
        let outputs = self.kernel(name, Kind::Vjp)?.outputs;
        let (points, cotangent) = (real(points, "points")?, real(cotangent, "the cotangent")?);
        // The kernel's outputs: the m values, then the k inputs' cotangents.
        let both = |c: &Compiled| vec![0..c.outputs, c.outputs..c.outputs + c.inputs];
        let extras = [(&cotangent, outputs, "the cotangent (of the values)")];
        let Evaluated {
            compiled,
            n,
            results,
            reductions,
        } = self.evaluate(py, name, Kind::Vjp, &points, &extras, both)?;
        let [values, d_points]: [Vec<f32>; 2] = results.try_into().expect("two results");
        let values = values_array(py, &compiled, n, values)?;
        let d_points = like_points(py, &points, n, compiled.inputs, d_points);
        let d_params = param_dict(py, &self.program.lock().expect("the program"), &reductions)?;
        Ok((values, d_points, d_params))
    }

    /// The backward pass of `vjp`'s d_points, g = Σᵢ cotangentᵢ ∂valueᵢ/∂points, with `d_points_cotangent` w
    /// (the shape of the points), as a host's double backward asks for it: `(d_points, d_cotangent,
    /// d_params)`, the derivatives of w·g in the points, the cotangent and the params.
    fn vjp_backward<'py>(
        &self,
        py: Python<'py>,
        name: &str,
        points: &Bound<'py, PyAny>,
        cotangent: &Bound<'py, PyAny>,
        d_points_cotangent: &Bound<'py, PyAny>,
    ) -> PyResult<(Bound<'py, PyAny>, Bound<'py, PyAny>, Bound<'py, PyDict>)> {
        let compiled = self.kernel(name, Kind::VjpBackward)?;
        let (inputs, outputs) = (compiled.inputs, compiled.outputs);
        let points = real(points, "points")?;
        let cotangent = real(cotangent, "the cotangent")?;
        let w = real(d_points_cotangent, "the cotangent of d_points")?;
        let extras = [
            (&cotangent, outputs, "the cotangent (of the values)"),
            (&w, inputs, "the cotangent of d_points (of the points)"),
        ];
        // The kernel's outputs: ∂(w·g)/∂points (k), then ∂(w·g)/∂cotangent (m).
        let both = |c: &Compiled| vec![0..c.inputs, c.inputs..c.inputs + c.outputs];
        let Evaluated {
            compiled,
            n,
            results,
            reductions,
        } = self.evaluate(py, name, Kind::VjpBackward, &points, &extras, both)?;
        let [d_points, d_cotangent]: [Vec<f32>; 2] = results.try_into().expect("two results");
        let d_points = like_points(py, &points, n, compiled.inputs, d_points);
        let d_cotangent = values_array(py, &compiled, n, d_cotangent)?;
        let d_params = param_dict(py, &self.program.lock().expect("the program"), &reductions)?;
        Ok((d_points, d_cotangent, d_params))
    }
}
