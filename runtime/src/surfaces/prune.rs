//! Which blocks of a marching-cubes grid can hold the level set, from bounds of the field over boxes: the
//! octree pass that lets [`crate::surfaces::marching::extract_pruned`] evaluate the field near the surface only.
//!
//! The grid's cells are grouped in blocks of [`BLOCK`]³ cells. Starting from one box around all of them, each
//! box's bounds (an interval function: 6 inputs, the box's low and high corners, → 2 outputs, the field's
//! lower and upper bound over the box) decide whether it lies wholly above the level, wholly below it, or may
//! cross it; boxes that may cross are split in eight, down to single blocks. One batch of boxes is evaluated
//! per depth, in parallel.
//!
//! A block is decided only when its bounds clear the level by a margin of `1e-4 · (1 + |level| + |bound|)`,
//! far above the f32 rounding of the field and of its bounds, so the field values the block holds have the
//! side its bounds say: it has no triangle, and the mesh of the blocks that remain is the brute-force mesh.

use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::field::BatchFn;

/// Cells per side of a block.
pub const BLOCK: usize = 8;

/// Boxes per call of the bounds function (a parallel task).
const BOXES_PER_TASK: usize = 1024;

/// The most boxes bounded at one depth (about 100 MB with their inputs): where bounds decide too little to
/// keep the octree small, the blocks below stay undecided and are evaluated.
const MAX_FRONTIER: usize = 1 << 21;

/// Where a block's field values lie with respect to the level.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Side {
    /// All at or above the level.
    Above,
    /// All below the level.
    Below,
    /// Undecided: the level set may cross the block.
    Near,
}

/// The blocks of a grid of `n` cells per axis, their sides, and which of them must be evaluated.
pub struct Blocks {
    /// Cells per axis of the grid.
    n: usize,
    /// Blocks per axis.
    count: usize,
    side: Vec<Side>,
    /// Whether the block's points are evaluated: it is [`Side::Near`], or next to one when `dilate` was
    /// asked (normals from differences read the values one point beyond a crossed cell).
    needed: Vec<bool>,
    /// The boxes whose bounds were evaluated.
    pub boxes: usize,
}

/// A range of blocks `[lo, hi)` along each axis.
pub(crate) type Range = [[usize; 2]; 3];

impl Blocks {
    /// Classifies the blocks of a grid of `n` cells per axis whose plane `i` along `axis` lies at
    /// `coord(axis, i)` (increasing in `i`), with `bounds` of the field over boxes.
    pub fn classify(
        bounds: &dyn BatchFn,
        n: usize,
        coord: &(dyn Fn(usize, usize) -> f32 + Sync),
        level: f32,
        dilate: bool,
    ) -> Result<Blocks> {
        if bounds.n_inputs() != 6 || bounds.n_outputs() != 2 {
            return Err(Error::Invalid(format!(
                "the bounds function must map 6 inputs (a box's corners) to 2 (a lower and an upper bound), not {} to {}",
                bounds.n_inputs(),
                bounds.n_outputs()
            )));
        }
        let count = n.div_ceil(BLOCK);
        let mut blocks = Blocks {
            n,
            count,
            side: vec![Side::Near; count * count * count],
            needed: Vec::new(),
            boxes: 0,
        };
        let mut frontier: Vec<Range> = vec![[[0, count]; 3]];
        while !frontier.is_empty() {
            let sides = frontier_sides(
                bounds,
                &frontier,
                |axis, b| coord(axis, (b * BLOCK).min(n)),
                level,
            );
            blocks.boxes += frontier.len();
            let mut next = Vec::new();
            for (range, side) in frontier.iter().zip(sides) {
                if side != Side::Near {
                    blocks.fill(range, side);
                } else if range.iter().any(|[lo, hi]| hi - lo > 1) {
                    next.extend(split(range));
                }
            }
            if next.len() > MAX_FRONTIER {
                break;
            }
            frontier = next;
        }
        blocks.needed = blocks.side.iter().map(|&s| s == Side::Near).collect();
        if dilate {
            blocks.dilate();
        }
        Ok(blocks)
    }

    fn index(&self, [i, j, k]: [usize; 3]) -> usize {
        (k * self.count + j) * self.count + i
    }

    fn fill(&mut self, range: &Range, side: Side) {
        for k in range[2][0]..range[2][1] {
            for j in range[1][0]..range[1][1] {
                for i in range[0][0]..range[0][1] {
                    let b = self.index([i, j, k]);
                    self.side[b] = side;
                }
            }
        }
    }

    /// Marks the neighbours (26-connected) of every [`Side::Near`] block as needed.
    fn dilate(&mut self) {
        let c = self.count as isize;
        let near: Vec<[usize; 3]> = (0..self.side.len())
            .filter(|&b| self.side[b] == Side::Near)
            .map(|b| {
                [
                    b % self.count,
                    b / self.count % self.count,
                    b / (self.count * self.count),
                ]
            })
            .collect();
        for [i, j, k] in near {
            for dk in -1..=1 {
                for dj in -1..=1 {
                    for di in -1..=1 {
                        let q = [i as isize + di, j as isize + dj, k as isize + dk];
                        if q.iter().all(|&x| (0..c).contains(&x)) {
                            let b = self.index(q.map(|x| x as usize));
                            self.needed[b] = true;
                        }
                    }
                }
            }
        }
    }

    /// Whether block `b` (indices along x, y, z) is evaluated.
    pub fn is_needed(&self, b: [usize; 3]) -> bool {
        self.needed[self.index(b)]
    }

    /// The number of blocks that are evaluated.
    pub fn needed_count(&self) -> usize {
        self.needed.iter().filter(|&&x| x).count()
    }

    /// The blocks along one axis that contain grid plane `i`: the one it starts (or, at the far end, ends),
    /// first, and the one it ends when it is a block boundary inside the grid.
    fn containing(&self, i: usize) -> (usize, Option<usize>) {
        let own = (i / BLOCK).min(self.count - 1);
        let before = (i.is_multiple_of(BLOCK) && i > 0 && i < self.n).then(|| i / BLOCK - 1);
        (own, before)
    }

    /// For z-slice `k` of the grid's points (point (i, j) at `j·(n + 1) + i` of `values`): gives every
    /// point the value `fill[0]` or `fill[1]` of its block's side (below or above the level) and lists in
    /// `runs`, in row order, the points that needed blocks hold (those to evaluate, whose fill is
    /// meaningless).
    pub fn slice(&self, k: usize, fill: [f32; 2], values: &mut [f32], runs: &mut Vec<Run>) {
        let (c, row) = (self.count, self.n + 1);
        let (own_k, before_k) = self.containing(k);
        let needed = |i: usize, j: usize| {
            self.needed[self.index([i, j, own_k])]
                || before_k.is_some_and(|kb| self.needed[self.index([i, j, kb])])
        };
        let mut row_needed = vec![false; c];
        for j in 0..row {
            let (own_j, before_j) = self.containing(j);
            let points = &mut values[j * row..(j + 1) * row];
            for (i, r) in row_needed.iter_mut().enumerate() {
                *r = needed(i, own_j) || before_j.is_some_and(|jb| needed(i, jb));
                let side = self.side[self.index([i, own_j, own_k])];
                let value = fill[usize::from(side != Side::Below)];
                points[i * BLOCK..((i + 1) * BLOCK).min(self.n) + 1].fill(value);
            }
            // Maximal runs of needed blocks, as runs of points from the first block's first plane
            // to the last block's last.
            let mut i = 0;
            while i < c {
                if !row_needed[i] {
                    i += 1;
                    continue;
                }
                let first = i;
                while i < c && row_needed[i] {
                    i += 1;
                }
                runs.push(Run {
                    row: j,
                    start: first * BLOCK,
                    end: (i * BLOCK).min(self.n),
                });
            }
        }
    }
}

/// A run of grid points in one row of a z-slice: points (i, `row`) for i in `start..=end`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Run {
    /// The row: j.
    pub row: usize,
    /// The first i.
    pub start: usize,
    /// The last i (included).
    pub end: usize,
}

/// The eight (or fewer, where a side is one block long) halves of a range.
pub(crate) fn split(range: &Range) -> Vec<Range> {
    let halves = range.map(|[lo, hi]| {
        let mid = lo + (hi - lo).div_ceil(2);
        if hi - lo > 1 {
            vec![[lo, mid], [mid, hi]]
        } else {
            vec![[lo, hi]]
        }
    });
    let mut out = Vec::with_capacity(8);
    for &z in &halves[2] {
        for &y in &halves[1] {
            for &x in &halves[0] {
                out.push([x, y, z]);
            }
        }
    }
    out
}

/// The side of each range's box, its corners at `corner(axis, block index)`.
fn frontier_sides(
    bounds: &dyn BatchFn,
    frontier: &[Range],
    corner: impl Fn(usize, usize) -> f32 + Sync,
    level: f32,
) -> Vec<Side> {
    frontier
        .par_chunks(BOXES_PER_TASK)
        .flat_map_iter(|ranges| {
            let m = ranges.len();
            let mut inputs = vec![vec![0f32; m]; 6];
            for (b, range) in ranges.iter().enumerate() {
                for axis in 0..3 {
                    inputs[axis][b] = corner(axis, range[axis][0]);
                    inputs[3 + axis][b] = corner(axis, range[axis][1]);
                }
            }
            let (mut lo, mut hi) = (vec![0f32; m], vec![0f32; m]);
            let refs: Vec<&[f32]> = inputs.iter().map(Vec::as_slice).collect();
            bounds.eval(m, &refs, &mut [&mut lo, &mut hi]);
            lo.into_iter().zip(hi).map(move |(l, h)| side(l, h, level))
        })
        .collect()
}

/// The side of a box whose field values lie in `[lo, hi]`, with the rounding margin.
fn side(lo: f32, hi: f32, level: f32) -> Side {
    let margin = 1e-4 * (1.0 + level.abs() + lo.abs().max(hi.abs()));
    if lo > level + margin {
        Side::Above
    } else if hi < level - margin {
        Side::Below
    } else {
        Side::Near
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::field::ClosureFn;

    /// Exact bounds of the distance to a sphere of radius `r` at the origin over a box.
    pub(crate) fn sphere_bounds(r: f32) -> impl BatchFn {
        ClosureFn::new(6, 2, move |x: &[f32], out: &mut [f32]| {
            let (mut near, mut far) = (0.0f32, 0.0f32);
            for a in 0..3 {
                let (lo, hi) = (x[a], x[3 + a]);
                let n = if lo > 0.0 {
                    lo
                } else if hi < 0.0 {
                    -hi
                } else {
                    0.0
                };
                near += n * n;
                far += lo.abs().max(hi.abs()).powi(2);
            }
            out[0] = near.sqrt() - r;
            out[1] = far.sqrt() - r;
        })
    }

    fn coord(axis: usize, i: usize) -> f32 {
        let _ = axis;
        -1.0 + 2.0 * i as f32 / 40.0
    }

    #[test]
    fn blocks_far_from_a_sphere_are_decided_and_those_it_crosses_are_not() {
        let blocks = Blocks::classify(&sphere_bounds(0.5), 40, &coord, 0.0, false).unwrap();
        assert_eq!(blocks.count, 5);
        // The corner block [0.6, 1]³ lies outside, the centre block [−0.2, 0.2]³ inside, and the one beside
        // it, from x = 0.2 to 0.6, holds the surface.
        assert_eq!(blocks.side[blocks.index([4, 4, 4])], Side::Above);
        assert_eq!(blocks.side[blocks.index([2, 2, 2])], Side::Below);
        assert_eq!(blocks.side[blocks.index([3, 2, 2])], Side::Near);
        assert!(blocks.needed_count() < 125 && blocks.needed_count() > 0);
        // Fewer boxes than a full octree's 1 + 8 + 64 + 125.
        assert!(blocks.boxes < 1 + 8 + 64 + 125, "{} boxes", blocks.boxes);
    }

    #[test]
    fn dilation_adds_the_neighbours() {
        let plain = Blocks::classify(&sphere_bounds(0.5), 40, &coord, 0.0, false).unwrap();
        let dilated = Blocks::classify(&sphere_bounds(0.5), 40, &coord, 0.0, true).unwrap();
        assert!(dilated.needed_count() > plain.needed_count());
        assert_eq!(dilated.side, plain.side);
    }

    #[test]
    fn slices_list_exactly_the_points_of_needed_blocks_and_fill_the_others_by_side() {
        let blocks = Blocks::classify(&sphere_bounds(0.5), 40, &coord, 0.0, false).unwrap();
        let row = 41;
        let mut values = vec![0.0; row * row];
        let mut runs = Vec::new();
        for k in 0..row {
            runs.clear();
            blocks.slice(k, [-1.0, 1.0], &mut values, &mut runs);
            let mut listed = vec![false; row * row];
            for r in &runs {
                for i in r.start..=r.end {
                    assert!(!listed[r.row * row + i], "point {i} {} {k} listed twice", r.row);
                    listed[r.row * row + i] = true;
                }
            }
            for j in 0..row {
                for i in 0..row {
                    // The blocks whose closed box holds the point.
                    let around =
                        |x: usize| (0..blocks.count).filter(move |&b| b * BLOCK <= x && x <= (b + 1) * BLOCK);
                    let (mut want, mut sides) = (false, Vec::new());
                    for kb in around(k) {
                        for jb in around(j) {
                            for ib in around(i) {
                                want |= blocks.needed[blocks.index([ib, jb, kb])];
                                sides.push(blocks.side[blocks.index([ib, jb, kb])]);
                            }
                        }
                    }
                    let p = j * row + i;
                    assert_eq!(listed[p], want, "point {i} {j} {k}");
                    if !want {
                        let side = if values[p] > 0.0 { Side::Above } else { Side::Below };
                        assert!(sides.iter().all(|&s| s == side), "point {i} {j} {k}: {sides:?}");
                    }
                }
            }
        }
    }

    #[test]
    fn a_bounds_function_of_the_wrong_shape_is_an_error() {
        let wrong = ClosureFn::new(3, 1, |_: &[f32], out: &mut [f32]| out[0] = 0.0);
        let message = Blocks::classify(&wrong, 8, &coord, 0.0, false)
            .err()
            .unwrap()
            .to_string();
        assert!(message.contains("6 inputs"), "{message}");
    }
}
