// What the dense experiments share: the clock, the FMA peak (16 independent 512-bit FMA chains in
// registers, as ../shared/bench/peak measures it), the product's operands and nerfjit's product
// micro-kernel as a macro. The includer defines K, the product's inner dimension.
#include <immintrin.h>
#include <stdlib.h>
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

// The FMA peak in GFLOP/s: 20 million rounds of `peak` timed (the results go to sink, 256 floats).
static double peak_gflops(float *sink) {
    const long fmas = 20000000;
    const double t0 = now();
    peak(fmas, sink);
    return fmas * 16.0 * 32 / (now() - t0) / 1e9;
}

// out = A·x's operands: A (rows × K, row-major) and K input and `rows` output columns whose starts lie
// `column` floats apart in one allocation each (nerfjit's arena), filled with small values.
typedef struct {
    float *a, *outs;
    const float **x;
    float **out;
} Operands;

static Operands operands(int rows, int column) {
    Operands o = {aligned_alloc(64, (size_t)rows * K * sizeof(float)),
                  aligned_alloc(64, (size_t)rows * column * sizeof(float)), malloc(K * sizeof(float *)),
                  malloc(rows * sizeof(float *))};
    float *xs = aligned_alloc(64, (size_t)K * column * sizeof(float));
    for (int k = 0; k < K; k++) {
        o.x[k] = xs + (size_t)k * column;
        for (int t = 0; t < column; t++) xs[(size_t)k * column + t] = 0.001f * t;
    }
    for (int r = 0; r < rows; r++) o.out[r] = o.outs + (size_t)r * column;
    for (int i = 0; i < rows * K; i++) o.a[i] = 0.001f * (i % 97);
    return o;
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
