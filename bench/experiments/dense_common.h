// What the dense experiments share: the clock, the FMA peak (16 independent 512-bit FMA chains in
// registers, as ../shared/bench/peak measures it) and nerfjit's product micro-kernel as a macro.
#include <immintrin.h>
#include <time.h>

static double now(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return t.tv_sec + t.tv_nsec * 1e-9;
}

// n rounds of 16 FMAs on 16-float vectors; the results go to o (256 floats), so that none is optimized away.
__attribute__((noinline)) static void peak(long n, float *o) {
    __m512 a[16];
    for (int i = 0; i < 16; i++) a[i] = _mm512_set1_ps((float)i);
    const __m512 b = _mm512_set1_ps(0.9999f), c = _mm512_set1_ps(0.0001f);
    for (long j = 0; j < n; j++)
        for (int i = 0; i < 16; i++) a[i] = _mm512_fmadd_ps(a[i], b, c);
    for (int i = 0; i < 16; i++) _mm512_storeu_ps(o + 16 * i, a[i]);
}

// R rows of out = A·x for the 16·QV points from t0 (A row-major with K columns; K defined by the includer):
// R × QV accumulators, per input column QV loads and R broadcasts, as jit/src/gemm.rs's matmul_block.
#define DENSE_BLOCK(NAME, R, QV)                                                                          \
    static inline void NAME(const float *a, const float *const *x, float *const *out, int t0) {           \
        __m512 acc[R][QV];                                                                                \
        for (int r = 0; r < R; r++)                                                                       \
            for (int q = 0; q < QV; q++) acc[r][q] = _mm512_setzero_ps();                                 \
        for (int k = 0; k < K; k++) {                                                                     \
            const float *p = x[k] + t0;                                                                   \
            __m512 b[QV];                                                                                 \
            for (int q = 0; q < QV; q++) b[q] = _mm512_loadu_ps(p + 16 * q);                              \
            for (int r = 0; r < R; r++) {                                                                 \
                const __m512 w = _mm512_set1_ps(a[r * K + k]);                                            \
                for (int q = 0; q < QV; q++) acc[r][q] = _mm512_fmadd_ps(w, b[q], acc[r][q]);             \
            }                                                                                             \
        }                                                                                                 \
        for (int r = 0; r < R; r++)                                                                       \
            for (int q = 0; q < QV; q++) _mm512_storeu_ps(out[r] + t0 + 16 * q, acc[r][q]);               \
    }
