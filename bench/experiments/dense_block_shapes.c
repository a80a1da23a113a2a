// Other register blocks for nerfjit's f32 product micro-kernel (jit/src/gemm.rs keeps 6 rows × 64 points):
// does a different shape reach 90% of the FMA peak on a whole 128 × 128 tile of 128 points?
//
//   gcc -O3 -march=native dense_block_shapes.c -o /tmp/dense_block_shapes && /tmp/dense_block_shapes
//
// Per round: the peak (16 independent 512-bit FMA chains, as ../shared/bench/peak), then out = A·x for a
// 128 × 128 A and 128 input columns 144 floats apart (nerfjit's arena) in blocks of R rows × 16·QV points:
// 6 × 64 (and a 2-row remainder), 8 × 32, 8 × 48 (and 8 × 32 for the last 32 points), 12 × 32 (and 8 × 32),
// 16 × 16, and 6 × 64 with the row blocks outermost ("r6x4"). Share of the same round's peak.
#include <immintrin.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
#define K 128
#define TILE 128
static double now(void){struct timespec t;clock_gettime(CLOCK_MONOTONIC,&t);return t.tv_sec+t.tv_nsec*1e-9;}
__attribute__((noinline)) static void peak(long n, float *o) {
    __m512 a[16];
    for (int i = 0; i < 16; i++) a[i] = _mm512_set1_ps((float)i);
    const __m512 b = _mm512_set1_ps(0.9999f), c = _mm512_set1_ps(0.0001f);
    for (long j = 0; j < n; j++)
        for (int i = 0; i < 16; i++) a[i] = _mm512_fmadd_ps(a[i], b, c);
    for (int i = 0; i < 16; i++) _mm512_storeu_ps(o + 16 * i, a[i]);
}
#define BLOCK(NAME,R,QV) \
static inline void NAME(const float *a, const float *const *x, float *const *out, int t0) { \
    __m512 acc[R][QV]; \
    for (int r = 0; r < R; r++) for (int q = 0; q < QV; q++) acc[r][q] = _mm512_setzero_ps(); \
    for (int k = 0; k < K; k++) { \
        const float *p = x[k] + t0; __m512 b[QV]; \
        for (int q = 0; q < QV; q++) b[q] = _mm512_loadu_ps(p + 16 * q); \
        for (int r = 0; r < R; r++) { const __m512 w = _mm512_set1_ps(a[r * K + k]); \
            for (int q = 0; q < QV; q++) acc[r][q] = _mm512_fmadd_ps(w, b[q], acc[r][q]); } } \
    for (int r = 0; r < R; r++) for (int q = 0; q < QV; q++) _mm512_storeu_ps(out[r] + t0 + 16 * q, acc[r][q]); }
BLOCK(b6x4,6,4) BLOCK(b2x4,2,4) BLOCK(b8x2,8,2) BLOCK(b8x3,8,3) BLOCK(b12x2,12,2) BLOCK(b16x1,16,1) BLOCK(b8x1,8,1)
__attribute__((noinline)) static void t6x4(const float *a, const float *const *x, float *const *out){
  for(int t0=0;t0<TILE;t0+=64){ int i=0; for(;i+6<=128;i+=6) b6x4(a+i*K,x,out+i,t0); b2x4(a+i*K,x,out+i,t0);} }
__attribute__((noinline)) static void t8x2(const float *a, const float *const *x, float *const *out){
  for(int t0=0;t0<TILE;t0+=32){ for(int i=0;i<128;i+=8) b8x2(a+i*K,x,out+i,t0);} }
__attribute__((noinline)) static void t8x3(const float *a, const float *const *x, float *const *out){
  for(int t0=0;t0<96;t0+=48){ for(int i=0;i<128;i+=8) b8x3(a+i*K,x,out+i,t0);} for(int i=0;i<128;i+=8) b8x2(a+i*K,x,out+i,96);}
__attribute__((noinline)) static void t12x2(const float *a, const float *const *x, float *const *out){
  for(int t0=0;t0<TILE;t0+=32){ int i=0; for(;i+12<=128;i+=12) b12x2(a+i*K,x,out+i,t0); b8x2(a+i*K,x,out+i,t0);} }
__attribute__((noinline)) static void t16x1(const float *a, const float *const *x, float *const *out){
  for(int t0=0;t0<TILE;t0+=16){ for(int i=0;i<128;i+=16) b16x1(a+i*K,x,out+i,t0);} }
/* rows outer: weights block stays in L1, x streams */
__attribute__((noinline)) static void r6x4(const float *a, const float *const *x, float *const *out){
  int i=0; for(;i+6<=128;i+=6) for(int t0=0;t0<TILE;t0+=64) b6x4(a+i*K,x,out+i,t0); for(int t0=0;t0<TILE;t0+=64) b2x4(a+i*K,x,out+i,t0); }
typedef void (*tf)(const float*, const float*const*, float*const*);
int main(int argc,char**argv){
  int column=144; float *xs=aligned_alloc(64,K*column*4), *outs=aligned_alloc(64,128*column*4), *a=aligned_alloc(64,128*K*4);
  const float *x[K]; float *out[128];
  for(int k=0;k<K;k++){x[k]=xs+k*column; for(int t=0;t<column;t++) xs[k*column+t]=0.001f*t;}
  for(int r=0;r<128;r++) out[r]=outs+r*column;
  for(int i=0;i<128*K;i++) a[i]=0.001f*(i%97);
  struct {const char*n; tf f;} ks[]={{"6x4",t6x4},{"8x2",t8x2},{"8x3",t8x3},{"12x2",t12x2},{"16x1",t16x1},{"r6x4",r6x4}};
  float sink[256];
  for(int round=0;round<4;round++){
    long fmas=20000000; double t0=now(); peak(fmas,sink); double pk=fmas*16.0*32/(now()-t0)/1e9;
    printf("peak %.1f:", pk);
    for(int i=0;i<6;i++){ long reps=300000; t0=now(); for(long j=0;j<reps;j++) ks[i].f(a,x,out);
      double g=(double)reps*128*K*TILE*2/(now()-t0)/1e9; printf(" %s %.0f%%", ks[i].n, 100*g/pk);}
    printf("\n");
  }
}
