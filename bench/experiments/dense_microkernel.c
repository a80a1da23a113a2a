// nerfjit's f32 product micro-kernel (jit/src/gemm.rs, avx512::matmul) written in C, timed beside the FMA
// peak it is judged against: is the 90% target out of reach of the loop itself, or of Rust's code for it?
//
//   gcc -O3 -march=native dense_microkernel.c -o /tmp/dense_microkernel
//   /tmp/dense_microkernel [COLUMN_FLOATS [ROWS]]       e.g. /tmp/dense_microkernel 144 128
//
// "peak": 16 independent 512-bit FMA chains in registers (dense_common.h, as ../shared/bench/peak). "tile": out = A·x for a
// ROWS × 128 matrix A (row-major) and a tile of 128 points whose 128 input columns lie COLUMN_FLOATS apart
// (nerfjit's arena: 144), in blocks of 6 rows × 64 points (24 accumulators; 4 loads and 6 broadcasts per 24
// FMAs), the rows left over in one smaller block. "block": one 6-row block over and over, its operands always
// in L1. Three rounds; GFLOP/s and the share of the peak of the same round.
#include <immintrin.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

#define K 128
#define TILE 128
#define QV 4

#include "dense_common.h"

DENSE_BLOCK(block1, 1, QV)
DENSE_BLOCK(block2, 2, QV)
DENSE_BLOCK(block3, 3, QV)
DENSE_BLOCK(block4, 4, QV)
DENSE_BLOCK(block5, 5, QV)
DENSE_BLOCK(block6, 6, QV)

__attribute__((noinline)) static void tile(const float *a, int rows, const float *const *x, float *const *out) {
    for (int t0 = 0; t0 < TILE; t0 += 16 * QV) {
        int i = 0;
        for (; i + 6 <= rows; i += 6) block6(a + i * K, x, out + i, t0);
        switch (rows - i) {
        case 5: block5(a + i * K, x, out + i, t0); break;
        case 4: block4(a + i * K, x, out + i, t0); break;
        case 3: block3(a + i * K, x, out + i, t0); break;
        case 2: block2(a + i * K, x, out + i, t0); break;
        case 1: block1(a + i * K, x, out + i, t0); break;
        }
    }
}

__attribute__((noinline)) static void one_block(const float *a, const float *const *x, float *const *out) {
    block6(a, x, out, 0);
}

int main(int argc, char **argv) {
    const int column = argc > 1 ? atoi(argv[1]) : 144, rows = argc > 2 ? atoi(argv[2]) : 128;
    if (column < TILE || column > 1 << 16 || rows < 6 || rows > 1024) {
        fprintf(stderr, "usage: %s [COLUMN_FLOATS >= %d [ROWS 6..1024]]\n", argv[0], TILE);
        return 2;
    }
    const Operands o = operands(rows, column);
    float sink[256];
    for (int round = 0; round < 3; round++) {
        const double pk = peak_gflops(sink);
        const long reps = 40000000L / rows;
        double t0 = now();
        for (long i = 0; i < reps; i++) tile(o.a, rows, o.x, o.out);
        const double tl = (double)reps * rows * K * TILE * 2 / (now() - t0) / 1e9;
        t0 = now();
        for (long i = 0; i < 64 * reps; i++) one_block(o.a, o.x, o.out);
        const double bl = 64.0 * reps * 6 * K * 64 * 2 / (now() - t0) / 1e9;
        printf("peak %.1f GFLOP/s   tile %.1f (%.0f%%)   block %.1f (%.0f%%)   [%g]\n", pk, tl, 100 * tl / pk, bl,
               100 * bl / pk, (double)o.outs[7] + sink[3]);
    }
    return 0;
}
