// The clock and the FMA peak shared by the dense experiments: 16 independent 512-bit FMA chains in
// registers, as ../shared/bench/peak measures it.
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
