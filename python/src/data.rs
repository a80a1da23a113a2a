//! `nerfjit.data.load`: a data set's views as numpy arrays, read as `nerfjit eval-views --cameras` reads them.

use std::path::PathBuf;

use nerfjit::training::data_source::{scored_views, ScoredViews};
use numpy::ndarray::{Array2, Array3, Array4};
use numpy::IntoPyArray;
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::{on_work_stack, to_py};

/// The views of a data set: a camera file or data folder read as `nerfjit eval-views --cameras` reads one
/// (its layout, or `format`; every frame, at about `width` pixels across, composited on `background`), or a
/// reader written as in a script (`llff("fern", downscale: 8)`). A dict of numpy arrays: `images` (N, H, W,
/// 3), `c2w` (N, 4, 4) in the OpenGL / Blender convention, `intrinsics` (N, 4) as fx, fy, cx, cy in pixels,
/// `masks` (N, H, W) where the data has object masks (else None), and `read_as`, how it was read.
#[pyfunction]
#[pyo3(signature = (path, *, format = None, width = None, background = None))]
pub(crate) fn load_views<'py>(
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
    let images = Array4::from_shape_fn((n, h, w, 3), |(i, r, c, k)| views.images[i].pixels[r * w + c][k]);
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
