// What every kernel shares: includes, the denormal guard, the ray-box slab test and a segment's points.
//
// Every kernel computes exactly what the reference torch code computes (encodings/base.py, hashvqad.py,
// traversal.py) with the same float32 operations in the same order where the order matters for the result:
// grid cells, hashes and box tests are bit-identical (built with -ffp-contract=off, no fused multiply-add);
// only the order of the 8-corner sums differs (float rounding, ~1e-7 relative). Plain C ABI (nbvh_kernels.h) on
// the memory of contiguous arrays; OpenMP over points (forward), levels (backward) or rays (traversal).
#pragma once
#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <omp.h>
#include <type_traits>
#include <vector>
#if defined(__AVX2__) && defined(__FMA__)
#include <immintrin.h>
#define NBVH_AVX2 1
#endif
#if defined(__SSE__)
#include <xmmintrin.h>
#endif

#include "nbvh_kernels.h"

namespace {

// Flush denormals to zero (FTZ) and read them as zero (DAZ) on this thread. As a KMLP trains, hit probabilities of
// far-from-surface pairs saturate and their gradients underflow into denormals; every arithmetic operation on one
// then takes a slow microcode path (the training step slowed down from 28 to 42 ms over 36 s without this).
// A guard at the top of each parallel region (OpenMP threads do not inherit the caller's MXCSR); it restores the
// thread's mode when the region ends, so the calling (Python) thread's numerics are left as they were.
struct FlushDenormals {
#if defined(__SSE__)
    unsigned old;
    FlushDenormals() : old(_mm_getcsr()) { _mm_setcsr(old | 0x8040); }
    ~FlushDenormals() { _mm_setcsr(old); }
#endif
};

// Slab test exactly as traversal.ray_box: returns entered; writes t_enter, t_exit.
inline bool ray_box(const float* o, const float* inv, const float* lo, const float* hi, float t_max, float* te,
                    float* tx) {
    float tn = -INFINITY, tf = INFINITY;
    for (int a = 0; a < 3; ++a) {
        const float t0 = (lo[a] - o[a]) * inv[a];
        const float t1 = (hi[a] - o[a]) * inv[a];
        float lo_t = std::fmin(t0, t1);
        float hi_t = std::fmax(t0, t1);
        if (std::isnan(lo_t)) lo_t = -INFINITY;
        if (std::isnan(hi_t)) hi_t = INFINITY;
        tn = lo_t > tn ? lo_t : tn;
        tf = hi_t < tf ? hi_t : tf;
    }
    tn = tn < 0.f ? 0.f : tn;
    *te = tn;
    *tx = tf;
    return tn <= tf && tn <= t_max;
}


// Point i of segment seg: t_i = t_enter + frac_i (t_exit - t_enter) along its ray, as NeuralBVH.segment_points.
inline void segment_point(const float* rays_o, const float* rays_d, const int64_t* ray, const float* te,
                          const float* tx, int64_t seg, float frac_i, float* p) {
    const float* o = rays_o + 3 * ray[seg];
    const float* d = rays_d + 3 * ray[seg];
    const float t = te[seg] + frac_i * (tx[seg] - te[seg]);
    p[0] = o[0] + t * d[0]; p[1] = o[1] + t * d[1]; p[2] = o[2] + t * d[2];
}

}  // namespace
