//! `nerfjit.load` and `nerfjit.Field`: a checkpoint's (or a script's) volume rendered into numpy images as
//! `nerfjit render` renders it.

use std::sync::{Arc, Mutex};

use nerfjit::commands::render_views::{FieldViews, ViewArgs};
use numpy::ndarray::Array2;
use numpy::IntoPyArray;
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::script::Script;
use crate::{on_work_stack, to_py};

/// A trained field: a checkpoint (or a script with its initial params) whose volume renders into numpy
/// images as `nerfjit render` renders it, and whose functions and params are its `script`'s.
#[pyclass(module = "nerfjit", name = "Field")]
pub(crate) struct Field {
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
        c2w: &Bound<'py, PyAny>,
        focal: Pair,
        size: Size,
        principal: Option<(f32, f32)>,
    ) -> PyResult<(Bound<'py, PyAny>, Bound<'py, PyAny>, Bound<'py, PyAny>)> {
        let View {
            camera,
            width,
            height,
        } = View::of(c2w, focal, size, principal)?;
        let views = self.views(py)?;
        let frame = py
            .detach(|| views.render(&camera, width, height))
            .map_err(to_py)?;
        frame_arrays(py, frame)
    }
}

/// A camera as Python gives it, and the size of its image.
pub(crate) struct View {
    pub camera: nerfjit_runtime::Camera,
    pub width: u32,
    pub height: u32,
}

impl View {
    /// The camera of `c2w` (4×4 or 3×4, OpenGL / Blender axes), `focal` (pixels), `size` (a side or the
    /// width and height) and `principal` (pixels; the center by default); refused with what is wrong.
    pub(crate) fn of(
        c2w: &Bound<'_, PyAny>,
        focal: Pair,
        size: Size,
        principal: Option<(f32, f32)>,
    ) -> PyResult<View> {
        let c2w = crate::script::real(c2w, "c2w's entries")?;
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
        Ok(View {
            camera,
            width,
            height,
        })
    }
}

/// A frame as numpy arrays: its (H, W, 3) colours, (H, W) depths and (H, W) opacities.
pub(crate) fn frame_arrays(
    py: Python<'_>,
    frame: nerfjit_runtime::VolumeFrame,
) -> PyResult<(Bound<'_, PyAny>, Bound<'_, PyAny>, Bound<'_, PyAny>)> {
    let (h, w) = (frame.height as usize, frame.width as usize);
    let image = numpy::ndarray::Array3::from_shape_fn((h, w, 3), |(r, c, k)| frame.rgb[r * w + c][k]);
    let depth = Array2::from_shape_vec((h, w), frame.depth).expect("a depth per pixel");
    let opacity = Array2::from_shape_vec((h, w), frame.opacity).expect("an opacity per pixel");
    Ok((
        image.into_pyarray(py).into_any(),
        depth.into_pyarray(py).into_any(),
        opacity.into_pyarray(py).into_any(),
    ))
}

/// A number, or two.
#[derive(FromPyObject)]
pub(crate) enum Pair {
    One(f32),
    Two(f32, f32),
}

/// An image's side, or its width and height.
#[derive(FromPyObject)]
pub(crate) enum Size {
    Side(u32),
    Sides(u32, u32),
}

/// Opens a trained field: a checkpoint written by `train` (`.safetensors` or `.json`), or a script with its
/// initial params. `near`, `far`, `samples` and `background` (`"black"` or `"white"`) override what its
/// train block renders with; `exact` evaluates every sample (no occupancy grid or early termination).
#[pyfunction]
#[pyo3(signature = (source, *, near = None, far = None, samples = None, background = None, exact = false))]
pub(crate) fn load(
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
        .detach(|| on_work_stack(|| nerfjit::checkpoint::load_source(&source)))
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
