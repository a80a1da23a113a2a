// What it costs to sort W7's random points into cells and to put results back in their order: the price
// of evaluating each cell with a kernel restricted to the primitives that can be nearest there.
//
//   gcc -O3 -march=native -fopenmp sort_points.c -o /tmp/sort_points
//   /tmp/sort_points CELLS_PER_AXIS THREADS      e.g. /tmp/sort_points 16 2
//
// 1,048,576 uniform random points in [-4, 4]^3 (structure of arrays, as W7). "sort" is a counting sort by
// cell (per-thread histograms, one prefix sum, a scatter of x, y, z and the point's index); "back" writes
// one float per point to its original position. "in blocks" does both per block of 4,096 points, so that
// everything stays in cache: cells, four interleaved histograms, the scatter of x, y, z and a 16-bit index,
// and the write back of one float per point (for at most 16^3 cells). Best of 21 runs, in ns per point.
#include <omp.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#define N (1 << 20)

static double now(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return t.tv_sec + t.tv_nsec * 1e-9;
}

#define BLOCK 4096
/// The most cells a block's sort handles (its histograms live on the stack; cell numbers fit 16 bits).
#define BLOCK_CELLS 4096

/// Sorts one block of points by cell and writes a stand-in result (x + y·z of each sorted point) back in the
/// points' order: the work that evaluating a block cell by cell adds to evaluating it in order.
static void sort_block(const float *x, const float *y, const float *z, float *out, int r, float scale) {
    float sx[BLOCK], sy[BLOCK], sz[BLOCK];
    uint16_t index[BLOCK];
    uint16_t cell[BLOCK];
    uint32_t count[4][BLOCK_CELLS], start[BLOCK_CELLS];
    const int cells = r * r * r;
    memset(count, 0, sizeof count);
    for (int i = 0; i < BLOCK; i++) {
        int a = (int)((x[i] + 4) * scale), b = (int)((y[i] + 4) * scale), d = (int)((z[i] + 4) * scale);
        a = a < r - 1 ? a : r - 1;
        b = b < r - 1 ? b : r - 1;
        d = d < r - 1 ? d : r - 1;
        cell[i] = (uint16_t)((d * r + b) * r + a);
    }
    for (int i = 0; i < BLOCK; i += 4)
        for (int u = 0; u < 4; u++) count[u][cell[i + u]]++;
    uint32_t next = 0;
    for (int k = 0; k < cells; k++) {
        start[k] = next;
        next += count[0][k] + count[1][k] + count[2][k] + count[3][k];
    }
    for (int i = 0; i < BLOCK; i++) {
        const uint32_t j = start[cell[i]]++;
        sx[j] = x[i];
        sy[j] = y[i];
        sz[j] = z[i];
        index[j] = (uint16_t)i;
    }
    for (int j = 0; j < BLOCK; j++) out[index[j]] = sx[j] + sy[j] * sz[j];
}

static float *floats(void) {
    float *v = malloc(N * sizeof(float));
    memset(v, 0, N * sizeof(float));
    return v;
}

int main(int argc, char **argv) {
    if (argc != 3) {
        fprintf(stderr, "usage: %s CELLS_PER_AXIS THREADS\n", argv[0]);
        return 2;
    }
    const int r = atoi(argv[1]), threads = atoi(argv[2]), cells = r * r * r;
    if (r < 1 || r > 40 || threads < 1) {
        fprintf(stderr, "CELLS_PER_AXIS must be 1..40, THREADS at least 1\n");
        return 2;
    }
    omp_set_num_threads(threads);
    float *x = floats(), *y = floats(), *z = floats(), *sx = floats(), *sy = floats(), *sz = floats();
    float *result = floats(), *out = floats();
    uint32_t *index = calloc(N, sizeof(uint32_t));
    uint16_t *cell = calloc(N, sizeof(uint16_t));
    uint32_t *count = calloc((size_t)threads * cells, sizeof(uint32_t));
    srand(7);
    for (int i = 0; i < N; i++) {
        x[i] = rand() / (float)RAND_MAX * 8 - 4;
        y[i] = rand() / (float)RAND_MAX * 8 - 4;
        z[i] = rand() / (float)RAND_MAX * 8 - 4;
        result[i] = (float)i;
    }
    const float scale = r / 8.0f;
    double best_sort = 1e9, best_back = 1e9, best_blocks = 1e9;
    for (int rep = 0; rep < 21; rep++) {
        const double t0 = now();
#pragma omp parallel
        {
            const int t = omp_get_thread_num();
            uint32_t *c = count + (size_t)t * cells;
            memset(c, 0, cells * sizeof(uint32_t));
            const int lo = (int)((long)N * t / threads), hi = (int)((long)N * (t + 1) / threads);
            for (int i = lo; i < hi; i++) {
                int a = (int)((x[i] + 4) * scale), b = (int)((y[i] + 4) * scale), d = (int)((z[i] + 4) * scale);
                a = a < r - 1 ? a : r - 1;
                b = b < r - 1 ? b : r - 1;
                d = d < r - 1 ? d : r - 1;
                const int k = (d * r + b) * r + a;
                cell[i] = (uint16_t)k;
                c[k]++;
            }
#pragma omp barrier
#pragma omp single
            {
                uint32_t start = 0;
                for (int k = 0; k < cells; k++)
                    for (int u = 0; u < threads; u++) {
                        const uint32_t n = count[(size_t)u * cells + k];
                        count[(size_t)u * cells + k] = start;
                        start += n;
                    }
            }
            for (int i = lo; i < hi; i++) {
                const uint32_t j = c[cell[i]]++;
                sx[j] = x[i];
                sy[j] = y[i];
                sz[j] = z[i];
                index[j] = (uint32_t)i;
            }
        }
        const double t1 = now();
#pragma omp parallel for
        for (int j = 0; j < N; j++) out[index[j]] = result[j] + sx[j];
        const double t2 = now();
        if (t1 - t0 < best_sort) best_sort = t1 - t0;
        if (t2 - t1 < best_back) best_back = t2 - t1;
        if (cells <= BLOCK_CELLS) {
#pragma omp parallel for schedule(static)
            for (int b = 0; b < N; b += BLOCK) sort_block(x + b, y + b, z + b, out + b, r, scale);
            const double t3 = now();
            if (t3 - t2 < best_blocks) best_blocks = t3 - t2;
        }
    }
    printf("%d^3 cells, %d thread(s): sort %.2f ns/point, back in order %.2f ns/point; ", r, threads,
           best_sort * 1e9 / N, best_back * 1e9 / N);
    if (cells <= BLOCK_CELLS)
        printf("both in blocks of %d %.2f ns/point", BLOCK, best_blocks * 1e9 / N);
    else
        printf("in blocks only up to %d cells", BLOCK_CELLS);
    printf(" (checksum %g)\n", (double)out[N / 2] + sy[N / 3] + sz[N / 5]);
    return 0;
}
