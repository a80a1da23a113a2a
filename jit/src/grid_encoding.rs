//! Grid encodings on tiles of points: the trilinear read of every level (forward, or differentiated
//! along some axes) into output columns, and the scatter of cotangents into the table's gradient.
//!
//! The layout, the hash and the weights are those of [`nerfjit_dsl::grid`] (the interpreter's oracle);
//! here they run in f32 over the columns of a tile, with the levels' layouts computed once per kernel.
//! On AVX-512 machines 16 points go through a level at once (the corners hashed in vector registers,
//! the table read by gathers, a point's two neighbouring features moved as one 8-byte element when they
//! are even in number, the cotangents' terms computed in vectors and added entry by entry); on AVX2 machines 8 (the
//! corners and the read in vectors, the scatter point by point), with the corners of levels larger than
//! the L1 cache computed two blocks ahead and their lines prefetched, so that the reads of a large table
//! overlap instead of waiting on memory one after the other. The arithmetic is the scalar path's,
//! operation for operation, so every path gives the same bits.

use nerfjit_dsl::grid::Level;
use nerfjit_dsl::ir::{GridRead, GridSpec};

/// A grid read or scatter prepared for tiles.
pub struct GridPlan {
    levels: Vec<Level>,
    table: usize,
    features: usize,
    deriv: u8,
    /// One past the table's last param.
    end: usize,
    /// Twice the half extent's inverse: maps p + extent into [0, 1].
    inv_size: f32,
    extent: f32,
    /// The instructions the reads and scatters run on.
    path: Path,
    /// Per level: its part of the table is larger than a core's L1 cache, so the AVX2 path fetches the
    /// lines of the points' corners ahead of their use.
    far: Vec<bool>,
}

/// Bytes of a level's table above which its corners' lines are prefetched (a core's L1 data cache).
const PREFETCH_ABOVE: u64 = 32 << 10;

/// The instruction set of a grid plan's loops.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Path {
    /// One point at a time.
    Scalar,
    /// 8 points at a time (AVX2): every table index fits 32-bit lanes.
    Avx2,
    /// 16 points at a time (AVX-512): every table index fits 32-bit lanes.
    Avx512,
}

impl Path {
    /// Every path this CPU runs for a table whose indices end at `end`, widest first.
    fn available(end: usize) -> Vec<Path> {
        let mut all = Vec::new();
        if end <= i32::MAX as usize {
            if crate::gemm::has_avx512() {
                all.push(Path::Avx512);
            }
            if crate::gemm::has_avx2_fma() {
                all.push(Path::Avx2);
            }
        }
        all.push(Path::Scalar);
        all
    }
}

/// A stretch of a gradient: `grads[i]` is the gradient of param `origin + i`.
pub struct GradWindow<'a> {
    /// The gradients of the stretch's params.
    pub grads: &'a mut [f32],
    /// The first param of the stretch.
    pub origin: usize,
}

/// The 8 corners of one point's cell in one level: entries and weights.
struct Corners {
    entry: [usize; 8],
    weight: [f32; 8],
}

impl GridPlan {
    /// The plan of a read (or scatter) of `read`'s grid.
    pub fn new(read: &GridRead) -> GridPlan {
        let spec: GridSpec = read.spec;
        let extent = f32::from_bits(spec.extent);
        let end = spec.table as usize + spec.n_params() as usize;
        GridPlan {
            levels: spec.layout(),
            table: spec.table as usize,
            features: spec.features as usize,
            deriv: read.deriv,
            end,
            inv_size: 1.0 / (2.0 * extent),
            extent,
            path: Path::available(end)[0],
            far: (0..spec.levels)
                .map(|l| spec.level_size(l) * u64::from(spec.features) * 4 > PREFETCH_ABOVE)
                .collect(),
        }
    }

    /// One past the last param the grid touches.
    pub fn params_end(&self) -> usize {
        self.end
    }

    /// The number of levels.
    pub fn levels(&self) -> usize {
        self.levels.len()
    }

    /// The params of level `l`'s part of the table.
    pub fn level_params(&self, l: usize) -> std::ops::Range<usize> {
        let start = |l: usize| match self.levels.get(l) {
            Some(level) => self.table + level.offset as usize * self.features,
            None => self.end,
        };
        start(l)..start(l + 1)
    }

    /// The table entries a point reads (or a scatter writes): 8 corners on each level, `features` floats
    /// each.
    pub fn corners_per_point(&self) -> u64 {
        8 * self.levels.len() as u64
    }

    /// The pairs of neighbouring features that the vector paths move as one 8-byte element: all of them
    /// when the features are even in number, else none.
    #[cfg(target_arch = "x86_64")]
    fn feature_pairs(&self) -> usize {
        if self.features.is_multiple_of(2) {
            self.features / 2
        } else {
            0
        }
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
    pub unsafe fn read(&self, p: [*const f32; 3], out: &[*mut f32], params: &[f32], count: usize) {
        assert!(params.len() >= self.end, "the grid's table is outside the params");
        assert_eq!(out.len(), self.levels.len() * self.features);
        // SAFETY (both vector paths): the CPU has their instructions and the indices fit (`Path::available`);
        // the caller's guarantees are passed on.
        #[cfg(target_arch = "x86_64")]
        match self.path {
            Path::Avx512 => return unsafe { avx512::read(self, p, out, params, count) },
            Path::Avx2 => return unsafe { avx2::read(self, p, out, params, count) },
            Path::Scalar => {}
        }
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

    /// `grads[corner·features + f] += w · cot[l·features + f][t]` for t < count, on every level.
    ///
    /// # Safety
    /// The pointers of `p` and `cot` must address `count` readable floats.
    pub unsafe fn scatter(&self, p: [*const f32; 3], cot: &[*const f32], grads: &mut [f32], count: usize) {
        let window = GradWindow { grads, origin: 0 };
        // SAFETY: passed on.
        unsafe { self.scatter_levels(p, cot, window, count, 0..self.levels.len()) };
    }

    /// [`GridPlan::scatter`] on the levels `levels` only, into a window of the gradient that holds their
    /// params: the same additions in the same order on each of those levels, so that a scatter split by
    /// level (into disjoint windows, on several threads) gives the whole scatter's bits.
    ///
    /// # Safety
    /// The pointers of `p` and `cot` must address `count` readable floats.
    ///
    /// # Panics
    /// If the window does not hold the params of those levels.
    pub unsafe fn scatter_levels(
        &self,
        p: [*const f32; 3],
        cot: &[*const f32],
        window: GradWindow<'_>,
        count: usize,
        levels: std::ops::Range<usize>,
    ) {
        assert!(
            levels.end <= self.levels.len(),
            "the grid has no level {}",
            levels.end - 1
        );
        if levels.is_empty() {
            return;
        }
        let params = self.level_params(levels.start).start..self.level_params(levels.end - 1).end;
        assert!(
            window.origin <= params.start && params.end <= window.origin + window.grads.len(),
            "the window of the gradient does not hold the levels' params"
        );
        assert_eq!(cot.len(), self.levels.len() * self.features);
        // SAFETY (both vector paths): the CPU has their instructions and the indices fit (`Path::available`);
        // the caller's guarantees are passed on.
        #[cfg(target_arch = "x86_64")]
        match self.path {
            Path::Avx512 => return unsafe { avx512::scatter(self, p, cot, window, count, levels) },
            Path::Avx2 => return unsafe { avx2::scatter(self, p, cot, window, count, levels) },
            Path::Scalar => {}
        }
        let GradWindow { grads, origin } = window;
        for l in levels {
            for t in 0..count {
                // SAFETY: t < count, as the caller guarantees for every column.
                let point = p.map(|c| unsafe { *c.add(t) });
                let corners = self.corners(&self.levels[l], point);
                // SAFETY: passed on from the caller; the window holds the level's params (asserted).
                unsafe { self.scatter_point(&corners, l, t, cot, grads, origin) };
            }
        }
    }

    /// Point `t`'s part of [`GridPlan::scatter`] in level `l`, its cell's corners given, into `grads`
    /// holding the params from `origin` on.
    ///
    /// # Safety
    /// The pointers of `cot` must address more than `t` readable floats; the corners' entries must be
    /// those of level `l` of this plan, whose params `grads` holds.
    #[inline(always)]
    unsafe fn scatter_point(
        &self,
        corners: &Corners,
        l: usize,
        t: usize,
        cot: &[*const f32],
        grads: &mut [f32],
        origin: usize,
    ) {
        for f in 0..self.features {
            // SAFETY: t is below the columns' length (caller).
            let c = unsafe { *cot[l * self.features + f].add(t) };
            if c == 0.0 {
                continue;
            }
            for k in 0..8 {
                // SAFETY: a corner's entry + f lies in its level's params (Level::entry masks or indexes
                // within the level), which grads holds from origin on.
                unsafe { *grads.get_unchecked_mut(corners.entry[k] + f - origin) += corners.weight[k] * c };
            }
        }
    }
}

/// The 16-point paths: [`GridPlan::read`] and [`GridPlan::scatter`] on AVX-512.
#[cfg(target_arch = "x86_64")]
mod avx512 {
    use std::arch::x86_64::*;
    use std::ops::Range;

    use nerfjit_dsl::grid::Level;

    use super::{GradWindow, GridPlan};

    /// Points per vector.
    const LANES: usize = 16;

    /// The 8 corners of 16 points' cells in one level: table indices (of the first feature) and weights.
    struct Corners16 {
        index: [__m512i; 8],
        weight: [__m512; 8],
    }

    /// The lanes of the points `start..start + 16` that are below `count`.
    fn lanes(start: usize, count: usize) -> __mmask16 {
        let n = (count - start).min(LANES);
        ((1u32 << n) - 1) as __mmask16
    }

    /// `GridPlan::corners` for 16 points, operation for operation.
    #[target_feature(enable = "avx512f")]
    fn corners(plan: &GridPlan, level: &Level, p: [__m512; 3]) -> Corners16 {
        let res = level.res as f32;
        let zero = _mm512_setzero_ps();
        let one = _mm512_set1_ps(1.0);
        let extent = _mm512_set1_ps(plan.extent);
        let inv_size = _mm512_set1_ps(plan.inv_size);
        let top = _mm512_set1_epi32(level.res.saturating_sub(1) as i32);
        let mut lower = [_mm512_setzero_si512(); 3];
        let mut factor = [[zero; 2]; 3];
        for a in 0..3 {
            let unit = _mm512_mul_ps(_mm512_add_ps(p[a], extent), inv_size);
            let inside =
                _mm512_cmp_ps_mask::<_CMP_GT_OQ>(unit, zero) & _mm512_cmp_ps_mask::<_CMP_LT_OQ>(unit, one);
            // max first: it maps NaN to 0 as the scalar path's clamp-then-max does.
            let u = _mm512_mul_ps(_mm512_min_ps(_mm512_max_ps(unit, zero), one), _mm512_set1_ps(res));
            let c = _mm512_min_epu32(_mm512_cvttps_epu32(u), top);
            let f = _mm512_sub_ps(u, _mm512_cvtepu32_ps(c));
            lower[a] = c;
            factor[a] = if plan.deriv >> a & 1 == 1 {
                let s = _mm512_maskz_mov_ps(inside, _mm512_set1_ps(res * plan.inv_size));
                let negated = _mm512_castsi512_ps(_mm512_xor_si512(
                    _mm512_castps_si512(s),
                    _mm512_set1_epi32(i32::MIN),
                ));
                [negated, s]
            } else {
                [_mm512_sub_ps(one, f), f]
            };
        }
        let features = _mm512_set1_epi32(plan.features as i32);
        let first = _mm512_set1_epi32(plan.table as i32);
        let offset = _mm512_set1_epi32(level.offset as i32);
        // Per axis, the lower and upper vertex's term of the local index: the vertex times the axis's
        // hash prime (hashed levels, the terms xored) or its stride (dense levels, the terms added). The
        // upper term is the lower one plus the factor, as (v + 1)·m = v·m + m in wrapping arithmetic: two
        // products per level instead of two per corner, with the same bits.
        let factors = match level.hash_mask {
            Some(_) => [1, 2_654_435_761u32 as i32, 805_459_861],
            None => {
                let n = level.res as i32 + 1;
                [1, n, n.wrapping_mul(n)]
            }
        };
        let term = [0, 1, 2].map(|a| {
            let m = _mm512_set1_epi32(factors[a]);
            let low = if a == 0 {
                lower[a]
            } else {
                _mm512_mullo_epi32(lower[a], m)
            };
            [low, _mm512_add_epi32(low, m)]
        });
        let mut corners = Corners16 {
            index: [_mm512_setzero_si512(); 8],
            weight: [zero; 8],
        };
        for k in 0..8usize {
            let bit = |a: usize| k >> a & 1;
            let local = match level.hash_mask {
                Some(mask) => _mm512_and_si512(
                    _mm512_xor_si512(
                        _mm512_xor_si512(term[0][bit(0)], term[1][bit(1)]),
                        term[2][bit(2)],
                    ),
                    _mm512_set1_epi32(mask as i32),
                ),
                None => _mm512_add_epi32(
                    _mm512_add_epi32(term[2][bit(2)], term[1][bit(1)]),
                    term[0][bit(0)],
                ),
            };
            corners.index[k] = _mm512_add_epi32(
                first,
                _mm512_mullo_epi32(_mm512_add_epi32(offset, local), features),
            );
            corners.weight[k] = _mm512_mul_ps(
                _mm512_mul_ps(factor[0][bit(0)], factor[1][bit(1)]),
                factor[2][bit(2)],
            );
        }
        corners
    }

    /// The point columns' lanes `start..start + 16` (0 beyond `count`).
    ///
    /// # Safety
    /// The columns must address `count` readable floats.
    #[target_feature(enable = "avx512f")]
    unsafe fn load_points(p: [*const f32; 3], start: usize, m: __mmask16) -> [__m512; 3] {
        // SAFETY: the masked lanes are below count.
        p.map(|c| unsafe { _mm512_maskz_loadu_ps(m, c.add(start)) })
    }

    /// Lane indices that spread the weights of points 0–7 (first) and 8–15 (second) over the two lanes of
    /// each point's pair of features: `[0, 0, 1, 1, …, 7, 7]` and `[8, 8, …, 15, 15]`.
    #[target_feature(enable = "avx512f")]
    fn pair_spread() -> [__m512i; 2] {
        [0, 8].map(|first| {
            let lanes: [i32; 16] = std::array::from_fn(|j| first + j as i32 / 2);
            // SAFETY: 16 i32s are the 64 bytes the load reads.
            unsafe { _mm512_loadu_si512(lanes.as_ptr().cast()) }
        })
    }

    /// The 8 table indices (of a pair's first feature) of points 0–7 (`half` 0) or 8–15 (`half` 1).
    #[target_feature(enable = "avx512f")]
    fn half_indices(at: __m512i, half: usize) -> __m256i {
        if half == 0 {
            _mm512_castsi512_si256(at)
        } else {
            _mm512_extracti64x4_epi64::<1>(at)
        }
    }

    /// [`GridPlan::read`] on AVX-512. With an even number of features, a point's two neighbouring features
    /// come in one 8-byte gather (8 points a gather instead of 16 floats: half the loads), summed in the
    /// pairs' interleaved order and separated into their columns at the end, with the same operations on
    /// each value.
    ///
    /// # Safety
    /// As [`GridPlan::read`]'s, with `params.len() ≥ plan.end` and every index below 2^31.
    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn read(
        plan: &GridPlan,
        p: [*const f32; 3],
        out: &[*mut f32],
        params: &[f32],
        count: usize,
    ) {
        let spread = pair_spread();
        let even = _mm512_setr_epi32(0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20, 22, 24, 26, 28, 30);
        let odd = _mm512_add_epi32(even, _mm512_set1_epi32(1));
        let pairs = plan.feature_pairs();
        for (l, level) in plan.levels.iter().enumerate() {
            for start in (0..count).step_by(LANES) {
                let m = lanes(start, count);
                // SAFETY: the caller's columns hold count floats.
                let corners = corners(plan, level, unsafe { load_points(p, start, m) });
                for pair in 0..pairs {
                    let shift = _mm512_set1_epi32(2 * pair as i32);
                    let mut sum = [_mm512_setzero_ps(); 2];
                    for k in 0..8 {
                        let at = _mm512_add_epi32(corners.index[k], shift);
                        for (half, sum) in sum.iter_mut().enumerate() {
                            // SAFETY: an index + 1 is below plan.end ≤ params.len() (the pair's second
                            // feature), as in the scalar path.
                            let value = _mm512_castpd_ps(unsafe {
                                _mm512_mask_i32gather_pd::<4>(
                                    _mm512_setzero_pd(),
                                    (m >> (8 * half)) as __mmask8,
                                    half_indices(at, half),
                                    params.as_ptr().cast(),
                                )
                            });
                            let weight = _mm512_permutexvar_ps(spread[half], corners.weight[k]);
                            *sum = _mm512_add_ps(*sum, _mm512_mul_ps(weight, value));
                        }
                    }
                    let column = l * plan.features + 2 * pair;
                    // SAFETY: the output columns hold count floats.
                    unsafe {
                        _mm512_mask_storeu_ps(
                            out[column].add(start),
                            m,
                            _mm512_permutex2var_ps(sum[0], even, sum[1]),
                        );
                        _mm512_mask_storeu_ps(
                            out[column + 1].add(start),
                            m,
                            _mm512_permutex2var_ps(sum[0], odd, sum[1]),
                        );
                    }
                }
                for f in 2 * pairs..plan.features {
                    let shift = _mm512_set1_epi32(f as i32);
                    let mut sum = _mm512_setzero_ps();
                    for k in 0..8 {
                        // SAFETY: an index + f is below plan.end ≤ params.len(), as in the scalar path.
                        let value = unsafe {
                            _mm512_mask_i32gather_ps::<4>(
                                _mm512_setzero_ps(),
                                m,
                                _mm512_add_epi32(corners.index[k], shift),
                                params.as_ptr(),
                            )
                        };
                        sum = _mm512_add_ps(sum, _mm512_mul_ps(corners.weight[k], value));
                    }
                    // SAFETY: the output columns hold count floats.
                    unsafe { _mm512_mask_storeu_ps(out[l * plan.features + f].add(start), m, sum) };
                }
            }
        }
    }

    /// [`GridPlan::scatter`] on AVX-512: the corners and the terms (weight × cotangent) 16 points at a
    /// time, then for each corner the terms added to the table entry by entry in point order, which also
    /// keeps points that share an entry (neighbouring samples of a ray in a coarse level's cell) right.
    /// Entry by entry rather than by gather, add and scatter: on AMD Zen 4 the scatter instruction is slow
    /// enough that plain 8-byte reads, adds and writes take 0.7× its time (`nerfjit bench grid`). With an
    /// even number of features a point's two neighbouring features go as one 8-byte element; a point
    /// whose pair has one cotangent 0 then adds ±0 to that feature, which leaves it as it was.
    ///
    /// # Safety
    /// As [`GridPlan::scatter_levels`]'s, with the window holding the levels' params (checked there) and
    /// every index below 2^31.
    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn scatter(
        plan: &GridPlan,
        p: [*const f32; 3],
        cot: &[*const f32],
        window: GradWindow<'_>,
        count: usize,
        levels: Range<usize>,
    ) {
        let GradWindow { grads, origin } = window;
        // Indices into the window: every entry of the levels is at least `origin` (checked by the caller).
        let origin = _mm512_set1_epi32(origin as i32);
        let zero = _mm512_setzero_ps();
        let spread = pair_spread();
        let interleave = [
            _mm512_setr_epi32(0, 16, 1, 17, 2, 18, 3, 19, 4, 20, 5, 21, 6, 22, 7, 23),
            _mm512_setr_epi32(8, 24, 9, 25, 10, 26, 11, 27, 12, 28, 13, 29, 14, 30, 15, 31),
        ];
        let pairs = plan.feature_pairs();
        let mut index = [0u32; LANES];
        let mut value = [0.0f32; LANES];
        let mut pairs_value = [0.0f32; 2 * LANES];
        for l in levels {
            let level = &plan.levels[l];
            for start in (0..count).step_by(LANES) {
                let m = lanes(start, count);
                // SAFETY: the caller's columns hold count floats.
                let corners = corners(plan, level, unsafe { load_points(p, start, m) });
                for pair in 0..pairs {
                    let column = l * plan.features + 2 * pair;
                    // SAFETY: as for the points.
                    let c =
                        [column, column + 1].map(|j| unsafe { _mm512_maskz_loadu_ps(m, cot[j].add(start)) });
                    // Points whose two cotangents are 0 add nothing (NaN is kept, as in the scalar path).
                    let live = m
                        & (_mm512_cmp_ps_mask::<_CMP_NEQ_UQ>(c[0], zero)
                            | _mm512_cmp_ps_mask::<_CMP_NEQ_UQ>(c[1], zero));
                    if live == 0 {
                        continue;
                    }
                    // Per half, the points' cotangents as pairs: [c0 of point 0, c1 of point 0, …].
                    let paired = interleave.map(|i| _mm512_permutex2var_ps(c[0], i, c[1]));
                    for k in 0..8 {
                        let at = _mm512_sub_epi32(
                            _mm512_add_epi32(corners.index[k], _mm512_set1_epi32(2 * pair as i32)),
                            origin,
                        );
                        // SAFETY: 16 indices and 32 values into arrays of 16 and 32.
                        unsafe {
                            _mm512_storeu_si512(index.as_mut_ptr().cast(), at);
                            for half in 0..2 {
                                let add = _mm512_mul_ps(
                                    _mm512_permutexvar_ps(spread[half], corners.weight[k]),
                                    paired[half],
                                );
                                _mm512_storeu_ps(pairs_value.as_mut_ptr().add(16 * half), add);
                            }
                        }
                        // SAFETY: every index + 1 (the pair's second feature) lies in the level's params,
                        // as in the scalar path, which the window holds from its origin on.
                        unsafe { add_pairs(grads, &index, &pairs_value, live) };
                    }
                }
                for f in 2 * pairs..plan.features {
                    // SAFETY: as for the points.
                    let c = unsafe { _mm512_maskz_loadu_ps(m, cot[l * plan.features + f].add(start)) };
                    // Points whose cotangent is 0 add nothing (NaN is kept, as in the scalar path).
                    let live = m & _mm512_cmp_ps_mask::<_CMP_NEQ_UQ>(c, zero);
                    if live == 0 {
                        continue;
                    }
                    for k in 0..8 {
                        let at = _mm512_sub_epi32(
                            _mm512_add_epi32(corners.index[k], _mm512_set1_epi32(f as i32)),
                            origin,
                        );
                        let add = _mm512_mul_ps(corners.weight[k], c);
                        // SAFETY: 16 lanes into arrays of 16.
                        unsafe {
                            _mm512_storeu_si512(index.as_mut_ptr().cast(), at);
                            _mm512_storeu_ps(value.as_mut_ptr(), add);
                        }
                        let mut lanes = live;
                        while lanes != 0 {
                            let lane = lanes.trailing_zeros() as usize;
                            lanes &= lanes - 1;
                            // SAFETY: an index + f lies in the level's params, as in the scalar path, which
                            // the window holds from its origin on.
                            unsafe { *grads.get_unchecked_mut(index[lane] as usize) += value[lane] };
                        }
                    }
                }
            }
        }
    }

    /// `grads[index[lane]..][..2] += value[2·lane..][..2]` for the live lanes, in lane order: one 8-byte
    /// read, add and write each, a straight run when every lane is live.
    ///
    /// # Safety
    /// Every live lane's index + 1 must be below `grads.len()`.
    #[inline(always)]
    unsafe fn add_pairs(grads: &mut [f32], index: &[u32; LANES], value: &[f32; 2 * LANES], live: __mmask16) {
        let grads = grads.as_mut_ptr();
        let add = |lane: usize| {
            // SAFETY: the caller's guarantee; lane < 16.
            unsafe {
                let entry = grads.add(index[lane] as usize).cast::<f64>();
                let term = value.as_ptr().add(2 * lane).cast::<f64>();
                let sum = _mm_add_ps(
                    _mm_castpd_ps(_mm_load_sd(entry)),
                    _mm_castpd_ps(_mm_load_sd(term)),
                );
                _mm_store_sd(entry, _mm_castps_pd(sum));
            }
        };
        if live == u16::MAX {
            (0..LANES).for_each(add);
        } else {
            let mut lanes = live;
            while lanes != 0 {
                add(lanes.trailing_zeros() as usize);
                lanes &= lanes - 1;
            }
        }
    }
}

/// The 8-point paths: [`GridPlan::read`] and [`GridPlan::scatter`] on AVX2 (which has gathers but no
/// scatters; the scatter adds point by point, in the scalar path's order).
#[cfg(target_arch = "x86_64")]
mod avx2 {
    use std::arch::x86_64::*;
    use std::ops::Range;

    use nerfjit_dsl::grid::Level;

    use super::{Corners, GradWindow, GridPlan};

    /// Points per vector.
    const LANES: usize = 8;

    /// The 8 corners of 8 points' cells in one level: table indices (of the first feature) and weights.
    #[derive(Clone, Copy)]
    struct Corners8 {
        index: [__m256i; 8],
        weight: [__m256; 8],
    }

    /// How many blocks of 8 points ahead of their use the corners of a far level are computed and their
    /// lines prefetched: the table reads of a level larger than the caches wait on memory otherwise.
    const AHEAD: usize = 2;

    /// The corners of a level's blocks of 8 points in order; for a far level each is computed [`AHEAD`]
    /// blocks before it is returned, and its entries' lines in `table` prefetched then.
    struct Lookahead<'a> {
        plan: &'a GridPlan,
        level: &'a Level,
        p: [*const f32; 3],
        count: usize,
        table: *const f32,
        ahead: usize,
        ring: [Corners8; AHEAD + 1],
    }

    impl<'a> Lookahead<'a> {
        /// Starts level `l` of `plan` over the points `p` (columns of `count` floats).
        ///
        /// # Safety
        /// The columns of `p` must hold `count` readable floats.
        #[target_feature(enable = "avx2")]
        unsafe fn new(
            plan: &'a GridPlan,
            l: usize,
            p: [*const f32; 3],
            count: usize,
            table: *const f32,
        ) -> Self {
            let zero = Corners8 {
                index: [_mm256_setzero_si256(); 8],
                weight: [_mm256_setzero_ps(); 8],
            };
            let ahead = if plan.far[l] {
                AHEAD.min(count.div_ceil(LANES))
            } else {
                0
            };
            let mut look = Lookahead {
                plan,
                level: &plan.levels[l],
                p,
                count,
                table,
                ahead,
                ring: [zero; AHEAD + 1],
            };
            for b in 0..ahead {
                // SAFETY: passed on; block b starts below count.
                unsafe { look.fetch(b) };
            }
            look
        }

        /// The corners of block `b` (points `8b..8b + 8`).
        ///
        /// # Safety
        /// As for [`Lookahead::new`], with `8b < count`.
        #[inline]
        #[target_feature(enable = "avx2")]
        unsafe fn compute(&self, b: usize) -> Corners8 {
            let start = b * LANES;
            // SAFETY: passed on.
            let points = unsafe { load_points(self.p, start, lanes(start, self.count)) };
            corners(self.plan, self.level, points)
        }

        /// Computes the corners of block `b` into the ring and prefetches their lines.
        ///
        /// # Safety
        /// As for [`Lookahead::compute`].
        #[inline]
        #[target_feature(enable = "avx2")]
        unsafe fn fetch(&mut self, b: usize) {
            // SAFETY: passed on.
            let corners = unsafe { self.compute(b) };
            let mut index = [0u32; LANES];
            for k in 0..8 {
                // SAFETY: 8 lanes into an array of 8.
                unsafe { _mm256_storeu_si256(index.as_mut_ptr().cast(), corners.index[k]) };
                for &i in &index {
                    // A prefetch is a hint that never faults; the address is computed without
                    // dereferencing (lanes past `count` hold the corners of a point at 0, in the table).
                    _mm_prefetch::<_MM_HINT_T0>(self.table.wrapping_add(i as usize).cast());
                }
            }
            self.ring[b % (AHEAD + 1)] = corners;
        }

        /// The corners of block `b`; blocks must be asked for in order 0, 1, ...
        ///
        /// # Safety
        /// As for [`Lookahead::compute`].
        #[inline]
        #[target_feature(enable = "avx2")]
        unsafe fn block(&mut self, b: usize) -> &Corners8 {
            if self.ahead == 0 {
                // SAFETY: passed on.
                self.ring[0] = unsafe { self.compute(b) };
                return &self.ring[0];
            }
            if (b + self.ahead) * LANES < self.count {
                // SAFETY: passed on; that block starts below count.
                unsafe { self.fetch(b + self.ahead) };
            }
            &self.ring[b % (AHEAD + 1)]
        }
    }

    /// All ones in the lanes of the points `start..start + 8` that are below `count`.
    #[target_feature(enable = "avx2")]
    fn lanes(start: usize, count: usize) -> __m256i {
        let n = (count - start).min(LANES) as i32;
        _mm256_cmpgt_epi32(_mm256_set1_epi32(n), _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7))
    }

    /// `GridPlan::corners` for 8 points, operation for operation.
    #[target_feature(enable = "avx2")]
    fn corners(plan: &GridPlan, level: &Level, p: [__m256; 3]) -> Corners8 {
        let res = level.res as f32;
        let zero = _mm256_setzero_ps();
        let one = _mm256_set1_ps(1.0);
        let extent = _mm256_set1_ps(plan.extent);
        let inv_size = _mm256_set1_ps(plan.inv_size);
        let top = _mm256_set1_epi32(level.res.saturating_sub(1) as i32);
        let mut lower = [_mm256_setzero_si256(); 3];
        let mut factor = [[zero; 2]; 3];
        for a in 0..3 {
            let unit = _mm256_mul_ps(_mm256_add_ps(p[a], extent), inv_size);
            let inside = _mm256_and_ps(
                _mm256_cmp_ps::<_CMP_GT_OQ>(unit, zero),
                _mm256_cmp_ps::<_CMP_LT_OQ>(unit, one),
            );
            // max first: it maps NaN to 0 as the scalar path's clamp-then-max does. The product lies in
            // [0, res], so the signed conversion is the scalar path's unsigned one.
            let u = _mm256_mul_ps(_mm256_min_ps(_mm256_max_ps(unit, zero), one), _mm256_set1_ps(res));
            let c = _mm256_min_epu32(_mm256_cvttps_epi32(u), top);
            let f = _mm256_sub_ps(u, _mm256_cvtepi32_ps(c));
            lower[a] = c;
            factor[a] = if plan.deriv >> a & 1 == 1 {
                let s = _mm256_and_ps(inside, _mm256_set1_ps(res * plan.inv_size));
                [_mm256_xor_ps(s, _mm256_set1_ps(-0.0)), s]
            } else {
                [_mm256_sub_ps(one, f), f]
            };
        }
        let features = _mm256_set1_epi32(plan.features as i32);
        let first = _mm256_set1_epi32(plan.table as i32);
        let offset = _mm256_set1_epi32(level.offset as i32);
        let mut corners = Corners8 {
            index: [_mm256_setzero_si256(); 8],
            weight: [zero; 8],
        };
        for k in 0..8usize {
            let bit = |a: usize| k >> a & 1;
            let v = [0, 1, 2].map(|a| _mm256_add_epi32(lower[a], _mm256_set1_epi32(bit(a) as i32)));
            let local = match level.hash_mask {
                Some(mask) => {
                    let h = _mm256_xor_si256(
                        _mm256_xor_si256(
                            v[0],
                            _mm256_mullo_epi32(v[1], _mm256_set1_epi32(2_654_435_761u32 as i32)),
                        ),
                        _mm256_mullo_epi32(v[2], _mm256_set1_epi32(805_459_861)),
                    );
                    _mm256_and_si256(h, _mm256_set1_epi32(mask as i32))
                }
                None => {
                    let n = _mm256_set1_epi32(level.res as i32 + 1);
                    let row = _mm256_add_epi32(_mm256_mullo_epi32(v[2], n), v[1]);
                    _mm256_add_epi32(_mm256_mullo_epi32(row, n), v[0])
                }
            };
            corners.index[k] = _mm256_add_epi32(
                first,
                _mm256_mullo_epi32(_mm256_add_epi32(offset, local), features),
            );
            corners.weight[k] = _mm256_mul_ps(
                _mm256_mul_ps(factor[0][bit(0)], factor[1][bit(1)]),
                factor[2][bit(2)],
            );
        }
        corners
    }

    /// The point columns' lanes `start..start + 8` (0 beyond `count`).
    ///
    /// # Safety
    /// The columns must address `count` readable floats.
    #[target_feature(enable = "avx2")]
    unsafe fn load_points(p: [*const f32; 3], start: usize, m: __m256i) -> [__m256; 3] {
        // SAFETY: the masked lanes are below count.
        p.map(|c| unsafe { _mm256_maskload_ps(c.add(start), m) })
    }

    /// [`GridPlan::read`] on AVX2. With an even number of features, a point's two neighbouring features
    /// come in one 8-byte element of a gather (two gathers of 4 points a corner instead of two of 8 floats:
    /// half the elements; gathers run element by element on AMD Zen), summed in the pairs' interleaved
    /// order and separated into their columns at the end, with the same operations on each value. Full
    /// blocks are stored plainly (masked stores are microcoded on Zen), the last one masked.
    ///
    /// # Safety
    /// As [`GridPlan::read`]'s, with `params.len() ≥ plan.end` and every index below 2^31.
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn read(
        plan: &GridPlan,
        p: [*const f32; 3],
        out: &[*mut f32],
        params: &[f32],
        count: usize,
    ) {
        // Each of points 0–3 (4–7) weight twice, for the two features of its pair.
        let spread = [
            _mm256_setr_epi32(0, 0, 1, 1, 2, 2, 3, 3),
            _mm256_setr_epi32(4, 4, 5, 5, 6, 6, 7, 7),
        ];
        let pairs = plan.feature_pairs();
        for l in 0..plan.levels.len() {
            // SAFETY: the caller's columns hold count floats.
            let mut look = unsafe { Lookahead::new(plan, l, p, count, params.as_ptr()) };
            for (b, start) in (0..count).step_by(LANES).enumerate() {
                let m = lanes(start, count);
                // Each half's 32-bit lane masks widened to its 4 64-bit lanes.
                let half_masks = [
                    _mm256_cvtepi32_epi64(_mm256_castsi256_si128(m)),
                    _mm256_cvtepi32_epi64(_mm256_extracti128_si256::<1>(m)),
                ];
                let store = |column: usize, sum: __m256| {
                    // SAFETY: the output columns hold count floats, and a full block lies below count.
                    unsafe {
                        if start + LANES <= count {
                            _mm256_storeu_ps(out[column].add(start), sum);
                        } else {
                            _mm256_maskstore_ps(out[column].add(start), m, sum);
                        }
                    }
                };
                // SAFETY: as above; the block starts below count.
                let corners = unsafe { look.block(b) };
                for pair in 0..pairs {
                    let shift = _mm256_set1_epi32(2 * pair as i32);
                    let mut sum = [_mm256_setzero_ps(); 2];
                    for k in 0..8 {
                        let at = _mm256_add_epi32(corners.index[k], shift);
                        let halves = [_mm256_castsi256_si128(at), _mm256_extracti128_si256::<1>(at)];
                        for half in 0..2 {
                            // SAFETY: an index + 1 is below plan.end ≤ params.len() (the pair's second
                            // feature), as in the scalar path.
                            let value = _mm256_castsi256_ps(unsafe {
                                _mm256_mask_i32gather_epi64::<4>(
                                    _mm256_setzero_si256(),
                                    params.as_ptr().cast(),
                                    halves[half],
                                    half_masks[half],
                                )
                            });
                            let weight = _mm256_permutevar8x32_ps(corners.weight[k], spread[half]);
                            sum[half] = _mm256_add_ps(sum[half], _mm256_mul_ps(weight, value));
                        }
                    }
                    // Points 0, 1, 4, 5, 2, 3, 6, 7 of each feature, then in order.
                    let first = _mm256_shuffle_ps::<0b10_00_10_00>(sum[0], sum[1]);
                    let second = _mm256_shuffle_ps::<0b11_01_11_01>(sum[0], sum[1]);
                    let order = |v: __m256| {
                        _mm256_castpd_ps(_mm256_permute4x64_pd::<0b11_01_10_00>(_mm256_castps_pd(v)))
                    };
                    let column = l * plan.features + 2 * pair;
                    store(column, order(first));
                    store(column + 1, order(second));
                }
                for f in 2 * pairs..plan.features {
                    let shift = _mm256_set1_epi32(f as i32);
                    let mut sum = _mm256_setzero_ps();
                    for k in 0..8 {
                        // SAFETY: an index + f is below plan.end ≤ params.len(), as in the scalar path.
                        let value = unsafe {
                            _mm256_mask_i32gather_ps::<4>(
                                _mm256_setzero_ps(),
                                params.as_ptr(),
                                _mm256_add_epi32(corners.index[k], shift),
                                _mm256_castsi256_ps(m),
                            )
                        };
                        sum = _mm256_add_ps(sum, _mm256_mul_ps(corners.weight[k], value));
                    }
                    store(l * plan.features + f, sum);
                }
            }
        }
    }

    /// [`GridPlan::scatter`] on AVX2: the corners 8 points at a time, the additions point by point.
    ///
    /// # Safety
    /// As [`GridPlan::scatter_levels`]'s, with the window holding the levels' params (checked there) and
    /// every index below 2^31.
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn scatter(
        plan: &GridPlan,
        p: [*const f32; 3],
        cot: &[*const f32],
        window: GradWindow<'_>,
        count: usize,
        levels: Range<usize>,
    ) {
        let GradWindow { grads, origin } = window;
        let mut index = [[0u32; LANES]; 8];
        let mut weight = [[0.0f32; LANES]; 8];
        for l in levels {
            // The lines the corners' entries fall on, prefetched (an address computed without
            // dereferencing: the window's start minus its origin).
            let table = grads.as_ptr().wrapping_sub(origin);
            // SAFETY: the caller's columns hold count floats.
            let mut look = unsafe { Lookahead::new(plan, l, p, count, table) };
            for (b, start) in (0..count).step_by(LANES).enumerate() {
                // SAFETY: as above; the block starts below count.
                let vectors = unsafe { look.block(b) };
                for k in 0..8 {
                    // SAFETY: 8 lanes into arrays of 8.
                    unsafe {
                        _mm256_storeu_si256(index[k].as_mut_ptr().cast(), vectors.index[k]);
                        _mm256_storeu_ps(weight[k].as_mut_ptr(), vectors.weight[k]);
                    }
                }
                for lane in 0..(count - start).min(LANES) {
                    let corners = Corners {
                        entry: std::array::from_fn(|k| index[k][lane] as usize),
                        weight: std::array::from_fn(|k| weight[k][lane]),
                    };
                    // SAFETY: start + lane < count; the entries are this plan's (as in the scalar path).
                    unsafe { plan.scatter_point(&corners, l, start + lane, cot, grads, origin) };
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use nerfjit_dsl::ir::{GridRead, GridSpec, V};
    use proptest::prelude::*;

    use super::{GradWindow, GridPlan, Path};

    /// A grid of dense and hashed levels with `features` features, its table at param 3.
    fn read(deriv: u8, extent: f32, features: u32) -> GridRead {
        GridRead {
            spec: GridSpec {
                table: 3,
                levels: 5,
                features,
                log2_size: 9,
                base: 3,
                finest: 40,
                extent: extent.to_bits(),
            },
            p: [V(0), V(1), V(2)],
            deriv,
        }
    }

    /// A point coordinate: mostly inside the bounds, sometimes outside, on a face, or NaN.
    fn coordinate() -> impl Strategy<Value = f32> {
        prop_oneof![
            8 => -1.2f32..1.2,
            1 => Just(1.0f32),
            1 => Just(-1.0f32),
            1 => Just(f32::NAN),
            1 => -1e30f32..1e30,
        ]
    }

    proptest! {
        /// The vector paths this machine has (16 points with AVX-512, 8 with AVX2, with and without the
        /// lookahead) give the scalar path's bits, for reads, their derivatives and scatters, at any count
        /// and number of features (an even number goes in pairs on AVX-512).
        #[test]
        fn vector_and_scalar_paths_agree(
            points in proptest::collection::vec([coordinate(), coordinate(), coordinate()], 0..=128),
            deriv in 0u8..8,
            features in 1u32..=4,
            seed in any::<u32>(),
        ) {
            let scalar = GridPlan { path: Path::Scalar, ..GridPlan::new(&read(deriv, 1.0, features)) };
            let columns_out = 5 * features as usize;
            let count = points.len();
            let columns: Vec<Vec<f32>> = (0..3).map(|a| points.iter().map(|p| p[a]).collect()).collect();
            let p = [0, 1, 2].map(|a| columns[a].as_ptr());
            let params: Vec<f32> = (0..scalar.params_end())
                .map(|i| ((i as u32).wrapping_mul(2_654_435_761) ^ seed) as f32 / u32::MAX as f32 - 0.5)
                .collect();
            let outputs = |plan: &GridPlan| {
                let mut out = vec![vec![0.0f32; count]; columns_out];
                let pointers: Vec<*mut f32> = out.iter_mut().map(|c| c.as_mut_ptr()).collect();
                // SAFETY: every column holds count floats.
                unsafe { plan.read(p, &pointers, &params, count) };
                out
            };
            let bits = |c: Vec<Vec<f32>>| c.concat().iter().map(|v| v.to_bits()).collect::<Vec<_>>();

            let cotangent: Vec<Vec<f32>> = (0..columns_out)
                .map(|j| (0..count).map(|t| if (t + j) % 5 == 0 { 0.0 } else { (t * 10 + j) as f32 * 0.01 }).collect())
                .collect();
            let cot: Vec<*const f32> = cotangent.iter().map(|c| c.as_ptr()).collect();
            let scattered = |plan: &GridPlan| {
                let mut grads = vec![0.0f32; plan.params_end()];
                // SAFETY: every column holds count floats.
                unsafe { plan.scatter(p, &cot, &mut grads, count) };
                grads
            };
            // Each vector path with and without the prefetched lookahead (this small table's levels are
            // all near, so `far` is set by hand).
            let paths = Path::available(scalar.params_end()).into_iter().flat_map(|path| [(path, false), (path, true)]);
            for (path, far) in paths {
                let plan = GridPlan { path, far: vec![far; 5], ..GridPlan::new(&read(deriv, 1.0, features)) };
                prop_assert_eq!(bits(outputs(&plan)), bits(outputs(&scalar)), "{:?} far {}", path, far);
                if path == Path::Avx512 {
                    // The same terms, added corner by corner over blocks of 16 points rather than point by
                    // point: the scalar path's additions in that order, bit for bit (points of a block
                    // that share an entry, common in these coarse levels, included).
                    let mut blocked = vec![0.0f32; scalar.params_end()];
                    for (l, level) in scalar.levels.iter().enumerate() {
                        for start in (0..count).step_by(16) {
                            let block = start..count.min(start + 16);
                            let corners: Vec<_> = block.clone().map(|t| scalar.corners(level, points[t])).collect();
                            for k in 0..8 {
                                for (t, c) in block.clone().zip(&corners) {
                                    for f in 0..features as usize {
                                        let cot = cotangent[l * features as usize + f][t];
                                        if cot != 0.0 {
                                            blocked[c.entry[k] + f] += c.weight[k] * cot;
                                        }
                                    }
                                }
                            }
                        }
                    }
                    let bits = |g: Vec<f32>| g.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
                    prop_assert_eq!(bits(scattered(&plan)), bits(blocked), "far {}", far);
                } else {
                    // The scalar path's additions in its order.
                    let bits = |g: Vec<f32>| g.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
                    prop_assert_eq!(bits(scattered(&plan)), bits(scattered(&scalar)), "{:?} far {}", path, far);
                }
                // Level by level, each into a window of its own params alone (as a step's held scatters
                // are added): the whole scatter's bits, and nothing outside the windows.
                let mut by_level = vec![0.0f32; plan.params_end()];
                let mut rest = by_level.as_mut_slice();
                let mut at = 0;
                for l in 0..plan.levels() {
                    let params = plan.level_params(l);
                    prop_assert_eq!(params.start, at.max(3), "levels follow each other from the table on");
                    let (_, tail) = std::mem::take(&mut rest).split_at_mut(params.start - at);
                    let (grads, tail) = tail.split_at_mut(params.len());
                    let window = GradWindow { grads, origin: params.start };
                    // SAFETY: every column holds count floats.
                    unsafe { plan.scatter_levels(p, &cot, window, count, l..l + 1) };
                    rest = tail;
                    at = params.end;
                }
                prop_assert_eq!(at, plan.params_end());
                let bits = |g: Vec<f32>| g.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
                prop_assert_eq!(bits(by_level), bits(scattered(&plan)), "{:?} far {} by level", path, far);
            }
        }
    }
}
