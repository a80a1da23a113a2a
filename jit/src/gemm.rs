//! The matrix products of dense layers on tiles of points, with AVX-512 and AVX2 micro-kernels.
//!
//! Activations are stored feature-major: one column of [`TILE`] floats per feature (the layout of the
//! JIT kernels' buffers), so a layer's input is a list of column pointers and needs no packing.
//! - [`matmul`]: `out_i = Σ_k A[i][k] · x_k` for a row-major matrix A (the forward product, and with Wᵀ
//!   the backward product of a layer). The micro-kernel keeps a block of 6 rows × 64 points in 24
//!   registers and streams the input columns: per input feature, 4 loads, 6 broadcasts and 24 FMAs.
//! - [`outer`]: `G[i][j] += Σ_t l_i[t] · r_j[t]` over the valid points of a tile (the gradient of a matrix).
//!   The right operand is transposed to point-major rows first, 64 columns at a time (16 × 16 blocks in
//!   registers, into a buffer that starts on a cache line), so that the micro-kernel again broadcasts one
//!   operand and streams the other into 6 × 64 accumulators, over all of a tile's points at once.
//! - [`crate::bf16`] has the same two products with bfloat16 operands, on AMX tiles where the CPU has them.
//!
//! Both run the widest [`Backend`] the CPU has (checked once at run time): 512-bit micro-kernels with
//! AVX-512F, 256-bit ones (6 rows × 16 points) with AVX2 and FMA, portable loops otherwise.

use std::ops::Range;
use std::sync::OnceLock;

/// The points of one tile (a multiple of 64, the width of the micro-kernels' point blocks).
pub const TILE: usize = 128;

/// The columns of the right operand [`outer`] transposes and consumes at a time: all of a tile's points
/// for 64 columns are 32 KB, which stay in L1 while every row block of G reads them.
const OUTER_COLUMNS: usize = 64;

/// Floats from one column of a tiled kernel's arena to the next: a tile's points and one cache line more
/// (576 bytes, 9 lines), so that the columns a product or segment reads at the same points fall in
/// different sets of the L1 cache. At 512 bytes apart they would share a quarter of the sets (lines
/// 0–3 of every eighth), fewer ways than the hundred-odd columns a layer reads at once.
pub const COLUMN: usize = TILE + 16;

/// Whether this CPU runs AVX-512 (checked once).
pub(crate) fn has_avx512() -> bool {
    static HAS: OnceLock<bool> = OnceLock::new();
    *HAS.get_or_init(|| {
        #[cfg(target_arch = "x86_64")]
        {
            std::arch::is_x86_feature_detected!("avx512f")
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            false
        }
    })
}

/// `len` floats of `buffer` (resized, its old values kept or zeroed) starting on a 64-byte cache line.
pub(crate) fn line_aligned(buffer: &mut Vec<f32>, len: usize) -> &mut [f32] {
    buffer.resize(len + 16, 0.0);
    let skip = buffer.as_ptr().align_offset(64).min(16);
    &mut buffer[skip..skip + len]
}

/// The width to which [`outer`] pads the right operand (and the rows of its accumulator).
pub fn padded(n: usize) -> usize {
    n.div_ceil(16) * 16
}

/// The instruction set a product runs on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Backend {
    /// 512-bit micro-kernels (AVX-512F).
    Avx512,
    /// 256-bit micro-kernels (AVX2 with FMA).
    Avx2,
    /// Plain loops, vectorized as the compiler can for the baseline target.
    Portable,
}

impl Backend {
    /// The widest backend this CPU runs.
    pub fn best() -> Backend {
        if has_avx512() {
            Backend::Avx512
        } else if has_avx2_fma() {
            Backend::Avx2
        } else {
            Backend::Portable
        }
    }

    /// Every backend this CPU runs, widest first.
    #[cfg_attr(not(feature = "bench"), allow(dead_code))] // its tests' and the benchmarks'
    pub fn available() -> Vec<Backend> {
        let mut all = Vec::new();
        if has_avx512() {
            all.push(Backend::Avx512);
        }
        if has_avx2_fma() {
            all.push(Backend::Avx2);
        }
        all.push(Backend::Portable);
        all
    }
}

/// Whether this CPU runs AVX2 and FMA (checked once).
pub(crate) fn has_avx2_fma() -> bool {
    static HAS: OnceLock<bool> = OnceLock::new();
    *HAS.get_or_init(|| {
        #[cfg(target_arch = "x86_64")]
        {
            std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            false
        }
    })
}

/// `out[i][t] = Σ_k a[i·k_len + k] · x[k][t]` for i < `out.len()` and t < `count` (≤ [`TILE`]), where k_len
/// = `x.len()`; the points from `count` up to the next multiple of 16 get their products too, the others
/// are left as they are. Each point's sums are the same whatever `count`.
///
/// # Safety
/// Every pointer of `x` must address [`TILE`] readable floats and every pointer of `out` [`TILE`]
/// writable floats that no pointer of `x` overlaps; `a` must hold `out.len() · x.len()` floats.
pub unsafe fn matmul(a: &[f32], x: &[*const f32], out: &[*mut f32], count: usize) {
    // SAFETY: the best backend runs on this CPU; the buffers are as the caller guarantees.
    unsafe { matmul_on(Backend::best(), a, x, out, count) }
}

/// [`matmul`] on a given backend.
///
/// # Safety
/// As [`matmul`], and `backend` must be one of [`Backend::available`].
pub unsafe fn matmul_on(backend: Backend, a: &[f32], x: &[*const f32], out: &[*mut f32], count: usize) {
    assert!(a.len() >= out.len() * x.len(), "matrix smaller than its product");
    assert!(count <= TILE, "more points than a tile");
    let count = count.next_multiple_of(16);
    // SAFETY: the backend runs on this CPU and the buffers are as the caller guarantees.
    unsafe {
        match backend {
            #[cfg(target_arch = "x86_64")]
            Backend::Avx512 => avx512::matmul(a, x, out, count),
            #[cfg(target_arch = "x86_64")]
            Backend::Avx2 => avx2::matmul(a, x, out, count),
            _ => matmul_plain(a, x, out, count),
        }
    }
}

/// [`matmul`] in plain loops, over points `0..count`.
///
/// # Safety
/// As [`matmul`].
unsafe fn matmul_plain(a: &[f32], x: &[*const f32], out: &[*mut f32], count: usize) {
    let k_len = x.len();
    for (i, &o) in out.iter().enumerate() {
        // SAFETY: `o` addresses TILE ≥ count floats that no input overlaps (caller).
        let o = unsafe { std::slice::from_raw_parts_mut(o, count) };
        o.fill(0.0);
        for (k, &xk) in x.iter().enumerate() {
            let w = a[i * k_len + k];
            // SAFETY: `xk` addresses TILE ≥ count floats (caller).
            let xk = unsafe { std::slice::from_raw_parts(xk, count) };
            for (ot, xt) in o.iter_mut().zip(xk) {
                *ot += w * xt;
            }
        }
    }
}

/// `g[i·stride + j] += Σ_{t < count} l[i][t] · r[j][t]` for i < `l.len()`, j < `r.len()`, with
/// stride = [`padded`]`(r.len())`. `scratch` is reused between calls (the transposed right operand).
///
/// # Safety
/// Every pointer of `l` and `r` must address `count` readable floats.
pub unsafe fn outer(l: &[*const f32], r: &[*const f32], count: usize, g: &mut [f32], scratch: &mut Vec<f32>) {
    // SAFETY: the best backend runs on this CPU; the buffers are as the caller guarantees.
    unsafe { outer_on(Backend::best(), l, r, count, g, scratch) }
}

/// [`outer`] on a given backend.
///
/// # Safety
/// As [`outer`], and `backend` must be one of [`Backend::available`].
pub unsafe fn outer_on(
    backend: Backend,
    l: &[*const f32],
    r: &[*const f32],
    count: usize,
    g: &mut [f32],
    scratch: &mut Vec<f32>,
) {
    let stride = padded(r.len());
    assert!(count <= TILE, "more points than a tile");
    assert!(g.len() >= l.len() * stride, "gradient buffer too small");
    // A block of columns at a time, over all the points: each row block of G then takes the whole tile's
    // points in one pass (its accumulators added to G once a tile), and the block's transposed columns
    // (32 KB) are written and read again in L1. The transposed block starts on a cache line, so that its
    // rows (a multiple of 16 floats) do too and no vector load straddles two lines.
    for j0 in (0..r.len()).step_by(OUTER_COLUMNS) {
        let columns = &r[j0..r.len().min(j0 + OUTER_COLUMNS)];
        let width = padded(columns.len());
        let rt = line_aligned(scratch, count * width);
        // Only the padding columns need clearing: the transposes write the others.
        for row in rt.chunks_exact_mut(width) {
            row[columns.len()..].fill(0.0);
        }
        let g = &mut g[j0..];
        // SAFETY (every arm): the backend runs on this CPU; sizes were checked above and by the caller.
        match backend {
            #[cfg(target_arch = "x86_64")]
            Backend::Avx512 => unsafe {
                avx512::transpose(columns, 0..count, rt, width);
                avx512::outer(l, rt, width, count, g, stride)
            },
            #[cfg(target_arch = "x86_64")]
            Backend::Avx2 => unsafe {
                avx2::transpose(columns, 0..count, rt, width);
                avx2::outer(l, rt, width, count, g, stride)
            },
            _ => {
                transpose_plain(columns, 0, 0..count, rt, width);
                for (i, &li) in l.iter().enumerate() {
                    // SAFETY: `li` addresses `count` floats (caller).
                    let li = unsafe { std::slice::from_raw_parts(li, count) };
                    let row = &mut g[i * stride..i * stride + width];
                    for (t, &lv) in li.iter().enumerate() {
                        for (gj, rv) in row.iter_mut().zip(&rt[t * width..(t + 1) * width]) {
                            *gj += lv * rv;
                        }
                    }
                }
            }
        }
    }
}

/// `rt[(t − points.start)·stride + j] = r[j][t]` for j ≥ `j0` and t in `points`.
fn transpose_plain(r: &[*const f32], j0: usize, points: Range<usize>, rt: &mut [f32], stride: usize) {
    for (j, &rj) in r.iter().enumerate().skip(j0) {
        // SAFETY: `rj` addresses the floats of `points` (the callers' contract).
        let rj = unsafe { std::slice::from_raw_parts(rj.add(points.start), points.len()) };
        for (t, &v) in rj.iter().enumerate() {
            rt[t * stride + j] = v;
        }
    }
}

/// What the blocked transposes leave to plain code: the columns from `full_j` at every point of `points`,
/// and the points from `points.start + full_t` in the columns before `full_j`.
fn transpose_edges(
    r: &[*const f32],
    full_j: usize,
    points: Range<usize>,
    full_t: usize,
    rt: &mut [f32],
    stride: usize,
) {
    transpose_plain(r, full_j, points.clone(), rt, stride);
    transpose_plain(
        &r[..full_j],
        0,
        points.start + full_t..points.end,
        &mut rt[full_t * stride..],
        stride,
    );
}

#[cfg(target_arch = "x86_64")]
pub(crate) mod avx512 {
    use std::arch::x86_64::*;
    use std::ops::Range;

    /// Rows of A per register block of the product.
    const MR: usize = 6;
    /// Rows of G per register block of the outer product.
    const GR: usize = 6;

    /// Vectors of 16 points per register block of the product.
    const QV: usize = 4;

    /// Points `0..count` (a multiple of 16) of the product.
    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn matmul(a: &[f32], x: &[*const f32], out: &[*mut f32], count: usize) {
        // Point blocks outermost: a block's inputs (k × 16·QV floats) stay in L1 for every row block.
        let full = count / (16 * QV) * (16 * QV);
        // SAFETY (all blocks): as the caller guarantees, with t0 + 16·Q ≤ count ≤ TILE.
        unsafe {
            for t0 in (0..full).step_by(16 * QV) {
                matmul_rows::<QV>(a, x, out, t0);
            }
            match (count - full) / 16 {
                3 => matmul_rows::<3>(a, x, out, full),
                2 => matmul_rows::<2>(a, x, out, full),
                1 => matmul_rows::<1>(a, x, out, full),
                _ => {}
            }
        }
    }

    /// Every row of the product for the 16·Q points from `t0`.
    #[target_feature(enable = "avx512f")]
    #[inline]
    unsafe fn matmul_rows<const Q: usize>(a: &[f32], x: &[*const f32], out: &[*mut f32], t0: usize) {
        let k = x.len();
        let mut i = 0;
        // SAFETY (all blocks): rows i.. of A exist (checked by the caller), columns hold t0 + 16·Q ≤ TILE
        // floats.
        unsafe {
            while i + MR <= out.len() {
                matmul_block::<MR, Q>(a.as_ptr().add(i * k), x, &out[i..i + MR], t0);
                i += MR;
            }
            match out.len() - i {
                5 => matmul_block::<5, Q>(a.as_ptr().add(i * k), x, &out[i..], t0),
                4 => matmul_block::<4, Q>(a.as_ptr().add(i * k), x, &out[i..], t0),
                3 => matmul_block::<3, Q>(a.as_ptr().add(i * k), x, &out[i..], t0),
                2 => matmul_block::<2, Q>(a.as_ptr().add(i * k), x, &out[i..], t0),
                1 => matmul_block::<1, Q>(a.as_ptr().add(i * k), x, &out[i..], t0),
                _ => {}
            }
        }
    }

    /// R rows of the product for the 16·Q points from `t0`.
    #[target_feature(enable = "avx512f")]
    #[inline]
    unsafe fn matmul_block<const R: usize, const Q: usize>(
        a: *const f32,
        x: &[*const f32],
        out: &[*mut f32],
        t0: usize,
    ) {
        let k = x.len();
        let mut acc = [[_mm512_setzero_ps(); Q]; R];
        for (kk, &xk) in x.iter().enumerate() {
            // SAFETY: xk addresses TILE floats and t0 + 16·Q ≤ TILE; row r of A has k floats.
            unsafe {
                let p = xk.add(t0);
                let mut b = [_mm512_setzero_ps(); Q];
                for (q, bq) in b.iter_mut().enumerate() {
                    *bq = _mm512_loadu_ps(p.add(16 * q));
                }
                for (r, acc_r) in acc.iter_mut().enumerate() {
                    let w = _mm512_set1_ps(*a.add(r * k + kk));
                    for q in 0..Q {
                        acc_r[q] = _mm512_fmadd_ps(w, b[q], acc_r[q]);
                    }
                }
            }
        }
        for (r, acc_r) in acc.iter().enumerate() {
            for (q, v) in acc_r.iter().enumerate() {
                // SAFETY: out[r] addresses TILE writable floats.
                unsafe { _mm512_storeu_ps(out[r].add(t0 + 16 * q), *v) };
            }
        }
    }

    /// `g[i·g_stride + j] += Σ_{t < count} l[i][t] · rt[t·width + j]` for j < `width` (a multiple of 16).
    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn outer(
        l: &[*const f32],
        rt: &[f32],
        width: usize,
        count: usize,
        g: &mut [f32],
        g_stride: usize,
    ) {
        let mut i = 0;
        while i < l.len() {
            let rows = (l.len() - i).min(GR);
            let mut j = 0;
            while j < width {
                let vecs = ((width - j) / 16).min(4);
                // SAFETY: rows i..i+rows of G and its columns j..j+16·vecs ≤ width exist; l pointers hold
                // `count` floats and rt holds a row of `width` floats for each (caller).
                unsafe {
                    let blk = Block {
                        l: &l[i..i + rows],
                        rt: rt.as_ptr().add(j),
                        width,
                        count,
                        g: g.as_mut_ptr().add(i * g_stride + j),
                        g_stride,
                    };
                    match (rows, vecs) {
                        (6, 4) => blk.run::<6, 4>(),
                        (6, 3) => blk.run::<6, 3>(),
                        (6, 2) => blk.run::<6, 2>(),
                        (6, 1) => blk.run::<6, 1>(),
                        (5, 4) => blk.run::<5, 4>(),
                        (5, 3) => blk.run::<5, 3>(),
                        (5, 2) => blk.run::<5, 2>(),
                        (5, 1) => blk.run::<5, 1>(),
                        (4, 4) => blk.run::<4, 4>(),
                        (4, 3) => blk.run::<4, 3>(),
                        (4, 2) => blk.run::<4, 2>(),
                        (4, 1) => blk.run::<4, 1>(),
                        (3, 4) => blk.run::<3, 4>(),
                        (3, 3) => blk.run::<3, 3>(),
                        (3, 2) => blk.run::<3, 2>(),
                        (3, 1) => blk.run::<3, 1>(),
                        (2, 4) => blk.run::<2, 4>(),
                        (2, 3) => blk.run::<2, 3>(),
                        (2, 2) => blk.run::<2, 2>(),
                        (2, 1) => blk.run::<2, 1>(),
                        (1, 4) => blk.run::<1, 4>(),
                        (1, 3) => blk.run::<1, 3>(),
                        (1, 2) => blk.run::<1, 2>(),
                        _ => blk.run::<1, 1>(),
                    }
                }
                j += 16 * vecs;
            }
            i += rows;
        }
    }

    /// `rt[(t − points.start)·stride + j] = r[j][t]` for t in `points`: 16 × 16 blocks in registers
    /// (unpacks and lane shuffles), the edges in plain code.
    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn transpose(r: &[*const f32], points: Range<usize>, rt: &mut [f32], stride: usize) {
        let (first, count) = (points.start, points.len());
        let (full_j, full_t) = (r.len() / 16 * 16, count / 16 * 16);
        for j0 in (0..full_j).step_by(16) {
            for t0 in (0..full_t).step_by(16) {
                // SAFETY: rows j0..j0+16 hold the points first + t0 .. first + t0 + 16; rt holds count
                // rows of stride ≥ j0 + 16 floats.
                unsafe {
                    let rows: [__m512; 16] =
                        std::array::from_fn(|q| _mm512_loadu_ps(r[j0 + q].add(first + t0)));
                    let cols = transpose16(rows);
                    for (p, v) in cols.iter().enumerate() {
                        _mm512_storeu_ps(rt.as_mut_ptr().add((t0 + p) * stride + j0), *v);
                    }
                }
            }
        }
        // The columns past the last whole block of rows, and the points past the last whole block.
        super::transpose_edges(r, full_j, points, full_t, rt, stride);
    }

    /// The transpose of a 16 × 16 block held as 16 rows.
    #[target_feature(enable = "avx512f")]
    #[inline]
    pub(crate) fn transpose16(r: [__m512; 16]) -> [__m512; 16] {
        // Interleave pairs of rows, then pairs of pairs (4 × 4 blocks inside each 128-bit lane), then
        // exchange 128-bit lanes twice.
        let t: [__m512; 16] = std::array::from_fn(|i| {
            let (a, b) = (r[i / 2 * 2], r[i / 2 * 2 + 1]);
            if i % 2 == 0 {
                _mm512_unpacklo_ps(a, b)
            } else {
                _mm512_unpackhi_ps(a, b)
            }
        });
        let pd = |x: __m512| _mm512_castps_pd(x);
        let u: [__m512; 16] = std::array::from_fn(|i| {
            let group = i / 4 * 4;
            let (a, b) = (t[group + (i % 4) / 2], t[group + 2 + (i % 4) / 2]);
            if i % 2 == 0 {
                _mm512_castpd_ps(_mm512_unpacklo_pd(pd(a), pd(b)))
            } else {
                _mm512_castpd_ps(_mm512_unpackhi_pd(pd(a), pd(b)))
            }
        });
        let v: [__m512; 16] = std::array::from_fn(|i| {
            let base = i / 8 * 8;
            let (a, b) = (u[base + i % 4], u[base + 4 + i % 4]);
            if i % 8 < 4 {
                _mm512_shuffle_f32x4::<0x88>(a, b)
            } else {
                _mm512_shuffle_f32x4::<0xdd>(a, b)
            }
        });
        std::array::from_fn(|i| {
            let (a, b) = (v[i % 8], v[8 + i % 8]);
            if i < 8 {
                _mm512_shuffle_f32x4::<0x88>(a, b)
            } else {
                _mm512_shuffle_f32x4::<0xdd>(a, b)
            }
        })
    }

    /// One register block of the outer product: R rows of G × 16·N columns, over `count` points (row t of
    /// `rt`, `width` floats apart, holding point t).
    struct Block<'a> {
        l: &'a [*const f32],
        rt: *const f32,
        width: usize,
        count: usize,
        g: *mut f32,
        g_stride: usize,
    }

    impl Block<'_> {
        #[target_feature(enable = "avx512f")]
        #[inline]
        unsafe fn run<const R: usize, const N: usize>(&self) {
            let mut acc = [[_mm512_setzero_ps(); N]; R];
            for t in 0..self.count {
                // SAFETY: row t of rt has 16·N floats from this block's start; l[r] has the block's points.
                unsafe {
                    let row = self.rt.add(t * self.width);
                    let mut b = [_mm512_setzero_ps(); N];
                    for (q, bq) in b.iter_mut().enumerate() {
                        *bq = _mm512_loadu_ps(row.add(16 * q));
                    }
                    for (r, acc_r) in acc.iter_mut().enumerate() {
                        let lv = _mm512_set1_ps(*self.l[r].add(t));
                        for q in 0..N {
                            acc_r[q] = _mm512_fmadd_ps(lv, b[q], acc_r[q]);
                        }
                    }
                }
            }
            for (r, acc_r) in acc.iter().enumerate() {
                for (q, v) in acc_r.iter().enumerate() {
                    // SAFETY: row r of G has 16·N floats from this block's start.
                    unsafe {
                        let p = self.g.add(r * self.g_stride + 16 * q);
                        _mm512_storeu_ps(p, _mm512_add_ps(_mm512_loadu_ps(p), *v));
                    }
                }
            }
        }
    }
}

/// The 256-bit micro-kernels: as the 512-bit ones with 8-float vectors and the register blocks that fit
/// AVX2's 16 registers (6 rows × 16 points: 12 accumulators, 2 loaded vectors, 1 broadcast).
#[cfg(target_arch = "x86_64")]
mod avx2 {
    use std::arch::x86_64::*;
    use std::ops::Range;

    /// Rows per register block (of the product's A, and of the outer product's G).
    const MR: usize = 6;
    /// Vectors of 8 floats per register block (16 points of the product, 16 columns of G).
    const NV: usize = 2;

    /// Points `0..count` (a multiple of 16) of the product.
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn matmul(a: &[f32], x: &[*const f32], out: &[*mut f32], count: usize) {
        let k = x.len();
        // Point blocks outermost: a block's inputs (k × 16 floats) stay in L1 for every row block.
        for t0 in (0..count).step_by(8 * NV) {
            let mut i = 0;
            // SAFETY (all blocks): rows i.. of A exist (checked by the caller), columns hold TILE floats.
            unsafe {
                while i + MR <= out.len() {
                    matmul_block::<MR>(a.as_ptr().add(i * k), x, &out[i..i + MR], t0);
                    i += MR;
                }
                match out.len() - i {
                    5 => matmul_block::<5>(a.as_ptr().add(i * k), x, &out[i..], t0),
                    4 => matmul_block::<4>(a.as_ptr().add(i * k), x, &out[i..], t0),
                    3 => matmul_block::<3>(a.as_ptr().add(i * k), x, &out[i..], t0),
                    2 => matmul_block::<2>(a.as_ptr().add(i * k), x, &out[i..], t0),
                    1 => matmul_block::<1>(a.as_ptr().add(i * k), x, &out[i..], t0),
                    _ => {}
                }
            }
        }
    }

    /// R rows of the product for the 8·NV points from `t0`.
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    unsafe fn matmul_block<const R: usize>(a: *const f32, x: &[*const f32], out: &[*mut f32], t0: usize) {
        let k = x.len();
        let mut acc = [[_mm256_setzero_ps(); NV]; R];
        // SAFETY: row r of A has k floats.
        let rows: [*const f32; R] = std::array::from_fn(|r| unsafe { a.add(r * k) });
        for (kk, &xk) in x.iter().enumerate() {
            // SAFETY: xk addresses TILE floats and t0 + 8·NV ≤ TILE; kk < k.
            unsafe {
                let p = xk.add(t0);
                let b: [__m256; NV] = std::array::from_fn(|q| _mm256_loadu_ps(p.add(8 * q)));
                for (r, acc_r) in acc.iter_mut().enumerate() {
                    let w = _mm256_broadcast_ss(&*rows[r].add(kk));
                    for q in 0..NV {
                        acc_r[q] = _mm256_fmadd_ps(w, b[q], acc_r[q]);
                    }
                }
            }
        }
        for (r, acc_r) in acc.iter().enumerate() {
            for (q, v) in acc_r.iter().enumerate() {
                // SAFETY: out[r] addresses TILE writable floats.
                unsafe { _mm256_storeu_ps(out[r].add(t0 + 8 * q), *v) };
            }
        }
    }

    /// `g[i·g_stride + j] += Σ_{t < count} l[i][t] · rt[t·width + j]` for j < `width` (a multiple of 16,
    /// 8·NV).
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn outer(
        l: &[*const f32],
        rt: &[f32],
        width: usize,
        count: usize,
        g: &mut [f32],
        g_stride: usize,
    ) {
        debug_assert_eq!(width % (8 * NV), 0);
        let mut i = 0;
        while i < l.len() {
            let rows = (l.len() - i).min(MR);
            for j in (0..width).step_by(8 * NV) {
                // SAFETY: rows i..i+rows of G and its columns j..j+16 ≤ width exist; l pointers hold
                // `count` floats and rt holds a row of `width` floats for each (caller).
                unsafe {
                    let (l, rt, g) = (
                        &l[i..i + rows],
                        rt.as_ptr().add(j),
                        g.as_mut_ptr().add(i * g_stride + j),
                    );
                    let rt = (rt, width);
                    match rows {
                        6 => outer_block::<6>(l, rt, count, g, g_stride),
                        5 => outer_block::<5>(l, rt, count, g, g_stride),
                        4 => outer_block::<4>(l, rt, count, g, g_stride),
                        3 => outer_block::<3>(l, rt, count, g, g_stride),
                        2 => outer_block::<2>(l, rt, count, g, g_stride),
                        _ => outer_block::<1>(l, rt, count, g, g_stride),
                    }
                }
            }
            i += rows;
        }
    }

    /// R rows of G × 16 columns: `g[r·g_stride + c] += Σ_{t < count} l[r][t] · rt[t·width + c]`, where
    /// `(rt, width)` is the transposed operand from this block's first column and its row length.
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    unsafe fn outer_block<const R: usize>(
        l: &[*const f32],
        (rt, width): (*const f32, usize),
        count: usize,
        g: *mut f32,
        g_stride: usize,
    ) {
        let mut acc = [[_mm256_setzero_ps(); NV]; R];
        for t in 0..count {
            // SAFETY: row t of rt has 16 floats from this block's start; l[r] has the block's points.
            unsafe {
                let row = rt.add(t * width);
                let b: [__m256; NV] = std::array::from_fn(|q| _mm256_loadu_ps(row.add(8 * q)));
                for (r, acc_r) in acc.iter_mut().enumerate() {
                    let lv = _mm256_broadcast_ss(&*l[r].add(t));
                    for q in 0..NV {
                        acc_r[q] = _mm256_fmadd_ps(lv, b[q], acc_r[q]);
                    }
                }
            }
        }
        for (r, acc_r) in acc.iter().enumerate() {
            for (q, v) in acc_r.iter().enumerate() {
                // SAFETY: row r of G has 16 floats from this block's start.
                unsafe {
                    let p = g.add(r * g_stride + 8 * q);
                    _mm256_storeu_ps(p, _mm256_add_ps(_mm256_loadu_ps(p), *v));
                }
            }
        }
    }

    /// `rt[(t − points.start)·stride + j] = r[j][t]` for t in `points`: 8 × 8 blocks in registers, the
    /// edges in plain code.
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn transpose(r: &[*const f32], points: Range<usize>, rt: &mut [f32], stride: usize) {
        let (first, count) = (points.start, points.len());
        let (full_j, full_t) = (r.len() / 8 * 8, count / 8 * 8);
        for j0 in (0..full_j).step_by(8) {
            for t0 in (0..full_t).step_by(8) {
                // SAFETY: rows j0..j0+8 hold the points first + t0 .. first + t0 + 8; rt holds count rows
                // of stride ≥ j0 + 8 floats.
                unsafe {
                    let rows: [__m256; 8] =
                        std::array::from_fn(|q| _mm256_loadu_ps(r[j0 + q].add(first + t0)));
                    let cols = transpose8(rows);
                    for (p, v) in cols.iter().enumerate() {
                        _mm256_storeu_ps(rt.as_mut_ptr().add((t0 + p) * stride + j0), *v);
                    }
                }
            }
        }
        super::transpose_edges(r, full_j, points, full_t, rt, stride);
    }

    /// The transpose of an 8 × 8 block held as 8 rows: interleave pairs of rows, gather 4 × 4 blocks inside
    /// each 128-bit lane, then exchange lanes.
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    fn transpose8(r: [__m256; 8]) -> [__m256; 8] {
        let t: [__m256; 8] = std::array::from_fn(|i| {
            let (a, b) = (r[i / 2 * 2], r[i / 2 * 2 + 1]);
            if i % 2 == 0 {
                _mm256_unpacklo_ps(a, b)
            } else {
                _mm256_unpackhi_ps(a, b)
            }
        });
        // u[4h + c] holds columns c and c + 4 of rows 4h..4h+4 (one per lane).
        let u: [__m256; 8] = std::array::from_fn(|i| {
            let (h, c) = (i / 4, i % 4);
            let (a, b) = (t[4 * h + c / 2], t[4 * h + 2 + c / 2]);
            if c % 2 == 0 {
                _mm256_shuffle_ps::<0x44>(a, b)
            } else {
                _mm256_shuffle_ps::<0xee>(a, b)
            }
        });
        std::array::from_fn(|i| {
            let (a, b) = (u[i % 4], u[4 + i % 4]);
            if i < 4 {
                _mm256_permute2f128_ps::<0x20>(a, b)
            } else {
                _mm256_permute2f128_ps::<0x31>(a, b)
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn column(seed: u32, len: usize) -> Vec<f32> {
        (0..len)
            .map(|t| (((t as u32 * 2654435761u32) ^ seed.wrapping_mul(40503)) % 1000) as f32 / 500.0 - 1.0)
            .collect()
    }

    /// On every backend, for every count of points: the plain product at the points up to the next
    /// multiple of 16, the very bits of the whole tile's product there, the other points untouched.
    #[test]
    fn matmul_matches_a_plain_product() {
        for (m, k) in [
            (1, 1),
            (3, 5),
            (4, 39),
            (7, 16),
            (128, 128),
            (9, 143),
            (64, 32),
            (17, 27),
        ] {
            let a = column(7, m * k);
            let xs: Vec<Vec<f32>> = (0..k).map(|c| column(c as u32, TILE)).collect();
            for backend in Backend::available() {
                let product = |count: usize| {
                    let mut outs = vec![vec![f32::NAN; TILE]; m];
                    let xp: Vec<*const f32> = xs.iter().map(|c| c.as_ptr()).collect();
                    let op: Vec<*mut f32> = outs.iter_mut().map(|c| c.as_mut_ptr()).collect();
                    // SAFETY: every column has TILE floats; outputs are separate buffers; the backend is
                    // available.
                    unsafe { matmul_on(backend, &a, &xp, &op, count) };
                    outs
                };
                let whole = product(TILE);
                for i in 0..m {
                    for t in 0..TILE {
                        let want: f64 = (0..k)
                            .map(|c| f64::from(a[i * k + c]) * f64::from(xs[c][t]))
                            .sum();
                        assert!(
                            (f64::from(whole[i][t]) - want).abs() < 1e-4,
                            "{backend:?} {m}x{k} at ({i}, {t})"
                        );
                    }
                }
                for count in [1, 15, 16, 17, 40, 64, 65, 100, 127] {
                    let part = product(count);
                    let done = count.next_multiple_of(16);
                    for i in 0..m {
                        assert_eq!(
                            part[i][..done].iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                            whole[i][..done].iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                            "{backend:?} {m}x{k}, {count} points, row {i}"
                        );
                        assert!(
                            part[i][done..].iter().all(|v| v.is_nan()),
                            "{backend:?} wrote past {done}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn outer_accumulates_over_the_valid_points() {
        for (m, n, count) in [
            (1, 1, 1),
            (3, 5, 7),
            (4, 64, 128),
            (6, 39, 100),
            (128, 143, 128),
            (13, 24, 9),
            (64, 32, 128),
            (5, 3, 0),
        ] {
            let ls: Vec<Vec<f32>> = (0..m).map(|c| column(c as u32 + 100, TILE)).collect();
            let rs: Vec<Vec<f32>> = (0..n).map(|c| column(c as u32 + 300, TILE)).collect();
            let stride = padded(n);
            for backend in Backend::available() {
                let mut g = vec![1.0f32; m * stride];
                let lp: Vec<*const f32> = ls.iter().map(|c| c.as_ptr()).collect();
                let rp: Vec<*const f32> = rs.iter().map(|c| c.as_ptr()).collect();
                let mut scratch = Vec::new();
                // SAFETY: every column has TILE ≥ count floats; the backend is available.
                unsafe { outer_on(backend, &lp, &rp, count, &mut g, &mut scratch) };
                for i in 0..m {
                    for j in 0..n {
                        let want: f64 = 1.0
                            + (0..count)
                                .map(|t| f64::from(ls[i][t]) * f64::from(rs[j][t]))
                                .sum::<f64>();
                        let got = f64::from(g[i * stride + j]);
                        assert!(
                            (got - want).abs() < 1e-4,
                            "{backend:?} {m}x{n}x{count} at ({i}, {j}): {got} vs {want}"
                        );
                    }
                }
            }
        }
    }
}
