/* Several voxel walks at once in SIMD lanes, for the dense marking of integrate_rays (_kernels.pyx).

   A scalar walk (_kernels._mark_walk) picks the axis of its next crossing with a branch that the
   processor cannot predict (the ray's direction decides it, step by step): most of its time goes to
   mispredicted branches, not to arithmetic. Here RAY_LANES walks advance together, one crossing each
   per step, with the choice made by vector compares and masks instead of branches. Each lane does the
   arithmetic of the scalar walk exactly (IEEE additions and compares of the same doubles, the same order
   on ties, an axis retired after its last crossing), so it marks the same voxels.

   The lanes are two vectors of four doubles (AVX2), so that the two dependency chains of a step overlap;
   the function is compiled for AVX2 whatever the flags of the build, and ray_lanes_available() asks the
   processor at run time. Elsewhere (another architecture or compiler, or an x86-64 without AVX2) it
   reports 0 and the scalar walk does all the work. Generic vectors of GCC and Clang: no intrinsics. */

#ifndef CELL_RAY_LANES_H
#define CELL_RAY_LANES_H

#include <math.h>
#include <stdint.h>

/* The state of one walk, in the dense box of integrate_rays. */
typedef struct {
    double t[3];     /* per axis: ray parameter of the next crossing; INFINITY when none is left */
    double dt[3];    /* per axis: parameter between crossings */
    int64_t n[3];    /* per axis: crossings left */
    int64_t dv[3];   /* per axis: move of the box index at a crossing */
    int64_t v;       /* box index of the current voxel (marked) */
    int64_t total;   /* crossings left in all; the walk stops with one left (the end voxel) */
} RayWalk;

#define RAY_LANES 8

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))

typedef double ray_lanes_vd __attribute__((vector_size(32)));
typedef int64_t ray_lanes_vi __attribute__((vector_size(32)));

typedef struct {
    ray_lanes_vd t[3], dt[3];
    ray_lanes_vi n[3], dv[3], v;
} RayLanes4;

__attribute__((target("avx2"), always_inline)) static inline void ray_lanes_load(RayLanes4* q, const RayWalk* w) {
    int a, l;
    for (a = 0; a < 3; a++)
        for (l = 0; l < 4; l++) {
            q->t[a][l] = w[l].t[a];
            q->dt[a][l] = w[l].dt[a];
            q->n[a][l] = w[l].n[a];
            q->dv[a][l] = w[l].dv[a];
        }
    for (l = 0; l < 4; l++)
        q->v[l] = w[l].v;
}

__attribute__((target("avx2"), always_inline)) static inline void ray_lanes_store(const RayLanes4* q, RayWalk* w,
                                                                   int64_t steps) {
    int a, l;
    for (l = 0; l < 4; l++) {
        for (a = 0; a < 3; a++) {
            w[l].t[a] = q->t[a][l];
            w[l].n[a] = q->n[a][l];
        }
        w[l].v = q->v[l];
        w[l].total -= steps;
    }
}

/* One crossing in each of four walks: the axis with the smallest t, y before x and z before both on a
   tie (the scalar walk's order); masks are all ones (-1) in the lanes that cross that axis. */
__attribute__((target("avx2"), always_inline)) static inline void ray_lanes_step(RayLanes4* q, uint8_t* seen) {
    const ray_lanes_vi zero = {0, 0, 0, 0};
    const ray_lanes_vd never = {INFINITY, INFINITY, INFINITY, INFINITY};
    ray_lanes_vi m[3], last;
    int a, l;
    m[0] = (q->t[0] < q->t[1]) & (q->t[0] < q->t[2]);
    m[2] = (q->t[2] <= q->t[0]) & (q->t[2] <= q->t[1]);
    m[1] = ~(m[0] | m[2]);
    q->v += (q->dv[0] & m[0]) | (q->dv[1] & m[1]) | (q->dv[2] & m[2]);
    for (a = 0; a < 3; a++) {
        q->n[a] += m[a];  /* -1 where the axis crosses */
        q->t[a] += (ray_lanes_vd)((ray_lanes_vi)q->dt[a] & m[a]);
        last = q->n[a] == zero;  /* retired: no crossing left on the axis */
        q->t[a] = (ray_lanes_vd)(((ray_lanes_vi)q->t[a] & ~last) | ((ray_lanes_vi)never & last));
    }
    for (l = 0; l < 4; l++)
        seen[q->v[l]] = 1;
}

/* Take `steps` crossings in each of the RAY_LANES walks `w` (each has more than `steps` crossings
   left), marking their voxels in `seen`; `w` is left at the state after them. */
__attribute__((target("avx2"))) static void ray_lanes_walk(RayWalk* w, uint8_t* seen, int64_t steps) {
    RayLanes4 lo, hi;
    int64_t i;
    ray_lanes_load(&lo, w);
    ray_lanes_load(&hi, w + 4);
    for (i = 0; i < steps; i++) {
        ray_lanes_step(&lo, seen);
        ray_lanes_step(&hi, seen);
    }
    ray_lanes_store(&lo, w, steps);
    ray_lanes_store(&hi, w + 4, steps);
}

static int ray_lanes_available(void) {
    __builtin_cpu_init();
    return __builtin_cpu_supports("avx2");
}

#else

static void ray_lanes_walk(RayWalk* w, uint8_t* seen, int64_t steps) {
    (void)w;
    (void)seen;
    (void)steps;
}

static int ray_lanes_available(void) { return 0; }

#endif

#endif
