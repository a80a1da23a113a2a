// Other register blocks for nerfjit's f32 product micro-kernel (jit/src/gemm.rs keeps 6 rows × 64 points):
// does a different shape reach 90% of the FMA peak on a whole 128 × 128 tile of 128 points?
//
//   gcc -O3 -march=native dense_block_shapes.c -o /tmp/dense_block_shapes && /tmp/dense_block_shapes
//
// Per round: the peak (16 independent 512-bit FMA chains, as ../shared/bench/peak), then out = A·x for a
// 128 × 128 A and 128 input columns 144 floats apart (nerfjit's arena) in blocks of R rows × 16·QV points:
// 6 × 64 (and a 2-row remainder), 8 × 32, 8 × 48 (and 8 × 32 for the last 32 points), 12 × 32 (and 8 × 32),
// 16 × 16, and 6 × 64 with the row blocks outermost. Share of the same round's peak.
#include <immintrin.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

#define K 128
#define TILE 128
#define ROWS 128

#include "dense_common.h"

DENSE_BLOCK(block_6x64, 6, 4)
DENSE_BLOCK(block_2x64, 2, 4)
DENSE_BLOCK(block_8x32, 8, 2)
DENSE_BLOCK(block_8x48, 8, 3)
DENSE_BLOCK(block_12x32, 12, 2)
DENSE_BLOCK(block_16x16, 16, 1)

typedef const float *const *Inputs;
typedef float *const *Outputs;

// 6 × 64 (nerfjit's): point blocks outermost, the 2 rows left over in a smaller block.
__attribute__((noinline)) static void tile_6x64(const float *a, Inputs x, Outputs out) {
    for (int t0 = 0; t0 < TILE; t0 += 64) {
        int i = 0;
        for (; i + 6 <= ROWS; i += 6) block_6x64(a + i * K, x, out + i, t0);
        block_2x64(a + i * K, x, out + i, t0);
    }
}

__attribute__((noinline)) static void tile_8x32(const float *a, Inputs x, Outputs out) {
    for (int t0 = 0; t0 < TILE; t0 += 32)
        for (int i = 0; i < ROWS; i += 8) block_8x32(a + i * K, x, out + i, t0);
}

// 8 × 48 for points 0..96, 8 × 32 for the last 32.
__attribute__((noinline)) static void tile_8x48(const float *a, Inputs x, Outputs out) {
    for (int t0 = 0; t0 < 96; t0 += 48)
        for (int i = 0; i < ROWS; i += 8) block_8x48(a + i * K, x, out + i, t0);
    for (int i = 0; i < ROWS; i += 8) block_8x32(a + i * K, x, out + i, 96);
}

// 12 × 32, the 8 rows left over as 8 × 32.
__attribute__((noinline)) static void tile_12x32(const float *a, Inputs x, Outputs out) {
    for (int t0 = 0; t0 < TILE; t0 += 32) {
        int i = 0;
        for (; i + 12 <= ROWS; i += 12) block_12x32(a + i * K, x, out + i, t0);
        block_8x32(a + i * K, x, out + i, t0);
    }
}

__attribute__((noinline)) static void tile_16x16(const float *a, Inputs x, Outputs out) {
    for (int t0 = 0; t0 < TILE; t0 += 16)
        for (int i = 0; i < ROWS; i += 16) block_16x16(a + i * K, x, out + i, t0);
}

// 6 × 64 with the row blocks outermost: a block's weights stay in L1, the inputs stream.
__attribute__((noinline)) static void tile_6x64_rows_outer(const float *a, Inputs x, Outputs out) {
    int i = 0;
    for (; i + 6 <= ROWS; i += 6)
        for (int t0 = 0; t0 < TILE; t0 += 64) block_6x64(a + i * K, x, out + i, t0);
    for (int t0 = 0; t0 < TILE; t0 += 64) block_2x64(a + i * K, x, out + i, t0);
}

int main(void) {
    const Operands o = operands(ROWS, 144);
    const struct {
        const char *name;
        void (*tile)(const float *, Inputs, Outputs);
    } shapes[] = {{"6x64", tile_6x64},     {"8x32", tile_8x32},   {"8x48", tile_8x48},
                  {"12x32", tile_12x32},   {"16x16", tile_16x16}, {"6x64 rows outer", tile_6x64_rows_outer}};
    const int n_shapes = sizeof shapes / sizeof shapes[0];
    float sink[256];
    for (int round = 0; round < 4; round++) {
        const double round_peak = peak_gflops(sink);
        printf("peak %.1f GFLOP/s:", round_peak);
        for (int s = 0; s < n_shapes; s++) {
            const long reps = 300000;
            const double t0 = now();
            for (long j = 0; j < reps; j++) shapes[s].tile(o.a, o.x, o.out);
            const double gflops = (double)reps * ROWS * K * TILE * 2 / (now() - t0) / 1e9;
            printf("  %s %.0f%%", shapes[s].name, 100 * gflops / round_peak);
        }
        printf("   [%g]\n", (double)o.outs[7] + sink[3]);
    }
    return 0;
}
