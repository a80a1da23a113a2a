//! The spaces an occupancy grid's box can be in: the scene's own, mip-NeRF 360's contraction of all of
//! space, or NeRF's normalized device coordinates of a forward-facing capture; and the fields a grid in a
//! warped space is built from.

use crate::error::{Error, Result};
use crate::field::BatchFn;
use crate::volume::composite::Mode;

/// The space an occupancy grid's box is in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum GridSpace {
    /// The scene's own coordinates: nothing outside the box is occupied.
    #[default]
    Scene,
    /// The coordinates of [`contract`]: a box of [−2, 2]³ covers all of space.
    Contracted,
    /// The normalized device coordinates of a forward-facing capture ([`ndc`]): a box of [−1, 1]³ covers
    /// its cameras' frustum from depth 4 (the nearest content, once `llff(...)` has normalized it) to
    /// infinity.
    Ndc,
}

impl GridSpace {
    /// The space named `name` (`scene` or `contracted`).
    pub fn named(name: &str) -> Option<GridSpace> {
        match name {
            "scene" => Some(GridSpace::Scene),
            "contracted" => Some(GridSpace::Contracted),
            "ndc" => Some(GridSpace::Ndc),
            _ => None,
        }
    }

    /// Calls `f` with `field` as a grid in this space reads it: at the scene points of its cells
    /// ([`Unwarped`]) for a grid in another space than the scene's.
    pub fn with_field<R>(self, field: &dyn BatchFn, f: impl FnOnce(&dyn BatchFn) -> R) -> R {
        match self {
            GridSpace::Scene => f(field),
            space => f(&Unwarped { space, field }),
        }
    }

    /// [`GridSpace::with_field`], and with `thickness` the field's first output, a density, times the
    /// length a ray crosses in a cell of the grid over `bounds` with `resolution`³ cells around each
    /// point ([`CellThickness`]): the cell's optical thickness, for a threshold that means the same in
    /// every space and at every scale. An error for `thickness` with a field of opacities (`mode`), whose
    /// values are a sample's already.
    pub fn with_grid_field<R>(
        self,
        field: &dyn BatchFn,
        (bounds, resolution): (([f32; 3], [f32; 3]), usize),
        (mode, thickness): (Mode, bool),
        f: impl FnOnce(&dyn BatchFn) -> Result<R>,
    ) -> Result<R> {
        if thickness {
            check_thickness(mode)?;
        }
        self.with_field(field, |field| {
            if thickness {
                let (lo, hi) = bounds;
                let volume: f32 = (0..3).map(|a| (hi[a] - lo[a]) / resolution as f32).product();
                f(&CellThickness {
                    space: self,
                    cell: volume.abs().cbrt(),
                    field,
                })
            } else {
                f(field)
            }
        })
    }

    /// The length in the scene that a unit of this space's coordinates spans along the rays at `c` (a
    /// point in them): 1 in the scene's space; in NDC, the depth a unit of its third coordinate spans
    /// there (d²/8 at depth d, taken from 1 to 1000 as [`unndc`] takes it), the rays of a forward-facing
    /// capture running along the depth; in the contraction, 1 inside the unit ball and beyond it the
    /// radial length a unit of contracted radius spans (r², r = 1/(2 − ‖c‖) up to [`uncontract`]'s
    /// clamp), the rays of a capture taken from inside running outwards.
    #[inline(always)]
    pub fn stretch(self, c: [f32; 3]) -> f32 {
        match self {
            GridSpace::Scene => 1.0,
            GridSpace::Ndc => {
                let d = unndc(c)[1] + 4.0;
                d * d / 8.0
            }
            GridSpace::Contracted => {
                let norm = (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt();
                if norm > 1.0 {
                    let r = 1.0 / (2.0 - norm.min(2.0 - 1e-3));
                    r * r
                } else {
                    1.0
                }
            }
        }
    }

    /// `p` in the coordinates of a grid in this space.
    #[inline(always)]
    pub fn point(self, p: [f32; 3]) -> [f32; 3] {
        match self {
            GridSpace::Scene => p,
            GridSpace::Contracted => contract(p),
            GridSpace::Ndc => ndc(p),
        }
    }

    /// The scene point of `c` in this space's coordinates (the inverse of [`GridSpace::point`], up to
    /// its clamps: [`uncontract`], [`unndc`]).
    pub fn scene_point(self, c: [f32; 3]) -> [f32; 3] {
        match self {
            GridSpace::Scene => c,
            GridSpace::Contracted => uncontract(c),
            GridSpace::Ndc => unndc(c),
        }
    }

    /// The space's name, as [`GridSpace::named`] reads it.
    pub fn name(self) -> &'static str {
        match self {
            GridSpace::Scene => "scene",
            GridSpace::Contracted => "contracted",
            GridSpace::Ndc => "ndc",
        }
    }
}

/// NeRF's normalized device coordinates of a forward-facing capture as `llff(...)` normalizes it (the
/// cameras looking along +y from about (0, −4, 0), z up), as `examples/instant_llff.sdf` warps space for
/// its hash grid: with d = max(y + 4, 1) the depth from the mean camera, (x/d, z/d, 8/d − 1). Depths 4 to
/// infinity take the third coordinate from 1 to −1.
#[inline(always)]
pub fn ndc([x, y, z]: [f32; 3]) -> [f32; 3] {
    let d = y + 4.0;
    let d = if d > 1.0 { d } else { 1.0 };
    [x / d, z / d, 8.0 / d - 1.0]
}

/// The inverse of [`ndc`] for depths from 1 to 1000 (points nearer or farther are taken at those depths).
#[inline(always)]
pub fn unndc([u, v, w]: [f32; 3]) -> [f32; 3] {
    // w + 1 at or below 8/1000 (and NaN) stands for the far end.
    let d = if w + 1.0 > 8e-3 {
        (8.0 / (w + 1.0)).clamp(1.0, 1000.0)
    } else {
        1000.0
    };
    [u * d, d - 4.0, v * d]
}

/// mip-NeRF 360's scene contraction, as the scripts' `contract(p)` has it: `p` inside the unit ball,
/// (2 − 1/‖p‖)·p/‖p‖ outside it.
#[inline(always)]
pub fn contract([x, y, z]: [f32; 3]) -> [f32; 3] {
    let r = (x * x + y * y + z * z).sqrt();
    // Without branches (a select), so that loops over points vectorize.
    let s = if r > 1.0 { (2.0 - 1.0 / r) / r } else { 1.0 };
    [x * s, y * s, z * s]
}

/// The inverse of [`contract`] for points of norm below 2 (points at or beyond norm 2, which stand
/// for infinity, are taken at norm 2 − 10⁻³: about 1000 units out).
#[inline(always)]
pub fn uncontract([x, y, z]: [f32; 3]) -> [f32; 3] {
    let r = (x * x + y * y + z * z).sqrt();
    let clamped = r.min(2.0 - 1e-3);
    // |c| = 2 − 1/|p| outside the unit ball, so |p| = 1/(2 − |c|).
    let s = if r > 1.0 { 1.0 / ((2.0 - clamped) * r) } else { 1.0 };
    [x * s, y * s, z * s]
}

/// A function of a position read at the scene point of its input in `space`'s coordinates
/// ([`GridSpace::scene_point`]): what a grid in that space is built from. Further inputs (a view
/// direction) pass unchanged.
pub struct Unwarped<'a> {
    /// The space of the inputs.
    pub space: GridSpace,
    /// The function of scene points.
    pub field: &'a dyn BatchFn,
}

impl BatchFn for Unwarped<'_> {
    fn n_inputs(&self) -> usize {
        self.field.n_inputs()
    }

    fn n_outputs(&self) -> usize {
        self.field.n_outputs()
    }

    fn eval(&self, n: usize, inputs: &[&[f32]], outputs: &mut [&mut [f32]]) {
        let mut points = vec![vec![0.0f32; n]; 3];
        for i in 0..n {
            let p = self.space.scene_point([inputs[0][i], inputs[1][i], inputs[2][i]]);
            for (column, value) in points.iter_mut().zip(p) {
                column[i] = value;
            }
        }
        let mut columns: Vec<&[f32]> = points.iter().map(Vec::as_slice).collect();
        columns.extend_from_slice(&inputs[3..]);
        self.field.eval(n, &columns, outputs);
    }
}

/// A density read per cell of a grid: the first output of `field` (a function of points in `space`'s
/// coordinates, as [`Unwarped`] gives one) times `cell` (the size of the grid's cells in those
/// coordinates) times [`GridSpace::stretch`] at the point: the optical thickness of the cell around the
/// point along the rays, which bounds the opacity a ray gathers crossing it (1 − e^−thickness). The other
/// outputs pass unchanged.
pub struct CellThickness<'a> {
    /// The space of the inputs.
    pub space: GridSpace,
    /// The cells' size in the space's coordinates (the cube root of a cell's volume).
    pub cell: f32,
    /// The function whose first output is a density.
    pub field: &'a dyn BatchFn,
}

impl BatchFn for CellThickness<'_> {
    fn n_inputs(&self) -> usize {
        self.field.n_inputs()
    }

    fn n_outputs(&self) -> usize {
        self.field.n_outputs()
    }

    fn eval(&self, n: usize, inputs: &[&[f32]], outputs: &mut [&mut [f32]]) {
        self.field.eval(n, inputs, outputs);
        for (i, value) in outputs[0][..n].iter_mut().enumerate() {
            *value *= self.cell * self.space.stretch([inputs[0][i], inputs[1][i], inputs[2][i]]);
        }
    }
}

/// Checks that a field whose first output is `mode` can have its cells' optical thickness thresholded
/// ([`GridSpace::with_grid_field`]): a density can, a sample's opacity cannot.
pub fn check_thickness(mode: Mode) -> Result<()> {
    match mode {
        Mode::Density => Ok(()),
        Mode::Opacity => Err(Error::Invalid(
            "an occupancy grid's thickness is for a field of densities; this field gives each sample's \
             opacity: give the grid a threshold instead"
                .into(),
        )),
    }
}
