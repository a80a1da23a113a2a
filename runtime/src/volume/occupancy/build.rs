//! Building an occupancy grid: probing a field on the sub-cell lattice, from its interval bounds, from
//! points or from cells' values; the dilation and the coarse summaries the walk reads.

use rayon::prelude::*;

use super::{bit_of, GridSpace, OccupancyGrid, BLOCK, COARSE_LEVELS, MAX_RESOLUTION, SUBDIVISIONS};
use crate::error::{Error, Result};
use crate::field::BatchFn;
use crate::volume::composite::Mode;

/// Probe points per field call while building.
const BUILD_BATCH: usize = 8192;

/// Layers of cells probed by one parallel task while building.
const LAYERS_PER_TASK: usize = 4;

/// Checks a threshold: finite and ≥ 0 for densities, in [0, 1) for opacities.
pub(crate) fn check_threshold(mode: Mode, threshold: f32) -> Result<()> {
    let threshold_ok = match mode {
        Mode::Density => threshold.is_finite() && threshold >= 0.0,
        Mode::Opacity => (0.0..1.0).contains(&threshold),
    };
    if !threshold_ok {
        return Err(Error::Invalid(format!(
            "occupancy threshold {threshold} must be >= 0 and finite (density) or in [0, 1) (opacity)"
        )));
    }
    Ok(())
}

/// The mean of `values` (in f64).
pub(crate) fn mean(values: &[f32]) -> f32 {
    (values.iter().map(|&v| f64::from(v)).sum::<f64>() / values.len().max(1) as f64) as f32
}

/// Checks an occupancy grid's bounds and resolution and that `field` is a density of a point (and
/// optionally a view direction).
pub(crate) fn check_grid(field: &dyn BatchFn, bounds: ([f32; 3], [f32; 3]), resolution: usize) -> Result<()> {
    check_box(bounds, resolution)?;
    let n_inputs = field.n_inputs();
    if !(n_inputs == 3 || n_inputs == 6) || field.n_outputs() == 0 {
        return Err(Error::Invalid(format!(
            "an occupancy grid needs a field of a point (3 inputs) or a point and a view \
                 direction (6 inputs) with at least 1 output, but it maps {n_inputs} inputs to {} outputs",
            field.n_outputs()
        )));
    }
    Ok(())
}

/// Checks a grid's bounds (finite, lo < hi on every axis) and resolution.
pub(super) fn check_box(bounds: ([f32; 3], [f32; 3]), resolution: usize) -> Result<()> {
    let (lo, hi) = bounds;
    if !(0..3).all(|i| lo[i].is_finite() && hi[i].is_finite() && lo[i] < hi[i]) {
        return Err(Error::Invalid(format!(
            "occupancy grid bounds {lo:?}..{hi:?} must be finite with lo < hi on every axis"
        )));
    }
    if !(1..=MAX_RESOLUTION).contains(&resolution) {
        return Err(Error::Invalid(format!(
            "occupancy grid resolution {resolution} must be in 1..={MAX_RESOLUTION}"
        )));
    }
    Ok(())
}

/// Each cell's peak over its probes (see the module docs): the field's first output on the lattice
/// of [`SUBDIVISIONS`] steps per cell, NaN counted as +∞; cell x + y·res + z·res² at index
/// x + y·res + z·res². Checks the bounds, the resolution and the field's shape.
pub(crate) fn cell_peaks(
    field: &dyn BatchFn,
    bounds: ([f32; 3], [f32; 3]),
    resolution: usize,
) -> Result<Vec<f32>> {
    check_grid(field, bounds, resolution)?;
    let (lo, hi) = bounds;
    let n_inputs = field.n_inputs();

    // 1. Probe the lattice of m³ points, a few layers of cells at a time (sharing their
    //    boundary planes of probes), and 2. take each cell's peak over the probes of its
    //    closed box: a max filter of width SUBDIVISIONS + 1 and stride SUBDIVISIONS along
    //    each axis. NaN probes count as +∞.
    let res = resolution;
    let (s, m) = (SUBDIVISIONS, res * SUBDIVISIONS + 1);
    let step = [0, 1, 2].map(|i| (hi[i] - lo[i]) / (m - 1) as f32);
    let coord = |i: usize, k: usize| {
        if k + 1 == m {
            hi[i]
        } else {
            lo[i] + step[i] * k as f32
        }
    };
    let mut peaks = vec![0.0f32; res * res * res];
    peaks
        .par_chunks_mut(res * res * LAYERS_PER_TASK)
        .enumerate()
        .for_each(|(task, cells)| {
            let (layers, z0) = (cells.len() / (res * res), task * LAYERS_PER_TASK * s);
            let mut probes = vec![0.0f32; (layers * s + 1) * m * m];
            let batch = BUILD_BATCH.min(probes.len());
            let mut inputs = vec![vec![0.0f32; batch]; n_inputs];
            if n_inputs == 6 {
                inputs[5].fill(1.0);
            }
            let mut outputs = vec![vec![0.0f32; batch]; field.n_outputs()];
            for (c, probes) in probes.chunks_mut(batch).enumerate() {
                let n = probes.len();
                for (k, i) in (c * batch..c * batch + n).enumerate() {
                    let (x, y, z) = (i % m, i / m % m, z0 + i / (m * m));
                    (inputs[0][k], inputs[1][k], inputs[2][k]) = (coord(0, x), coord(1, y), coord(2, z));
                }
                let inputs: Vec<&[f32]> = inputs.iter().map(|v| &v[..n]).collect();
                let mut outs: Vec<&mut [f32]> = outputs.iter_mut().map(|v| &mut v[..n]).collect();
                field.eval(n, &inputs, &mut outs);
                for (probe, &v) in probes.iter_mut().zip(&outputs[0]) {
                    *probe = if v.is_nan() { f32::INFINITY } else { v };
                }
            }
            let window = |c: usize| c * s..=c * s + s;
            cells.copy_from_slice(&max_filter(
                &probes,
                [m, m, layers * s + 1],
                window,
                [res, res, layers],
            ));
        });

    Ok(peaks)
}

/// A max (or) filter of the `dims` = [x, y, z] volume `v` (x fastest) along each axis in
/// turn: output cell c along an axis is the or of the input cells `window(c)`; the axes
/// become `out` = [x, y, z] long.
fn max_filter<W: Iterator<Item = usize>>(
    v: &[f32],
    [nx, ny, nz]: [usize; 3],
    window: impl Fn(usize) -> W,
    [ox, oy, oz]: [usize; 3],
) -> Vec<f32> {
    // Along x: rows of nx → ox.
    let mut a = vec![f32::NEG_INFINITY; ox * ny * nz];
    for (src, dst) in v.chunks_exact(nx).zip(a.chunks_exact_mut(ox)) {
        for (c, d) in dst.iter_mut().enumerate() {
            *d = window(c).map(|i| src[i]).fold(f32::NEG_INFINITY, f32::max);
        }
    }
    // Along y: planes of ox·ny → ox·oy.
    let mut b = vec![f32::NEG_INFINITY; ox * oy * nz];
    for (src, dst) in a.chunks_exact(ox * ny).zip(b.chunks_exact_mut(ox * oy)) {
        for (c, row) in dst.chunks_exact_mut(ox).enumerate() {
            for i in window(c) {
                for (d, s) in row.iter_mut().zip(&src[i * ox..(i + 1) * ox]) {
                    *d = d.max(*s);
                }
            }
        }
    }
    // Along z: planes of ox·oy, nz → oz.
    let plane = ox * oy;
    let mut c = vec![f32::NEG_INFINITY; plane * oz];
    for (k, dst) in c.chunks_exact_mut(plane).enumerate() {
        for i in window(k) {
            for (d, s) in dst.iter_mut().zip(&b[i * plane..(i + 1) * plane]) {
                *d = d.max(*s);
            }
        }
    }
    c
}

impl OccupancyGrid {
    /// Probes `field` (3 inputs, or 6 with a view direction; its first output is σ or a as
    /// `mode` says) in `resolution`³ cells over `bounds` = (lo, hi) and marks the cells with a
    /// probe value above `threshold` (σ itself in [`Mode::Density`], a in [`Mode::Opacity`]),
    /// dilated by one cell. See the module docs.
    pub fn build(
        field: &dyn BatchFn,
        bounds: ([f32; 3], [f32; 3]),
        resolution: usize,
        mode: Mode,
        threshold: f32,
    ) -> Result<OccupancyGrid> {
        OccupancyGrid::build_with(field, bounds, resolution, mode, threshold, false)
    }

    /// [`OccupancyGrid::build`] with the threshold lowered to the mean of the cells' peak probe values
    /// where that is lower (instant-ngp's rule for training): a field whose values are all small keeps
    /// its larger half occupied instead of an empty grid, whose samples would never be trained again.
    pub fn build_for_training(
        field: &dyn BatchFn,
        bounds: ([f32; 3], [f32; 3]),
        resolution: usize,
        mode: Mode,
        threshold: f32,
    ) -> Result<OccupancyGrid> {
        OccupancyGrid::build_with(field, bounds, resolution, mode, threshold, true)
    }

    fn build_with(
        field: &dyn BatchFn,
        bounds: ([f32; 3], [f32; 3]),
        resolution: usize,
        mode: Mode,
        threshold: f32,
        capped_by_mean: bool,
    ) -> Result<OccupancyGrid> {
        check_threshold(mode, threshold)?;
        let peaks = cell_peaks(field, bounds, resolution)?;
        // 3. The cells above the threshold, 4. dilated: a max filter of width 3 and stride 1
        //    along each axis.
        let threshold = if capped_by_mean {
            threshold.min(mean(&peaks))
        } else {
            threshold
        };
        let res = resolution;
        let hot: Vec<f32> = peaks
            .iter()
            .map(|&p| if p > threshold { 1.0 } else { 0.0 })
            .collect();
        let dilate = |c: usize| c.saturating_sub(1)..=(c + 1).min(res - 1);
        let dilated = max_filter(&hot, [res, res, res], dilate, [res, res, res]);
        Ok(OccupancyGrid::from_cells(bounds, res, |i| dilated[i] > 0.0))
    }

    /// The grid over `bounds` with `resolution`³ cells in which a cell is occupied unless `bounds_of`
    /// (the interval bounds of the field's first output over boxes: 6 inputs, a box's low and high
    /// corners, and 2 outputs, a lower and an upper bound) places the whole cell below `threshold`, by a
    /// margin of 10⁻⁴ of the bound for rounding. Each cell's box is widened by 10⁻⁴ of a cell on every
    /// side, so that a point the grid places in a cell ([`OccupancyGrid::occupied`]) lies in its box
    /// despite the rounding of either. Unlike [`OccupancyGrid::build`] this misses nothing inside the
    /// bounds, however thin: every value of the field in an empty cell is at or below the threshold, so
    /// no dilation is needed. Cells whose bounds are NaN are occupied.
    pub fn from_bounds(
        bounds_of: &dyn BatchFn,
        bounds: ([f32; 3], [f32; 3]),
        resolution: usize,
        mode: Mode,
        threshold: f32,
    ) -> Result<OccupancyGrid> {
        check_threshold(mode, threshold)?;
        check_box(bounds, resolution)?;
        if bounds_of.n_inputs() != 6 || bounds_of.n_outputs() != 2 {
            return Err(Error::Invalid(format!(
                "the bounds function must map 6 inputs (a box's corners) to 2 (a lower and an upper bound), not {} to {}",
                bounds_of.n_inputs(),
                bounds_of.n_outputs()
            )));
        }
        let (res, (lo, hi)) = (resolution, bounds);
        let cell = [0, 1, 2].map(|axis| (hi[axis] - lo[axis]) / res as f32);
        // Plane k along an axis, moved outwards (side 0: a low corner, side 1: a high one).
        let plane = |axis: usize, k: usize, side: usize| {
            let pad = 1e-4 * cell[axis];
            lo[axis] + cell[axis] * k as f32 + if side == 0 { -pad } else { pad }
        };
        let mut empty = vec![false; res * res * res];
        empty
            .par_chunks_mut(BUILD_BATCH)
            .enumerate()
            .for_each(|(task, cells)| {
                let first = task * BUILD_BATCH;
                let n = cells.len();
                // Inputs 0..3 are the cells' low corners, 3..6 their high ones.
                let corners: Vec<Vec<f32>> = (0..6)
                    .map(|input| {
                        let (axis, side) = (input % 3, input / 3);
                        (first..first + n)
                            .map(|i| {
                                let k = [i % res, i / res % res, i / (res * res)][axis];
                                plane(axis, k + side, side)
                            })
                            .collect()
                    })
                    .collect();
                let inputs: Vec<&[f32]> = corners.iter().map(Vec::as_slice).collect();
                let lower_upper = bounds_of.eval_columns(&inputs);
                for (cell, &upper) in cells.iter_mut().zip(&lower_upper[1]) {
                    // NaN compares false: occupied.
                    *cell = upper + 1e-4 * upper.abs() < threshold;
                }
            });
        Ok(OccupancyGrid::from_cells(bounds, res, |i| !empty[i]))
    }

    /// The grid over `bounds` with `resolution`³ cells whose occupied cells are those within
    /// `dilation` cells (along each axis: a (2·dilation + 1)³ block) of a cell holding one of
    /// `points`; points outside the bounds (or NaN) are ignored. For a first state before the field
    /// has learned anything, from a capture's sparse points (COLMAP's `points3D`).
    pub fn from_points(
        bounds: ([f32; 3], [f32; 3]),
        resolution: usize,
        points: &[[f32; 3]],
        dilation: usize,
    ) -> Result<OccupancyGrid> {
        check_box(bounds, resolution)?;
        let (res, (lo, hi)) = (resolution, bounds);
        let mut hot = vec![0.0f32; res * res * res];
        for p in points {
            // The cell coordinates; the upper bounds belong to the last cells, as in `occupied`.
            let f = [0, 1, 2].map(|i| (p[i] - lo[i]) * res as f32 / (hi[i] - lo[i]));
            if f.iter().all(|f| (0.0..=res as f32).contains(f)) {
                let [x, y, z] = f.map(|f| (f as usize).min(res - 1));
                hot[x + y * res + z * res * res] = 1.0;
            }
        }
        let dilate = |c: usize| c.saturating_sub(dilation)..=(c + dilation).min(res - 1);
        let dilated = max_filter(&hot, [res, res, res], dilate, [res, res, res]);
        Ok(OccupancyGrid::from_cells(bounds, res, |i| dilated[i] > 0.0))
    }

    /// The grid over `bounds` with `resolution`³ cells of which those with `occupied(i)` (cell
    /// x + y·res + z·res² for i) are occupied; the bounds and resolution must be valid (as
    /// [`cell_peaks`] checks).
    pub(crate) fn from_cells(
        (lo, hi): ([f32; 3], [f32; 3]),
        resolution: usize,
        occupied: impl Fn(usize) -> bool,
    ) -> OccupancyGrid {
        let res = resolution;
        let shift = res.next_power_of_two().trailing_zeros();
        let mut bits = vec![0u64; (1usize << (3 * shift)).div_ceil(64) + 1];
        for i in (0..res * res * res).filter(|&i| occupied(i)) {
            let bit = bit_of(shift, [i % res, i / res % res, i / (res * res)].map(|c| c as u32)) as usize;
            bits[bit / 64] |= 1 << (bit % 64);
        }
        let center = [0, 1, 2].map(|i| 0.5 * (lo[i] + hi[i]));
        let mut grid = OccupancyGrid {
            space: GridSpace::Scene,
            lo,
            hi,
            resolution,
            shift,
            scale: [0, 1, 2].map(|i| res as f32 / (hi[i] - lo[i])),
            outer: [lo, hi].map(|side| [0, 1, 2].map(|i| side[i] + (side[i] - center[i]) * 2e-4)),
            bits,
            blocks: Vec::new(),
            coarse: Default::default(),
        };
        grid.summarize_cells();
        grid
    }

    /// Blocks per axis.
    pub(super) fn blocks_per_axis(&self) -> usize {
        self.resolution.div_ceil(BLOCK)
    }

    /// Sets `blocks` and `coarse` from the cells' bits.
    pub(super) fn summarize_cells(&mut self) {
        let (res, n) = (self.resolution, self.blocks_per_axis());
        let mut blocks = vec![0u64; (n * n * n).div_ceil(64)];
        let coarse_shift = |k: usize| self.shift.saturating_sub(k as u32);
        let mut coarse: [Vec<u64>; COARSE_LEVELS] =
            std::array::from_fn(|level| vec![0u64; (1usize << (3 * coarse_shift(level + 1))).div_ceil(64)]);
        let row = 1usize << self.shift;
        for (w, &word) in self.bits.iter().enumerate() {
            let mut word = word;
            while word != 0 {
                let bit = w * 64 + word.trailing_zeros() as usize;
                word &= word - 1;
                let (x, y, z) = (bit % row, bit / row % row, bit / (row * row));
                for (level, bits) in coarse.iter_mut().enumerate() {
                    let k = level + 1;
                    let at = bit_of(coarse_shift(k), [x >> k, y >> k, z >> k].map(|c| c as u32)) as usize;
                    bits[at / 64] |= 1 << (at % 64);
                }
                // The blocks within one cell of the cell: those of its neighbours'.
                let near = |c: usize| c.saturating_sub(1) / BLOCK..=(c + 1).min(res - 1) / BLOCK;
                for bz in near(z) {
                    for by in near(y) {
                        for bx in near(x) {
                            let b = bx + n * (by + n * bz);
                            blocks[b / 64] |= 1 << (b % 64);
                        }
                    }
                }
            }
        }
        (self.blocks, self.coarse) = (blocks, coarse);
    }
}
