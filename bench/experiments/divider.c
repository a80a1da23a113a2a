// The square-root and division throughput of this CPU at each vector width: are wider vectors faster on
// square-root-bound code such as W7 (26 square roots a point)?
//
//   gcc -O2 -march=native divider.c -o /tmp/divider && /tmp/divider
//
// 12 independent chains of `sqrt` (or `1.0001 / x`) per width, 10^7 rounds; the time per instruction and
// per lane, on one thread. Two rounds.
#include <immintrin.h>
#include <stdio.h>
#include <time.h>

#define CHAINS 12
#define ROUNDS 10000000L

static double now(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return t.tv_sec + t.tv_nsec * 1e-9;
}

// The empty asm keeps each chain in its register and the compiler from folding the loop.
#define CHAIN_KERNEL(name, type, set1, op, first, constraint)                                             \
    __attribute__((noinline)) static float name(long n) {                                              \
        type a[CHAINS];                                                                                \
        const type b = set1(1.0001f);                                                                  \
        (void)b;                                                                                       \
        for (int i = 0; i < CHAINS; i++) a[i] = set1(1.0f + i);                                        \
        for (long j = 0; j < n; j++)                                                                   \
            for (int i = 0; i < CHAINS; i++) {                                                         \
                a[i] = op;                                                                             \
                __asm__("" : "+" constraint(a[i]));                                                    \
            }                                                                                          \
        float s = 0;                                                                                   \
        for (int i = 0; i < CHAINS; i++) s += first(a[i]);                                             \
        return s;                                                                                      \
    }
CHAIN_KERNEL(sqrt128, __m128, _mm_set1_ps, _mm_sqrt_ps(a[i]), _mm_cvtss_f32, "x")
CHAIN_KERNEL(sqrt256, __m256, _mm256_set1_ps, _mm256_sqrt_ps(a[i]), _mm256_cvtss_f32, "x")
CHAIN_KERNEL(sqrt512, __m512, _mm512_set1_ps, _mm512_sqrt_ps(a[i]), _mm512_cvtss_f32, "v")
CHAIN_KERNEL(div128, __m128, _mm_set1_ps, _mm_div_ps(b, a[i]), _mm_cvtss_f32, "x")
CHAIN_KERNEL(div256, __m256, _mm256_set1_ps, _mm256_div_ps(b, a[i]), _mm256_cvtss_f32, "x")
CHAIN_KERNEL(div512, __m512, _mm512_set1_ps, _mm512_div_ps(b, a[i]), _mm512_cvtss_f32, "v")

static double per_instruction_ns(float (*kernel)(long), float *sink) {
    const double t = now();
    *sink += kernel(ROUNDS);
    return (now() - t) / (ROUNDS * CHAINS) * 1e9;
}

int main(void) {
    float sink = 0;
    for (int round = 0; round < 2; round++) {
        const double s[3] = {per_instruction_ns(sqrt128, &sink), per_instruction_ns(sqrt256, &sink),
                             per_instruction_ns(sqrt512, &sink)};
        const double d[3] = {per_instruction_ns(div128, &sink), per_instruction_ns(div256, &sink),
                             per_instruction_ns(div512, &sink)};
        printf("sqrt: %.3f / %.3f / %.3f ns an instruction of 4 / 8 / 16 lanes = %.3f / %.3f / %.3f ns a lane\n",
               s[0], s[1], s[2], s[0] / 4, s[1] / 8, s[2] / 16);
        printf("div:  %.3f / %.3f / %.3f ns an instruction of 4 / 8 / 16 lanes = %.3f / %.3f / %.3f ns a lane\n",
               d[0], d[1], d[2], d[0] / 4, d[1] / 8, d[2] / 16);
    }
    printf("(checksum %g)\n", (double)sink);
    return 0;
}
