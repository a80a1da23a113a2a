//! Fields specialized to regions of a marching-cubes grid: fidget's tape simplification applied to meshing.
//!
//! The grid is cut into regions of whole blocks ([`crate::surfaces::prune::BLOCK`]³ cells), about
//! [`REGIONS_PER_AXIS`] per axis. A [`Specialize`] implementation (the compiler's, which drops the
//! `min`/`max` branches that a box's bounds decide) restricts the field to boxes, down an octree of regions
//! (each restriction starts from its parent's, so the work shrinks with the boxes), and gives for every
//! region that holds blocks to evaluate a field and gradient equal to the originals there. Each grid point
//! is then evaluated by the field of the region it belongs to (the one whose low planes it starts, or the
//! last along an axis), so a point shared by two chunks of the mesher is always evaluated by the same
//! kernel, and each vertex's normal by the gradient of the region that holds it.

use rayon::prelude::*;

use crate::error::Result;
use crate::field::BatchFn;
use crate::surfaces::prune::{split, Blocks, Range, BLOCK};

/// Regions per axis of a grid (fewer where the grid has fewer blocks): more regions decide more branches
/// each, at the cost of more restrictions.
pub const REGIONS_PER_AXIS: usize = 32;

/// A field and its gradient restricted to a box.
pub struct Specialized {
    /// The field (3 inputs → 1 output), equal to the original at every point of the box.
    pub field: Box<dyn BatchFn + Send>,
    /// Its value and gradient (3 inputs → 4 outputs), where normals come from the gradient.
    pub gradient: Option<Box<dyn BatchFn + Send>>,
}

/// A field that can be restricted to boxes.
pub trait Specialize: Sync + Send {
    /// The field restricted to the box `lo ≤ p ≤ hi` (within the box this one is restricted to, if any).
    fn restrict(&self, lo: [f32; 3], hi: [f32; 3]) -> Result<Box<dyn Specialize>>;

    /// The field (and, when `gradient`, its gradient) as restricted, or `None` where that would not be
    /// cheaper to evaluate than the field itself.
    fn fields(&self, gradient: bool) -> Result<Option<Specialized>>;
}

/// The specialized fields of a grid's regions.
pub struct Regions {
    /// Cells per axis of the grid.
    n: usize,
    /// Cells per side of a region (a multiple of [`BLOCK`]).
    size: usize,
    /// Regions per axis.
    count: usize,
    /// Per region (x fastest): its fields, where it holds blocks to evaluate and they specialize.
    fields: Vec<Option<Specialized>>,
    /// Grid point coordinates along each axis: `min`, and the step between planes.
    min: [f32; 3],
    step: [f32; 3],
}

impl Regions {
    /// Specializes the field to each region of the grid of `n` cells per axis (plane `i` along `axis` at
    /// `coord(axis, i)`) that holds a block `blocks` evaluates: down an octree of ranges of regions, one
    /// depth at a time, in parallel.
    pub fn build(
        specialize: &dyn Specialize,
        blocks: &Blocks,
        n: usize,
        coord: &(dyn Fn(usize, usize) -> f32 + Sync),
        gradient: bool,
    ) -> Result<Regions> {
        let block_count = n.div_ceil(BLOCK);
        let blocks_per_region = block_count.div_ceil(REGIONS_PER_AXIS).max(1);
        let size = blocks_per_region * BLOCK;
        let count = n.div_ceil(size);
        let holds_needed = |range: &Range| {
            let blocks_of =
                |[lo, hi]: [usize; 2]| lo * blocks_per_region..(hi * blocks_per_region).min(block_count);
            blocks_of(range[2]).any(|k| {
                blocks_of(range[1]).any(|j| blocks_of(range[0]).any(|i| blocks.is_needed([i, j, k])))
            })
        };
        let restrict = |parent: &dyn Specialize, range: &Range| {
            let lo = std::array::from_fn(|axis| coord(axis, range[axis][0] * size));
            let hi = std::array::from_fn(|axis| coord(axis, (range[axis][1] * size).min(n)));
            parent.restrict(lo, hi)
        };
        let single = |range: &Range| range.iter().all(|[lo, hi]| hi - lo == 1);
        let whole: Range = [[0, count]; 3];
        let mut frontier = vec![(whole, restrict(specialize, &whole)?)];
        let mut leaves = Vec::new();
        while !frontier.is_empty() {
            let (done, open): (Vec<_>, Vec<_>) = frontier.into_iter().partition(|(range, _)| single(range));
            leaves.extend(done);
            frontier = open
                .par_iter()
                .flat_map_iter(|(range, parent)| {
                    split(range)
                        .into_iter()
                        .filter(|child| holds_needed(child))
                        .map(|child| Ok((child, restrict(parent.as_ref(), &child)?)))
                        .collect::<Vec<Result<_>>>()
                })
                .collect::<Result<_>>()?;
        }
        let mut fields: Vec<Option<Specialized>> = (0..count * count * count).map(|_| None).collect();
        let made = leaves
            .par_iter()
            .map(|(range, restricted)| Ok((range.map(|[lo, _]| lo), restricted.fields(gradient)?)))
            .collect::<Result<Vec<_>>>()?;
        for ([i, j, k], specialized) in made {
            fields[(k * count + j) * count + i] = specialized;
        }
        let min = std::array::from_fn(|axis| coord(axis, 0));
        let step = std::array::from_fn(|axis| (coord(axis, n) - coord(axis, 0)) / n as f32);
        Ok(Regions {
            n,
            size,
            count,
            fields,
            min,
            step,
        })
    }

    /// How many regions the grid has.
    pub fn len(&self) -> usize {
        self.fields.len()
    }

    /// Whether the grid has no region (never: a grid has at least one cell).
    pub fn is_empty(&self) -> bool {
        self.fields.is_empty()
    }

    /// How many regions have a specialized field.
    pub fn specialized(&self) -> usize {
        self.fields.iter().filter(|f| f.is_some()).count()
    }

    /// The region of grid point `p`.
    pub fn of_point(&self, p: [usize; 3]) -> usize {
        let r = p.map(|i| (i / self.size).min(self.count - 1));
        (r[2] * self.count + r[1]) * self.count + r[0]
    }

    /// The region of a position inside the grid (a vertex): that of the grid point at or below it.
    pub fn of_position(&self, p: [f32; 3]) -> usize {
        let cell = std::array::from_fn(|axis| {
            let t = ((p[axis] - self.min[axis]) / self.step[axis]).floor();
            (t.max(0.0) as usize).min(self.n)
        });
        self.of_point(cell)
    }

    /// The last grid plane along an axis that belongs to the same region as plane `i`.
    pub fn last_of_region(&self, i: usize) -> usize {
        let r = i / self.size;
        if r + 1 >= self.count {
            self.n
        } else {
            (r + 1) * self.size - 1
        }
    }

    /// The specialized field of region `r`, if it has one.
    pub fn field(&self, r: usize) -> Option<&dyn BatchFn> {
        self.fields[r].as_ref().map(|s| s.field.as_ref() as &dyn BatchFn)
    }

    /// The specialized gradient of region `r`, if it has one.
    pub fn gradient(&self, r: usize) -> Option<&dyn BatchFn> {
        self.fields[r]
            .as_ref()?
            .gradient
            .as_deref()
            .map(|g| g as &dyn BatchFn)
    }
}
