//! Where a ray's samples lie, as the lanes read them: depths shared by every ray of a batch, or a column
//! of depths per ray.

use super::LAST_DELTA;

/// The depths of one ray's samples, and their δ: the gap to the next depth, [`LAST_DELTA`] for the last.
pub(crate) trait RayDepths: Copy {
    /// Depth `j`.
    fn at(&self, j: usize) -> f32;
    /// The δ of sample `j`.
    fn delta(&self, j: usize) -> f32;
}

/// Depths shared by every ray, with their δ.
#[derive(Debug, Clone, Copy)]
pub(crate) struct SharedDepths<'a> {
    /// The depths.
    pub(crate) t: &'a [f32],
    /// Their δ.
    pub(crate) delta: &'a [f32],
}

impl RayDepths for SharedDepths<'_> {
    #[inline(always)]
    fn at(&self, j: usize) -> f32 {
        self.t[j]
    }

    #[inline(always)]
    fn delta(&self, j: usize) -> f32 {
        self.delta[j]
    }
}

/// The depths of one ray of a sample-major tile: `len` of them at `t[first + j·stride]`.
#[derive(Debug, Clone, Copy)]
pub(crate) struct DepthColumn<'a> {
    /// Where the depths are.
    pub(crate) t: &'a [f32],
    /// The index of the first.
    pub(crate) first: usize,
    /// From one depth to the next.
    pub(crate) stride: usize,
    /// How many.
    pub(crate) len: usize,
}

impl RayDepths for DepthColumn<'_> {
    #[inline(always)]
    fn at(&self, j: usize) -> f32 {
        self.t[self.first + j * self.stride]
    }

    #[inline(always)]
    fn delta(&self, j: usize) -> f32 {
        if j + 1 < self.len {
            self.at(j + 1) - self.at(j)
        } else {
            LAST_DELTA
        }
    }
}

impl DepthColumn<'_> {
    /// The number of depths below `t` (at most `t` if `inclusive`): the partition point of the
    /// sorted depths, by bisection.
    pub(crate) fn count_below(&self, t: f32, inclusive: bool) -> usize {
        let below = |d: f32| d < t || (inclusive && d == t);
        let (mut lo, mut hi) = (0, self.len);
        while lo < hi {
            let mid = (lo + hi) / 2;
            if below(self.at(mid)) {
                lo = mid + 1;
            } else {
                hi = mid;
            }
        }
        lo
    }
}
