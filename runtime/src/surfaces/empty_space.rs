//! Empty space skipping for the sphere tracer. The rays of a tile are grouped by pixel columns; the
//! interval bounds of the SDF over the box that encloses a stretch of depths of every ray of a group
//! prove, where their lower bound is above the hit threshold, that no ray of the group hits in that
//! stretch, and the group's rays start marching after it.
//!
//! Per group, from its nearest start depth: a stretch of 1/[`FIRST`] of the group's depth range is
//! bounded; a proven stretch is skipped and the next one is twice as long, a stretch that is not proven
//! is halved, until a stretch shorter than 1/[`FINEST`] of the range fails, the range is used up (every
//! ray of the group misses) or [`MAX_BOUNDS`] bounds were taken. The groups of a tile are bounded
//! together, one batch of boxes per round. The constants are those that traced the city of `nerfjit
//! bench large` fastest among a few tried (2026-11-25: 0.62 of the time without skipping).

use glam::Vec3;

use crate::field::BatchFn;

/// Pixel columns of a group of rays (its rows are those of the tile).
pub(crate) const GROUP_COLUMNS: usize = 16;
/// The first stretch of a group is 1/FIRST of its depth range.
const FIRST: f32 = 4.0;
/// A group stops at a failed stretch shorter than 1/FINEST of its depth range.
const FINEST: f32 = 64.0;
/// Bounds taken per group at most.
const MAX_BOUNDS: u32 = 12;
/// Relative margin of a lower bound over the hit threshold, for the f32 rounding of the bounds.
const BOUND_MARGIN: f32 = 1e-4;
/// Relative padding of a box, for the rounding of the points the tracer computes in it.
const POINT_MARGIN: f32 = 1e-6;

/// The rays of a tile, as [`advance`] reads them.
pub(crate) struct GroupedRays<'a> {
    /// The origin of every ray.
    pub origin: Vec3,
    /// The unit direction of each ray.
    pub direction: [&'a [f32]; 3],
    /// Where each ray ends.
    pub t_end: &'a [f32],
    /// The group of each ray, below `groups`.
    pub group: &'a [u32],
    /// The number of groups.
    pub groups: usize,
}

/// One group's search.
#[derive(Clone, Copy)]
struct Search {
    d_min: Vec3,
    d_max: Vec3,
    /// Depth up to which the group is proven empty (infinite: all of it).
    start: f32,
    /// The group's farthest ray end.
    stop: f32,
    /// The length of the next stretch.
    stride: f32,
    /// The shortest stretch worth bounding.
    finest: f32,
    bounds_taken: u32,
}

impl Search {
    fn empty() -> Search {
        Search {
            d_min: Vec3::INFINITY,
            d_max: Vec3::NEG_INFINITY,
            start: f32::INFINITY,
            stop: f32::NEG_INFINITY,
            stride: 0.0,
            finest: 0.0,
            bounds_taken: 0,
        }
    }

    fn active(&self) -> bool {
        self.start < self.stop
            && self.stride > 0.0
            && self.stride >= self.finest
            && self.bounds_taken < MAX_BOUNDS
    }

    /// The box enclosing the points of every ray of the group from `start` to `start + stride`.
    fn stretch(&self, origin: Vec3) -> (Vec3, Vec3) {
        let (ta, tb) = (self.start, (self.start + self.stride).min(self.stop));
        let low = (self.d_min * ta).min(self.d_min * tb) + origin;
        let high = (self.d_max * ta).max(self.d_max * tb) + origin;
        let pad = (origin.abs() + Vec3::splat(tb)) * POINT_MARGIN;
        (low - pad, high + pad)
    }

    /// Takes the lower bound of the SDF over the current stretch. Once the whole range is proven
    /// empty, the start is infinite: every ray of the group misses.
    fn record(&mut self, lower: f32, eps: f32) {
        self.bounds_taken += 1;
        if lower - BOUND_MARGIN * lower.abs() > eps {
            self.start += self.stride;
            if self.start >= self.stop {
                self.start = f32::INFINITY;
            }
            self.stride *= 2.0;
        } else {
            self.stride *= 0.5;
        }
    }
}

/// Per-worker buffers of [`advance`].
#[derive(Default)]
pub(crate) struct Scratch {
    searches: Vec<Search>,
    active: Vec<usize>,
    boxes: [Vec<f32>; 6],
    bounds: [Vec<f32>; 2],
}

/// Raises each ray's start depth `t[k]` to where its group's search stopped: `bounds` (a box's low and
/// high corners → a lower and an upper bound of the SDF) places the SDF above `eps` at every point of the
/// ray between them, so sphere tracing from there hits the same surface. A ray may end up starting past
/// its end (at infinity where its whole group is proven empty): it misses.
pub(crate) fn advance(bounds: &dyn BatchFn, rays: &GroupedRays, eps: f32, t: &mut [f32], s: &mut Scratch) {
    s.searches.clear();
    s.searches.resize(rays.groups, Search::empty());
    for (k, &group) in rays.group.iter().enumerate() {
        let search = &mut s.searches[group as usize];
        let d = Vec3::new(rays.direction[0][k], rays.direction[1][k], rays.direction[2][k]);
        search.d_min = search.d_min.min(d);
        search.d_max = search.d_max.max(d);
        search.start = search.start.min(t[k]);
        search.stop = search.stop.max(rays.t_end[k]);
    }
    for search in &mut s.searches {
        let range = search.stop - search.start;
        // Unbounded rays (an infinite far plane) have no range to divide.
        if range.is_finite() {
            (search.stride, search.finest) = (range / FIRST, range / FINEST);
        }
    }
    loop {
        s.active.clear();
        s.active
            .extend((0..s.searches.len()).filter(|&g| s.searches[g].active()));
        let n = s.active.len();
        if n == 0 {
            break;
        }
        for column in s.boxes.iter_mut().chain(&mut s.bounds) {
            column.resize(n, 0.0);
        }
        for (i, &g) in s.active.iter().enumerate() {
            let (low, high) = s.searches[g].stretch(rays.origin);
            for axis in 0..3 {
                s.boxes[axis][i] = low[axis];
                s.boxes[axis + 3][i] = high[axis];
            }
        }
        let inputs: [&[f32]; 6] = std::array::from_fn(|c| &s.boxes[c][..n]);
        let [lower, upper] = &mut s.bounds;
        bounds.eval(n, &inputs, &mut [&mut lower[..n], &mut upper[..n]]);
        for (i, &g) in s.active.iter().enumerate() {
            s.searches[g].record(lower[i], eps);
        }
    }
    for (t, &group) in t.iter_mut().zip(rays.group) {
        let start = s.searches[group as usize].start;
        *t = t.max(start);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::ClosureFn;

    /// Exact bounds of the unit sphere's SDF over a box (6 inputs → 2 outputs).
    fn sphere_bounds() -> ClosureFn<impl Fn(&[f32], &mut [f32]) + Sync> {
        ClosureFn::new(6, 2, |b: &[f32], out: &mut [f32]| {
            let (low, high) = (Vec3::new(b[0], b[1], b[2]), Vec3::new(b[3], b[4], b[5]));
            let nearest = Vec3::ZERO.clamp(low, high);
            let farthest = Vec3::select(low.abs().cmpgt(high.abs()), low, high);
            out[0] = nearest.length() - 1.0;
            out[1] = farthest.length() - 1.0;
        })
    }

    #[test]
    fn rays_start_before_the_sphere_and_rays_that_miss_are_past_their_end() {
        // Four groups of rays from z = -5: at the sphere (x = 0, 0.1), grazing past it (x = 1.5 at
        // depth 5) and two away from it.
        let origin = Vec3::new(0.0, 0.0, -5.0);
        let xs = [0.0f32, 0.02, 0.3, 0.31, 0.6, 0.61, -0.6, -0.61];
        let dirs: Vec<Vec3> = xs.iter().map(|&x| Vec3::new(x, 0.0, 1.0).normalize()).collect();
        let columns: [Vec<f32>; 3] = [0, 1, 2].map(|a| dirs.iter().map(|d| d[a]).collect());
        let t_end = vec![10.0f32; xs.len()];
        let group: Vec<u32> = (0..xs.len() as u32).map(|k| k / 2).collect();
        let rays = GroupedRays {
            origin,
            direction: [&columns[0], &columns[1], &columns[2]],
            t_end: &t_end,
            group: &group,
            groups: 4,
        };
        let mut t = vec![0.0f32; xs.len()];
        advance(&sphere_bounds(), &rays, 1e-3, &mut t, &mut Scratch::default());
        for (k, d) in dirs.iter().enumerate() {
            // The first depth at which the ray comes within 1e-3 of the sphere, if it does.
            let first = (0..100_000)
                .map(|i| i as f32 * 1e-4)
                .find(|&s| (origin + *d * s).length() - 1.0 < 1e-3);
            match first {
                Some(hit) => assert!(
                    t[k] <= hit && t[k] > 0.5 * hit,
                    "ray {k}: start {} hit {hit}",
                    t[k]
                ),
                None => assert!(t[k] > 4.0, "ray {k} misses but starts at {}", t[k]),
            }
        }
        // The rays far from the sphere are proven empty all along.
        assert!(t[4] > t_end[4] && t[7] > t_end[7], "{t:?}");
    }

    #[test]
    fn bounds_that_prove_nothing_leave_the_starts_and_infinite_rays_are_left_alone() {
        let nothing = ClosureFn::new(6, 2, |_: &[f32], out: &mut [f32]| {
            out[0] = f32::NEG_INFINITY;
            out[1] = f32::INFINITY;
        });
        let everything = ClosureFn::new(6, 2, |_: &[f32], out: &mut [f32]| {
            out[0] = 1.0;
            out[1] = 2.0;
        });
        let d = [0.0f32, 0.6];
        let z = [1.0f32, 0.8];
        let group = [0u32, 0];
        let cases: [(&dyn BatchFn, _, _); 2] = [
            (&nothing, [3.0f32, 4.0], [0.5f32, 1.0]),
            (&everything, [f32::INFINITY, 4.0], [0.5, 1.0]),
        ];
        for (bounds, t_end, expected) in cases {
            let rays = GroupedRays {
                origin: Vec3::ZERO,
                direction: [&d, &d, &z],
                t_end: &t_end,
                group: &group,
                groups: 1,
            };
            let mut t = [0.5f32, 1.0];
            advance(bounds, &rays, 1e-3, &mut t, &mut Scratch::default());
            assert_eq!(t, expected);
        }
    }
}
