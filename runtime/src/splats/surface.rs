//! Splats as a surface: their opacity accumulated on a grid ([`SplatGrid`]), whose level set marching cubes
//! meshes ([`splat_surface`]), and their colors on that surface ([`SplatGrid`]'s [`SplatColors`]).
//!
//! Each splat adds `opacity · exp(−½ dᵀ Σ⁻¹ d)` to the grid points within [`REACH`] standard deviations of
//! its center along each axis, and its color weighted the same into three more channels, so that a
//! point's color is the splats' colors weighted by what each adds there. Σ is the splat's covariance plus
//! a low-pass of half a cell's standard deviation ([`LOW_PASS`]), so that a splat thinner than a cell still
//! reaches a grid point. The grid is sparse: blocks of [`BLOCK`]³ points that no splat reaches are not
//! stored (empty space costs nothing), and its blocks are filled in parallel, each from the splats that
//! reach it.
//!
//! The bake's splats are a skin over the surfaces its cameras saw, with nothing inside: the level set of
//! their opacity around a closed surface is two walls, one outside and one inside the skin. The space below
//! the level that the grid's boundary cannot reach through space below the level (a flood fill, six
//! neighbours) is counted as solid, so that only the outer wall is meshed. Where the skin has a hole (an
//! object never seen from below), the fill reaches the inside and both walls stay.

use glam::{Mat3, Quat, Vec3};
use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::field::BatchFn;
use crate::splats::Splats;
use crate::surfaces::marching::extract;
use crate::surfaces::mesh::Mesh;

/// Points per side of a stored block.
pub const BLOCK: usize = 8;
/// Points in a block.
const BLOCK_POINTS: usize = BLOCK * BLOCK * BLOCK;
/// Channels a point holds: the accumulated opacity, and the color channels weighted by it.
const CHANNELS: usize = 4;

/// How far a splat reaches, in standard deviations along each axis (past it, `exp(−½·9)` = 1.1% of its
/// opacity).
pub const REACH: f32 = 3.0;

/// The low-pass added to every splat, as a standard deviation in cells.
pub const LOW_PASS: f32 = 0.5;

/// The most cells along the grid's longest side that [`SurfaceOptions::resolution`] defaults to (as
/// `nerfjit mesh`'s default grid: lego's bake so meshes into 0.77M triangles, a 77 MB file; at 512, into
/// 3.3M triangles, 285 MB).
pub const DEFAULT_MAX_RESOLUTION: usize = 256;

/// The default cell's width in the splats' median scales: about the spacing of a bake's overlapping splats
/// (each 0.6 of its cell wide), which the level set of their opacity does not follow more finely.
pub const DEFAULT_CELL_SCALES: f32 = 2.0;

/// The most cells along a side that may be asked for.
pub const MAX_RESOLUTION: usize = 1024;

/// The most memory the grid's stored blocks may take (16 bytes a point).
pub const MAX_GRID_BYTES: usize = 1 << 31;

/// The most (splat, block) pairs the grid may bin (4 bytes each).
pub const MAX_PAIRS: usize = 1 << 27;

/// The default level: where the accumulated opacity reaches one half, as it does at 1.18 standard
/// deviations from the center of a single opaque splat (its half maximum).
pub const DEFAULT_LEVEL: f32 = 0.5;

/// No block stored: no splat reaches it, and the fill reached it from the grid's boundary.
const EMPTY: u32 = u32::MAX;
/// No block stored, and the fill did not reach it: inside a closed surface.
const ENCLOSED: u32 = u32::MAX - 1;

/// What [`splat_surface`] meshes.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfaceOptions {
    /// The grid's corners; by default a cube around every splat's reach.
    pub bounds: Option<([f32; 3], [f32; 3])>,
    /// Cells along each axis; by default the longest side over [`DEFAULT_CELL_SCALES`] times the median
    /// scale of the splats within the bounds (see [`median_scale`]), at most [`DEFAULT_MAX_RESOLUTION`].
    pub resolution: Option<usize>,
    /// The level of accumulated opacity meshed (> 0).
    pub level: f32,
}

/// A splat ready to be accumulated: its center, the inverse of its covariance (low-pass included), its
/// reach along each axis, opacity and color.
struct Prepared {
    center: Vec3,
    inverse: Mat3,
    reach: Vec3,
    opacity: f32,
    color: [f32; 3],
}

/// The splats binned by the stored blocks they reach: those of stored block k are
/// `members[starts[k]..starts[k + 1]]`, and `present[k]` is its index in the grid.
struct Bins {
    members: Vec<u32>,
    starts: Vec<usize>,
    present: Vec<usize>,
}

/// The splats' opacity and colors accumulated on a grid of `n` cells a side from `min` to `max` (points at
/// `min·(1 − i/n) + max·i/n`, as marching cubes places them).
pub struct SplatGrid {
    n: usize,
    min: [f32; 3],
    max: [f32; 3],
    level: f32,
    /// Blocks per axis.
    blocks: usize,
    /// Each block's slot among the stored ones, or [`EMPTY`] / [`ENCLOSED`].
    slot: Vec<u32>,
    /// The stored blocks' points, [`CHANNELS`] values each.
    values: Vec<f32>,
    /// The stored blocks' points below the level that the fill did not reach (counted at the level).
    enclosed: Vec<bool>,
    /// Stored blocks.
    pub stored: usize,
    /// The splats within the grid.
    pub splats: usize,
    /// The largest accumulated opacity of a grid point.
    pub peak: f32,
}

/// The median over the splats centered within `bounds` (min and max corners) of their middle scale (of the
/// three standard deviations, the one between the others: the narrower width of a flat splat); `None`
/// without such splats.
pub fn median_scale(splats: &Splats, (min, max): ([f32; 3], [f32; 3])) -> Option<f32> {
    let mut middle: Vec<f32> = splats
        .scales
        .iter()
        .zip(&splats.positions)
        .filter(|(_, p)| (0..3).all(|a| (min[a]..=max[a]).contains(&p[a])))
        .map(|(s, _)| {
            let mut s = *s;
            s.sort_by(f32::total_cmp);
            s[1]
        })
        .collect();
    if middle.is_empty() {
        return None;
    }
    let half = middle.len() / 2;
    Some(*middle.select_nth_unstable_by(half, f32::total_cmp).1)
}

/// The covariance of a splat: R diag(s²) Rᵀ.
fn covariance(scale: [f32; 3], rotation: [f32; 4]) -> Mat3 {
    let [w, x, y, z] = rotation;
    let r = Mat3::from_quat(Quat::from_xyzw(x, y, z, w).normalize());
    let s2 = Mat3::from_diagonal(Vec3::from(scale) * Vec3::from(scale));
    r * s2 * r.transpose()
}

/// A cube around every splat's reach (its covariance's [`REACH`] standard deviations along each axis).
fn default_bounds(splats: &Splats) -> ([f32; 3], [f32; 3]) {
    let (mut lo, mut hi) = (Vec3::INFINITY, Vec3::NEG_INFINITY);
    for i in 0..splats.len() {
        let cov = covariance(splats.scales[i], splats.rotations[i]);
        let reach = REACH
            * Vec3::new(cov.x_axis.x, cov.y_axis.y, cov.z_axis.z)
                .max(Vec3::ZERO)
                .sqrt();
        let c = Vec3::from(splats.positions[i]);
        lo = lo.min(c - reach);
        hi = hi.max(c + reach);
    }
    let (center, half) = ((lo + hi) / 2.0, ((hi - lo) / 2.0).max_element().max(1e-6));
    ((center - half).into(), (center + half).into())
}

impl SplatGrid {
    /// Accumulates `splats` on a grid as `options` say, and fills the space the grid's boundary cannot reach
    /// below the level (see the module's doc).
    pub fn new(splats: &Splats, options: &SurfaceOptions) -> Result<SplatGrid> {
        splats.check()?;
        if splats.is_empty() {
            return Err(Error::Invalid("the bake has no splats".into()));
        }
        if !(options.level.is_finite() && options.level > 0.0) {
            return Err(Error::Invalid(format!(
                "the level {} must be above 0 (the splats' accumulated opacity is 0 far from them)",
                options.level
            )));
        }
        let (min, max) = options.bounds.unwrap_or_else(|| default_bounds(splats));
        if !(0..3).all(|a| min[a].is_finite() && max[a].is_finite() && min[a] < max[a]) {
            return Err(Error::Invalid(format!(
                "the grid's bounds need finite min < max on every axis, got {min:?} and {max:?}"
            )));
        }
        let n = match options.resolution {
            Some(n) => n,
            None => {
                let side = (0..3).map(|a| max[a] - min[a]).fold(0.0, f32::max);
                let scale = median_scale(splats, (min, max)).unwrap_or(side);
                ((side / (DEFAULT_CELL_SCALES * scale)).ceil() as usize).clamp(16, DEFAULT_MAX_RESOLUTION)
            }
        };
        if !(2..=MAX_RESOLUTION).contains(&n) {
            return Err(Error::Invalid(format!(
                "{n} cells a side: use 2 to {MAX_RESOLUTION}"
            )));
        }
        let mut grid = SplatGrid {
            n,
            min,
            max,
            level: options.level,
            blocks: (n + 1).div_ceil(BLOCK),
            slot: Vec::new(),
            values: Vec::new(),
            enclosed: Vec::new(),
            stored: 0,
            splats: 0,
            peak: 0.0,
        };
        let prepared = grid.prepare(splats);
        grid.splats = prepared.len();
        let bins = grid.bin(&prepared)?;
        grid.accumulate(&prepared, &bins);
        grid.fill();
        Ok(grid)
    }

    /// Cells a side.
    pub fn resolution(&self) -> usize {
        self.n
    }

    /// The grid's corners.
    pub fn bounds(&self) -> ([f32; 3], [f32; 3]) {
        (self.min, self.max)
    }

    /// The width of a cell along `axis`.
    fn cell(&self, axis: usize) -> f32 {
        (self.max[axis] - self.min[axis]) / self.n as f32
    }

    /// Coordinate `axis` of grid plane `i`, as marching cubes computes it.
    fn coord(&self, axis: usize, i: usize) -> f32 {
        let t = i as f32 / self.n as f32;
        self.min[axis] * (1.0 - t) + self.max[axis] * t
    }

    /// The splats that reach into the grid, their covariances widened by the low-pass.
    fn prepare(&self, splats: &Splats) -> Vec<Prepared> {
        let cell = Vec3::new(self.cell(0), self.cell(1), self.cell(2));
        let low_pass = Mat3::from_diagonal(LOW_PASS * LOW_PASS * cell * cell);
        let (lo, hi) = (Vec3::from(self.min), Vec3::from(self.max));
        (0..splats.len())
            .into_par_iter()
            .filter_map(|i| {
                let cov = covariance(splats.scales[i], splats.rotations[i]) + low_pass;
                let reach = REACH * Vec3::new(cov.x_axis.x, cov.y_axis.y, cov.z_axis.z).sqrt();
                let center = Vec3::from(splats.positions[i]);
                let inside = (center + reach).cmpge(lo).all() && (center - reach).cmple(hi).all();
                let inverse = cov.inverse();
                (inside && splats.opacities[i] > 0.0 && inverse.is_finite()).then(|| Prepared {
                    center,
                    inverse,
                    reach,
                    opacity: splats.opacities[i],
                    color: splats.colors[i],
                })
            })
            .collect()
    }

    /// The grid points a splat reaches along `axis`: `lo..=hi` (empty when `lo > hi`).
    fn points_reached(&self, s: &Prepared, axis: usize) -> (usize, usize) {
        let to_grid = |x: f32| (x - self.min[axis]) / self.cell(axis);
        let lo = to_grid(s.center[axis] - s.reach[axis]).ceil().max(0.0);
        let hi = to_grid(s.center[axis] + s.reach[axis]).floor().min(self.n as f32);
        if lo > hi {
            return (1, 0);
        }
        (lo as usize, hi as usize)
    }

    /// The blocks a splat's reach overlaps along `axis` (as continuous spans: block b holds [8b, 8b + 8),
    /// so that a point between two grid points finds every splat reaching it in the block of its floor).
    fn blocks_reached(&self, s: &Prepared, axis: usize) -> Option<(usize, usize)> {
        let to_grid = |x: f32| (x - self.min[axis]) / self.cell(axis);
        let lo = to_grid(s.center[axis] - s.reach[axis]).max(0.0);
        let hi = to_grid(s.center[axis] + s.reach[axis]).min(self.n as f32);
        (lo <= hi).then_some((lo as usize / BLOCK, hi as usize / BLOCK))
    }

    /// The index of block (x, y, z).
    fn block_index(&self, [x, y, z]: [usize; 3]) -> usize {
        (z * self.blocks + y) * self.blocks + x
    }

    /// Bins the splats by the blocks they reach, and sets the blocks' slots.
    fn bin(&mut self, prepared: &[Prepared]) -> Result<Bins> {
        let total = self.blocks.pow(3);
        let mut counts = vec![0u32; total];
        let mut pairs = 0usize;
        let ranges: Vec<Option<[(usize, usize); 3]>> = prepared
            .iter()
            .map(|s| {
                let r = [0, 1, 2].map(|a| self.blocks_reached(s, a));
                Some([r[0]?, r[1]?, r[2]?])
            })
            .collect();
        for r in ranges.iter().flatten() {
            for z in r[2].0..=r[2].1 {
                for y in r[1].0..=r[1].1 {
                    for x in r[0].0..=r[0].1 {
                        counts[self.block_index([x, y, z])] += 1;
                    }
                }
            }
            pairs += (r[0].1 - r[0].0 + 1) * (r[1].1 - r[1].0 + 1) * (r[2].1 - r[2].0 + 1);
            if pairs > MAX_PAIRS {
                return Err(Error::Invalid(format!(
                    "the splats reach more than {MAX_PAIRS} blocks of the grid between them: ask for fewer \
                     cells (--res) or a smaller part of the scene (--bounds)"
                )));
            }
        }
        self.slot = vec![EMPTY; total];
        let present: Vec<usize> = (0..total).filter(|&b| counts[b] > 0).collect();
        let bytes = present.len() * BLOCK_POINTS * CHANNELS * 4;
        if bytes > MAX_GRID_BYTES {
            return Err(Error::Invalid(format!(
                "the grid of {} cells a side would take {:.1} GB where the splats reach (at most {:.1}): ask \
                 for fewer cells (--res) or a smaller part of the scene (--bounds)",
                self.n,
                bytes as f64 / 1e9,
                MAX_GRID_BYTES as f64 / 1e9
            )));
        }
        let mut starts = Vec::with_capacity(present.len() + 1);
        starts.push(0);
        for (k, &b) in present.iter().enumerate() {
            self.slot[b] = k as u32;
            starts.push(starts[k] + counts[b] as usize);
        }
        let mut fill: Vec<usize> = starts[..present.len()].to_vec();
        let mut members = vec![0u32; pairs];
        for (i, r) in ranges.iter().enumerate() {
            let Some(r) = r else { continue };
            for z in r[2].0..=r[2].1 {
                for y in r[1].0..=r[1].1 {
                    for x in r[0].0..=r[0].1 {
                        let k = self.slot[self.block_index([x, y, z])] as usize;
                        members[fill[k]] = i as u32;
                        fill[k] += 1;
                    }
                }
            }
        }
        self.stored = present.len();
        Ok(Bins {
            members,
            starts,
            present,
        })
    }

    /// The block (x, y, z) of index `b`.
    fn block_at(&self, b: usize) -> [usize; 3] {
        [
            b % self.blocks,
            (b / self.blocks) % self.blocks,
            b / (self.blocks * self.blocks),
        ]
    }

    /// Adds every splat to the points of the stored blocks it reaches, the blocks in parallel.
    fn accumulate(&mut self, prepared: &[Prepared], bins: &Bins) {
        let Bins {
            members,
            starts,
            present,
        } = bins;
        let mut values = vec![0.0f32; present.len() * BLOCK_POINTS * CHANNELS];
        values
            .par_chunks_mut(BLOCK_POINTS * CHANNELS)
            .enumerate()
            .for_each(|(k, block)| {
                let origin = self.block_at(present[k]).map(|b| b * BLOCK);
                for &i in &members[starts[k]..starts[k + 1]] {
                    let s = &prepared[i as usize];
                    let range = [0, 1, 2].map(|a| {
                        let (lo, hi) = self.points_reached(s, a);
                        (lo.max(origin[a]), hi.min(origin[a] + BLOCK - 1))
                    });
                    for z in range[2].0..=range[2].1 {
                        for y in range[1].0..=range[1].1 {
                            for x in range[0].0..=range[0].1 {
                                let p = Vec3::new(self.coord(0, x), self.coord(1, y), self.coord(2, z));
                                let d = p - s.center;
                                let q = d.dot(s.inverse * d);
                                let w = s.opacity * (-0.5 * q).exp();
                                let local =
                                    ((z - origin[2]) * BLOCK + (y - origin[1])) * BLOCK + (x - origin[0]);
                                let at = &mut block[local * CHANNELS..(local + 1) * CHANNELS];
                                at[0] += w;
                                for c in 0..3 {
                                    at[1 + c] += w * s.color[c];
                                }
                            }
                        }
                    }
                }
            });
        self.peak = values.par_chunks(CHANNELS).map(|v| v[0]).reduce(|| 0.0, f32::max);
        self.values = values;
    }

    /// The stored value of point (x, y, z) in channel `c` (0 in a block not stored).
    fn stored_value(&self, [x, y, z]: [usize; 3], c: usize) -> f32 {
        let b = self.block_index([x / BLOCK, y / BLOCK, z / BLOCK]);
        match self.slot[b] {
            EMPTY | ENCLOSED => 0.0,
            k => {
                let local = ((z % BLOCK) * BLOCK + y % BLOCK) * BLOCK + x % BLOCK;
                self.values[(k as usize * BLOCK_POINTS + local) * CHANNELS + c]
            }
        }
    }

    /// The opacity marching cubes sees at point (x, y, z): the accumulated opacity, or the level where the
    /// fill did not reach.
    fn density(&self, [x, y, z]: [usize; 3]) -> f32 {
        let b = self.block_index([x / BLOCK, y / BLOCK, z / BLOCK]);
        match self.slot[b] {
            EMPTY => 0.0,
            ENCLOSED => self.level,
            k => {
                let local = ((z % BLOCK) * BLOCK + y % BLOCK) * BLOCK + x % BLOCK;
                let at = k as usize * BLOCK_POINTS + local;
                match self.enclosed[at] {
                    true => self.level,
                    false => self.values[at * CHANNELS],
                }
            }
        }
    }

    /// Marks the space below the level that the grid's boundary cannot reach through space below the level
    /// (six neighbours): blocks not stored as a whole, stored blocks point by point.
    fn fill(&mut self) {
        let (n, level) = (self.n, self.level);
        let mut block_seen = vec![false; self.slot.len()];
        let mut point_seen = vec![false; self.stored * BLOCK_POINTS];
        // Work: a block (its index) or a point (its coordinates).
        enum Item {
            Block(usize),
            Point([usize; 3]),
        }
        let mut queue = std::collections::VecDeque::new();
        let local = |[x, y, z]: [usize; 3]| ((z % BLOCK) * BLOCK + y % BLOCK) * BLOCK + x % BLOCK;
        // Reaches point p: its block if not stored, else the point if below the level.
        let mut visit = |p: [usize; 3], queue: &mut std::collections::VecDeque<Item>| {
            let b = self.block_index(p.map(|c| c / BLOCK));
            match self.slot[b] {
                EMPTY => {
                    if !block_seen[b] {
                        block_seen[b] = true;
                        queue.push_back(Item::Block(b));
                    }
                }
                k => {
                    let at = k as usize * BLOCK_POINTS + local(p);
                    if !point_seen[at] && self.values[at * CHANNELS] < level {
                        point_seen[at] = true;
                        queue.push_back(Item::Point(p));
                    }
                }
            }
        };
        for a in 0..3 {
            for u in 0..=n {
                for v in 0..=n {
                    for w in [0, n] {
                        let mut p = [0; 3];
                        (p[a], p[(a + 1) % 3], p[(a + 2) % 3]) = (w, u, v);
                        visit(p, &mut queue);
                    }
                }
            }
        }
        while let Some(item) = queue.pop_front() {
            match item {
                Item::Point(p) => {
                    for a in 0..3 {
                        for step in [-1i64, 1] {
                            let c = p[a] as i64 + step;
                            if (0..=n as i64).contains(&c) {
                                let mut q = p;
                                q[a] = c as usize;
                                visit(q, &mut queue);
                            }
                        }
                    }
                }
                Item::Block(b) => {
                    // The points just past each face of the block.
                    let origin = self.block_at(b).map(|c| c * BLOCK);
                    for a in 0..3 {
                        for beyond in [origin[a] as i64 - 1, (origin[a] + BLOCK) as i64] {
                            if !(0..=n as i64).contains(&beyond) {
                                continue;
                            }
                            let (a1, a2) = ((a + 1) % 3, (a + 2) % 3);
                            for u in origin[a1]..(origin[a1] + BLOCK).min(n + 1) {
                                for v in origin[a2]..(origin[a2] + BLOCK).min(n + 1) {
                                    let mut q = [0; 3];
                                    (q[a], q[a1], q[a2]) = (beyond as usize, u, v);
                                    visit(q, &mut queue);
                                }
                            }
                        }
                    }
                }
            }
        }
        for (b, seen) in block_seen.iter().enumerate() {
            if self.slot[b] == EMPTY && !seen {
                self.slot[b] = ENCLOSED;
            }
        }
        self.enclosed = point_seen
            .iter()
            .enumerate()
            .map(|(at, &seen)| !seen && self.values[at * CHANNELS] < level)
            .collect();
    }

    /// Point `p`'s position in grid units along each axis.
    fn grid_units(&self, p: [f32; 3]) -> [f32; 3] {
        [0, 1, 2].map(|a| ((p[a] - self.min[a]) / self.cell(a)).clamp(0.0, self.n as f32))
    }

    /// Trilinear interpolation of `value` over the grid points around `t` (in grid units); a point within
    /// 10⁻³ cells of a grid point takes that point's value.
    fn trilinear(&self, t: [f32; 3], value: &dyn Fn([usize; 3]) -> f32) -> f32 {
        let near = t.map(|x| x.round());
        if (0..3).all(|a| (t[a] - near[a]).abs() < 1e-3) {
            return value(near.map(|x| x as usize));
        }
        let lo = t.map(|x| (x.floor() as usize).min(self.n.saturating_sub(1)));
        let f = [0, 1, 2].map(|a| t[a] - lo[a] as f32);
        let mut sum = 0.0;
        for corner in 0..8 {
            let mut weight = 1.0;
            let mut p = lo;
            for a in 0..3 {
                let up = corner >> a & 1 == 1;
                weight *= if up { f[a] } else { 1.0 - f[a] };
                p[a] += usize::from(up);
            }
            if weight > 0.0 {
                sum += weight * value(p);
            }
        }
        sum
    }

    /// The splats' color at point `p`: their colors weighted by the opacity each adds around it
    /// (trilinear over the grid points), or mid-gray where none reaches.
    pub fn color_at(&self, p: [f32; 3]) -> [f32; 3] {
        let t = self.grid_units(p);
        let weight = self.trilinear(t, &|q| self.stored_value(q, 0));
        if weight <= 1e-12 {
            return [0.5; 3];
        }
        [1, 2, 3].map(|c| self.trilinear(t, &|q| self.stored_value(q, c)) / weight)
    }
}

/// The grid's opacity as marching cubes samples it (3 inputs → 1 output), the enclosed space at the level.
impl BatchFn for SplatGrid {
    fn n_inputs(&self) -> usize {
        3
    }

    fn n_outputs(&self) -> usize {
        1
    }

    fn eval(&self, n: usize, inputs: &[&[f32]], outputs: &mut [&mut [f32]]) {
        for k in 0..n {
            let t = self.grid_units([inputs[0][k], inputs[1][k], inputs[2][k]]);
            outputs[0][k] = self.trilinear(t, &|q| self.density(q));
        }
    }
}

/// The splats' colors on a [`SplatGrid`] (3 inputs → 3 outputs; see [`SplatGrid::color_at`]).
pub struct SplatColors<'a>(pub &'a SplatGrid);

impl BatchFn for SplatColors<'_> {
    fn n_inputs(&self) -> usize {
        3
    }

    fn n_outputs(&self) -> usize {
        3
    }

    fn eval(&self, n: usize, inputs: &[&[f32]], outputs: &mut [&mut [f32]]) {
        for k in 0..n {
            let rgb = self.0.color_at([inputs[0][k], inputs[1][k], inputs[2][k]]);
            for c in 0..3 {
                outputs[c][k] = rgb[c];
            }
        }
    }
}

/// The surface of `splats` (see the module's doc): the grid, and the marching-cubes mesh of its level with
/// its triangles and normals facing out of the solid; an error if the splats' opacity never reaches the
/// level or no surface is left.
pub fn splat_surface(splats: &Splats, options: &SurfaceOptions) -> Result<(SplatGrid, Mesh)> {
    let grid = SplatGrid::new(splats, options)?;
    if grid.peak < options.level {
        return Err(Error::Invalid(format!(
            "no surface at level {}: the splats' accumulated opacity peaks at {:.3} on this grid of {} cells a \
             side (use a lower --level)",
            options.level, grid.peak, grid.n
        )));
    }
    let mut mesh = extract(&grid, None, (grid.min, grid.max), grid.n, options.level)?;
    if mesh.triangles.is_empty() {
        return Err(Error::Invalid(format!(
            "no surface at level {}: no grid cell crosses it",
            options.level
        )));
    }
    // Marching cubes faces increasing values: into the solid.
    for t in &mut mesh.triangles {
        t.swap(1, 2);
    }
    for normal in &mut mesh.normals {
        *normal = normal.map(|x| -x);
    }
    Ok((grid, mesh))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `count` round splats of standard deviation `scale` spread evenly over a sphere of `radius` (a
    /// Fibonacci lattice), red above z = 0 and blue below.
    fn shell(count: usize, radius: f32, scale: f32) -> Splats {
        let mut splats = Splats::default();
        let golden = std::f32::consts::PI * (3.0 - 5f32.sqrt());
        for i in 0..count {
            let z = 1.0 - 2.0 * (i as f32 + 0.5) / count as f32;
            let r = (1.0 - z * z).sqrt();
            let phi = golden * i as f32;
            splats
                .positions
                .push([radius * r * phi.cos(), radius * r * phi.sin(), radius * z]);
            splats
                .colors
                .push(if z > 0.0 { [0.9, 0.1, 0.1] } else { [0.1, 0.1, 0.9] });
            splats.opacities.push(0.9);
            splats.scales.push([scale; 3]);
            splats.rotations.push([1.0, 0.0, 0.0, 0.0]);
        }
        splats
    }

    const OPTIONS: SurfaceOptions = SurfaceOptions {
        bounds: None,
        resolution: None,
        level: DEFAULT_LEVEL,
    };

    /// A shell of splats gives one closed surface just outside it (the inner wall filled), facing out, its
    /// colors those of the nearest splats.
    #[test]
    fn a_shell_of_splats_meshes_into_its_outer_wall() {
        let splats = shell(2000, 1.0, 0.05);
        let (grid, mesh) = splat_surface(&splats, &OPTIONS).unwrap();
        assert!(mesh.is_closed());
        assert!(mesh.volume() > 4.0, "{}", mesh.volume());
        for v in &mesh.vertices {
            let r = Vec3::from(*v).length();
            assert!((1.0..1.2).contains(&r), "{v:?} at {r}");
        }
        for (v, normal) in mesh.vertices.iter().zip(&mesh.normals) {
            assert!(Vec3::from(*v).normalize().dot(Vec3::from(*normal)) > 0.8);
        }
        for v in &mesh.vertices {
            let c = grid.color_at(*v);
            match v[2] {
                z if z > 0.2 => assert!(c[0] > 0.85 && c[2] < 0.15, "{v:?}: {c:?}"),
                z if z < -0.2 => assert!(c[2] > 0.85 && c[0] < 0.15, "{v:?}: {c:?}"),
                _ => {}
            }
        }
    }

    /// An open shell (a cap cut off) keeps both walls: the fill reaches the inside.
    #[test]
    fn an_open_shell_keeps_both_walls() {
        let mut splats = shell(2000, 1.0, 0.05);
        let keep: Vec<bool> = splats.positions.iter().map(|p| p[2] > -0.7).collect();
        splats.retain(&keep);
        let (_, mesh) = splat_surface(&splats, &OPTIONS).unwrap();
        let inner = mesh
            .vertices
            .iter()
            .filter(|v| Vec3::from(**v).length() < 1.0)
            .count();
        assert!(
            inner > mesh.vertices.len() / 3,
            "{inner} of {}",
            mesh.vertices.len()
        );
    }

    #[test]
    fn levels_the_splats_never_reach_and_empty_bakes_are_refused() {
        let splats = shell(200, 1.0, 0.05);
        let high = SurfaceOptions {
            level: 50.0,
            ..OPTIONS
        };
        let e = splat_surface(&splats, &high).err().unwrap().to_string();
        assert!(e.contains("no surface at level 50"), "{e}");
        let zero = SurfaceOptions {
            level: 0.0,
            ..OPTIONS
        };
        assert!(splat_surface(&splats, &zero).is_err());
        let e = splat_surface(&Splats::default(), &OPTIONS)
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("no splats"), "{e}");
    }
}
