//! Matrix products with bfloat16 operands and f32 sums, for the dense layers of kernels compiled with
//! [`Precision::Bf16`]: [`matmul`] (forward and backward products) and [`outer`] (weight gradients).
//!
//! Both operands are rounded to bfloat16 (8 significant bits, to nearest, ties to even) and their products
//! summed in f32, as mixed-precision training on GPUs does. Where the CPU has AMX (Intel's tile matrix unit,
//! `amx-tile` and `amx-bf16`, from Sapphire Rapids on) and the kernel grants the process its tile state,
//! the products run on the tile unit (3.5–4× the f32 micro-kernels' rate on 128-wide layers); elsewhere the rounded operands
//! go through the f32 [`gemm::matmul`], which gives the same numbers up to the order of the sums (a product
//! of two bfloat16 values is exact in f32).

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

/// Whether products run on AMX tiles (checked, and the tile state requested, once).
pub fn uses_amx() -> bool {
    #[cfg(all(target_arch = "x86_64", target_os = "linux"))]
    {
        amx::available()
    }
    #[cfg(not(all(target_arch = "x86_64", target_os = "linux")))]
    {
        false
    }
}

/// A matrix prepared for bfloat16 products: in AMX's tile layout where AMX runs them, else rounded in place.
pub struct Bf16Matrix {
    rows: usize,
    cols: usize,
    /// Row-major, every entry rounded to bfloat16 (without AMX).
    rounded: Vec<f32>,
    /// Blocks of 16 rows × 32 columns, each row-major, blocks ordered by row block then column block,
    /// zero-padded (with AMX).
    tiles: Vec<u16>,
}

impl Bf16Matrix {
    /// The row-major `rows × cols` matrix `a`, rounded to bfloat16.
    pub fn new(a: &[f32], rows: usize, cols: usize) -> Bf16Matrix {
        assert!(a.len() >= rows * cols, "matrix smaller than its shape");
        let a = &a[..rows * cols];
        if !uses_amx() {
            return Bf16Matrix {
                rows,
                cols,
                rounded: a.iter().map(|&v| round_bf16(v)).collect(),
                tiles: Vec::new(),
            };
        }
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
        Bf16Matrix {
            rows,
            cols,
            rounded: Vec::new(),
            tiles,
        }
    }
}

/// 64 bytes, aligned as a cache line: the unit of the buffers AMX loads and stores.
#[derive(Clone, Copy, Default)]
#[repr(C, align(64))]
struct Line([u32; 16]);

/// Buffers reused from one product to the next.
#[derive(Default)]
pub struct Bf16Scratch {
    /// The input columns rounded (without AMX).
    columns: Vec<f32>,
    /// The input columns as pairs of bfloat16 rows (with AMX).
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

/// `out[i][t] = Σ_k a[i][k] · x[k][t]` for t < [`TILE`], with both operands rounded to bfloat16 and the
/// sum in f32.
///
/// # Safety
/// Every pointer of `x` must address [`TILE`] readable floats and every pointer of `out` [`TILE`]
/// writable floats that no pointer of `x` overlaps.
pub unsafe fn matmul(a: &Bf16Matrix, x: &[*const f32], out: &[*mut f32], scratch: &mut Bf16Scratch) {
    assert!(a.cols == x.len() && a.rows == out.len(), "product shapes differ");
    #[cfg(all(target_arch = "x86_64", target_os = "linux"))]
    if !a.tiles.is_empty() {
        // SAFETY: AMX and AVX-512F run (the tiles exist only then); the buffers are as the caller guarantees.
        unsafe { amx::matmul(a, x, out, scratch) };
        return;
    }
    let columns = &mut scratch.columns;
    columns.clear();
    for &xk in x {
        // SAFETY: xk addresses TILE floats (caller).
        let xk = unsafe { std::slice::from_raw_parts(xk, TILE) };
        columns.extend(xk.iter().map(|&v| round_bf16(v)));
    }
    let rounded: Vec<*const f32> = columns.chunks_exact(TILE).map(|c| c.as_ptr()).collect();
    // SAFETY: the rounded columns hold TILE floats each, in a buffer no output overlaps.
    unsafe { gemm::matmul(&a.rounded, &rounded, out, TILE) };
}

/// `g[i·stride + j] += Σ_{t < count} l[i][t] · r[j][t]` as [`gemm::outer`] (stride =
/// [`gemm::padded`]`(r.len())`), with both operands rounded to bfloat16 and the sums in f32.
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
    assert!(count <= TILE, "more points than a tile");
    assert!(
        g.len() >= l.len() * gemm::padded(r.len()),
        "gradient buffer too small"
    );
    #[cfg(all(target_arch = "x86_64", target_os = "linux"))]
    if uses_amx() {
        // SAFETY: AMX and AVX-512F run; the buffers are as the caller guarantees and checked above.
        unsafe { amx::outer(l, r, count, g, scratch) };
        return;
    }
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

#[cfg(all(target_arch = "x86_64", target_os = "linux"))]
mod amx {
    use std::arch::asm;
    use std::arch::x86_64::*;
    use std::sync::OnceLock;

    use super::{Bf16Matrix, Bf16Scratch, Line};
    use crate::gemm::avx512::transpose16;
    use crate::gemm::{has_avx512, padded, TILE};

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

    /// Whether this CPU has AMX with bfloat16 and AVX-512F, and Linux granted this process the tile
    /// state (asked once).
    pub(super) fn available() -> bool {
        static OK: OnceLock<bool> = OnceLock::new();
        *OK.get_or_init(|| {
            // CPUID leaf 7 exists on every x86-64 CPU that has AVX-512F.
            let has_amx = has_avx512() && {
                let leaf = __cpuid_count(7, 0);
                leaf.edx & (1 << 22) != 0 && leaf.edx & (1 << 24) != 0
            };
            // SAFETY: arch_prctl with this request only changes the process's permitted state components.
            has_amx
                && unsafe { libc::syscall(libc::SYS_arch_prctl, ARCH_REQ_XCOMP_PERM, XFEATURE_XTILEDATA) }
                    == 0
        })
    }

    /// Each lane's bfloat16 (to nearest, ties to even; NaN kept quiet) in its low 16 bits, as `bf16_bits`.
    #[target_feature(enable = "avx512f")]
    #[inline]
    fn bf16_lanes(v: __m512) -> __m512i {
        let b = _mm512_castps_si512(v);
        let high = _mm512_srli_epi32::<16>(b);
        let bias = _mm512_add_epi32(
            _mm512_and_si512(high, _mm512_set1_epi32(1)),
            _mm512_set1_epi32(0x7fff),
        );
        let rounded = _mm512_srli_epi32::<16>(_mm512_add_epi32(b, bias));
        let nan = _mm512_cmp_ps_mask::<_CMP_UNORD_Q>(v, v);
        _mm512_mask_blend_epi32(nan, rounded, _mm512_or_si512(high, _mm512_set1_epi32(0x40)))
    }

    /// The input columns as AMX's second operand: row r (of `rows`) holds, for each of the TILE points, the
    /// bfloat16 pair (x[2r][t], x[2r + 1][t]) in one 32-bit word; missing columns are zero.
    ///
    /// # Safety
    /// Every pointer of `x` addresses TILE readable floats; `pairs` holds rows · TILE / 16 lines.
    #[target_feature(enable = "avx512f")]
    unsafe fn pack_pairs(x: &[*const f32], rows: usize, pairs: &mut [Line]) {
        let lines = TILE / 16;
        for r in 0..rows {
            for q in 0..lines {
                // SAFETY: x's pointers address TILE floats (caller) and 16·q + 16 ≤ TILE.
                let (low, high) = unsafe { (column_lanes(x, 2 * r, q), column_lanes(x, 2 * r + 1, q)) };
                let word = _mm512_or_si512(low, _mm512_slli_epi32::<16>(high));
                // SAFETY: the line exists (caller) and is 64-byte aligned.
                unsafe { _mm512_store_si512(pairs[r * lines + q].0.as_mut_ptr().cast(), word) };
            }
        }
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

    /// The bfloat16 of points 16·q.. of column k (zero if there is no such column), as [`bf16_lanes`].
    ///
    /// # Safety
    /// Column k, if any, addresses at least 16·q + 16 floats.
    #[target_feature(enable = "avx512f")]
    #[inline]
    unsafe fn column_lanes(x: &[*const f32], k: usize, q: usize) -> __m512i {
        match x.get(k) {
            // SAFETY: as the caller guarantees.
            Some(&p) => bf16_lanes(unsafe { _mm512_loadu_ps(p.add(16 * q)) }),
            None => _mm512_setzero_si512(),
        }
    }

    /// See [`super::matmul`].
    ///
    /// # Safety
    /// As [`super::matmul`]; [`available`] is true and `a` has its tiles.
    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn matmul(
        a: &Bf16Matrix,
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
        unsafe { pack_pairs(x, col_blocks * 16, &mut scratch.pairs) };
        let tiles = a.tiles.as_ptr();
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

    /// The bfloat16 of the 32 points 32·b.. of a column of `count` floats (zero from `count` on), packed
    /// in order: 16 words, each the pair of points (2p, 2p + 1).
    ///
    /// # Safety
    /// `c` addresses `count` readable floats.
    #[target_feature(enable = "avx512f")]
    #[inline]
    unsafe fn point_pairs(c: *const f32, count: usize, b: usize) -> __m512i {
        let half = |h: usize| {
            let from = 32 * b + 16 * h;
            let n = count.saturating_sub(from).min(16);
            let mask = ((1u32 << n) - 1) as u16;
            // SAFETY: the mask reads only points below `count` (caller).
            let v = unsafe { _mm512_maskz_loadu_ps(mask, c.add(from.min(count))) };
            _mm512_cvtepi32_epi16(bf16_lanes(v))
        };
        _mm512_inserti64x4::<1>(_mm512_castsi256_si512(half(0)), half(1))
    }

    /// See [`super::outer`].
    ///
    /// # Safety
    /// As [`super::outer`], whose checks passed; [`available`] is true.
    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn outer(
        l: &[*const f32],
        r: &[*const f32],
        count: usize,
        g: &mut [f32],
        scratch: &mut Bf16Scratch,
    ) {
        let stride = padded(r.len());
        let (row_blocks, col_blocks, point_blocks) = (l.len().div_ceil(16), stride / 16, count.div_ceil(32));
        if row_blocks == 0 || col_blocks == 0 || point_blocks == 0 {
            return;
        }
        // The left operand: row i's points 32·b.. in line i·point_blocks + b (rows past l.len() zero).
        let left = &mut scratch.left;
        left.clear();
        left.resize(row_blocks * 16 * point_blocks, Line::default());
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
        // The right operand: for column block jb and point block b, 16 lines: line p holds the pairs of
        // points (32·b + 2p, 32·b + 2p + 1) of the block's 16 columns (missing columns zero).
        let right = &mut scratch.right;
        right.clear();
        right.resize(col_blocks * point_blocks * 16, Line::default());
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

    /// On AMX and on the portable path alike: the sums of the products of the rounded operands, to f32's
    /// accuracy (a wrongly rounded operand would be off by ~1/256 of its term).
    #[test]
    fn matmul_sums_the_products_of_rounded_operands() {
        let mut scratch = Bf16Scratch::default();
        for (m, k) in [
            (1, 1),
            (3, 5),
            (16, 32),
            (17, 33),
            (40, 100),
            (128, 128),
            (256, 63),
            (5, 0),
            (0, 7),
        ] {
            let a = values(7, m * k);
            let xs: Vec<Vec<f32>> = (0..k).map(|c| values(c as u32 + 11, TILE)).collect();
            let matrix = Bf16Matrix::new(&a, m, k);
            let mut outs = vec![vec![f32::NAN; TILE]; m];
            let xp: Vec<*const f32> = xs.iter().map(|c| c.as_ptr()).collect();
            let op: Vec<*mut f32> = outs.iter_mut().map(|c| c.as_mut_ptr()).collect();
            // SAFETY: every column holds TILE floats; the outputs are separate buffers.
            unsafe { matmul(&matrix, &xp, &op, &mut scratch) };
            for (i, row) in outs.iter().enumerate() {
                for (t, &got) in row.iter().enumerate() {
                    let terms =
                        (0..k).map(|c| f64::from(round_bf16(a[i * k + c])) * f64::from(round_bf16(xs[c][t])));
                    let (want, size) = terms.fold((0.0, 0.0), |(s, z), v| (s + v, z + v.abs()));
                    assert!(
                        (f64::from(got) - want).abs() <= 1e-6 * (size + 1.0),
                        "amx {} {m}x{k} at ({i}, {t}): {got} vs {want}",
                        uses_amx()
                    );
                }
            }
        }
    }

    /// On AMX and on the portable path alike: the outer product adds the sums over the valid points of
    /// the products of the rounded operands.
    #[test]
    fn outer_adds_the_products_of_rounded_operands_over_the_valid_points() {
        let mut scratch = Bf16Scratch::default();
        for (m, n, count) in [
            (1, 1, 1),
            (3, 5, 7),
            (16, 16, 32),
            (17, 40, 100),
            (64, 128, 128),
            (33, 3, 128),
            (6, 9, 0),
        ] {
            let ls: Vec<Vec<f32>> = (0..m).map(|c| values(c as u32 + 100, TILE)).collect();
            let rs: Vec<Vec<f32>> = (0..n).map(|c| values(c as u32 + 300, TILE)).collect();
            let stride = gemm::padded(n);
            let mut g: Vec<f32> = values(5, m * stride);
            let before = g.clone();
            let lp: Vec<*const f32> = ls.iter().map(|c| c.as_ptr()).collect();
            let rp: Vec<*const f32> = rs.iter().map(|c| c.as_ptr()).collect();
            // SAFETY: every column holds TILE ≥ count floats.
            unsafe { outer(&lp, &rp, count, &mut g, &mut scratch) };
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
                        "amx {} {m}x{n}x{count} at ({i}, {j}): {got} vs {want}",
                        uses_amx()
                    );
                }
            }
        }
    }

    #[test]
    fn a_nan_operand_gives_nan() {
        let a = values(3, 2 * 40);
        let mut xs: Vec<Vec<f32>> = (0..40).map(|c| values(c as u32, TILE)).collect();
        xs[37][5] = f32::NAN;
        let mut outs = vec![vec![0.0; TILE]; 2];
        let xp: Vec<*const f32> = xs.iter().map(|c| c.as_ptr()).collect();
        let op: Vec<*mut f32> = outs.iter_mut().map(|c| c.as_mut_ptr()).collect();
        // SAFETY: every column holds TILE floats; the outputs are separate buffers.
        unsafe { matmul(&Bf16Matrix::new(&a, 2, 40), &xp, &op, &mut Bf16Scratch::default()) };
        for row in &outs {
            assert!(row[5].is_nan());
            assert!(row.iter().enumerate().all(|(t, v)| t == 5 || v.is_finite()));
        }
    }
}
