//! A ray's walk through an occupancy grid: the interval where it meets the grid, the stretch that may
//! hold occupied cells, and the next occupied sample along it (stepping over empty coarse cells).

use std::ops::Range;

use super::{bit_of, contract, is_set, ndc, GridSpace, OccupancyGrid, BLOCK, COARSE_LEVELS};

/// How far inside an empty coarse cell, in cells, the walk stops stepping over samples, so that a
/// rounding of a sample's point cannot carry it into a neighbouring cell unlooked.
const SKIP_MARGIN: f32 = 1e-2;

impl OccupancyGrid {
    /// Whether block (x, y, z) is marked (see `blocks`).
    fn block(&self, [x, y, z]: [i32; 3]) -> bool {
        let n = self.blocks_per_axis();
        let b = x as usize + n * (y as usize + n * z as usize);
        is_set(&self.blocks, b)
    }

    /// The stretch [a, b] of depths within the ray's interval `(t0, t1)` in the box
    /// ([`OccupancyGrid::ray_interval`]) where the ray `o + t·d` may meet an occupied cell: from where it
    /// enters the first marked block of [`BLOCK`]³ cells it crosses to where it leaves the last, widened
    /// by a cell's diagonal; a < b fails if it crosses none. Every depth t of the interval outside the
    /// stretch has `occupied(o + t·d)` false (the blocks are marked with a cell's dilation, so a rounding
    /// of the walk cannot lose a cell). A grid in another space than the scene's, where a ray's depths are
    /// not those of a straight line through the cells, gives the interval unchanged.
    pub(crate) fn occupied_stretch(&self, o: [f32; 3], d: [f32; 3], (t0, t1): (f32, f32)) -> (f32, f32) {
        // A miss (or NaN) stays one; a warped grid has no straight rays to walk.
        if t0.partial_cmp(&t1).is_none_or(|order| order.is_gt()) || self.space != GridSpace::Scene {
            return (t0, t1);
        }
        // From the near end to the first marked block, then from the far end back to the last, so
        // that neither walk crosses what lies between them.
        let (first, last) = match self.first_marked_block(o, d, (t0, t1)) {
            Some(first) => {
                let back = self.first_marked_block(o, d.map(|v| -v), (-t1, -first));
                (first, back.map_or(t1, |t| -t))
            }
            None => (f32::INFINITY, f32::NEG_INFINITY),
        };
        let cell = [0, 1, 2].map(|i| 1.0 / self.scale[i]);
        let length = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        let margin = (cell[0] * cell[0] + cell[1] * cell[1] + cell[2] * cell[2]).sqrt() / length;
        (first - margin, last + margin)
    }

    /// Where the ray `o + t·d`, walked from t0 to t1 (t0 ≤ t1), enters the first marked block of
    /// [`BLOCK`]³ cells it crosses (t0 if it starts in one); `None` if it crosses none.
    fn first_marked_block(&self, o: [f32; 3], d: [f32; 3], (t0, t1): (f32, f32)) -> Option<f32> {
        let n = self.blocks_per_axis() as i32;
        // Blocks per unit length along each axis (the last block may reach past the box: that is empty).
        let density = self.scale.map(|s| s / BLOCK as f32);
        let at = |i: usize, t: f32| (o[i] + d[i] * t - self.lo[i]) * density[i];
        let mut block = [0, 1, 2].map(|i| (at(i, t0).floor() as i32).clamp(0, n - 1));
        let step = d.map(|d| {
            if d > 0.0 {
                1
            } else if d < 0.0 {
                -1
            } else {
                0
            }
        });
        // Where the ray crosses the next block side along each axis, and the depth between two sides.
        let side = |i: usize, b: i32| {
            let plane = self.lo[i] + (b + i32::from(step[i] > 0)) as f32 / density[i];
            if step[i] == 0 {
                f32::INFINITY
            } else {
                (plane - o[i]) / d[i]
            }
        };
        let mut next = [0, 1, 2].map(|i| side(i, block[i]));
        let gap = [0, 1, 2].map(|i| (1.0 / (density[i] * d[i])).abs());
        let mut t = t0;
        for _ in 0..3 * n + 3 {
            if self.block(block) {
                return Some(t);
            }
            let axis = (0..3).fold(0, |best, i| if next[i] < next[best] { i } else { best });
            let leave = next[axis].min(t1);
            block[axis] += step[axis];
            if leave >= t1 || !(0..n).contains(&block[axis]) {
                return None;
            }
            t = leave;
            next[axis] += gap[axis];
        }
        None
    }

    /// Walks the samples `samples` of the ray `o + t·d` (sample j at depth `depth(j)`) and writes the
    /// first of them in occupied cells, at most `index.len()`: their points to `x`, `y`, `z` and their
    /// sample indices to `index`. Returns how many it wrote and the sample after the last one it
    /// looked at (the start of the samples left).
    pub(crate) fn next_occupied(
        &self,
        (o, d): ([f32; 3], [f32; 3]),
        samples: Range<usize>,
        depth: impl Fn(usize) -> f32,
        [x, y, z]: [&mut [f32]; 3],
        index: &mut [u32],
    ) -> (usize, usize) {
        // The space's branch outside the walk.
        match self.space {
            GridSpace::Scene => {
                // The ray in cell coordinates (cell c spans [c, c + 1) along each axis), for stepping
                // over empty coarse cells: rays are straight through the cells in the scene's space.
                let start = [0, 1, 2].map(|i| (o[i] - self.lo[i]) * self.scale[i]);
                let inverse = [0, 1, 2].map(|i| 1.0 / (d[i] * self.scale[i]));
                self.walk(
                    (o, d),
                    samples,
                    depth,
                    [x, y, z],
                    index,
                    |p| self.box_bit_index(p[0], p[1], p[2]),
                    |p, t| Some(self.empty_until(p, t, (start, inverse))),
                )
            }
            GridSpace::Contracted => self.walk_warped((o, d), samples, depth, [x, y, z], index, contract),
            GridSpace::Ndc => self.walk_warped((o, d), samples, depth, [x, y, z], index, ndc),
        }
    }

    /// [`OccupancyGrid::walk`] in a space whose box coordinates `warp` gives (no straight rays through the
    /// cells: nothing is stepped over).
    #[inline(always)]
    fn walk_warped(
        &self,
        ray: ([f32; 3], [f32; 3]),
        samples: Range<usize>,
        depth: impl Fn(usize) -> f32,
        points: [&mut [f32]; 3],
        index: &mut [u32],
        warp: impl Fn([f32; 3]) -> [f32; 3],
    ) -> (usize, usize) {
        let bit_index = |p| {
            let [x, y, z] = warp(p);
            self.box_bit_index(x, y, z)
        };
        self.walk(ray, samples, depth, points, index, bit_index, |_, _| None)
    }

    /// [`OccupancyGrid::next_occupied`] with each point's bit from `bit_index`; after a sample at point
    /// p and depth t in an empty cell, the samples of depths from t up to `empty_until(p, t)` (if it
    /// gives one: the depth to which the ray stays in empty cells, [`OccupancyGrid::empty_until`]) are
    /// stepped over without looking them up.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn walk(
        &self,
        (o, d): ([f32; 3], [f32; 3]),
        samples: Range<usize>,
        depth: impl Fn(usize) -> f32,
        [x, y, z]: [&mut [f32]; 3],
        index: &mut [u32],
        bit_index: impl Fn([f32; 3]) -> u32,
        empty_until: impl Fn([f32; 3], f32) -> Option<f32>,
    ) -> (usize, usize) {
        let (want, mut found, mut j) = (index.len(), 0, samples.start);
        while j < samples.end && found < want {
            let t = depth(j);
            let p = [o[0] + d[0] * t, o[1] + d[1] * t, o[2] + d[2] * t];
            // Written at `found` either way (there is room: found < want), kept only if occupied.
            (x[found], y[found], z[found]) = (p[0], p[1], p[2]);
            index[found] = j as u32;
            let occupied = self.bit(bit_index(p));
            found += usize::from(occupied);
            j += 1;
            let skip_to = if occupied { None } else { empty_until(p, t) };
            if let Some(until) = skip_to {
                // Only samples between this one and where the empty cells end: all in them.
                while j < samples.end && (t..until).contains(&depth(j)) {
                    j += 1;
                }
            }
        }
        (found, j)
    }

    /// The depth, a little short of where the ray leaves it, up to which the ray that passes point `p`
    /// (inside the box) at depth `t` stays in the largest empty cube of [`COARSE_LEVELS`]' cells around
    /// `p`; `t` or less if no coarse cell around `p` is empty or `p` is outside the box (or NaN). The
    /// ray is given in cell coordinates: its point at depth 0 and the inverse of its direction.
    #[inline(always)]
    fn empty_until(&self, p: [f32; 3], t: f32, (start, inverse): ([f32; 3], [f32; 3])) -> f32 {
        let f = [0, 1, 2].map(|i| (p[i] - self.lo[i]) * self.scale[i]);
        let top = self.resolution as f32;
        if !f.iter().all(|&f| (0.0..top).contains(&f)) {
            return t;
        }
        let cell = f.map(|f| f as u32);
        for k in (1..=COARSE_LEVELS).rev() {
            let cube = cell.map(|c| c >> k);
            let at = bit_of(self.shift.saturating_sub(k as u32), cube) as usize;
            if !is_set(&self.coarse[k - 1], at) {
                // Where the ray meets the far side of the cube along each axis, the margin inside it.
                let size = (1u32 << k) as f32;
                let leave = |i: usize| {
                    let side = (cube[i] << k) as f32;
                    let plane = if inverse[i] > 0.0 {
                        side + size - SKIP_MARGIN
                    } else {
                        side + SKIP_MARGIN
                    };
                    (plane - start[i]) * inverse[i]
                };
                // A NaN (a zero direction on a side) drops out of the minimum.
                return leave(0).min(leave(1)).min(leave(2));
            }
        }
        t
    }

    /// The depths [t0, t1] (t0 may be negative) where the ray `o + t·d` is inside the bounds
    /// widened by a tiny margin, or `None` if it misses them: every point of the ray that
    /// [`OccupancyGrid::occupied`] may accept is in that interval (the whole ray for a grid in another
    /// space than the scene's).
    pub fn ray_interval(&self, o: [f32; 3], d: [f32; 3]) -> Option<(f32, f32)> {
        let (t0, t1) = self.interval(o, d);
        (t0 <= t1).then_some((t0, t1))
    }

    /// [`OccupancyGrid::ray_interval`] of the rays from (ox, oy, oz)[k] in directions (dx, dy, dz)[k]
    /// to (t0, t1)[k], with t0 > t1 (or NaN) for rays that miss, for k below the length of `ox`.
    pub(crate) fn ray_intervals(
        &self,
        [ox, oy, oz]: [&[f32]; 3],
        [dx, dy, dz]: [&[f32]; 3],
        t0: &mut [f32],
        t1: &mut [f32],
    ) {
        let n = ox.len();
        let (oy, oz, dx, dy, dz) = (&oy[..n], &oz[..n], &dx[..n], &dy[..n], &dz[..n]);
        let (t0, t1) = (&mut t0[..n], &mut t1[..n]);
        for k in 0..n {
            (t0[k], t1[k]) = self.interval([ox[k], oy[k], oz[k]], [dx[k], dy[k], dz[k]]);
        }
    }

    /// The slab test, without branches so that loops over rays vectorize: a zero direction
    /// component gives infinite slab depths, of the same sign (a miss) if `o` is outside
    /// the slab.
    #[inline(always)]
    fn interval(&self, o: [f32; 3], d: [f32; 3]) -> (f32, f32) {
        let (mut t0, mut t1) = (f32::NEG_INFINITY, f32::INFINITY);
        if self.space != GridSpace::Scene {
            return (t0, t1);
        }
        for i in 0..3 {
            let inv = 1.0 / d[i];
            let (a, b) = ((self.outer[0][i] - o[i]) * inv, (self.outer[1][i] - o[i]) * inv);
            let (near, far) = if a < b { (a, b) } else { (b, a) };
            t0 = if near > t0 { near } else { t0 };
            t1 = if far < t1 { far } else { t1 };
        }
        (t0, t1)
    }
}
