//! `nerfjit.bake` and `nerfjit.Bake`: a trained field baked into Gaussian splats as `nerfjit bake` bakes it,
//! a `.bake` file's splats as numpy arrays, and its views drawn by the CPU splat renderer.

use std::path::PathBuf;

use nerfjit::bake_file;
use nerfjit::commands::bake::{self as baking, Tuning};
use nerfjit::commands::point_cloud::PointsArgs;
use nerfjit::commands::render_views::{CameraSource, ViewArgs};
use nerfjit_runtime::splats::SplatScene;
use numpy::ndarray::{Array1, Array2, Array3};
use numpy::IntoPyArray;
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::field::{frame_arrays, Pair, Size, View};
use crate::{on_work_stack, to_py};

/// A baked scene: the splats of a `.bake` file, drawn by nerfjit's CPU splat renderer.
#[pyclass(module = "nerfjit", name = "Bake")]
pub(crate) struct Bake {
    bake: bake_file::Bake,
}

#[pymethods]
impl Bake {
    /// Opens a `.bake` file (written by `nerfjit bake`, a script's `bake` block or `nerfjit.bake`).
    #[new]
    fn new(py: Python<'_>, path: PathBuf) -> PyResult<Bake> {
        let bake = py.detach(|| bake_file::read(&path)).map_err(to_py)?;
        Ok(Bake { bake })
    }

    /// How many splats it holds.
    fn __len__(&self) -> usize {
        self.bake.splats.len()
    }

    /// The color its views are drawn on.
    #[getter]
    fn background(&self) -> [f32; 3] {
        self.bake.background
    }

    /// The checkpoint (or script) it was baked from.
    #[getter]
    fn baked_from(&self) -> PathBuf {
        self.bake.source.clone()
    }

    /// The splats as numpy arrays (copies), one row a splat: `positions` (N, 3), `colors` (N, 3) in
    /// [0, 1], `opacities` (N,), `scales` (N, 3) (standard deviations along the rotated axes),
    /// `rotations` (N, 4) (unit quaternions w, x, y, z) and, where the colors change with the view,
    /// `sh` (N, 3, 3): the degree-one coefficients h₀, h₁, h₂ of each, RGB.
    #[getter]
    fn splats<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let s = &self.bake.splats;
        let n = s.len();
        let rows =
            |values: &[[f32; 3]]| Array2::from_shape_fn((n, 3), |(i, k)| values[i][k]).into_pyarray(py);
        let dict = PyDict::new(py);
        dict.set_item("positions", rows(&s.positions))?;
        dict.set_item("colors", rows(&s.colors))?;
        dict.set_item("opacities", Array1::from(s.opacities.clone()).into_pyarray(py))?;
        dict.set_item("scales", rows(&s.scales))?;
        let rotations = Array2::from_shape_fn((n, 4), |(i, k)| s.rotations[i][k]);
        dict.set_item("rotations", rotations.into_pyarray(py))?;
        if !s.sh.is_empty() {
            let sh = Array3::from_shape_fn((n, 3, 3), |(i, k, c)| s.sh[i][k][c]);
            dict.set_item("sh", sh.into_pyarray(py))?;
        }
        Ok(dict)
    }

    /// The view of a camera, as `Field.render` takes it (`c2w` 4×4 or 3×4 in the OpenGL / Blender
    /// convention, `focal` in pixels or `(fx, fy)`, `size` a side or `(width, height)`, `principal` in
    /// pixels): `(image, depth, opacity)`, the (H, W, 3) colour over the background, the (H, W) expected
    /// distance Σ wᵢdᵢ and the (H, W) opacity, float32, as `nerfjit render` draws the bake.
    #[pyo3(signature = (c2w, focal, size, principal = None))]
    fn render<'py>(
        &self,
        py: Python<'py>,
        c2w: &Bound<'py, PyAny>,
        focal: Pair,
        size: Size,
        principal: Option<(f32, f32)>,
    ) -> PyResult<(Bound<'py, PyAny>, Bound<'py, PyAny>, Bound<'py, PyAny>)> {
        let view = View::of(c2w, focal, size, principal)?;
        let frame = py
            .detach(|| -> nerfjit::failure::Result<_> {
                let scene = SplatScene::new(&self.bake.splats, nerfjit_field::splat_shader()?);
                let (w, h) = (view.width, view.height);
                Ok(scene.render(&view.camera, w, h, self.bake.background)?.0)
            })
            .map_err(to_py)?;
        frame_arrays(py, frame)
    }
}

/// Bakes a trained field (a checkpoint, or a script with its initial params) into Gaussian splats written
/// to `out` (a `.bake` file) as `nerfjit bake` does, and opens them: its training views rendered at `size`
/// (by default half their larger side), pixels below `min_opacity` left out, then `tune` seconds of
/// fine-tuning against those views (`sh_degree` 1: colors that change with the view; splats that weighed
/// under `min_weight` pixels in every view dropped halfway). Returns the bake and the report `nerfjit
/// bake` prints: `(bake, report)`.
#[pyfunction]
#[pyo3(signature = (source, out, *, tune = 0.0, size = None, sh_degree = 1, min_weight = 1.0, min_opacity = 0.5))]
#[allow(clippy::too_many_arguments)]
pub(crate) fn bake(
    py: Python<'_>,
    source: String,
    out: PathBuf,
    tune: f64,
    size: Option<u32>,
    sh_degree: u8,
    min_weight: f32,
    min_opacity: f32,
) -> PyResult<(Bake, String)> {
    if !(tune.is_finite() && tune >= 0.0) {
        return Err(PyValueError::new_err("tune is a number of seconds, 0 or more"));
    }
    if sh_degree > 1 {
        return Err(PyValueError::new_err("sh_degree is 0 or 1"));
    }
    if !(min_weight.is_finite() && min_weight >= 0.0) {
        return Err(PyValueError::new_err(
            "min_weight is a number of pixels, 0 or more",
        ));
    }
    if !(min_opacity > 0.0 && min_opacity <= 1.0) {
        return Err(PyValueError::new_err("min_opacity is in (0, 1]"));
    }
    if size.is_some_and(|s| !(1..=4096).contains(&s)) {
        return Err(PyValueError::new_err("size is 1 to 4096 pixels"));
    }
    let args = PointsArgs {
        view: ViewArgs::as_trained(&source, size),
        cameras: CameraSource::Default,
        min_opacity,
        out: &out,
    };
    let tuning = Tuning {
        seconds: tune,
        sh_degree,
        min_weight,
    };
    let report = py
        .detach(|| on_work_stack(|| baking::run(&args, tuning)))
        .map_err(to_py)?;
    Ok((Bake::new(py, out.clone())?, report))
}
