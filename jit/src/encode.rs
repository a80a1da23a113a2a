//! Grid encodings on tiles of points: the trilinear read of every level (forward, or differentiated
//! along some axes) into output columns, and the scatter of cotangents into the table's gradient.
//!
//! The layout, the hash and the weights are those of [`nerfjit_dsl::grid`] (the interpreter's oracle);
//! here they run in f32 over the columns of a tile, with the levels' layouts computed once per kernel.

use nerfjit_dsl::grid::Level;
use nerfjit_dsl::ir::{GridRead, GridSpec};

/// A grid read or scatter prepared for tiles.
pub(crate) struct GridPlan {
    levels: Vec<Level>,
    table: usize,
    features: usize,
    deriv: u8,
    /// One past the table's last param.
    end: usize,
    /// Twice the half extent's inverse: maps p + extent into [0, 1].
    inv_size: f32,
    extent: f32,
}

/// The 8 corners of one point's cell in one level: entries and weights.
struct Corners {
    entry: [usize; 8],
    weight: [f32; 8],
}

impl GridPlan {
    /// The plan of a read (or scatter) of `read`'s grid.
    pub(crate) fn new(read: &GridRead) -> GridPlan {
        let spec: GridSpec = read.spec;
        let extent = f32::from_bits(spec.extent);
        GridPlan {
            levels: spec.layout(),
            table: spec.table as usize,
            features: spec.features as usize,
            deriv: read.deriv,
            end: spec.table as usize + spec.n_params() as usize,
            inv_size: 1.0 / (2.0 * extent),
            extent,
        }
    }

    /// One past the last param the grid touches.
    pub(crate) fn params_end(&self) -> usize {
        self.end
    }

    #[inline(always)]
    fn corners(&self, level: &Level, p: [f32; 3]) -> Corners {
        let res = level.res as f32;
        let mut lower = [0u32; 3];
        // Per axis: the factors of the lower and upper corner.
        let mut factor = [[0.0f32; 2]; 3];
        for a in 0..3 {
            let unit = (p[a] + self.extent) * self.inv_size;
            let inside = unit > 0.0 && unit < 1.0;
            // max(0) also maps NaN to 0, so that no point indexes outside the level.
            let u = unit.clamp(0.0, 1.0).max(0.0) * res;
            let c = (u as u32).min(level.res.saturating_sub(1));
            let f = u - c as f32;
            lower[a] = c;
            factor[a] = if self.deriv >> a & 1 == 1 {
                let s = if inside { res * self.inv_size } else { 0.0 };
                [-s, s]
            } else {
                [1.0 - f, f]
            };
        }
        let mut corners = Corners {
            entry: [0; 8],
            weight: [0.0; 8],
        };
        for k in 0..8u32 {
            let bit = |a: u32| (k >> a & 1) as usize;
            let v = [0, 1, 2].map(|a| lower[a] + (k >> a & 1));
            corners.entry[k as usize] = self.table + level.entry(v) as usize * self.features;
            corners.weight[k as usize] = factor[0][bit(0)] * factor[1][bit(1)] * factor[2][bit(2)];
        }
        corners
    }

    /// `out[l·features + f][t] = Σ_corners w · table[corner·features + f]` for t < count.
    ///
    /// Levels are the outer loop, so that a level's part of the table stays in cache across the tile.
    ///
    /// # Safety
    /// The pointers of `p` must address `count` readable floats and those of `out` (levels × features of
    /// them) `count` writable floats.
    pub(crate) unsafe fn read(&self, p: [*const f32; 3], out: &[*mut f32], params: &[f32], count: usize) {
        assert!(params.len() >= self.end, "the grid's table is outside the params");
        assert_eq!(out.len(), self.levels.len() * self.features);
        for (l, level) in self.levels.iter().enumerate() {
            for t in 0..count {
                // SAFETY: t < count, as the caller guarantees for every column.
                let point = p.map(|c| unsafe { *c.add(t) });
                let corners = self.corners(level, point);
                for f in 0..self.features {
                    let mut sum = 0.0;
                    for k in 0..8 {
                        // SAFETY: a corner's entry is below its level's end (Level::entry masks or
                        // indexes within the level), so entry + f < self.end ≤ params.len().
                        sum += corners.weight[k] * unsafe { params.get_unchecked(corners.entry[k] + f) };
                    }
                    // SAFETY: as above for the columns.
                    unsafe { *out[l * self.features + f].add(t) = sum };
                }
            }
        }
    }

    /// `grads[corner·features + f] += w · cot[l·features + f][t]` for t < count.
    ///
    /// # Safety
    /// The pointers of `p` and `cot` must address `count` readable floats.
    pub(crate) unsafe fn scatter(
        &self,
        p: [*const f32; 3],
        cot: &[*const f32],
        grads: &mut [f32],
        count: usize,
    ) {
        assert!(
            grads.len() >= self.end,
            "the grid's table is outside the gradients"
        );
        assert_eq!(cot.len(), self.levels.len() * self.features);
        for (l, level) in self.levels.iter().enumerate() {
            for t in 0..count {
                // SAFETY: t < count, as the caller guarantees for every column.
                let point = p.map(|c| unsafe { *c.add(t) });
                let corners = self.corners(level, point);
                for f in 0..self.features {
                    // SAFETY: as above.
                    let c = unsafe { *cot[l * self.features + f].add(t) };
                    if c == 0.0 {
                        continue;
                    }
                    for k in 0..8 {
                        // SAFETY: entry + f < self.end ≤ grads.len(), as in `read`.
                        unsafe { *grads.get_unchecked_mut(corners.entry[k] + f) += corners.weight[k] * c };
                    }
                }
            }
        }
    }
}
