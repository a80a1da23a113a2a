//! Multiresolution grid encodings (instant-ngp's hash grid, and dense voxel grids as its one-level case):
//! the layout of their tables and the trilinear read of one level, shared by the interpreter and the JIT.
//!
//! A grid has `levels` levels. Level l has `resolution(l)` cells per axis, growing geometrically from
//! `base` to `finest`; its (res + 1)³ vertices are stored densely when they fit in 2^`log2_size` entries,
//! and hashed into 2^`log2_size` entries otherwise (instant-ngp's spatial hash). Each entry holds
//! `features` floats, stored consecutively, levels one after the other. A point is mapped into the unit
//! cube by the bounds [−extent, extent]³ and clamped to it: points outside read the nearest face, and
//! the read's derivative along a clamped axis is 0.
//!
//! The read of level l at p is Σ over the cell's 8 corners of w(corner)·table\[corner\], with the trilinear
//! weights w. Its derivative along axis a replaces that axis's factor (1 − f or f) by ∓res/(2·extent);
//! along the same axis twice it is 0, so the mixed derivatives selected by a 3-bit mask close the set.

use crate::ir::GridSpec;

/// instant-ngp's hash primes (the first is 1 so that x is used as is).
const PRIMES: [u32; 3] = [1, 2_654_435_761, 805_459_861];

/// One level's layout: its resolution, its indexing and its first entry in the table.
#[derive(Clone, Copy, Debug)]
pub struct Level {
    /// Cells per axis.
    pub res: u32,
    /// For a hashed level, the table size − 1 (a power of two minus one); None for a dense level.
    pub hash_mask: Option<u64>,
    /// The level's first entry in the table.
    pub offset: u64,
}

impl Level {
    /// The table entry of vertex `v` (offset included).
    #[inline]
    pub fn entry(&self, v: [u32; 3]) -> u64 {
        let local = match self.hash_mask {
            Some(mask) => {
                let h = v[0].wrapping_mul(PRIMES[0])
                    ^ v[1].wrapping_mul(PRIMES[1])
                    ^ v[2].wrapping_mul(PRIMES[2]);
                u64::from(h) & mask
            }
            None => {
                let n = u64::from(self.res) + 1;
                (u64::from(v[2]) * n + u64::from(v[1])) * n + u64::from(v[0])
            }
        };
        self.offset + local
    }
}

/// Where a point lies in one level: per axis the lower vertex, the fraction within the cell, and whether
/// the point is inside the bounds (else the derivative along that axis is 0).
#[derive(Clone, Copy, Debug)]
pub struct Cell {
    /// The lower vertex of the cell, per axis.
    pub corner: [u32; 3],
    /// The position within the cell, per axis, in [0, 1].
    pub frac: [f64; 3],
    /// ∂(position in cells)/∂p per axis: res / (2·extent), or 0 where the point was clamped.
    pub scale: [f64; 3],
}

impl GridSpec {
    /// The half extent of the bounds (the grid covers [−extent, extent]³).
    pub fn extent(&self) -> f64 {
        f64::from(f32::from_bits(self.extent))
    }

    /// Cells per axis of level `l`: ⌊base · b^l⌋ with b = (finest / base)^(1 / (levels − 1)).
    pub fn resolution(&self, l: u32) -> u32 {
        if self.levels <= 1 || self.finest == self.base {
            return self.base;
        }
        let growth = (f64::from(self.finest) / f64::from(self.base)).ln() / f64::from(self.levels - 1);
        // The small epsilon keeps exact powers (e.g. 2048 at the last level) from flooring one below.
        ((f64::from(self.base) * (growth * f64::from(l)).exp()) + 1e-6).floor() as u32
    }

    /// Entries of level `l`: its (res + 1)³ vertices if they fit in 2^log2_size, else 2^log2_size.
    pub fn level_size(&self, l: u32) -> u64 {
        let vertices = u64::from(self.resolution(l)) + 1;
        (vertices * vertices * vertices).min(1u64 << self.log2_size)
    }

    /// Whether level `l` is hashed (its vertices do not fit in the table).
    pub fn is_hashed(&self, l: u32) -> bool {
        let vertices = u64::from(self.resolution(l)) + 1;
        vertices * vertices * vertices > (1u64 << self.log2_size)
    }

    /// The first entry of each level, and the total number of entries (last).
    pub fn level_offsets(&self) -> Vec<u64> {
        let mut offsets = Vec::with_capacity(self.levels as usize + 1);
        let mut at = 0;
        for l in 0..self.levels {
            offsets.push(at);
            at += self.level_size(l);
        }
        offsets.push(at);
        offsets
    }

    /// Floats in the table: entries × features.
    pub fn n_params(&self) -> u64 {
        self.level_offsets()[self.levels as usize] * u64::from(self.features)
    }

    /// Outputs of a read: levels × features.
    pub fn n_outputs(&self) -> usize {
        (self.levels * self.features) as usize
    }

    /// Each level's layout, for reads that visit many points.
    pub fn layout(&self) -> Vec<Level> {
        let offsets = self.level_offsets();
        (0..self.levels)
            .map(|l| Level {
                res: self.resolution(l),
                hash_mask: self.is_hashed(l).then(|| (1u64 << self.log2_size) - 1),
                offset: offsets[l as usize],
            })
            .collect()
    }

    /// Where `p` lies in level `l`.
    pub fn cell(&self, l: u32, p: [f64; 3]) -> Cell {
        let res = self.resolution(l);
        let extent = self.extent();
        let mut cell = Cell {
            corner: [0; 3],
            frac: [0.0; 3],
            scale: [0.0; 3],
        };
        for (a, &x) in p.iter().enumerate() {
            let unit = (x + extent) / (2.0 * extent);
            let inside = unit > 0.0 && unit < 1.0;
            // NaN is clamped to 0 (max and min ignore it), so a NaN point never indexes out of the table.
            let u = unit.clamp(0.0, 1.0).max(0.0) * f64::from(res);
            let c = (u.floor() as u32).min(res.saturating_sub(1));
            cell.corner[a] = c;
            cell.frac[a] = u - f64::from(c);
            cell.scale[a] = if inside {
                f64::from(res) / (2.0 * extent)
            } else {
                0.0
            };
        }
        cell
    }
}

/// The weight of corner `k` (bit a of k: the upper vertex along axis a) of `cell`, differentiated along the
/// axes in `deriv` (bit a: ∂/∂p_a).
pub fn corner_weight(cell: &Cell, k: u32, deriv: u8) -> f64 {
    (0..3).fold(1.0, |w, a| {
        let upper = k >> a & 1 == 1;
        let factor = if deriv >> a & 1 == 1 {
            if upper {
                cell.scale[a]
            } else {
                -cell.scale[a]
            }
        } else if upper {
            cell.frac[a]
        } else {
            1.0 - cell.frac[a]
        };
        w * factor
    })
}

/// The vertex of corner `k` of `cell`.
pub fn corner_vertex(cell: &Cell, k: u32) -> [u32; 3] {
    [0, 1, 2].map(|a| cell.corner[a] + (k >> a & 1))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec(levels: u32, log2_size: u32, base: u32, finest: u32) -> GridSpec {
        GridSpec {
            table: 0,
            levels,
            features: 2,
            log2_size,
            base,
            finest,
            extent: 1.5f32.to_bits(),
        }
    }

    #[test]
    fn resolutions_grow_from_base_to_finest() {
        let s = spec(16, 19, 16, 2048);
        assert_eq!(s.resolution(0), 16);
        assert_eq!(s.resolution(15), 2048);
        assert!((1..16).all(|l| s.resolution(l) > s.resolution(l - 1)));
        // Levels up to 79 cells per axis (80³ vertices ≤ 2^19) are dense, the rest hashed.
        assert!(!s.is_hashed(0) && s.is_hashed(15));
        assert_eq!(s.level_size(0), 17 * 17 * 17);
        assert_eq!(s.level_size(15), 1 << 19);
    }

    #[test]
    fn weights_sum_to_one_and_derivatives_to_zero() {
        let s = spec(4, 12, 4, 32);
        let cell = s.cell(2, [0.3, -0.7, 1.1]);
        let total: f64 = (0..8).map(|k| corner_weight(&cell, k, 0)).sum();
        assert!((total - 1.0).abs() < 1e-12);
        for deriv in 1..8u8 {
            let d: f64 = (0..8).map(|k| corner_weight(&cell, k, deriv)).sum();
            assert!(d.abs() < 1e-9, "mask {deriv}: {d}");
        }
    }

    #[test]
    fn entries_stay_in_their_level() {
        let s = spec(6, 10, 2, 64);
        for (l, level) in s.layout().iter().enumerate() {
            let n = level.res + 1;
            for v in [[0, 0, 0], [n - 1, n - 1, n - 1], [n / 2, 1, n - 1]] {
                let local = level.entry(v) - level.offset;
                assert!(local < s.level_size(l as u32), "level {l} vertex {v:?}");
            }
        }
        let far = s.cell(5, [f64::NAN, 1e30, -1e30]);
        assert!(far.corner.iter().all(|&c| c < s.resolution(5)));
    }
}
