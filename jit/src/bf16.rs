//! Matrix products with bfloat16 operands and f32 sums, for the dense layers of kernels compiled with
//! [`Precision::Bf16`]: [`matmul`] (forward and backward products) and [`outer`] (weight gradients).
//!
//! Both operands are rounded to bfloat16 (8 significant bits, to nearest, ties to even) and their products
//! summed in f32, as mixed-precision training on GPUs does. The products run on the fastest [`Unit`] the
//! CPU has: AMX's tile unit (Intel's, from Sapphire Rapids on, once the kernel grants the process its
//! tile state: 3.5–4× the f32 micro-kernels' rate on 128-wide layers), AVX-512 BF16's dot products of
//! pairs (Cooper Lake, Zen 4 and later: twice that rate), or else the rounded operands through the f32
//! [`gemm::matmul`]. All give the same numbers up to the order of the sums (a product of two bfloat16
//! values is exact in f32), but for subnormal operands and sums, which AMX and AVX-512 BF16 take as 0.

use std::sync::OnceLock;

use crate::gemm::{self, TILE};

/// The arithmetic of dense products.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum Precision {
    /// f32 operands and sums.
    #[default]
    F32,
    /// bfloat16 operands, f32 sums.
    Bf16,
}

impl Precision {
    /// Every precision, by the name scripts and the command line give it.
    pub const NAMED: [(&'static str, Precision); 2] = [("f32", Precision::F32), ("bf16", Precision::Bf16)];

    /// The precision called `name` (`f32` or `bf16`).
    pub fn named(name: &str) -> Option<Precision> {
        Self::NAMED.iter().find(|(n, _)| *n == name).map(|&(_, p)| p)
    }

    /// Its name in scripts and on the command line.
    pub fn name(self) -> &'static str {
        Self::NAMED
            .iter()
            .find(|(_, p)| *p == self)
            .map_or("f32", |&(n, _)| n)
    }
}

/// The bfloat16 nearest `x` (ties to even) in the low 16 bits; NaN stays a (quiet) NaN. Branch-free, so
/// that loops of it vectorize.
fn bf16_bits(x: f32) -> u16 {
    let b = x.to_bits();
    let rounded = (b.wrapping_add(0x7fff + ((b >> 16) & 1)) >> 16) as u16;
    let quiet = ((b >> 16) | 0x40) as u16;
    if x.is_nan() {
        quiet
    } else {
        rounded
    }
}

/// `x` rounded to the nearest bfloat16 (ties to even), as an f32.
pub fn round_bf16(x: f32) -> f32 {
    f32::from_bits(u32::from(bf16_bits(x)) << 16)
}

/// The unit that runs bfloat16 products on this CPU.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Unit {
    /// AMX tiles (Intel, from Sapphire Rapids on), once Linux grants the process their state: 3.5–4×
    /// the f32 micro-kernels' rate on 128-wide layers.
    Amx,
    /// AVX-512 BF16's dot products of pairs (`vdpbf16ps`: Intel from Cooper Lake on, AMD from Zen 4 on):
    /// 32 products an instruction where an f32 FMA makes 16, twice the f32 micro-kernels' rate.
    Avx512Bf16,
    /// The f32 micro-kernels on operands rounded to bfloat16 (any CPU): the same numbers at f32's rate.
    Rounded,
}

impl Unit {
    /// The fastest unit this CPU has (checked once).
    pub fn best() -> Unit {
        static BEST: OnceLock<Unit> = OnceLock::new();
        *BEST.get_or_init(|| Unit::available()[0])
    }

    /// Every unit this CPU runs, fastest first.
    pub fn available() -> Vec<Unit> {
        let mut all = Vec::new();
        #[cfg(all(target_arch = "x86_64", target_os = "linux"))]
        if amx::available() {
            all.push(Unit::Amx);
        }
        #[cfg(target_arch = "x86_64")]
        if dot::available() {
            all.push(Unit::Avx512Bf16);
        }
        all.push(Unit::Rounded);
        all
    }

    /// A short name for reports (the benchmarks').
    #[cfg(feature = "bench")]
    pub fn name(self) -> &'static str {
        match self {
            Unit::Amx => "AMX",
            Unit::Avx512Bf16 => "AVX-512 BF16",
            Unit::Rounded => "rounded, f32 products",
        }
    }
}

/// A matrix prepared for bfloat16 products on one [`Unit`], in that unit's layout.
pub struct Bf16Matrix {
    rows: usize,
    cols: usize,
    layout: Layout,
}

/// The entries of a [`Bf16Matrix`] as its unit reads them.
enum Layout {
    /// Row-major, every entry rounded to bfloat16 (for [`Unit::Rounded`]).
    Rounded(Vec<f32>),
    /// Blocks of 16 rows × 32 columns, each row-major, blocks ordered by row block then column block,
    /// zero-padded (for [`Unit::Amx`]).
    Tiles(Vec<u16>),
    /// Row-major pairs of neighbouring columns, (a[i][2c], a[i][2c + 1]) in one 32-bit word (the first in
    /// the low half), the last pair zero-padded (for [`Unit::Avx512Bf16`]).
    Pairs(Vec<u32>),
}

impl Bf16Matrix {
    /// The row-major `rows × cols` matrix `a`, rounded to bfloat16, for [`Unit::best`].
    pub fn new(a: &[f32], rows: usize, cols: usize) -> Bf16Matrix {
        Bf16Matrix::on(Unit::best(), a, rows, cols)
    }

    /// [`Bf16Matrix::new`] for `unit`, which must be one of [`Unit::available`] (the products run on the
    /// unit of the matrix's layout).
    fn on(unit: Unit, a: &[f32], rows: usize, cols: usize) -> Bf16Matrix {
        assert!(a.len() >= rows * cols, "matrix smaller than its shape");
        let a = &a[..rows * cols];
        let layout = match unit {
            Unit::Rounded => Layout::Rounded(a.iter().map(|&v| round_bf16(v)).collect()),
            Unit::Amx => {
                let col_blocks = cols.div_ceil(32);
                let mut tiles = vec![0u16; rows.div_ceil(16) * col_blocks * 512];
                for (i, row) in a.chunks_exact(cols.max(1)).enumerate().take(rows) {
                    // Row i's 32 columns of block b are 32 consecutive values of block (i / 16, b).
                    for (b, part) in row.chunks(32).enumerate() {
                        let at = ((i / 16) * col_blocks + b) * 512 + (i % 16) * 32;
                        for (t, &v) in tiles[at..at + part.len()].iter_mut().zip(part) {
                            *t = bf16_bits(v);
                        }
                    }
                }
                Layout::Tiles(tiles)
            }
            Unit::Avx512Bf16 => {
                let word = |i: usize, c: usize| match a.get(i * cols + c).filter(|_| c < cols) {
                    Some(&v) => u32::from(bf16_bits(v)),
                    None => 0,
                };
                let pairs = (0..rows)
                    .flat_map(|i| (0..cols.div_ceil(2)).map(move |c| (i, c)))
                    .map(|(i, c)| word(i, 2 * c) | word(i, 2 * c + 1) << 16)
                    .collect();
                Layout::Pairs(pairs)
            }
        };
        Bf16Matrix { rows, cols, layout }
    }
}

/// 64 bytes, aligned as a cache line: the unit of the packed operands AMX and AVX-512 BF16 load.
#[derive(Clone, Copy, Default)]
#[repr(C, align(64))]
struct Line([u32; 16]);

/// Buffers reused from one product to the next.
#[derive(Default)]
pub struct Bf16Scratch {
    /// The input columns rounded (without AMX or AVX-512 BF16).
    columns: Vec<f32>,
    /// The input columns as pairs of bfloat16 rows.
    pairs: Vec<Line>,
    /// Four tiles of results.
    results: Vec<Line>,
    /// The outer product's operands: the left one's rows, the right one transposed in pairs of points.
    left: Vec<Line>,
    right: Vec<Line>,
    /// The outer product's accumulator padded to whole blocks of 16 rows, and the f32 product's scratch.
    padded: Vec<f32>,
    transposed: Vec<f32>,
}

/// `out[i][t] = Σ_k a[i][k] · x[k][t]` for t < `count` (rounded up to 16; AMX computes every point of the
/// tile), with both operands rounded to bfloat16 and the sum in f32, on the unit `a` was prepared for.
///
/// # Safety
/// Every pointer of `x` must address [`TILE`] readable floats and every pointer of `out` [`TILE`]
/// writable floats that no pointer of `x` overlaps.
pub unsafe fn matmul(
    a: &Bf16Matrix,
    x: &[*const f32],
    out: &[*mut f32],
    count: usize,
    scratch: &mut Bf16Scratch,
) {
    assert!(a.cols == x.len() && a.rows == out.len(), "product shapes differ");
    assert!(count <= TILE, "more points than a tile");
    match &a.layout {
        #[cfg(all(target_arch = "x86_64", target_os = "linux"))]
        // SAFETY: AMX and AVX-512F run (the tiles exist only then); the buffers are as the caller guarantees.
        Layout::Tiles(tiles) => unsafe { amx::matmul(a, tiles, x, out, scratch) },
        #[cfg(target_arch = "x86_64")]
        // SAFETY: AVX-512 BF16 runs (the pairs exist only then); the buffers are as the caller guarantees.
        Layout::Pairs(pairs) => unsafe { dot::matmul(pairs, x, out, count, scratch) },
        Layout::Rounded(rounded) => {
            let columns = &mut scratch.columns;
            columns.clear();
            for &xk in x {
                // SAFETY: xk addresses TILE floats (caller).
                let xk = unsafe { std::slice::from_raw_parts(xk, TILE) };
                columns.extend(xk.iter().map(|&v| round_bf16(v)));
            }
            let rounded_x: Vec<*const f32> = columns.chunks_exact(TILE).map(|c| c.as_ptr()).collect();
            // SAFETY: the rounded columns hold TILE floats each, in a buffer no output overlaps.
            unsafe { gemm::matmul(rounded, &rounded_x, out, count) };
        }
        #[allow(unreachable_patterns)]
        _ => unreachable!("a layout for a unit this CPU lacks"),
    }
}

/// `g[i·stride + j] += Σ_{t < count} l[i][t] · r[j][t]` as [`gemm::outer`] (stride =
/// [`gemm::padded`]`(r.len())`), with both operands rounded to bfloat16 and the sums in f32, on
/// [`Unit::best`].
///
/// # Safety
/// Every pointer of `l` and `r` must address `count` readable floats.
pub unsafe fn outer(
    l: &[*const f32],
    r: &[*const f32],
    count: usize,
    g: &mut [f32],
    scratch: &mut Bf16Scratch,
) {
    // SAFETY: the best unit runs on this CPU; the buffers are as the caller guarantees.
    unsafe { outer_on(Unit::best(), l, r, count, g, scratch) }
}

/// [`outer`] on a given unit.
///
/// # Safety
/// As [`outer`], and `unit` must be one of [`Unit::available`].
unsafe fn outer_on(
    unit: Unit,
    l: &[*const f32],
    r: &[*const f32],
    count: usize,
    g: &mut [f32],
    scratch: &mut Bf16Scratch,
) {
    assert!(count <= TILE, "more points than a tile");
    assert!(
        g.len() >= l.len() * gemm::padded(r.len()),
        "gradient buffer too small"
    );
    match unit {
        #[cfg(all(target_arch = "x86_64", target_os = "linux"))]
        // SAFETY: AMX and AVX-512F run (caller); the buffers are as the caller guarantees and checked above.
        Unit::Amx => unsafe { amx::outer(l, r, count, g, scratch) },
        #[cfg(target_arch = "x86_64")]
        // SAFETY: AVX-512 BF16 runs (caller); the buffers are as above.
        Unit::Avx512Bf16 => unsafe { dot::outer(l, r, count, g, scratch) },
        _ => {
            let columns = &mut scratch.columns;
            columns.clear();
            for &c in l.iter().chain(r) {
                // SAFETY: c addresses `count` floats (caller).
                let c = unsafe { std::slice::from_raw_parts(c, count) };
                columns.extend(c.iter().map(|&v| round_bf16(v)));
                columns.resize(columns.len() + TILE - count, 0.0);
            }
            let rounded: Vec<*const f32> = columns.chunks_exact(TILE).map(|c| c.as_ptr()).collect();
            let (left, right) = rounded.split_at(l.len());
            // SAFETY: the rounded columns hold TILE ≥ count floats each.
            unsafe { gemm::outer(left, right, count, g, &mut scratch.transposed) };
        }
    }
}

/// The packing of operands into pairs of bfloat16 values, one 32-bit word a pair (the first value in the
/// low half), as AMX's and AVX-512 BF16's dot products of pairs read them. The values are rounded by
/// AVX-512 BF16's conversion (to nearest, ties to even, NaN kept; subnormals to 0, which both units' dot
/// products would take as 0 anyway), which every CPU with AMX also has.
#[cfg(target_arch = "x86_64")]
mod pack {
    use std::arch::x86_64::*;

    use super::{Bf16Scratch, Line};
    use crate::gemm::avx512::transpose16;
    use crate::gemm::{padded, TILE};

    /// The bfloat16 values of `low` (first) and `high` (then), 16 each, in one vector.
    #[target_feature(enable = "avx512f,avx512bf16")]
    #[inline]
    fn both(low: __m512, high: __m512) -> __m512i {
        // SAFETY: both are 64 bytes of plain bits.
        unsafe { std::mem::transmute::<__m512bh, __m512i>(_mm512_cvtne2ps_pbh(high, low)) }
    }

    /// Points 16·q.. of column k (zero if there is no such column).
    ///
    /// # Safety
    /// Column k, if any, addresses at least 16·q + 16 floats.
    #[target_feature(enable = "avx512f")]
    #[inline]
    unsafe fn column(x: &[*const f32], k: usize, q: usize) -> __m512 {
        match x.get(k) {
            // SAFETY: as the caller guarantees.
            Some(&p) => unsafe { _mm512_loadu_ps(p.add(16 * q)) },
            None => _mm512_setzero_ps(),
        }
    }

    /// The input columns in pairs of rows: line r·TILE/16 + q holds, for the points 16·q.. of the tile, the
    /// pairs (x[2r][t], x[2r + 1][t]) for r < `rows` and q < `lines`; missing columns are zero.
    ///
    /// # Safety
    /// Every pointer of `x` addresses TILE readable floats; `pairs` holds rows · TILE / 16 lines;
    /// `lines` ≤ TILE / 16.
    #[target_feature(enable = "avx512f,avx512bw,avx512bf16")]
    pub(super) unsafe fn pack_pairs(x: &[*const f32], rows: usize, lines: usize, pairs: &mut [Line]) {
        // Word t of the result takes halves t and 16 + t of the two rows' values.
        let order: [u16; 32] = std::array::from_fn(|h| (h / 2 + 16 * (h % 2)) as u16);
        // SAFETY: 32 u16s are the 64 bytes the load reads.
        let interleave = unsafe { _mm512_loadu_si512(order.as_ptr().cast()) };
        for r in 0..rows {
            for q in 0..lines {
                // SAFETY: x's pointers address TILE floats (caller) and 16·q + 16 ≤ TILE.
                let values = unsafe { both(column(x, 2 * r, q), column(x, 2 * r + 1, q)) };
                let word = _mm512_permutexvar_epi16(interleave, values);
                // SAFETY: the line exists (caller) and is 64-byte aligned.
                unsafe { _mm512_store_si512(pairs[r * (TILE / 16) + q].0.as_mut_ptr().cast(), word) };
            }
        }
    }

    /// The bfloat16 of the 32 points 32·b.. of a column of `count` floats (zero from `count` on), packed
    /// in order: 16 words, each the pair of points (2p, 2p + 1).
    ///
    /// # Safety
    /// `c` addresses `count` readable floats.
    #[target_feature(enable = "avx512f,avx512bf16")]
    #[inline]
    unsafe fn point_pairs(c: *const f32, count: usize, b: usize) -> __m512i {
        let half = |h: usize| {
            let from = 32 * b + 16 * h;
            let n = count.saturating_sub(from).min(16);
            let mask = ((1u32 << n) - 1) as u16;
            // SAFETY: the mask reads only points below `count` (caller).
            unsafe { _mm512_maskz_loadu_ps(mask, c.add(from.min(count))) }
        };
        both(half(0), half(1))
    }

    /// The weight gradient's blocks: its columns padded to `stride` (a multiple of 16), `col_blocks` of 16
    /// columns and `point_blocks` of 32 points.
    pub(super) struct OuterBlocks {
        pub stride: usize,
        pub col_blocks: usize,
        pub point_blocks: usize,
    }

    /// Packs both operands of the weight gradient into `scratch` (`left`: [`point_rows`] of `l`; `right`:
    /// [`transposed_pairs`] of `r`) and gives its blocks; none when it sums nothing (no rows, columns or
    /// points).
    ///
    /// # Safety
    /// Every pointer of `l` and `r` addresses `count` readable floats.
    #[target_feature(enable = "avx512f,avx512bf16")]
    pub(super) unsafe fn outer_operands(
        l: &[*const f32],
        r: &[*const f32],
        count: usize,
        scratch: &mut Bf16Scratch,
    ) -> Option<OuterBlocks> {
        let stride = padded(r.len());
        let (col_blocks, point_blocks) = (stride / 16, count.div_ceil(32));
        if l.is_empty() || col_blocks == 0 || point_blocks == 0 {
            return None;
        }
        // SAFETY: the columns address `count` floats (caller).
        unsafe {
            point_rows(l, count, point_blocks, &mut scratch.left);
            transposed_pairs(r, count, col_blocks, point_blocks, &mut scratch.right);
        }
        Some(OuterBlocks {
            stride,
            col_blocks,
            point_blocks,
        })
    }

    /// The outer product's left operand: row i's points 32·b.. in line i·`point_blocks` + b, as pairs of
    /// points (zero from `count` on); rows padded with zeros to a multiple of 16.
    ///
    /// # Safety
    /// Every pointer of `l` addresses `count` readable floats; `point_blocks` = ⌈count / 32⌉.
    #[target_feature(enable = "avx512f,avx512bf16")]
    unsafe fn point_rows(l: &[*const f32], count: usize, point_blocks: usize, left: &mut Vec<Line>) {
        // Every row's lines are written below; only the padding rows are cleared.
        let lines = l.len().div_ceil(16) * 16 * point_blocks;
        if left.len() < lines {
            left.resize(lines, Line::default());
        }
        left[l.len() * point_blocks..lines].fill(Line::default());
        for (i, &c) in l.iter().enumerate() {
            for b in 0..point_blocks {
                // SAFETY: c addresses `count` floats (caller); the line exists and is aligned.
                unsafe {
                    _mm512_store_si512(
                        left[i * point_blocks + b].0.as_mut_ptr().cast(),
                        point_pairs(c, count, b),
                    )
                };
            }
        }
    }

    /// The outer product's right operand transposed: for column block jb and point block b, 16 lines, line
    /// (jb·`point_blocks` + b)·16 + p holding the pairs of points (32·b + 2p, 32·b + 2p + 1) of the block's
    /// 16 columns (missing columns and points zero).
    ///
    /// # Safety
    /// Every pointer of `r` addresses `count` readable floats; `point_blocks` = ⌈count / 32⌉.
    #[target_feature(enable = "avx512f,avx512bf16")]
    unsafe fn transposed_pairs(
        r: &[*const f32],
        count: usize,
        col_blocks: usize,
        point_blocks: usize,
        right: &mut Vec<Line>,
    ) {
        // Every line is written below.
        let lines = col_blocks * point_blocks * 16;
        if right.len() < lines {
            right.resize(lines, Line::default());
        }
        for jb in 0..col_blocks {
            for b in 0..point_blocks {
                let words: [__m512; 16] = std::array::from_fn(|q| match r.get(16 * jb + q) {
                    // SAFETY: c addresses `count` floats (caller).
                    Some(&c) => _mm512_castsi512_ps(unsafe { point_pairs(c, count, b) }),
                    None => _mm512_setzero_ps(),
                });
                for (p, v) in transpose16(words).iter().enumerate() {
                    let line = &mut right[(jb * point_blocks + b) * 16 + p];
                    // SAFETY: the line exists and is aligned.
                    unsafe { _mm512_store_ps(line.0.as_mut_ptr().cast(), *v) };
                }
            }
        }
    }
}

/// The products on AVX-512 BF16: `vdpbf16ps` adds to each of 16 f32 lanes the products of a pair of
/// bfloat16 values with another pair, so the register blocks of [`gemm`]'s f32 micro-kernels (6 rows × 64
/// points for the product, 6 rows × 64 columns for the weight gradient) take two terms of their sums an
/// instruction. The input columns are packed in pairs of rows (the product) or of points (the weight
/// gradient) as AMX's operands are.
#[cfg(target_arch = "x86_64")]
mod dot {
    use std::arch::x86_64::*;
    use std::sync::OnceLock;

    use super::pack::{outer_operands, pack_pairs, OuterBlocks};
    use super::{Bf16Scratch, Line};
    use crate::gemm::{has_avx512, TILE};

    /// Rows of a register block.
    const ROWS: usize = 6;
    /// Vectors of 16 points (the product) or columns (the weight gradient) of a register block.
    const VECTORS: usize = 4;

    /// Whether this CPU has AVX-512F, BW and BF16 (checked once).
    pub(super) fn available() -> bool {
        static OK: OnceLock<bool> = OnceLock::new();
        *OK.get_or_init(|| {
            has_avx512()
                && std::arch::is_x86_feature_detected!("avx512bw")
                && std::arch::is_x86_feature_detected!("avx512bf16")
        })
    }

    /// A vector's 32 bfloat16 values, as `vdpbf16ps` takes them.
    #[target_feature(enable = "avx512f")]
    #[inline]
    fn pairs(v: __m512i) -> __m512bh {
        // SAFETY: both are 64 bytes of plain bits.
        unsafe { std::mem::transmute::<__m512i, __m512bh>(v) }
    }

    /// See [`super::matmul`]; `a` holds the matrix's rows as pairs of columns.
    ///
    /// # Safety
    /// As [`super::matmul`]; [`available`] is true; `a` holds out.len() · ⌈x.len() / 2⌉ words.
    #[target_feature(enable = "avx512f,avx512bw,avx512bf16")]
    pub(super) unsafe fn matmul(
        a: &[u32],
        x: &[*const f32],
        out: &[*mut f32],
        count: usize,
        scratch: &mut Bf16Scratch,
    ) {
        let k = x.len().div_ceil(2);
        let lines = count.div_ceil(16);
        // The lines the kernel reads are written by the packing: no need to clear them.
        if scratch.pairs.len() < k * TILE / 16 {
            scratch.pairs.resize(k * TILE / 16, Line::default());
        }
        // SAFETY: x is as the caller guarantees; pairs holds k · TILE / 16 lines; lines ≤ TILE / 16.
        unsafe { pack_pairs(x, k, lines, &mut scratch.pairs) };
        let x = scratch.pairs.as_ptr().cast::<u32>();
        let full = lines / VECTORS * VECTORS;
        // SAFETY (every call): rows of `a` exist for every output, the packed pairs for k rows of TILE
        // points, and t0 + 16·Q ≤ 16·lines ≤ TILE.
        unsafe {
            for q in (0..full).step_by(VECTORS) {
                matmul_rows::<VECTORS>(a, k, x, out, 16 * q);
            }
            match lines - full {
                3 => matmul_rows::<3>(a, k, x, out, 16 * full),
                2 => matmul_rows::<2>(a, k, x, out, 16 * full),
                1 => matmul_rows::<1>(a, k, x, out, 16 * full),
                _ => {}
            }
        }
    }

    /// Every row of the product for the 16·Q points from `t0`.
    #[target_feature(enable = "avx512f,avx512bf16")]
    #[inline]
    unsafe fn matmul_rows<const Q: usize>(a: &[u32], k: usize, x: *const u32, out: &[*mut f32], t0: usize) {
        let mut i = 0;
        // SAFETY (every block): as for `matmul`.
        unsafe {
            while i + ROWS <= out.len() {
                matmul_block::<ROWS, Q>(a.as_ptr().add(i * k), k, x, &out[i..i + ROWS], t0);
                i += ROWS;
            }
            let a = a.as_ptr().add(i * k);
            match out.len() - i {
                5 => matmul_block::<5, Q>(a, k, x, &out[i..], t0),
                4 => matmul_block::<4, Q>(a, k, x, &out[i..], t0),
                3 => matmul_block::<3, Q>(a, k, x, &out[i..], t0),
                2 => matmul_block::<2, Q>(a, k, x, &out[i..], t0),
                1 => matmul_block::<1, Q>(a, k, x, &out[i..], t0),
                _ => {}
            }
        }
    }

    /// R rows of the product (their pairs of columns from `a`, `k` a row) for the 16·Q points from `t0`.
    #[target_feature(enable = "avx512f,avx512bf16")]
    #[inline]
    unsafe fn matmul_block<const R: usize, const Q: usize>(
        a: *const u32,
        k: usize,
        x: *const u32,
        out: &[*mut f32],
        t0: usize,
    ) {
        let mut acc = [[_mm512_setzero_ps(); Q]; R];
        for kk in 0..k {
            // SAFETY: pair row kk holds TILE words, and t0 + 16·Q ≤ TILE; each of the R rows of `a` holds k
            // words.
            unsafe {
                let p = x.add(kk * TILE + t0);
                let b: [__m512bh; Q] =
                    std::array::from_fn(|q| pairs(_mm512_load_si512(p.add(16 * q).cast())));
                for (r, acc_r) in acc.iter_mut().enumerate() {
                    let w = pairs(_mm512_set1_epi32(*a.add(r * k + kk) as i32));
                    for q in 0..Q {
                        acc_r[q] = _mm512_dpbf16_ps(acc_r[q], w, b[q]);
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

    /// See [`super::outer`].
    ///
    /// # Safety
    /// As [`super::outer`], whose checks passed; [`available`] is true.
    #[target_feature(enable = "avx512f,avx512bf16")]
    pub(super) unsafe fn outer(
        l: &[*const f32],
        r: &[*const f32],
        count: usize,
        g: &mut [f32],
        scratch: &mut Bf16Scratch,
    ) {
        // SAFETY: the columns address `count` floats (caller).
        let Some(OuterBlocks {
            stride,
            col_blocks,
            point_blocks,
        }) = (unsafe { outer_operands(l, r, count, scratch) })
        else {
            return;
        };
        let operands = Operands {
            left: scratch.left.as_ptr().cast(),
            right: scratch.right.as_ptr().cast(),
            point_blocks,
            count,
            g: g.as_mut_ptr(),
            stride,
        };
        for i in (0..l.len()).step_by(ROWS) {
            for jb in (0..col_blocks).step_by(VECTORS) {
                let vectors = (col_blocks - jb).min(VECTORS);
                // SAFETY: rows i.. of G and its column blocks jb.. exist (checked by the caller); the
                // packed operands hold them.
                unsafe {
                    match (l.len() - i).min(ROWS) {
                        6 => operands.block_rows::<6>(i, jb, vectors),
                        5 => operands.block_rows::<5>(i, jb, vectors),
                        4 => operands.block_rows::<4>(i, jb, vectors),
                        3 => operands.block_rows::<3>(i, jb, vectors),
                        2 => operands.block_rows::<2>(i, jb, vectors),
                        _ => operands.block_rows::<1>(i, jb, vectors),
                    }
                }
            }
        }
    }

    /// The packed operands and the accumulator of one weight gradient.
    struct Operands {
        /// Row i's pairs of points 32·b.. in the 16 words from (i·point_blocks + b)·16.
        left: *const u32,
        /// The pairs of points (32·b + 2p, 32·b + 2p + 1) of column block jb in line
        /// (jb·point_blocks + b)·16 + p.
        right: *const Line,
        point_blocks: usize,
        count: usize,
        g: *mut f32,
        stride: usize,
    }

    impl Operands {
        /// The block of R rows from `i` and `vectors` column blocks from `jb`.
        ///
        /// # Safety
        /// As [`Operands::block`].
        #[target_feature(enable = "avx512f,avx512bf16")]
        #[inline]
        unsafe fn block_rows<const R: usize>(&self, i: usize, jb: usize, vectors: usize) {
            // SAFETY: passed on.
            unsafe {
                match vectors {
                    4 => self.block::<R, 4>(i, jb),
                    3 => self.block::<R, 3>(i, jb),
                    2 => self.block::<R, 2>(i, jb),
                    _ => self.block::<R, 1>(i, jb),
                }
            }
        }

        /// `G[i.. i + R][16·jb.. 16·(jb + V)] +=` the sums over the points, in registers.
        ///
        /// # Safety
        /// Rows i..i + R and column blocks jb..jb + V are inside G and the packed operands.
        #[target_feature(enable = "avx512f,avx512bf16")]
        #[inline]
        unsafe fn block<const R: usize, const V: usize>(&self, i: usize, jb: usize) {
            let at = |r: usize, v: usize| self.g.wrapping_add((i + r) * self.stride + 16 * (jb + v));
            // SAFETY: G's rows hold `stride` ≥ 16·(jb + V) floats (caller).
            let mut acc: [[__m512; V]; R] =
                std::array::from_fn(|r| std::array::from_fn(|v| unsafe { _mm512_loadu_ps(at(r, v)) }));
            for b in 0..self.point_blocks {
                // Pairs of points past the last valid one are zero: skip them.
                let used = (self.count - 32 * b).div_ceil(2).min(16);
                for p in 0..used {
                    // SAFETY: the lines and words exist (caller).
                    unsafe {
                        let line = |v: usize| self.right.add(((jb + v) * self.point_blocks + b) * 16 + p);
                        let columns: [__m512bh; V] =
                            std::array::from_fn(|v| pairs(_mm512_load_si512(line(v).cast())));
                        for (r, acc_r) in acc.iter_mut().enumerate() {
                            let word = *self.left.add(((i + r) * self.point_blocks + b) * 16 + p);
                            let w = pairs(_mm512_set1_epi32(word as i32));
                            for v in 0..V {
                                acc_r[v] = _mm512_dpbf16_ps(acc_r[v], w, columns[v]);
                            }
                        }
                    }
                }
            }
            for (r, acc_r) in acc.iter().enumerate() {
                for (v, sum) in acc_r.iter().enumerate() {
                    // SAFETY: as for the loads.
                    unsafe { _mm512_storeu_ps(at(r, v), *sum) };
                }
            }
        }
    }
}

#[cfg(all(target_arch = "x86_64", target_os = "linux"))]
mod amx {
    use std::arch::asm;
    use std::arch::x86_64::*;
    use std::sync::OnceLock;

    use super::pack::{outer_operands, pack_pairs, OuterBlocks};
    use super::{Bf16Matrix, Bf16Scratch, Line};
    use crate::gemm::TILE;

    // The tile registers live from one `asm!` block to the next: nothing between them calls a function
    // (the ABI leaves tiles to the caller to save), and each product configures the tiles on entry and
    // releases them on exit, so a thread holds no tile state between products.

    /// The tile configuration (palette 1): tiles 0–7 all 16 rows of 64 bytes. Tiles 0–3 hold the four
    /// 16 × 16 blocks of results, 4–5 two blocks of the matrix (16 rows × 32 columns), 6–7 two blocks of
    /// the input (16 pairs of rows × 16 points).
    #[repr(C, align(64))]
    struct TileConfig {
        palette: u8,
        start_row: u8,
        reserved: [u8; 14],
        bytes_per_row: [u16; 16],
        rows: [u8; 16],
    }

    const CONFIG: TileConfig = TileConfig {
        palette: 1,
        start_row: 0,
        reserved: [0; 14],
        bytes_per_row: [64, 64, 64, 64, 64, 64, 64, 64, 0, 0, 0, 0, 0, 0, 0, 0],
        rows: [16, 16, 16, 16, 16, 16, 16, 16, 0, 0, 0, 0, 0, 0, 0, 0],
    };

    /// `arch_prctl` request for permission to use an extended state component.
    const ARCH_REQ_XCOMP_PERM: libc::c_long = 0x1023;
    /// The extended state component of AMX's tile data.
    const XFEATURE_XTILEDATA: libc::c_long = 18;

    /// Whether this CPU has AMX with bfloat16 and AVX-512 (F, BW and BF16, for the operands' packing),
    /// and Linux granted this process the tile state (asked once).
    pub(super) fn available() -> bool {
        static OK: OnceLock<bool> = OnceLock::new();
        *OK.get_or_init(|| {
            // CPUID leaf 7 exists on every x86-64 CPU that has AVX-512F.
            let has_amx = super::dot::available() && {
                let leaf = __cpuid_count(7, 0);
                leaf.edx & (1 << 22) != 0 && leaf.edx & (1 << 24) != 0
            };
            // SAFETY: arch_prctl with this request only changes the process's permitted state components.
            has_amx
                && unsafe { libc::syscall(libc::SYS_arch_prctl, ARCH_REQ_XCOMP_PERM, XFEATURE_XTILEDATA) }
                    == 0
        })
    }

    /// One step of a 2 × 2 block of results: tiles 0–3 (results (0, 0), (0, 1), (1, 0), (1, 1)) add the
    /// products of the two first-operand tiles at `a` (rows `a_stride` bytes apart) with the two
    /// second-operand tiles at `b` (rows `b_stride` bytes apart).
    ///
    /// # Safety
    /// The tile configuration is loaded; each pointer addresses 16 rows of 64 readable bytes at its stride.
    #[inline(always)]
    unsafe fn step_2x2(a: [*const u8; 2], a_stride: usize, b: [*const u8; 2], b_stride: usize) {
        // SAFETY: as the caller guarantees.
        unsafe {
            asm!(
                "tileloadd tmm4, [{a0} + {sa}*1]",
                "tileloadd tmm5, [{a1} + {sa}*1]",
                "tileloadd tmm6, [{b0} + {sb}*1]",
                "tileloadd tmm7, [{b1} + {sb}*1]",
                "tdpbf16ps tmm0, tmm4, tmm6",
                "tdpbf16ps tmm1, tmm4, tmm7",
                "tdpbf16ps tmm2, tmm5, tmm6",
                "tdpbf16ps tmm3, tmm5, tmm7",
                a0 = in(reg) a[0],
                a1 = in(reg) a[1],
                b0 = in(reg) b[0],
                b1 = in(reg) b[1],
                sa = in(reg) a_stride,
                sb = in(reg) b_stride,
                options(nostack, readonly)
            );
        }
    }

    /// See [`super::matmul`].
    ///
    /// # Safety
    /// As [`super::matmul`]; [`available`] is true and `a` has its tiles.
    #[target_feature(enable = "avx512f,avx512bw,avx512bf16")]
    pub(super) unsafe fn matmul(
        a: &Bf16Matrix,
        tiles: &[u16],
        x: &[*const f32],
        out: &[*mut f32],
        scratch: &mut Bf16Scratch,
    ) {
        let (row_blocks, col_blocks) = (a.rows.div_ceil(16), a.cols.div_ceil(32));
        let lines = TILE / 16;
        scratch.pairs.clear();
        scratch.pairs.resize(col_blocks * 16 * lines, Line::default());
        scratch.results.clear();
        scratch.results.resize(64, Line::default());
        // SAFETY: x is as the caller guarantees; pairs was sized for col_blocks · 16 rows.
        unsafe { pack_pairs(x, col_blocks * 16, lines, &mut scratch.pairs) };
        let tiles = tiles.as_ptr();
        let pairs = scratch.pairs.as_ptr().cast::<u32>();
        let results = scratch.results.as_mut_ptr().cast::<f32>();
        // Strides in bytes: a matrix block's row is 32 bfloat16, an input row TILE pairs, a result row 16 f32.
        let (a_stride, x_stride, r_stride) = (64usize, 4 * TILE, 64usize);
        // SAFETY (every block below): the configuration is valid; every tile load reads a 16 × 64-byte block
        // inside `tiles` (row block i, column block k of row_blocks × col_blocks blocks of 512 values) or
        // `pairs` (rows 16·k.., points 16·t.. of col_blocks·16 rows × TILE words); stores write `results`
        // (4 × 16 lines).
        unsafe {
            asm!("ldtilecfg [{}]", in(reg) &CONFIG, options(nostack, readonly));
            for i in (0..row_blocks).step_by(2) {
                let two = i + 1 < row_blocks;
                for t in (0..lines).step_by(2) {
                    asm!(
                        "tilezero tmm0",
                        "tilezero tmm1",
                        "tilezero tmm2",
                        "tilezero tmm3",
                        options(nostack, nomem)
                    );
                    for k in 0..col_blocks {
                        let a0 = tiles.add((i * col_blocks + k) * 512);
                        let b0 = pairs.add(k * 16 * TILE + 16 * t);
                        if two {
                            step_2x2(
                                [a0.cast(), a0.add(col_blocks * 512).cast()],
                                a_stride,
                                [b0.cast(), b0.add(16).cast()],
                                x_stride,
                            );
                        } else {
                            asm!(
                                "tileloadd tmm4, [{a0} + {sa}*1]",
                                "tileloadd tmm6, [{b0} + {sb}*1]",
                                "tileloadd tmm7, [{b1} + {sb}*1]",
                                "tdpbf16ps tmm0, tmm4, tmm6",
                                "tdpbf16ps tmm1, tmm4, tmm7",
                                a0 = in(reg) a0,
                                b0 = in(reg) b0,
                                b1 = in(reg) b0.add(16),
                                sa = in(reg) a_stride,
                                sb = in(reg) x_stride,
                                options(nostack, readonly)
                            );
                        }
                    }
                    asm!(
                        "tilestored [{r0} + {s}*1], tmm0",
                        "tilestored [{r1} + {s}*1], tmm1",
                        "tilestored [{r2} + {s}*1], tmm2",
                        "tilestored [{r3} + {s}*1], tmm3",
                        r0 = in(reg) results,
                        r1 = in(reg) results.add(256),
                        r2 = in(reg) results.add(512),
                        r3 = in(reg) results.add(768),
                        s = in(reg) r_stride,
                        options(nostack)
                    );
                    // Result tile h holds rows 16·(i + h / 2).. and points 16·(t + h % 2)..
                    for h in 0..if two { 4 } else { 2 } {
                        let row0 = 16 * (i + h / 2);
                        for (m, &o) in out.iter().enumerate().skip(row0).take(16) {
                            let v = _mm512_load_ps(results.add(256 * h + 16 * (m - row0)));
                            _mm512_storeu_ps(o.add(16 * (t + h % 2)), v);
                        }
                    }
                }
            }
            asm!("tilerelease", options(nostack, nomem));
        }
    }

    /// See [`super::outer`].
    ///
    /// # Safety
    /// As [`super::outer`], whose checks passed; [`available`] is true.
    #[target_feature(enable = "avx512f,avx512bf16")]
    pub(super) unsafe fn outer(
        l: &[*const f32],
        r: &[*const f32],
        count: usize,
        g: &mut [f32],
        scratch: &mut Bf16Scratch,
    ) {
        // SAFETY: the columns address `count` floats (caller).
        let Some(OuterBlocks {
            stride,
            col_blocks,
            point_blocks,
        }) = (unsafe { outer_operands(l, r, count, scratch) })
        else {
            return;
        };
        let row_blocks = l.len().div_ceil(16);
        // The accumulator in whole blocks of 16 rows: g itself, or a padded copy.
        let whole = l.len().is_multiple_of(16);
        if !whole {
            scratch.padded.clear();
            scratch.padded.extend_from_slice(&g[..l.len() * stride]);
            scratch.padded.resize(row_blocks * 16 * stride, 0.0);
        }
        let acc = if whole {
            g.as_mut_ptr()
        } else {
            scratch.padded.as_mut_ptr()
        };
        let (left, right) = (
            scratch.left.as_ptr().cast::<u8>(),
            scratch.right.as_ptr().cast::<u8>(),
        );
        let c_at = |ib: usize, jb: usize| acc.wrapping_add(16 * (ib * stride + jb));
        let a_at = |ib: usize, b: usize| left.wrapping_add(64 * (16 * ib * point_blocks + b));
        let b_at = |jb: usize, b: usize| right.wrapping_add(64 * 16 * (jb * point_blocks + b));
        // Strides in bytes: the accumulator's rows, the left operand's rows, the right one's lines.
        let (sc, sa, sb) = (4 * stride, 64 * point_blocks, 64usize);
        // SAFETY (every block): the configuration is valid; each accumulator tile is 16 rows of 16 floats
        // inside acc (row_blocks·16 rows of `stride` ≥ 16·(jb + 1) floats); each left tile 16 rows of 64
        // bytes inside `left`, each right tile 16 lines inside `right`.
        unsafe {
            asm!("ldtilecfg [{}]", in(reg) &CONFIG, options(nostack, readonly));
            for ib in (0..row_blocks).step_by(2) {
                for jb in (0..col_blocks).step_by(2) {
                    if ib + 1 < row_blocks && jb + 1 < col_blocks {
                        let c = [
                            c_at(ib, jb),
                            c_at(ib, jb + 1),
                            c_at(ib + 1, jb),
                            c_at(ib + 1, jb + 1),
                        ];
                        asm!(
                            "tileloadd tmm0, [{c00} + {sc}*1]",
                            "tileloadd tmm1, [{c01} + {sc}*1]",
                            "tileloadd tmm2, [{c10} + {sc}*1]",
                            "tileloadd tmm3, [{c11} + {sc}*1]",
                            c00 = in(reg) c[0],
                            c01 = in(reg) c[1],
                            c10 = in(reg) c[2],
                            c11 = in(reg) c[3],
                            sc = in(reg) sc,
                            options(nostack, readonly)
                        );
                        for b in 0..point_blocks {
                            step_2x2(
                                [a_at(ib, b), a_at(ib + 1, b)],
                                sa,
                                [b_at(jb, b), b_at(jb + 1, b)],
                                sb,
                            );
                        }
                        asm!(
                            "tilestored [{c00} + {sc}*1], tmm0",
                            "tilestored [{c01} + {sc}*1], tmm1",
                            "tilestored [{c10} + {sc}*1], tmm2",
                            "tilestored [{c11} + {sc}*1], tmm3",
                            c00 = in(reg) c[0],
                            c01 = in(reg) c[1],
                            c10 = in(reg) c[2],
                            c11 = in(reg) c[3],
                            sc = in(reg) sc,
                            options(nostack)
                        );
                        continue;
                    }
                    // An edge: each of the (one or two) blocks on its own.
                    for i in ib..(ib + 2).min(row_blocks) {
                        for j in jb..(jb + 2).min(col_blocks) {
                            asm!(
                                "tileloadd tmm0, [{c} + {sc}*1]",
                                c = in(reg) c_at(i, j),
                                sc = in(reg) sc,
                                options(nostack, readonly)
                            );
                            for b in 0..point_blocks {
                                asm!(
                                    "tileloadd tmm4, [{a} + {sa}*1]",
                                    "tileloadd tmm6, [{b} + {sb}*1]",
                                    "tdpbf16ps tmm0, tmm4, tmm6",
                                    a = in(reg) a_at(i, b),
                                    b = in(reg) b_at(j, b),
                                    sa = in(reg) sa,
                                    sb = in(reg) sb,
                                    options(nostack, readonly)
                                );
                            }
                            asm!(
                                "tilestored [{c} + {sc}*1], tmm0",
                                c = in(reg) c_at(i, j),
                                sc = in(reg) sc,
                                options(nostack)
                            );
                        }
                    }
                }
            }
            asm!("tilerelease", options(nostack, nomem));
        }
        if !whole {
            g[..l.len() * stride].copy_from_slice(&scratch.padded[..l.len() * stride]);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn precisions_are_found_by_their_names() {
        for (name, precision) in Precision::NAMED {
            assert_eq!(Precision::named(name), Some(precision));
            assert_eq!(precision.name(), name);
        }
        assert_eq!(Precision::named("f16"), None);
    }

    #[test]
    fn rounding_is_to_nearest_with_ties_to_even() {
        assert_eq!(round_bf16(1.0), 1.0);
        // 1 + 2^-8 lies halfway between 1 and 1 + 2^-7: ties go to the even 1.
        assert_eq!(round_bf16(1.0 + 1.0 / 256.0), 1.0);
        assert_eq!(round_bf16(1.0 + 3.0 / 256.0), 1.0 + 4.0 / 256.0);
        assert_eq!(round_bf16(1.0 + 1.1 / 256.0), 1.0 + 2.0 / 256.0);
        assert_eq!(round_bf16(-3.0), -3.0);
        assert_eq!(round_bf16(f32::MAX), f32::INFINITY);
        assert_eq!(round_bf16(f32::INFINITY), f32::INFINITY);
        assert!(round_bf16(f32::NAN).is_nan());
        assert!(round_bf16(f32::from_bits(0x7f80_0001)).is_nan());
        assert!(round_bf16(f32::from_bits(0xffff_ffff)).is_nan());
    }

    fn values(seed: u32, len: usize) -> Vec<f32> {
        (0..len)
            .map(|t| {
                (((t as u32).wrapping_mul(2654435761) ^ seed.wrapping_mul(40503)) % 10_007) as f32 / 5003.0
                    - 1.0
            })
            .collect()
    }

    /// On every unit of this CPU: the sums of the products of the rounded operands over the points asked
    /// for, to f32's accuracy (a wrongly rounded operand would be off by ~1/256 of its term).
    #[test]
    fn matmul_sums_the_products_of_rounded_operands() {
        let mut scratch = Bf16Scratch::default();
        for (unit, (m, k), count) in Unit::available().into_iter().flat_map(|unit| {
            [
                (1, 1),
                (3, 5),
                (16, 32),
                (17, 33),
                (40, 100),
                (128, 128),
                (256, 63),
                (5, 0),
                (0, 7),
            ]
            .into_iter()
            .flat_map(move |shape| [TILE, 80, 17].map(|count| (unit, shape, count)))
        }) {
            let a = values(7, m * k);
            let xs: Vec<Vec<f32>> = (0..k).map(|c| values(c as u32 + 11, TILE)).collect();
            let matrix = Bf16Matrix::on(unit, &a, m, k);
            let mut outs = vec![vec![f32::NAN; TILE]; m];
            let xp: Vec<*const f32> = xs.iter().map(|c| c.as_ptr()).collect();
            let op: Vec<*mut f32> = outs.iter_mut().map(|c| c.as_mut_ptr()).collect();
            // SAFETY: every column holds TILE floats; the outputs are separate buffers.
            unsafe { matmul(&matrix, &xp, &op, count, &mut scratch) };
            for (i, row) in outs.iter().enumerate() {
                for (t, &got) in row.iter().enumerate().take(count) {
                    let terms =
                        (0..k).map(|c| f64::from(round_bf16(a[i * k + c])) * f64::from(round_bf16(xs[c][t])));
                    let (want, size) = terms.fold((0.0, 0.0), |(s, z), v| (s + v, z + v.abs()));
                    assert!(
                        (f64::from(got) - want).abs() <= 1e-6 * (size + 1.0),
                        "{unit:?} {m}x{k} ({count} points) at ({i}, {t}): {got} vs {want}"
                    );
                }
            }
        }
    }

    /// On every unit of this CPU: the outer product adds the sums over the valid points of the products of
    /// the rounded operands.
    #[test]
    fn outer_adds_the_products_of_rounded_operands_over_the_valid_points() {
        let mut scratch = Bf16Scratch::default();
        for (unit, (m, n, count)) in Unit::available().into_iter().flat_map(|unit| {
            [
                (1, 1, 1),
                (3, 5, 7),
                (16, 16, 32),
                (17, 40, 100),
                (64, 128, 128),
                (33, 3, 128),
                (6, 9, 0),
                (7, 70, 45),
            ]
            .map(|shape| (unit, shape))
        }) {
            let ls: Vec<Vec<f32>> = (0..m).map(|c| values(c as u32 + 100, TILE)).collect();
            let rs: Vec<Vec<f32>> = (0..n).map(|c| values(c as u32 + 300, TILE)).collect();
            let stride = gemm::padded(n);
            let mut g: Vec<f32> = values(5, m * stride);
            let before = g.clone();
            let lp: Vec<*const f32> = ls.iter().map(|c| c.as_ptr()).collect();
            let rp: Vec<*const f32> = rs.iter().map(|c| c.as_ptr()).collect();
            // SAFETY: every column holds TILE ≥ count floats.
            unsafe { outer_on(unit, &lp, &rp, count, &mut g, &mut scratch) };
            for i in 0..m {
                for j in 0..n {
                    let terms =
                        (0..count).map(|t| f64::from(round_bf16(ls[i][t])) * f64::from(round_bf16(rs[j][t])));
                    let (sum, size) = terms.fold((0.0, 0.0), |(s, z), v| (s + v, z + v.abs()));
                    let (got, want) = (
                        f64::from(g[i * stride + j]),
                        f64::from(before[i * stride + j]) + sum,
                    );
                    assert!(
                        (got - want).abs() <= 1e-6 * (size + 2.0),
                        "{unit:?} {m}x{n}x{count} at ({i}, {j}): {got} vs {want}"
                    );
                }
            }
        }
    }

    #[test]
    fn a_nan_operand_gives_nan() {
        for unit in Unit::available() {
            let a = values(3, 2 * 40);
            let mut xs: Vec<Vec<f32>> = (0..40).map(|c| values(c as u32, TILE)).collect();
            xs[37][5] = f32::NAN;
            let mut outs = vec![vec![0.0; TILE]; 2];
            let xp: Vec<*const f32> = xs.iter().map(|c| c.as_ptr()).collect();
            let op: Vec<*mut f32> = outs.iter_mut().map(|c| c.as_mut_ptr()).collect();
            let matrix = Bf16Matrix::on(unit, &a, 2, 40);
            // SAFETY: every column holds TILE floats; the outputs are separate buffers.
            unsafe { matmul(&matrix, &xp, &op, TILE, &mut Bf16Scratch::default()) };
            for row in &outs {
                assert!(row[5].is_nan(), "{unit:?}");
                assert!(
                    row.iter().enumerate().all(|(t, v)| t == 5 || v.is_finite()),
                    "{unit:?}"
                );
            }
        }
    }
}
