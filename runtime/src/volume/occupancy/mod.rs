//! Occupancy grids for empty-space skipping in volume rendering (as in instant-ngp and
//! nerfacc): a bit per cell of a regular grid over an axis-aligned box, set where the field's
//! first output (density σ or per-sample opacity a) may exceed a threshold.
//!
//! [`OccupancyGrid::build`] evaluates the field on the lattice that splits every cell into
//! [`SUBDIVISIONS`]³ sub-cells: each cell is probed at its 8 corners, the midpoints of its 12
//! edges and 6 faces, and its center (27 points with 2 subdivisions, shared with the
//! neighbouring cells). A cell is occupied if any of its probes has a value above the
//! threshold (or NaN); the occupied set is then dilated by one cell (the 26 neighbours), so
//! that the falloff around a detected feature, which lies partly in cells whose own probes
//! are all below the threshold, is kept.
//!
//! [`OccupancyGrid::from_bounds`] builds the grid from the field's interval bounds over each cell
//! instead, where they are known (a script's analytic density): it misses nothing inside the grid's
//! bounds, and costs one bounds evaluation per cell instead of 27 probes.
//!
//! A probed grid is an approximation, which is why renderers use a grid only when asked
//! ([`crate::volume::render::render_volume_with`]). What it can miss:
//! - anything outside the grid's bounds (the grid says "empty" there);
//! - a feature that contains no probe and lies more than one cell away from any probe above
//!   the threshold: e.g. a blob or a sheet thinner than the probe spacing (cell /
//!   [`SUBDIVISIONS`]) that falls between probes, away from detected features;
//! - values at or below the threshold. In [`Mode::Opacity`](crate::Mode::Opacity) the threshold bounds the alpha of
//!   a skipped sample; in [`Mode::Density`](crate::Mode::Density) it is compared with σ itself, so a skipped sample
//!   has alpha = 1 − exp(−σδ) ≤ threshold·δ for sample spacing δ (and, as the last sample of
//!   a ray has δ = [`crate::volume::composite::LAST_DELTA`], a skipped last sample contributes
//!   nothing although σ·1e10 might be large).
//!
//! A density threshold means different things at different scales and in warped spaces: in NDC a cell
//! near the cameras spans a fraction of a unit of depth and one far off spans hundreds. Thresholding
//! each cell's optical thickness instead ([`CellThickness`]: the density times the length a ray crosses
//! in the cell) bounds the opacity a skipped cell could have added, whatever the space and the scene's
//! size.
//!
//! The first output is assumed not to depend on the view direction: a field that takes one
//! is probed with direction (0, 0, 1).
//!
//! A grid in [`GridSpace::Contracted`] covers all of space, as instant-ngp's cascades and nerfacto's
//! grids do for unbounded captures: its box is in the coordinates of mip-NeRF 360's contraction
//! ([`contract`]: the identity inside the unit ball, all of space inside the ball of radius 2), and a
//! point is looked up at its contracted coordinates. Such a grid is built from the field read at the
//! uncontracted points ([`Unwarped`]): the cells far out stand for ever larger regions of space.
//!
//! A grid in [`GridSpace::Ndc`] covers the frustum of a forward-facing capture out to infinity, in NeRF's
//! normalized device coordinates of the mean camera as `llff(...)` places it ([`ndc`]): its cells are
//! small near the cameras and ever deeper far from them, as the capture's detail is.
//!
//! This module holds the grid and its lookups; `spaces` the spaces and the fields a warped grid is built
//! from, `build` the building, `walk` a ray's walk through the grid, and `ema` instant-ngp's running grid
//! for training ([`DensityEma`]).

mod build;
mod ema;
mod spaces;
mod walk;

use crate::error::{Error, Result};
use build::check_box;

pub use ema::DensityEma;
pub use spaces::{check_thickness, contract, ndc, uncontract, unndc, CellThickness, GridSpace, Unwarped};

/// Each cell is probed on a lattice of this many steps per cell and axis.
pub const SUBDIVISIONS: usize = 2;

/// Largest supported resolution (cells per axis).
pub const MAX_RESOLUTION: usize = 256;

/// Cells per side of the blocks over which a ray finds the stretch it may meet occupied cells in
/// ([`OccupancyGrid::occupied_stretch`]).
const BLOCK: usize = 8;

/// Coarse levels of the cells the walk over a ray's samples steps over empty space with: level k
/// (1 to `COARSE_LEVELS`) has a bit per cube of 2^k cells per side ([`OccupancyGrid::next_occupied`]).
const COARSE_LEVELS: usize = 3;

/// A bit per cell of a `resolution`³ grid over an axis-aligned box. See the module docs.
#[derive(Debug, Clone, PartialEq)]
pub struct OccupancyGrid {
    /// The space the box is in.
    space: GridSpace,
    lo: [f32; 3],
    hi: [f32; 3],
    resolution: usize,
    /// Bits per row (and rows per plane) are 2^shift >= resolution: no multiplications.
    shift: u32,
    /// Cells per unit length along each axis.
    scale: [f32; 3],
    /// The bounds widened by 1e-4 of their size, for ray intervals.
    outer: [[f32; 3]; 2],
    /// Bit `(z << 2·shift) | (y << shift) | x` is set for an occupied cell x, y, z; the
    /// others, and the last word, past the cells, are 0.
    bits: Vec<u64>,
    /// Bit `x + y·n + z·n²` of the n³ blocks of [`BLOCK`]³ cells is set if a cell within one cell of
    /// block (x, y, z) is occupied (the dilation makes [`OccupancyGrid::occupied_stretch`] robust to
    /// rounding).
    blocks: Vec<u64>,
    /// Level k's bits (k = 1 to [`COARSE_LEVELS`], at index k − 1), in the cells' layout with rows of
    /// 2^(shift − k) bits: bit (x, y, z) is set if a cell of the cube of 2^k cells per side at
    /// (x, y, z)·2^k is occupied (no dilation).
    coarse: [Vec<u64>; COARSE_LEVELS],
}

impl OccupancyGrid {
    /// The cells' bits packed 8 to a byte, cell x + y·res + z·res² at bit i % 8 of byte i / 8 (the
    /// form a checkpoint keeps the grid in; [`OccupancyGrid::from_packed_cells`] reads it back).
    pub fn packed_cells(&self) -> Vec<u8> {
        let res = self.resolution;
        let mut bytes = vec![0u8; (res * res * res).div_ceil(8)];
        for z in 0..res {
            for y in 0..res {
                for x in 0..res {
                    if self.cell(x, y, z) {
                        let i = x + y * res + z * res * res;
                        bytes[i / 8] |= 1 << (i % 8);
                    }
                }
            }
        }
        bytes
    }

    /// The grid over `bounds` with `resolution`³ cells as [`OccupancyGrid::packed_cells`] wrote them, or
    /// an error if the bounds, the resolution or the number of bytes are wrong.
    pub fn from_packed_cells(
        bounds: ([f32; 3], [f32; 3]),
        resolution: usize,
        bytes: &[u8],
    ) -> Result<OccupancyGrid> {
        check_box(bounds, resolution)?;
        let cells = resolution * resolution * resolution;
        if bytes.len() != cells.div_ceil(8) {
            return Err(Error::Invalid(format!(
                "{} bytes of cells for a {resolution}³ grid, which needs {}",
                bytes.len(),
                cells.div_ceil(8)
            )));
        }
        Ok(OccupancyGrid::from_cells(bounds, resolution, |i| {
            bytes[i / 8] & (1 << (i % 8)) != 0
        }))
    }

    /// The same cells in `space`: a grid built over a space's coordinates (from [`Unwarped`]) is one in
    /// that space; in [`GridSpace::Contracted`] the cells wholly outside the ball of radius 2 are cleared
    /// (no contracted point lies there).
    pub fn in_space(self, space: GridSpace) -> OccupancyGrid {
        let mut grid = OccupancyGrid { space, ..self };
        if space == GridSpace::Contracted {
            let res = grid.resolution;
            let cell = [0, 1, 2].map(|i| (grid.hi[i] - grid.lo[i]) / res as f32);
            // The distance from the origin to cell k's interval along axis i.
            let gap = |i: usize, k: usize| {
                let (a, b) = (
                    grid.lo[i] + cell[i] * k as f32,
                    grid.lo[i] + cell[i] * (k + 1) as f32,
                );
                if a > 0.0 {
                    a
                } else if b < 0.0 {
                    -b
                } else {
                    0.0
                }
            };
            for z in 0..res {
                for y in 0..res {
                    for x in 0..res {
                        let nearest = gap(0, x).powi(2) + gap(1, y).powi(2) + gap(2, z).powi(2);
                        if nearest >= 4.0 {
                            let bit = bit_of(grid.shift, [x, y, z].map(|c| c as u32)) as usize;
                            grid.bits[bit / 64] &= !(1 << (bit % 64));
                        }
                    }
                }
            }
            grid.summarize_cells();
        }
        grid
    }

    /// The space the grid's box is in.
    pub fn space(&self) -> GridSpace {
        self.space
    }

    /// The box (lo, hi) covered by the grid, in its space's coordinates.
    pub fn bounds(&self) -> ([f32; 3], [f32; 3]) {
        (self.lo, self.hi)
    }

    /// Cells per axis.
    pub fn resolution(&self) -> usize {
        self.resolution
    }

    /// Number of occupied cells.
    pub fn occupied_cells(&self) -> usize {
        self.bits.iter().map(|b| b.count_ones() as usize).sum()
    }

    /// Fraction of the cells that are occupied.
    pub fn occupancy(&self) -> f64 {
        self.occupied_cells() as f64 / (self.resolution as f64).powi(3)
    }

    /// Whether cell (x, y, z) (each in 0..resolution) is occupied.
    pub fn cell(&self, x: usize, y: usize, z: usize) -> bool {
        let r = self.resolution;
        assert!(
            x < r && y < r && z < r,
            "cell ({x}, {y}, {z}) outside a {r}³ grid"
        );
        self.bit(bit_of(self.shift, [x, y, z].map(|c| c as u32)))
    }

    /// Whether the cell containing `p` (in the scene's coordinates; contracted first for a grid in
    /// [`GridSpace::Contracted`]) is occupied; points outside the bounds (or NaN) are empty. Cells are
    /// half-open, except that the upper bounds belong to the last cells.
    #[inline]
    pub fn occupied(&self, p: [f32; 3]) -> bool {
        self.bit(self.bit_index(p[0], p[1], p[2]))
    }

    /// The bit of the cell containing scene point (x, y, z) (see [`OccupancyGrid::occupied`]), or the
    /// last bit (always clear) if the point is outside the bounds or NaN.
    #[inline(always)]
    fn bit_index(&self, x: f32, y: f32, z: f32) -> u32 {
        match self.space {
            GridSpace::Scene => self.box_bit_index(x, y, z),
            GridSpace::Contracted => {
                let [x, y, z] = contract([x, y, z]);
                self.box_bit_index(x, y, z)
            }
            GridSpace::Ndc => {
                let [x, y, z] = ndc([x, y, z]);
                self.box_bit_index(x, y, z)
            }
        }
    }

    /// The bit of the cell containing (x, y, z) in the box's coordinates, or the last bit (always clear)
    /// if the point is outside the bounds or NaN. Without branches, so that loops over points vectorize.
    #[inline(always)]
    fn box_bit_index(&self, x: f32, y: f32, z: f32) -> u32 {
        let r = self.resolution as u32;
        let (last, top) = ((r - 1) as f32, r as f32);
        let fx = (x - self.lo[0]) * self.scale[0];
        let fy = (y - self.lo[1]) * self.scale[1];
        let fz = (z - self.lo[2]) * self.scale[2];
        let inside = (fx >= 0.0) & (fx <= top) & (fy >= 0.0) & (fy <= top) & (fz >= 0.0) & (fz <= top);
        // ⌊f⌋ clamped to the cells, with selects and integer operations only (a saturating
        // `as` does not vectorize): NaN and negative values give 0.
        let cell = |f: f32| {
            let f = if f >= 0.0 { f } else { 0.0 };
            let f = if f <= last { f } else { last };
            // f + 2²³ rounds f to the nearest integer, found in the low bits; then floor.
            let nearest = (f + 8_388_608.0).to_bits() - 0x4B00_0000;
            nearest - u32::from(nearest as f32 > f)
        };
        let index = bit_of(self.shift, [cell(fx), cell(fy), cell(fz)]);
        if inside {
            index
        } else {
            (self.bits.len() * 64 - 1) as u32
        }
    }

    /// Whether bit `index` (from [`OccupancyGrid::bit_index`]) is set.
    #[inline(always)]
    fn bit(&self, index: u32) -> bool {
        is_set(&self.bits, index as usize)
    }
}

/// Whether bit `i` of the words `bits` (bit i % 64 of word i / 64) is set.
#[inline(always)]
fn is_set(bits: &[u64], i: usize) -> bool {
    bits[i / 64] >> (i % 64) & 1 == 1
}

/// The bit of cell (x, y, z) in rows and planes of 2^`shift` bits.
#[inline(always)]
fn bit_of(shift: u32, [x, y, z]: [u32; 3]) -> u32 {
    (z << (2 * shift)) | (y << shift) | x
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::{BatchFn, ClosureFn};
    use crate::volume::composite::Mode;
    use proptest::strategy::Strategy;

    const UNIT: ([f32; 3], [f32; 3]) = ([-1.0; 3], [1.0; 3]);

    /// A grid over `bounds` whose cells are each occupied with probability `fill`.
    fn random_grid(bounds: ([f32; 3], [f32; 3]), resolution: usize, fill: f64, seed: u64) -> OccupancyGrid {
        let mut rng = crate::rng::Rng::new(seed);
        let cells: Vec<bool> = (0..resolution.pow(3))
            .map(|_| f64::from(rng.next_f32()) < fill)
            .collect();
        OccupancyGrid::from_cells(bounds, resolution, |i| cells[i])
    }

    proptest::proptest! {
        /// The contraction puts all of space inside the ball of radius 2, and its inverse takes it back.
        #[test]
        fn contraction_round_trips(p in proptest::array::uniform3(-300.0f32..300.0)) {
            let c = contract(p);
            let norm = |v: [f32; 3]| v.iter().map(|x| x * x).sum::<f32>().sqrt();
            proptest::prop_assert!(norm(c) < 2.0 && norm(c) <= norm(p) + 1e-6);
            let back = uncontract(c);
            // The inverse loses precision as |c| nears 2: |p| = 1/(2 − |c|).
            let tolerance = 1e-5 * norm(p).max(1.0).powi(2);
            proptest::prop_assert!((0..3).all(|k| (back[k] - p[k]).abs() <= tolerance), "{p:?} {c:?} {back:?}");
        }

        /// NDC maps the frustum from depth 1 to 1000 (the third coordinate from 7 to −0.992), and its
        /// inverse takes it back.
        #[test]
        fn ndc_round_trips(x in -1.0f32..1.0, depth in 1.0f32..1000.0, z in -1.0f32..1.0) {
            let p = [x * depth, depth - 4.0, z * depth];
            let c = ndc(p);
            proptest::prop_assert!((c[0] - x).abs() <= 1e-5 && (c[1] - z).abs() <= 1e-5);
            proptest::prop_assert!(c[2] > -1.0 && c[2] <= 7.0);
            let back = unndc(c);
            // The inverse loses precision as the depth grows: d = 8/(w + 1).
            let tolerance = 1e-5 * depth * depth;
            proptest::prop_assert!((0..3).all(|k| (back[k] - p[k]).abs() <= tolerance), "{p:?} {c:?} {back:?}");
        }

        /// A space's stretch is the length in the scene a unit of its coordinates spans along the rays, by
        /// central differences of its inverse: the depth a unit of NDC's third coordinate spans, the
        /// radius a unit of contracted radius spans (1 inside the unit ball), 1 in the scene's space.
        #[test]
        fn the_stretch_is_the_scene_length_a_unit_spans_along_the_rays(
            c in proptest::array::uniform3(-1.0f32..1.0),
            w in -0.9f32..1.3,
            norm in 0.2f32..1.95,
        ) {
            let h = 1e-3f32;
            // NDC: the depth (y + 4) at the third coordinate w ± h.
            let depth = |w: f32| f64::from(unndc([c[0], c[1], w])[1]) + 4.0;
            let ndc = (depth(w - h) - depth(w + h)) / (2.0 * f64::from(h));
            let stretch = f64::from(GridSpace::Ndc.stretch([c[0], c[1], w]));
            proptest::prop_assert!((ndc / stretch - 1.0).abs() < 1e-3, "{ndc} {stretch}");
            // The contraction: the radius of the point at contracted radius norm ± h along c (away from
            // the unit sphere, where the stretch has a kink).
            let length = c.iter().map(|x| x * x).sum::<f32>().sqrt().max(1e-3);
            let at = |r: f32| c.map(|x| x / length * r);
            let radius = |r: f32| f64::from(uncontract(at(r)).iter().map(|x| x * x).sum::<f32>().sqrt());
            let radial = (radius(norm + h) - radius(norm - h)) / (2.0 * f64::from(h));
            let stretch = f64::from(GridSpace::Contracted.stretch(at(norm)));
            if (norm - 1.0).abs() > 2.0 * h && norm + h < 2.0 - 1e-3 {
                proptest::prop_assert!((radial / stretch - 1.0).abs() < 1e-2, "{norm}: {radial} {stretch}");
            }
            proptest::prop_assert_eq!(GridSpace::Scene.stretch(c), 1.0);
        }

        /// No occupied point of a ray lies outside its occupied stretch: grids of random cells (of sizes
        /// that are and are not multiples of a block, over boxes that are not cubes), rays from inside and
        /// outside the box, including ones along an axis or through blocks' edges, each swept densely.
        #[test]
        fn occupied_points_lie_in_the_occupied_stretch(
            resolution in 1usize..40,
            fill in 0.0f64..0.05,
            seed in 0u64..1000,
            origin in proptest::array::uniform3(-3.0f32..3.0),
            target in proptest::array::uniform3(-1.2f32..1.2),
            snap in 0usize..4,
        ) {
            let bounds = ([-1.0, -0.5, -1.25], [1.0, 0.75, 0.5]);
            let grid = random_grid(bounds, resolution, fill, seed);
            // Some rays along an axis, or from a block corner: the walk's ties.
            let mut d: [f32; 3] = [0, 1, 2].map(|i| target[i] - origin[i]);
            if snap == 1 {
                d = [0.0, 0.0, d[2].signum()];
            }
            let o = if snap == 2 { [0.0, 0.0, -3.0] } else { origin };
            let length = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            proptest::prop_assume!(length > 1e-3);
            let d = d.map(|x| x / length);
            let Some((t0, t1)) = grid.ray_interval(o, d) else { return Ok(()) };
            let (a, b) = grid.occupied_stretch(o, d, (t0, t1));
            for step in 0..=4000 {
                let t = t0 + (t1 - t0) * step as f32 / 4000.0;
                let p = [0, 1, 2].map(|i| o[i] + d[i] * t);
                proptest::prop_assert!(!grid.occupied(p) || (a <= t && t <= b), "t {t} outside [{a}, {b}] at {p:?}");
            }
        }

        /// The walk keeps exactly the samples whose points `occupied` accepts, in order, stops after
        /// the wanted count with the sample after the last one kept, and otherwise at the range's end:
        /// random grids (mostly sparse ones, whose empty coarse cells the walk steps over; of sizes
        /// that are and are not multiples of the coarsest cells, over boxes that are not cubes), rays
        /// (some along an axis), sample spacings, ranges and counts, each walk continued from where
        /// the call before left off.
        #[test]
        fn the_walk_keeps_the_occupied_samples_in_order(
            resolution in 1usize..40,
            fill in (0.0f64..1.0).prop_map(|u| 0.6 * u * u * u),
            seed in 0u64..1000,
            origin in proptest::array::uniform3(-2.0f32..2.0),
            target in proptest::array::uniform3(-1.0f32..1.0),
            along_axis in proptest::bool::weighted(0.2),
            spacing in 0.002f32..0.05,
            start in 0usize..40,
            len in 0usize..400,
            want in 1usize..12,
        ) {
            let bounds = ([-1.0, -0.5, -1.25], [1.0, 0.75, 0.5]);
            let grid = random_grid(bounds, resolution, fill, seed);
            let mut d = [0, 1, 2].map(|i| target[i] - origin[i]);
            if along_axis {
                d = [0.0, -0.0, d[2]];
            }
            let depth = |j: usize| spacing * j as f32;
            let point = |j: usize| [0, 1, 2].map(|i| origin[i] + d[i] * depth(j));
            let samples = start..start + len;
            let expected: Vec<u32> =
                samples.clone().filter(|&j| grid.occupied(point(j))).map(|j| j as u32).collect();
            let (mut kept, mut from) = (Vec::new(), samples.start);
            while from < samples.end {
                let [mut x, mut y, mut z] = [0; 3].map(|_| vec![0.0f32; want]);
                let mut index = vec![0u32; want];
                let columns = [&mut x[..], &mut y[..], &mut z[..]];
                let rest = from..samples.end;
                let (n, next) = grid.next_occupied((origin, d), rest, depth, columns, &mut index);
                proptest::prop_assert!(n <= want && next > from && next <= samples.end);
                proptest::prop_assert!(n == want || next == samples.end, "{n} of {want}, stopped at {next}");
                if n == want {
                    proptest::prop_assert_eq!(next, index[n - 1] as usize + 1);
                }
                for k in 0..n {
                    let p = point(index[k] as usize);
                    proptest::prop_assert_eq!([x[k], y[k], z[k]], p);
                }
                kept.extend_from_slice(&index[..n]);
                from = next;
            }
            proptest::prop_assert_eq!(kept, expected);
        }
    }

    #[test]
    fn occupied_stretch_spans_the_occupied_cells_a_ray_crosses() {
        // One occupied cell of 32³ over [-1, 1]³ at x, y in [0, 1/16), z in [0.5, 0.5625).
        let res = 32;
        let cell = |i: usize| (i % res, i / res % res, i / (res * res)) == (16, 16, 24);
        let grid = OccupancyGrid::from_cells(UNIT, res, cell);
        let (o, d) = ([0.03, 0.03, -3.0], [0.0, 0.0, 1.0]);
        let (a, b) = grid.occupied_stretch(o, d, grid.ray_interval(o, d).unwrap());
        // The cell's depths are [3.5, 3.5625]; its block's [3.5, 4.0], and with the cell's dilation the
        // block before it, [3.0, 3.5), is marked too; a cell's diagonal (0.108) widens the stretch.
        assert!(a <= 3.5 && b >= 3.5625, "[{a}, {b}]");
        assert!(
            a >= 2.85 && b <= 4.15,
            "the stretch [{a}, {b}] reaches beyond the marked blocks"
        );
        // A ray that passes far from the cell's block crosses no marked block: an empty stretch.
        let (o, d) = ([-0.9, -0.9, -3.0], [0.0, 0.0, 1.0]);
        let (a, b) = grid.occupied_stretch(o, d, grid.ray_interval(o, d).unwrap());
        assert!(a > b, "[{a}, {b}]");
    }

    #[test]
    fn an_ndc_grid_covers_the_frustum_to_infinity() {
        // A ball of radius 2 at depth 20 in front of the mean camera at (0, −4, 0), and nothing else: in
        // an NDC grid over [−1, 1]³ it lies in the cells of the third coordinate from 8/22 − 1 to 8/18 − 1.
        let field = ClosureFn::new(3, 4, |p, out| {
            let d2 = p[0] * p[0] + (p[1] - 16.0).powi(2) + p[2] * p[2];
            out.fill(0.0);
            out[0] = if d2 < 4.0 { 1.0 } else { 0.0 };
        });
        let unwarped = Unwarped {
            space: GridSpace::Ndc,
            field: &field,
        };
        let grid = OccupancyGrid::build(&unwarped, UNIT, 64, Mode::Density, 0.5)
            .unwrap()
            .in_space(GridSpace::Ndc);
        assert_eq!(grid.space(), GridSpace::Ndc);
        assert!(grid.occupied([0.0, 16.0, 0.0]) && grid.occupied([1.0, 15.0, -1.0]));
        assert!(
            !grid.occupied([0.0, 6.0, 0.0])
                && !grid.occupied([0.0, 100.0, 0.0])
                && !grid.occupied([8.0, 16.0, 0.0])
        );
        assert!(grid.occupancy() < 0.01, "{}", grid.occupancy());
        // Rays are never clipped by its box, and a ray's walk agrees with the lookup of each of its points
        // (from the camera along +y in steps of 1).
        let ray = ([0.0, -4.0, 0.0], [0.0, 1.0, 0.0]);
        assert_eq!(
            grid.ray_interval(ray.0, ray.1),
            Some((f32::NEG_INFINITY, f32::INFINITY))
        );
        let all: Vec<u32> = (0..60u32)
            .filter(|&j| grid.occupied([0.0, j as f32 - 4.0, 0.0]))
            .collect();
        assert!(
            all.len() >= 3 && all[0] >= 15 && *all.last().unwrap() <= 26,
            "{all:?}"
        );
        let ([mut x, mut y, mut z], mut index) = ([[0.0f32; 64]; 3], [0u32; 64]);
        let (n, next) = grid.next_occupied(ray, 0..60, |j| j as f32, [&mut x, &mut y, &mut z], &mut index);
        assert_eq!((n, next, &index[..n]), (all.len(), 60, &all[..]));
    }

    #[test]
    fn a_contracted_grid_covers_all_of_space() {
        // A ball of radius 3 ten units out along x, and nothing else: in a contracted grid over
        // [−2, 2]³ it lies in the cells of x from 2 − 1/7 to 2 − 1/13.
        let field = ClosureFn::new(3, 4, |p, out| {
            let d2 = (p[0] - 10.0).powi(2) + p[1] * p[1] + p[2] * p[2];
            out.fill(0.0);
            out[0] = if d2 < 9.0 { 1.0 } else { 0.0 };
        });
        let box2 = ([-2.0; 3], [2.0; 3]);
        let unwarped = Unwarped {
            space: GridSpace::Contracted,
            field: &field,
        };
        let grid = OccupancyGrid::build(&unwarped, box2, 32, Mode::Density, 0.5)
            .unwrap()
            .in_space(GridSpace::Contracted);
        assert_eq!(grid.space(), GridSpace::Contracted);
        assert!(grid.occupied([10.0, 0.0, 0.0]) && grid.occupied([8.5, 1.0, -1.0]));
        assert!(
            !grid.occupied([0.0; 3]) && !grid.occupied([-10.0, 0.0, 0.0]) && !grid.occupied([2.0, 0.0, 0.0])
        );
        assert!(grid.occupancy() < 0.02, "{}", grid.occupancy());
        // Rays are never clipped by its box.
        assert_eq!(
            grid.ray_interval([0.0; 3], [1.0, 0.0, 0.0]),
            Some((f32::NEG_INFINITY, f32::INFINITY))
        );
        // A ray's walk agrees with the lookup of each of its points (along x from −10 in steps of 1,
        // those in cells the ball touches) and stops at the wanted count.
        let ([mut x, mut y, mut z], mut index) = ([[0.0f32; 4]; 3], [0u32; 4]);
        let ray = ([-12.0, 0.0, 0.0], [1.0, 0.0, 0.0]);
        let all: Vec<u32> = (2..30u32)
            .filter(|&j| grid.occupied([j as f32 - 12.0, 0.0, 0.0]))
            .collect();
        assert!(all.len() > 4 && all[0] > 2, "{all:?}");
        let (n, next) = grid.next_occupied(ray, 2..30, |j| j as f32, [&mut x, &mut y, &mut z], &mut index);
        assert_eq!((n, next, &index[..]), (4, all[3] as usize + 1, &all[..4]));
        assert_eq!(x, [0, 1, 2, 3].map(|i| all[i] as f32 - 12.0));
        let ([mut x, mut y, mut z], mut index) = ([[0.0f32; 32]; 3], [0u32; 32]);
        let (n, next) = grid.next_occupied(ray, next..30, |j| j as f32, [&mut x, &mut y, &mut z], &mut index);
        assert_eq!((n, next, &index[..n]), (all.len() - 4, 30, &all[4..]));
        // The same cells in the scene's space are a box of side 4 at the origin, which holds nothing there.
        let scene = grid.clone().in_space(GridSpace::Scene);
        assert!(!scene.occupied([10.0, 0.0, 0.0]));
        // The corners of the box, beyond the contraction's reach, are empty whatever the field says.
        let everywhere = ClosureFn::new(3, 4, |_, out| out.fill(1.0));
        let full = OccupancyGrid::build(&everywhere, box2, 8, Mode::Density, 0.5).unwrap();
        assert_eq!(full.occupied_cells(), 512);
        let contracted = full.in_space(GridSpace::Contracted);
        // Of 8³ cells of side 0.5, those whose nearest point is 2 or more from the center: along each
        // axis a cell's nearest coordinate is 0, 0.5, 1 or 1.5 (two cells each side).
        let near: usize = (0..512)
            .filter(|i| {
                let gap = |k: usize| [1.5f32, 1.0, 0.5, 0.0, 0.0, 0.5, 1.0, 1.5][k];
                gap(i % 8).powi(2) + gap(i / 8 % 8).powi(2) + gap(i / 64).powi(2) < 4.0
            })
            .count();
        assert_eq!(contracted.occupied_cells(), near);
        assert!(contracted.occupied([1e6, 0.0, 0.0]) && !contracted.cell(0, 0, 0));
    }

    #[test]
    fn a_cells_thickness_is_its_density_times_the_length_a_ray_crosses_in_it() {
        // The scene's space, cells of 0.25 × 0.5 × 1 (the side of a cube of their volume: 0.5): a
        // thickness of 0.6 marks the cells a density of 1.2 marks.
        let bounds = ([-1.0, -1.0, -1.0], [1.0, 3.0, 7.0]);
        let field = ClosureFn::new(3, 4, |p, out| {
            out.fill(0.0);
            out[0] = (p[0] + 0.5 * p[1] - 0.25 * p[2]).abs();
        });
        let thickness = |space: GridSpace, bounds, resolution, mode, threshold| {
            space.with_grid_field(&field, (bounds, resolution), (mode, true), |f| {
                OccupancyGrid::build(f, bounds, resolution, mode, threshold)
            })
        };
        let by_thickness = thickness(GridSpace::Scene, bounds, 8, Mode::Density, 0.6).unwrap();
        let by_density = OccupancyGrid::build(&field, bounds, 8, Mode::Density, 1.2).unwrap();
        assert_eq!(by_thickness, by_density);
        assert!((1..512).contains(&by_density.occupied_cells()));
        // In NDC a constant density 0.05 is thicker the farther the cell: 16³ cells of 0.1625 over
        // [−1.3, 1.3]³ have thickness 0.05 · 0.1625 · d²/8 at depth d, 0.1016 at depth 10 (w = −0.2).
        // Cells two or more layers past it are all occupied, and those two or more before it empty.
        let fog = ClosureFn::new(3, 4, |_, out| {
            out.fill(0.0);
            out[0] = 0.05;
        });
        let ndc_box = ([-1.3; 3], [1.3; 3]);
        let grid = GridSpace::Ndc
            .with_grid_field(&fog, (ndc_box, 16), (Mode::Density, true), |f| {
                OccupancyGrid::build(f, ndc_box, 16, Mode::Density, 0.1016)
            })
            .unwrap();
        let layer = |z: usize| (0..256).filter(|i| grid.cell(i % 16, i / 16, z)).count();
        let boundary = (-0.2f32 + 1.3) / 0.1625;
        for z in 0..16 {
            if (z as f32 + 1.0) < boundary - 2.0 {
                assert_eq!(layer(z), 256, "far layer {z}");
            } else if (z as f32) > boundary + 2.0 {
                assert_eq!(layer(z), 0, "near layer {z}");
            }
        }
        // A density threshold cannot tell them apart: all or nothing.
        let flat = GridSpace::Ndc.with_field(&fog, |f| {
            OccupancyGrid::build(f, ndc_box, 16, Mode::Density, 0.04)
        });
        assert_eq!(flat.unwrap().occupied_cells(), 4096);
        // A field of opacities has no thickness.
        let err = thickness(GridSpace::Scene, bounds, 8, Mode::Opacity, 0.5)
            .unwrap_err()
            .to_string();
        assert!(err.contains("thickness is for a field of densities"), "{err}");
    }

    #[test]
    fn a_field_in_one_cell_marks_it_and_its_26_neighbours() {
        // 8³ cells of width 0.25 over [-1, 1]³: cell (5, 2, 3) spans x in [0.25, 0.5),
        // y in [-0.5, -0.25), z in [-0.25, 0). The field is non-zero on a small ball around
        // the cell's center, which only the center probe sees.
        let center = [0.375f32, -0.375, -0.125];
        let field = ClosureFn::new(3, 4, move |p, out| {
            let d2: f32 = (0..3).map(|i| (p[i] - center[i]).powi(2)).sum();
            out.fill(0.0);
            out[0] = if d2 < 0.01 { 0.5 } else { 0.0 };
        });
        let grid = OccupancyGrid::build(&field, UNIT, 8, Mode::Opacity, 1e-3).unwrap();
        for z in 0..8usize {
            for y in 0..8usize {
                for x in 0..8usize {
                    let near = x.abs_diff(5) <= 1 && y.abs_diff(2) <= 1 && z.abs_diff(3) <= 1;
                    assert_eq!(grid.cell(x, y, z), near, "cell ({x}, {y}, {z})");
                }
            }
        }
        assert_eq!(grid.occupied_cells(), 27);
        assert!(grid.occupied(center));
        assert!(grid.occupied([0.6, -0.6, 0.1]));
        assert!(!grid.occupied([0.8, -0.6, 0.1]));
        // Dilation stops at the bounds: a field in a corner cell marks 2³ cells.
        let corner = ClosureFn::new(3, 4, |p, out| {
            out.fill(0.0);
            out[0] = if p.iter().all(|&x| x > 0.9) { 1.0 } else { 0.0 };
        });
        let grid = OccupancyGrid::build(&corner, UNIT, 8, Mode::Density, 0.0).unwrap();
        assert_eq!(grid.occupied_cells(), 8);
        assert!(grid.cell(6, 6, 6) && grid.cell(7, 7, 7) && !grid.cell(5, 7, 7));
        // The upper bound belongs to the last cell; outside and NaN are empty.
        assert!(grid.occupied([1.0, 1.0, 1.0]));
        assert!(!grid.occupied([1.001, 1.0, 1.0]));
        assert!(!grid.occupied([f32::NAN, 1.0, 1.0]));
    }

    #[test]
    fn zero_fields_are_empty_and_nan_is_occupied() {
        let zero = ClosureFn::new(6, 4, |_, out| out.fill(0.0));
        let grid = OccupancyGrid::build(&zero, UNIT, 16, Mode::Density, 0.0).unwrap();
        assert_eq!((grid.occupied_cells(), grid.occupancy()), (0, 0.0));
        let nan = ClosureFn::new(3, 1, |_, out| out[0] = f32::NAN);
        let grid = OccupancyGrid::build(&nan, UNIT, 4, Mode::Opacity, 0.5).unwrap();
        assert_eq!(grid.occupancy(), 1.0);
    }

    #[test]
    fn a_training_grid_of_a_faint_field_keeps_its_denser_half() {
        // σ = 0.01 in the half x > 0, 0.001 elsewhere: all below the threshold 0.3.
        let faint = ClosureFn::new(3, 4, |p, out| {
            out.fill(0.0);
            out[0] = if p[0] > 0.0 { 0.01 } else { 0.001 };
        });
        let bounds = ([-1.0; 3], [1.0; 3]);
        let plain = OccupancyGrid::build(&faint, bounds, 16, Mode::Density, 0.3).unwrap();
        assert_eq!(plain.occupied_cells(), 0);
        let training = OccupancyGrid::build_for_training(&faint, bounds, 16, Mode::Density, 0.3).unwrap();
        // The cells of x > 0 (and the dilated layer next to them), none further.
        for x in 0..16 {
            let expected = x >= 7;
            assert!(
                (0..16).all(|y| (0..16).all(|z| training.cell(x, y, z) == expected)),
                "x = {x}"
            );
        }
        // A field above the threshold somewhere keeps the threshold.
        let bright = ClosureFn::new(3, 4, |p, out| {
            out.fill(0.0);
            out[0] = if p[0] > 0.5 { 100.0 } else { 0.2 };
        });
        let a = OccupancyGrid::build(&bright, bounds, 16, Mode::Density, 0.3).unwrap();
        let b = OccupancyGrid::build_for_training(&bright, bounds, 16, Mode::Density, 0.3).unwrap();
        assert_eq!(a, b);
    }

    #[test]
    fn ray_intervals_cover_the_box() {
        let grid = OccupancyGrid::build(
            &ClosureFn::new(3, 1, |_, o| o[0] = 1.0),
            UNIT,
            2,
            Mode::Opacity,
            0.5,
        )
        .unwrap();
        let (t0, t1) = grid.ray_interval([0.0, 0.0, -3.0], [0.0, 0.0, 1.0]).unwrap();
        assert!((t0 - 2.0).abs() < 1e-3 && (t1 - 4.0).abs() < 1e-3, "{t0} {t1}");
        assert!(grid.ray_interval([0.0, 2.0, -3.0], [0.0, 0.0, 1.0]).is_none());
        assert!(grid.ray_interval([0.0, 0.0, -3.0], [0.0, 0.0, -1.0]).unwrap().1 < 0.0);
        let d = 1.0 / 3f32.sqrt();
        let (t0, t1) = grid.ray_interval([-2.0; 3], [d; 3]).unwrap();
        assert!((t0 - 3f32.sqrt()).abs() < 1e-3 && (t1 - 3.0 * 3f32.sqrt()).abs() < 1e-3);
    }

    #[test]
    fn a_grid_from_points_holds_the_cells_near_them() {
        let bounds = ([-1.0; 3], [1.0; 3]);
        // Cells of 0.25: (0.1, 0.1, 0.1) is in cell (4, 4, 4), (1, 1, 1) in the last, the rest outside.
        let points = [
            [0.1, 0.1, 0.1],
            [1.0, 1.0, 1.0],
            [2.0, 0.0, 0.0],
            [f32::NAN, 0.0, 0.0],
        ];
        let grid = OccupancyGrid::from_points(bounds, 8, &points, 1).unwrap();
        let near = |c: usize, at: usize| c.abs_diff(at) <= 1;
        for (x, y, z) in (0..512).map(|i| (i % 8, i / 8 % 8, i / 64)) {
            let want = (near(x, 4) && near(y, 4) && near(z, 4)) || (x >= 6 && y >= 6 && z >= 6);
            assert_eq!(grid.cell(x, y, z), want, "cell ({x}, {y}, {z})");
        }
        assert_eq!(grid.occupied_cells(), 27 + 8);
        let exact = OccupancyGrid::from_points(bounds, 8, &points[..1], 0).unwrap();
        assert_eq!(exact.occupied_cells(), 1);
        assert!(exact.occupied([0.2, 0.2, 0.2]) && !exact.occupied([0.3, 0.2, 0.2]));
        assert!(OccupancyGrid::from_points(bounds, 0, &points, 1).is_err());
    }

    /// A shell |p| = 0.6 of half-width 0.005: between the probes of an 8³ grid over [-1, 1]³ (their
    /// distances from the origin all differ from 0.6 by more than 0.012).
    fn thin_shell(p: &[f32]) -> f32 {
        let r = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
        if (r - 0.6).abs() < 0.005 {
            10.0
        } else {
            0.0
        }
    }

    /// Interval bounds of [`thin_shell`] over boxes (6 inputs: low and high corners; 2 outputs).
    fn thin_shell_bounds() -> impl BatchFn {
        ClosureFn::new(6, 2, |b, out| {
            let (lo, hi) = (&b[..3], &b[3..]);
            let nearest: f32 = (0..3).map(|i| (0.0f32).clamp(lo[i], hi[i]).powi(2)).sum();
            let farthest: f32 = (0..3).map(|i| lo[i].abs().max(hi[i].abs()).powi(2)).sum();
            let crosses = nearest.sqrt() < 0.605 && farthest.sqrt() > 0.595;
            out[0] = 0.0;
            out[1] = if crosses { 10.0 } else { 0.0 };
        })
    }

    #[test]
    fn a_grid_from_bounds_keeps_a_shell_the_probes_miss() {
        let field = ClosureFn::new(3, 4, |p, out| {
            out.fill(0.0);
            out[0] = thin_shell(p);
        });
        let probed = OccupancyGrid::build(&field, UNIT, 8, Mode::Density, 0.5).unwrap();
        assert_eq!(probed.occupied_cells(), 0, "the probes see the shell");
        let grid = OccupancyGrid::from_bounds(&thin_shell_bounds(), UNIT, 8, Mode::Density, 0.5).unwrap();
        // Every point of the shell lies in an occupied cell ...
        let mut rng = crate::Rng::new(3);
        for _ in 0..20_000 {
            let d = [0; 3].map(|_| rng.next_f32() * 2.0 - 1.0);
            let norm = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            if norm > 1e-3 {
                let p = d.map(|x| x / norm * (0.6 + 0.009 * (rng.next_f32() - 0.5)));
                assert!(grid.occupied(p), "{p:?} on the shell is in an empty cell");
            }
        }
        // ... and the field is zero at every point of an empty cell (no cell is occupied for nothing here:
        // the bounds are exact for a shell, so the cells left empty are those it does not cross).
        for _ in 0..20_000 {
            let p = [0; 3].map(|_| rng.next_f32() * 2.0 - 1.0);
            if !grid.occupied(p) {
                assert_eq!(thin_shell(&p), 0.0, "{p:?}");
            }
        }
        assert!(grid.occupied_cells() > 0 && grid.occupied_cells() < 8 * 8 * 8);
        assert_eq!(
            grid.occupied_cells(),
            8 * 8 * 8 - (0..512).filter(|&i| !shell_crosses(i)).count()
        );
    }

    /// Whether the shell of [`thin_shell`] crosses cell i of the 8³ grid over [-1, 1]³.
    fn shell_crosses(i: usize) -> bool {
        let c = [i % 8, i / 8 % 8, i / 64].map(|k| -1.0 + 0.25 * k as f32);
        let mut bound = [0.0f32; 2];
        let corners: Vec<f32> = c.iter().chain(&c.map(|x| x + 0.25)).copied().collect();
        let inputs: Vec<&[f32]> = corners.chunks(1).collect();
        let (lower, upper) = bound.split_at_mut(1);
        thin_shell_bounds().eval(1, &inputs, &mut [lower, upper]);
        bound[1] > 0.5
    }

    #[test]
    fn bad_arguments_are_errors() {
        let f = ClosureFn::new(3, 4, |_, out| out.fill(0.0));
        assert!(OccupancyGrid::build(&f, ([0.0; 3], [1.0, 0.0, 1.0]), 4, Mode::Opacity, 0.1).is_err());
        assert!(OccupancyGrid::build(&f, UNIT, 0, Mode::Opacity, 0.1).is_err());
        assert!(OccupancyGrid::build(&f, UNIT, MAX_RESOLUTION + 1, Mode::Opacity, 0.1).is_err());
        assert!(OccupancyGrid::build(&f, UNIT, 4, Mode::Opacity, 1.0).is_err());
        assert!(OccupancyGrid::build(&f, UNIT, 4, Mode::Density, f32::NAN).is_err());
        let g = ClosureFn::new(2, 4, |_, out| out.fill(0.0));
        assert!(OccupancyGrid::build(&g, UNIT, 4, Mode::Opacity, 0.1).is_err());
        assert!(OccupancyGrid::from_bounds(&f, UNIT, 4, Mode::Opacity, 0.1).is_err());
        let b = thin_shell_bounds();
        assert!(OccupancyGrid::from_bounds(&b, UNIT, 0, Mode::Opacity, 0.1).is_err());
        assert!(OccupancyGrid::from_bounds(&b, UNIT, 4, Mode::Opacity, 1.0).is_err());
    }
}
