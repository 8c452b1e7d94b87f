// Fused CPU kernels of the fast path (see kernels/__init__.py). Plain C ABI, called through ctypes on the
// memory of contiguous torch tensors; OpenMP over points (forward), levels (backward) or rays (traversal).
//
// Every kernel computes exactly what the reference torch code computes (encodings/base.py, hashvqad.py,
// traversal.py) with the same float32 operations in the same order where the order matters for the result:
// grid cells, hashes and box tests are bit-identical (built with -ffp-contract=off, no fused multiply-add);
// only the order of the 8-corner sums differs (float rounding, ~1e-7 relative).
#include <algorithm>
#include <cmath>
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

constexpr uint32_t P1 = 2654435761u;
constexpr uint32_t P2 = 805459861u;

struct Grid {
    int levels, features;
    const float* scales;      // (L,) s_l
    const int64_t* res;       // (L,) vertices per axis
    const uint8_t* dense;     // (L,) 1 when level l indexes densely
    int64_t vertex_table;     // vertex index range: T (HashGrid) or H (HashVQAD)
    int64_t rows;             // rows per level in `table`; 0: `table` holds the reachable entries' rows only,
                              // level after level (HashVQAD's soft row table): level l's start at code_start[l]
    const uint8_t* codes;     // frozen HashVQAD codes of the reachable entries, level after level, bit-packed
                              // (code_bits each, little-endian within a byte, as the file stores them), or null
    int64_t code_rows;        // T: candidate rows hash2(i, code) mod T (with codes)
    int code_bits = 8;        // 1, 2, 4 or 8
    const float* qoffset = nullptr;  // (L, F) uint8 tables: value = offset + code * scale
    const float* qscale = nullptr;
    uint32_t vertex_mask = 0; // vertex_table - 1 when it is a power of two <= 2^32, else 0
    uint32_t code_mask = 0;
    int64_t code_start[17] = {0};  // level l's first code in `codes`: a dense level reaches res^3 entries, else all
    int code_shift = 0;            // log2(codes per byte)
    uint32_t code_value_mask = 255;
    int64_t row_start[17] = {0};   // level l's first row in `table`: l * rows, or code_start[l] when rows is 0

    void init_masks() {
        auto pow2 = [](int64_t v) { return v > 0 && v <= (int64_t(1) << 32) && (v & (v - 1)) == 0; };
        vertex_mask = pow2(vertex_table) ? (uint32_t)(vertex_table - 1) : 0;
        code_mask = pow2(code_rows) ? (uint32_t)(code_rows - 1) : 0;
        for (int l = 0; l < levels && l < 16; ++l)
            code_start[l + 1] = code_start[l] + (dense[l] ? res[l] * res[l] * res[l] : vertex_table);
        for (int l = 0; l < levels && l < 17; ++l) row_start[l] = rows > 0 ? (int64_t)l * rows : code_start[l];
        code_shift = code_bits == 1 ? 3 : code_bits == 2 ? 2 : code_bits == 4 ? 1 : 0;
        code_value_mask = code_bits >= 8 ? 255u : (1u << code_bits) - 1u;
    }
};

// Cell of point x (clamped to the unit box) at level l: corner 0 (`base`) and the position inside it (`frac`).
template <typename I>
inline void cell(const Grid& g, int l, const float* x, float* frac, I* base) {
    const float s = g.scales[l];
    for (int a = 0; a < 3; ++a) {
        float xa = x[a];
        xa = xa < 0.f ? 0.f : (xa > 1.f ? 1.f : xa);
        const float p = xa * s + 0.5f;
        const float b = std::floor(p);
        frac[a] = p - b;
        base[a] = (I)b;
    }
}

// Row a frozen HashVQAD code selects for vertex index idx at level l (identity without codes).
inline int64_t code_row(const Grid& g, int l, int64_t idx) {
    if (!g.codes) return idx;
    const int64_t j = g.code_start[l] + idx;
    const uint32_t shift = (uint32_t)(j & ((1 << g.code_shift) - 1)) * (uint32_t)g.code_bits;
    const uint32_t code = ((uint32_t)g.codes[j >> g.code_shift] >> shift) & g.code_value_mask;
    const uint32_t h = ((uint32_t)idx * P1) ^ (code * P2);
    return g.code_mask ? (int64_t)(h & g.code_mask) : (int64_t)(h % (uint64_t)g.code_rows);
}

// Row of `table` (within level l) and trilinear weight of the 8 corners of point x at level l.
inline void corners(const Grid& g, int l, const float* x, int64_t* row, float* w) {
    float frac[3];
    int64_t base[3];
    cell(g, l, x, frac, base);
    const int64_t r = g.res[l];
    for (int c = 0; c < 8; ++c) {
        const int bx = c & 1, by = (c >> 1) & 1, bz = (c >> 2) & 1;
        const int64_t cx = base[0] + bx, cy = base[1] + by, cz = base[2] + bz;
        // Same product order as the reference: (w_x * w_y) * w_z.
        w[c] = ((bx ? frac[0] : 1.f - frac[0]) * (by ? frac[1] : 1.f - frac[1])) * (bz ? frac[2] : 1.f - frac[2]);
        int64_t idx;
        if (g.dense[l]) {
            idx = cx + cy * r + cz * r * r;
        } else {
            const uint32_t h = (uint32_t)cx ^ ((uint32_t)cy * P1) ^ ((uint32_t)cz * P2);
            // Table sizes are powers of two in practice: a mask instead of a 64-bit division (~30 cycles).
            idx = g.vertex_mask ? (int64_t)(h & g.vertex_mask) : (int64_t)(h % (uint64_t)g.vertex_table);
        }
        row[c] = code_row(g, l, idx);
    }
}

#ifdef NBVH_AVX2
// `corners` for the 8 corners at once in AVX2 lanes (lane c = corner c): the same cells, weights (same product
// order) and rows, bit for bit; int32 lanes, so only for levels whose index arithmetic fits 32 bits (see fits32).
inline void corners8(const Grid& g, int l, const float* x, int64_t* row, float* w) {
    float frac[3];
    int32_t base[3];
    cell(g, l, x, frac, base);
    const __m256 one = _mm256_set1_ps(1.f);
    const __m256 fx = _mm256_set1_ps(frac[0]), fy = _mm256_set1_ps(frac[1]), fz = _mm256_set1_ps(frac[2]);
    const __m256 wx = _mm256_blend_ps(_mm256_sub_ps(one, fx), fx, 0xAA);  // lanes with bit 0 set take frac
    const __m256 wy = _mm256_blend_ps(_mm256_sub_ps(one, fy), fy, 0xCC);
    const __m256 wz = _mm256_blend_ps(_mm256_sub_ps(one, fz), fz, 0xF0);
    _mm256_storeu_ps(w, _mm256_mul_ps(_mm256_mul_ps(wx, wy), wz));
    const __m256i cx = _mm256_add_epi32(_mm256_set1_epi32(base[0]), _mm256_setr_epi32(0, 1, 0, 1, 0, 1, 0, 1));
    const __m256i cy = _mm256_add_epi32(_mm256_set1_epi32(base[1]), _mm256_setr_epi32(0, 0, 1, 1, 0, 0, 1, 1));
    const __m256i cz = _mm256_add_epi32(_mm256_set1_epi32(base[2]), _mm256_setr_epi32(0, 0, 0, 0, 1, 1, 1, 1));
    __m256i idx;
    if (g.dense[l]) {
        const int32_t r = (int32_t)g.res[l];
        idx = _mm256_add_epi32(cx, _mm256_add_epi32(_mm256_mullo_epi32(cy, _mm256_set1_epi32(r)),
                                                    _mm256_mullo_epi32(cz, _mm256_set1_epi32(r * r))));
    } else {
        const __m256i h = _mm256_xor_si256(cx, _mm256_xor_si256(_mm256_mullo_epi32(cy, _mm256_set1_epi32((int32_t)P1)),
                                                                _mm256_mullo_epi32(cz, _mm256_set1_epi32((int32_t)P2))));
        idx = _mm256_and_si256(h, _mm256_set1_epi32((int32_t)g.vertex_mask));
    }
    alignas(32) uint32_t v[8];
    _mm256_store_si256(reinterpret_cast<__m256i*>(v), idx);
    for (int c = 0; c < 8; ++c) row[c] = code_row(g, l, (int64_t)v[c]);
}
#endif

// The vectorised corners where they give the same answer: hashed levels need a power-of-two vertex table (mask),
// dense levels r^3 < 2^31 (int32 lanes).
inline bool fits32(const Grid& g, int l) {
    if (g.dense[l]) return g.res[l] * g.res[l] * g.res[l] < (int64_t(1) << 31);
    return g.vertex_mask != 0 && g.vertex_table <= (int64_t(1) << 31);
}

inline void corners_any(const Grid& g, int l, const float* x, int64_t* row, float* w, bool vec) {
#ifdef NBVH_AVX2
    if (vec) { corners8(g, l, x, row, w); return; }
#endif
    (void)vec;
    corners(g, l, x, row, w);
}

// Table entries are float32, float16 (`_Float16`, inference only: half the bytes to gather; the compiler turns
// the conversion into vcvtph2ps), or uint8 codes (inference only; the caller applies the level's affine map to the
// sum, which is exact because the 8 weights sum to 1).
template <int F, typename T>
inline void accumulate(float* __restrict out, const T* __restrict tab, const int64_t* row, const float* w, int f_dyn) {
#ifdef NBVH_AVX2
    // Explicit FMAs in registers: the plain loop below compiles to a store and reload of `out` per corner (2.4x
    // slower on the bunny's F = 16 lookups).
    if constexpr (F > 0 && F % 8 == 0) {
        __m256 acc[F / 8];
        for (int j = 0; j < F / 8; ++j) acc[j] = _mm256_setzero_ps();
        for (int c = 0; c < 8; ++c) {
            const T* src = tab + row[c] * F;
            const __m256 wc = _mm256_set1_ps(w[c]);
            for (int j = 0; j < F / 8; ++j) {
                __m256 v;
                if constexpr (std::is_same<T, float>::value)
                    v = _mm256_loadu_ps(src + 8 * j);
                else if constexpr (std::is_same<T, uint8_t>::value)
                    v = _mm256_cvtepi32_ps(_mm256_cvtepu8_epi32(
                        _mm_loadl_epi64(reinterpret_cast<const __m128i*>(src + 8 * j))));
                else
                    v = _mm256_cvtph_ps(_mm_loadu_si128(reinterpret_cast<const __m128i*>(src + 8 * j)));
                acc[j] = _mm256_fmadd_ps(wc, v, acc[j]);
            }
        }
        for (int j = 0; j < F / 8; ++j) _mm256_storeu_ps(out + 8 * j, acc[j]);
        return;
    }
#endif
    const int nf = F > 0 ? F : f_dyn;
    for (int f = 0; f < nf; ++f) out[f] = 0.f;
    for (int c = 0; c < 8; ++c) {
        const T* __restrict src = tab + row[c] * nf;
        const float wc = w[c];
#pragma omp simd
        for (int f = 0; f < nf; ++f) out[f] += wc * (float)src[f];
    }
}

// The L * F features of one point p (3,) into out: every level's 8-corner weighted row sum.
template <int F, typename T>
inline void encode_point(const Grid& g, const float* p, const T* table, float* out) {
    const int nf = F > 0 ? F : g.features;
    int64_t row[8];
    float w[8];
    for (int l = 0; l < g.levels; ++l) {
        corners_any(g, l, p, row, w, fits32(g, l));
        accumulate<F>(out + l * nf, table + g.row_start[l] * nf, row, w, nf);
        if constexpr (std::is_same<T, uint8_t>::value) {
            const float* off = g.qoffset + l * nf;
            const float* sc = g.qscale + l * nf;
            float* o = out + l * nf;
#pragma omp simd
            for (int f = 0; f < nf; ++f) o[f] = off[f] + sc[f] * o[f];
        }
    }
}

template <int F, typename T = float>
void encode_forward_t(const Grid& g, const float* points, int64_t n, const T* table, float* out, int threads) {
    const int width = g.levels * (F > 0 ? F : g.features);
#pragma omp parallel for schedule(static) num_threads(threads)
    for (int64_t i = 0; i < n; ++i) encode_point<F>(g, points + 3 * i, table, out + i * width);
}

template <int F>
void encode_backward_t(const Grid& g, const float* points, int64_t n, const float* grad_out, float* grad_table,
                       int threads) {
    const int L = g.levels;
    const int nf = F > 0 ? F : g.features;
    // One level per thread at a time: no two threads write the same row, and the sum order is fixed.
#pragma omp parallel num_threads(threads)
    {
    const FlushDenormals ftz_guard;
#pragma omp for schedule(dynamic, 1)
    for (int l = 0; l < L; ++l) {
        float* gt = grad_table + g.row_start[l] * nf;
        int64_t row[8];
        float w[8];
        for (int64_t i = 0; i < n; ++i) {
            corners_any(g, l, points + 3 * i, row, w, fits32(g, l));
            const float* __restrict go = grad_out + (i * L + l) * nf;
#ifdef NBVH_AVX2
            if constexpr (F > 0 && F % 8 == 0) {
                __m256 gv[F / 8];
                for (int j = 0; j < F / 8; ++j) gv[j] = _mm256_loadu_ps(go + 8 * j);
                for (int c = 0; c < 8; ++c) {
                    float* dst = gt + row[c] * F;
                    const __m256 wc = _mm256_set1_ps(w[c]);
                    for (int j = 0; j < F / 8; ++j)
                        _mm256_storeu_ps(dst + 8 * j, _mm256_fmadd_ps(wc, gv[j], _mm256_loadu_ps(dst + 8 * j)));
                }
                continue;
            }
#endif
            for (int c = 0; c < 8; ++c) {
                float* __restrict dst = gt + row[c] * nf;
                const float wc = w[c];
#pragma omp simd
                for (int f = 0; f < nf; ++f) dst[f] += wc * go[f];
            }
        }
    }
    }
}

// Calls fn(table) with the table pointer typed by table_kind: 0 float32, 1 float16, 2 uint8 codes.
template <typename Fn>
void by_table(int table_kind, const void* table, Fn&& fn) {
    if (table_kind == 2) fn(static_cast<const uint8_t*>(table));
    else if (table_kind == 1) fn(static_cast<const _Float16*>(table));
    else fn(static_cast<const float*>(table));
}

// Calls fn(std::integral_constant<int, F>) with F = features for the common sizes (unrolled inner loops) and
// F = 0 (runtime size) otherwise.
template <typename Fn>
void by_features(int features, Fn&& fn) {
    switch (features) {
        case 2: fn(std::integral_constant<int, 2>{}); break;
        case 4: fn(std::integral_constant<int, 4>{}); break;
        case 8: fn(std::integral_constant<int, 8>{}); break;
        case 16: fn(std::integral_constant<int, 16>{}); break;
        case 32: fn(std::integral_constant<int, 32>{}); break;
        default: fn(std::integral_constant<int, 0>{});
    }
}

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


// ---- Fused MLP models: inference (mlp_segments_t) and one training step (mlp_train_t), per tile of TILE
// segments whose points, features and activations stay in the cache. The reference builds (B, k*L*F) features in
// memory (hundreds of MB per wave at 1000^2) and runs torch's Linear layers over them.

constexpr int TILE = 48;  // segments per tile (a multiple of the micro-kernel's 6 rows)

// Columns a GEMM computes for an output width d: d rounded up to the micro-kernel's 16 (a narrow layer, the 5
// outputs, then runs in vector registers on zero-padded weights instead of the scalar loop; the extra columns are
// never read).
inline int lanes(int d) { return (d + 15) / 16 * 16; }
// Row stride of a width-d buffer: room for lanes(d) columns, and multiples of 16 floats get 16 more, so that rows
// are not 2 KB (or 256 B) apart; power-of-two strides map a column's rows onto a few L1 sets and evict each other.
inline int64_t padded(int d) { return d % 16 == 0 ? d + 16 : lanes(d); }

// C (M, N) (+)= A (M, K) B (K, N); A(r, q) = A[r * a_row + q * a_k] (so A may be a transposed view); B row-major.
#ifdef NBVH_AVX2
// MR x 16 register block. Named accumulators: with an array, GCC stored every accumulator to the stack after each
// FMA (half the speed); C is added at the end when accumulating.
// 16 consecutive B values of row q as two float vectors: float rows load directly, float16 rows (inference with
// the stored half-precision weights) convert with F16C on the way into the registers.
inline void load_b16(const float* b, __m256& lo, __m256& hi) { lo = _mm256_loadu_ps(b); hi = _mm256_loadu_ps(b + 8); }
inline void load_b16(const _Float16* b, __m256& lo, __m256& hi) {
    lo = _mm256_cvtph_ps(_mm_loadu_si128(reinterpret_cast<const __m128i*>(b)));
    hi = _mm256_cvtph_ps(_mm_loadu_si128(reinterpret_cast<const __m128i*>(b + 8)));
}

template <int MR, typename TB>
inline void micro_16(const float* A, int64_t a_row, int64_t a_k, const TB* B, int64_t ldb, int k_in, float* C,
                     int64_t ldc, bool acc) {
    static_assert(MR >= 1 && MR <= 6, "1 to 6 rows");
    __m256 c00 = _mm256_setzero_ps(), c01 = c00, c10 = c00, c11 = c00, c20 = c00, c21 = c00, c30 = c00, c31 = c00,
           c40 = c00, c41 = c00, c50 = c00, c51 = c00;
    const float* a0 = A;
    for (int q = 0; q < k_in; ++q, a0 += a_k) {
        __m256 b0, b1;
        load_b16(B + q * ldb, b0, b1);
        __m256 a = _mm256_broadcast_ss(a0);
        c00 = _mm256_fmadd_ps(a, b0, c00); c01 = _mm256_fmadd_ps(a, b1, c01);
        if constexpr (MR > 1) { a = _mm256_broadcast_ss(a0 + a_row); c10 = _mm256_fmadd_ps(a, b0, c10); c11 = _mm256_fmadd_ps(a, b1, c11); }
        if constexpr (MR > 2) { a = _mm256_broadcast_ss(a0 + 2 * a_row); c20 = _mm256_fmadd_ps(a, b0, c20); c21 = _mm256_fmadd_ps(a, b1, c21); }
        if constexpr (MR > 3) { a = _mm256_broadcast_ss(a0 + 3 * a_row); c30 = _mm256_fmadd_ps(a, b0, c30); c31 = _mm256_fmadd_ps(a, b1, c31); }
        if constexpr (MR > 4) { a = _mm256_broadcast_ss(a0 + 4 * a_row); c40 = _mm256_fmadd_ps(a, b0, c40); c41 = _mm256_fmadd_ps(a, b1, c41); }
        if constexpr (MR > 5) { a = _mm256_broadcast_ss(a0 + 5 * a_row); c50 = _mm256_fmadd_ps(a, b0, c50); c51 = _mm256_fmadd_ps(a, b1, c51); }
    }
    auto put = [&](int r, __m256 lo, __m256 hi) {
        float* cr = C + r * ldc;
        if (acc) { lo = _mm256_add_ps(lo, _mm256_loadu_ps(cr)); hi = _mm256_add_ps(hi, _mm256_loadu_ps(cr + 8)); }
        _mm256_storeu_ps(cr, lo);
        _mm256_storeu_ps(cr + 8, hi);
    };
    put(0, c00, c01);
    if constexpr (MR > 1) put(1, c10, c11);
    if constexpr (MR > 2) put(2, c20, c21);
    if constexpr (MR > 3) put(3, c30, c31);
    if constexpr (MR > 4) put(4, c40, c41);
    if constexpr (MR > 5) put(5, c50, c51);
}
#endif

template <typename TB>
void gemm(int m, int n, int k_in, const float* A, int64_t a_row, int64_t a_k, const TB* B, int64_t ldb, float* C,
          int64_t ldc, bool acc) {
#ifdef NBVH_AVX2
    if (n % 16 == 0) {
        for (int j = 0; j < n; j += 16) {
            int r = 0;
            for (; r + 6 <= m; r += 6) micro_16<6, TB>(A + r * a_row, a_row, a_k, B + j, ldb, k_in, C + r * ldc + j, ldc, acc);
            const float* a = A + r * a_row;
            float* cc = C + r * ldc + j;
            switch (m - r) {
                case 1: micro_16<1, TB>(a, a_row, a_k, B + j, ldb, k_in, cc, ldc, acc); break;
                case 2: micro_16<2, TB>(a, a_row, a_k, B + j, ldb, k_in, cc, ldc, acc); break;
                case 3: micro_16<3, TB>(a, a_row, a_k, B + j, ldb, k_in, cc, ldc, acc); break;
                case 4: micro_16<4, TB>(a, a_row, a_k, B + j, ldb, k_in, cc, ldc, acc); break;
                case 5: micro_16<5, TB>(a, a_row, a_k, B + j, ldb, k_in, cc, ldc, acc); break;
                default: break;
            }
        }
        return;
    }
#endif
    for (int r = 0; r < m; ++r) {
        float* c = C + r * ldc;
        if (!acc)
            for (int j = 0; j < n; ++j) c[j] = 0.f;
        for (int q = 0; q < k_in; ++q) {
            const float av = A[r * a_row + q * a_k];
            const TB* b = B + q * ldb;
#pragma omp simd
            for (int j = 0; j < n; ++j) c[j] += av * (float)b[j];
        }
    }
}


// The network's Linear layers in the layouts the kernels read, padded rows: wt[j] (in, out) = weight^T for the
// forward pass, w[j] (out, in) = torch's layout for the backward pass. params: for each layer j, W_j^T
// (dims[j], dims[j+1]) row-major then bias_j (dims[j+1]); hidden layers use ReLU, the last none. TW: the weights'
// type as stored (float, or float16 for inference with network_bits 16: read by the GEMM as they are).
template <typename TW = float>
struct Layers {
    int n;
    const int32_t* dims;
    std::vector<std::vector<TW>> wt;
    // A layer whose width is not a multiple of 16 (the 5 outputs) runs the scalar GEMM, where converting float16
    // per element costs more than the layer: its few weights are widened to float32 once per call instead.
    std::vector<std::vector<float>> wt_wide, w, bias;

    Layers(int n_layers, const int32_t* dims_, const TW* params, bool backward) : n(n_layers), dims(dims_) {
        wt.resize(n); wt_wide.resize(n); w.resize(n); bias.resize(n);
        const TW* p = params;
        for (int j = 0; j < n; ++j) {
            const int in = dims[j], out = dims[j + 1];
            if (!std::is_same<TW, float>::value && out % 16 != 0) {
                wt_wide[j].assign((size_t)in * padded(out), 0.f);
                for (int i = 0; i < in; ++i)
                    for (int o = 0; o < out; ++o) wt_wide[j][i * padded(out) + o] = (float)p[(int64_t)i * out + o];
            } else {
                wt[j].assign((size_t)in * padded(out), TW(0));
                for (int i = 0; i < in; ++i)
                    std::memcpy(&wt[j][i * padded(out)], p + (int64_t)i * out, sizeof(TW) * out);
            }
            if (backward) {
                w[j].assign((size_t)out * padded(in), 0.f);
                for (int i = 0; i < in; ++i)
                    for (int o = 0; o < out; ++o) w[j][o * padded(in) + i] = (float)p[(int64_t)i * out + o];
            }
            bias[j].resize(out);
            for (int o = 0; o < out; ++o) bias[j][o] = (float)p[(int64_t)in * out + o];
            p += (int64_t)in * out + out;
        }
    }
    int widest() const {
        int wd = 0;
        for (int j = 0; j <= n; ++j) wd = dims[j] > wd ? dims[j] : wd;
        return wd;
    }
    // act[j]: input of layer j, (TILE, padded(dims[j])); act[n]: the raw outputs.
    std::vector<std::vector<float>> activations() const {
        std::vector<std::vector<float>> act(n + 1);
        for (int j = 0; j <= n; ++j) act[j].assign((size_t)TILE * padded(dims[j]), 0.f);
        return act;
    }
    // x0 (TILE rows of stride ld0) is the first layer's input when given (a KMLP pair: a window of the segment's
    // feature row), else act[0]; only the first `rows` rows are computed (a KMLP's live segments).
    void forward(std::vector<std::vector<float>>& act, const float* x0 = nullptr, int64_t ld0 = 0,
                 int rows = TILE) const {
        for (int j = 0; j < n; ++j) {
            const int in = dims[j], out = dims[j + 1];
            float* y = act[j + 1].data();
            const float* x = (j == 0 && x0) ? x0 : act[j].data();
            const int64_t ldx = (j == 0 && x0) ? ld0 : padded(in);
            if (!wt_wide[j].empty())
                gemm(rows, lanes(out), in, x, ldx, 1, wt_wide[j].data(), padded(out), y, padded(out), false);
            else
                gemm(rows, lanes(out), in, x, ldx, 1, wt[j].data(), padded(out), y, padded(out), false);
            const bool relu = j + 1 < n;
            const float* bj = bias[j].data();
            for (int r = 0; r < rows; ++r) {
                float* yr = y + r * padded(out);
                for (int o = 0; o < out; ++o) {
                    const float v = yr[o] + bj[o];
                    yr[o] = relu ? (v > 0.f ? v : 0.f) : v;
                }
            }
        }
    }
};

// Point i of segment seg: t_i = t_enter + frac_i (t_exit - t_enter) along its ray, as NeuralBVH.segment_points.
inline void segment_point(const float* rays_o, const float* rays_d, const int64_t* ray, const float* te,
                          const float* tx, int64_t seg, float frac_i, float* p) {
    const float* o = rays_o + 3 * ray[seg];
    const float* d = rays_d + 3 * ray[seg];
    const float t = te[seg] + frac_i * (tx[seg] - te[seg]);
    p[0] = o[0] + t * d[0]; p[1] = o[1] + t * d[1]; p[2] = o[2] + t * d[2];
}

// Features of the m segments from s0 (their k points, segment_point) into rows of x (stride ldx); points
// (B * k, 3) written when not null.
template <int F, typename T>
inline void encode_tile(const Grid& g, const float* rays_o, const float* rays_d, const int64_t* ray, const float* te,
                        const float* tx, int64_t s0, int m, int k, const float* frac, const T* table, float* x,
                        int64_t ldx, float* points) {
    const int width = g.levels * (F > 0 ? F : g.features);
    for (int s = 0; s < m; ++s) {
        const int64_t seg = s0 + s;
        for (int i = 0; i < k; ++i) {
            float p[3];
            segment_point(rays_o, rays_d, ray, te, tx, seg, frac[i], p);
            if (points) std::memcpy(points + (seg * k + i) * 3, p, sizeof p);
            encode_point<F>(g, p, table, x + s * ldx + i * width);
        }
    }
}

template <int F, typename T, typename TW>
void mlp_segments_t(const Grid& g, const float* rays_o, const float* rays_d, const int64_t* ray, const float* te,
                    const float* tx, int64_t b, int k, const float* frac, const T* table, int n_layers,
                    const int32_t* dims, const TW* params, float* out, int threads) {
    const Layers<TW> net(n_layers, dims, params, false);
    const int n_out = dims[n_layers];
    const int64_t tiles = (b + TILE - 1) / TILE;
#pragma omp parallel num_threads(threads)
    {
        const FlushDenormals ftz_guard;
        // Zeroed once: the rows past the last segment of a short tile are computed but never read.
        auto act = net.activations();
#pragma omp for schedule(dynamic, 4)
        for (int64_t tile = 0; tile < tiles; ++tile) {
            const int64_t s0 = tile * TILE;
            const int m = (int)((b - s0) < TILE ? (b - s0) : TILE);
            encode_tile<F>(g, rays_o, rays_d, ray, te, tx, s0, m, k, frac, table, act[0].data(), padded(dims[0]),
                           (float*)nullptr);
            net.forward(act);
            for (int r = 0; r < m; ++r)
                std::memcpy(out + (s0 + r) * n_out, act[n_layers].data() + r * padded(n_out), sizeof(float) * n_out);
        }
    }
}

struct LossSums {
    double bce = 0, depth = 0, normal = 0, unit = 0;
};

// The masked terms of one hit row o (5,) = (hit logit, depth logit, normal xyz): |sigmoid(o[1]) - target_t|,
// |normalize(o[2:5]) - target_n|_1 (unoriented: to the nearer of +-target_n) and the unit pull (|o[2:5]| - 1)^2,
// added to the sums; their gradients (weights w_t, w_n, w_unit, over the hit count) into g[1..4]. Shared by the MLP
// loss and the KMLP loss (its true sub-segment's row).
inline void depth_normal_rows(const float* o, float target_t, const float* target_n, float w_t, float w_n, int unoriented,
                              float w_unit, float inv_hits, float* g, double& depth_sum, double& normal_sum,
                              double& unit_sum) {
    const float s = 1.f / (1.f + std::exp(-o[1]));
    const float dt = s - target_t;
    depth_sum += std::fabs(dt);
    g[1] = w_t * inv_hits * (float)((dt > 0.f) - (dt < 0.f)) * s * (1.f - s);
    const float vx = o[2], vy = o[3], vz = o[4];
    const float norm = std::sqrt(vx * vx + vy * vy + vz * vz);
    const float den = norm > 1e-12f ? norm : 1e-12f;
    const float n[3] = {vx / den, vy / den, vz / den};
    // Unoriented: the L1 to the nearer of +target and -target (every consumer faces the normal toward the ray, so
    // only its line matters; the two sides of a thin wall then need no ray direction to tell apart).
    float sign = 1.f;
    if (unoriented) {
        float plus = 0.f, minus = 0.f;
        for (int a = 0; a < 3; ++a) { plus += std::fabs(n[a] - target_n[a]); minus += std::fabs(n[a] + target_n[a]); }
        sign = minus < plus ? -1.f : 1.f;
    }
    float gn[3];
    for (int a = 0; a < 3; ++a) {
        const float d = n[a] - sign * target_n[a];
        normal_sum += std::fabs(d);
        gn[a] = w_n * inv_hits * (float)((d > 0.f) - (d < 0.f));
    }
    if (norm > 1e-12f) {  // d (v / |v|) = (g - n (n . g)) / |v|
        const float dot = gn[0] * n[0] + gn[1] * n[1] + gn[2] * n[2];
        for (int a = 0; a < 3; ++a) g[2 + a] = (gn[a] - n[a] * dot) / norm;
    } else {  // the clamp: v / eps, constant denominator
        for (int a = 0; a < 3; ++a) g[2 + a] = gn[a] / 1e-12f;
    }
    const float du = norm - 1.f;  // d (|v| - 1)^2 = 2 (|v| - 1) v / |v| (0 at v = 0, as torch's norm backward)
    unit_sum += du * du;
    const float gu = norm > 1e-12f ? w_unit * inv_hits * 2.f * du / norm : 0.f;
    for (int a = 0; a < 3; ++a) g[2 + a] += gu * o[2 + a];
}

// Where layer j's gradients start in a thread's buffer: W^T (in, padded(out)) then the bias (out), layer after layer.
inline std::vector<int64_t> grad_offsets(const int32_t* dims, int n_layers) {
    std::vector<int64_t> g_off(n_layers + 1, 0);
    for (int j = 0; j < n_layers; ++j) g_off[j + 1] = g_off[j] + (int64_t)dims[j] * padded(dims[j + 1]) + dims[j + 1];
    return g_off;
}

// The threads' weight gradients (each W^T (in, padded(out)) then the bias, at g_off[j]) summed in thread order
// (deterministic) into the packed, unpadded layout of params.
inline void sum_thread_grads(const std::vector<std::vector<float>>& grads, const std::vector<int64_t>& g_off,
                             const int32_t* dims, int n_layers, float* grad_params) {
    int64_t q = 0;
    for (int j = 0; j < n_layers; ++j) {
        const int n_in = dims[j], n_out = dims[j + 1];
        for (int i = 0; i <= n_in; ++i) {  // rows of W^T, then the bias as row n_in
            for (int o = 0; o < n_out; ++o) {
                float v = 0.f;
                for (const auto& gt : grads)
                    if (!gt.empty()) v += gt[g_off[j] + (int64_t)i * padded(n_out) + o];
                grad_params[q++] = v;
            }
        }
    }
}

// Loss of networks.MLP (BCE on the hit logit; masked L1 of sigmoid depth and of the normalised normal, divided by
// the batch's hit count) for rows [0, m) of raw (TILE, 5 of ld); writes d loss / d raw into d_raw (TILE, ld),
// zero rows from m on and zero columns from 5 on. inv_b = 1 / batch size, inv_hits = 1 / max(hit count, 1).
inline void mlp_loss_rows(const float* raw, int64_t ld, int m, const uint8_t* hit, const float* local_t,
                          const float* normal, float inv_b, float inv_hits, float w_t, float w_n, int unoriented,
                          float w_unit, float* d_raw, LossSums& sums) {
    for (int r = 0; r < TILE; ++r) {
        float* g = d_raw + r * ld;
        for (int c = 0; c < ld; ++c) g[c] = 0.f;
        if (r >= m) continue;
        const float* o = raw + r * ld;
        const float x = o[0], y = hit[r] ? 1.f : 0.f;
        sums.bce += std::fmax(x, 0.f) - x * y + std::log1p(std::exp(-std::fabs(x)));
        const float p = 1.f / (1.f + std::exp(-x));
        g[0] = (p - y) * inv_b;
        if (!hit[r]) continue;
        depth_normal_rows(o, local_t[r], normal + 3 * r, w_t, w_n, unoriented, w_unit, inv_hits, g, sums.depth, sums.normal,
                          sums.unit);
    }
}

template <int F>
void mlp_train_t(const Grid& g, const float* rays_o, const float* rays_d, const int64_t* ray, const float* te,
                 const float* tx, int64_t b, int k, const float* frac, const float* table, int n_layers,
                 const int32_t* dims, const float* params, const uint8_t* hit, const float* local_t,
                 const float* normal, float inv_hits, float w_t, float w_n, int unoriented, float w_unit, double* loss_out, float* grad_params,
                 float* points, float* dx, float* out_raw, int threads) {
    const Layers<float> net(n_layers, dims, params, true);
    const std::vector<int64_t> g_off = grad_offsets(dims, n_layers);
    const int64_t tiles = (b + TILE - 1) / TILE;
    const float inv_b = 1.f / (float)b;
    const int n_threads = threads < 1 ? 1 : threads;
    std::vector<std::vector<float>> grads(n_threads);
    std::vector<LossSums> sums(n_threads);
#pragma omp parallel num_threads(n_threads)
    {
        const FlushDenormals ftz_guard;
        const int tid = omp_get_thread_num();
        std::vector<float>& gp = grads[tid];
        gp.assign(g_off[n_layers], 0.f);
        auto act = net.activations();
        const int64_t ld_max = padded(net.widest());
        std::vector<float> d_a((size_t)TILE * ld_max, 0.f), d_b((size_t)TILE * ld_max, 0.f);
        // Static schedule: each thread's tiles, and so every float sum, are the same from run to run.
#pragma omp for schedule(static)
        for (int64_t tile = 0; tile < tiles; ++tile) {
            const int64_t s0 = tile * TILE;
            const int m = (int)((b - s0) < TILE ? (b - s0) : TILE);
            encode_tile<F>(g, rays_o, rays_d, ray, te, tx, s0, m, k, frac, table, act[0].data(), padded(dims[0]),
                           points);
            net.forward(act);
            if (out_raw)  // the raw outputs, for per-sample errors (loss-proportional leaf sampling)
                for (int r = 0; r < m; ++r)
                    std::memcpy(out_raw + (s0 + r) * dims[n_layers], act[n_layers].data() + r * padded(dims[n_layers]),
                                sizeof(float) * dims[n_layers]);
            float* d_cur = d_a.data();
            float* d_prev = d_b.data();
            mlp_loss_rows(act[n_layers].data(), padded(dims[n_layers]), m, hit + s0, local_t + s0, normal + 3 * s0, inv_b, inv_hits, w_t, w_n, unoriented,
                          w_unit, d_cur, sums[tid]);  // (TILE, ld), zero rows from m on, zero columns from 5: they add nothing below
            for (int j = n_layers - 1; j >= 0; --j) {
                const int n_in = dims[j], n_out = dims[j + 1];
                const int64_t ld_in = padded(n_in), ld_out = padded(n_out);
                float* gw = gp.data() + g_off[j];
                // dW^T (in, out) += act[j]^T d_cur; db += column sums of d_cur
                gemm(n_in, lanes(n_out), TILE, act[j].data(), 1, ld_in, d_cur, ld_out, gw, ld_out, true);
                float* gb = gw + (int64_t)n_in * ld_out;
                for (int r = 0; r < m; ++r)
                    for (int c = 0; c < n_out; ++c) gb[c] += d_cur[r * ld_out + c];
                // d input = d_cur W (torch layout (out, in)); through the previous layer's ReLU (act[j] > 0)
                gemm(TILE, n_in, n_out, d_cur, ld_out, 1, net.w[j].data(), ld_in, d_prev, ld_in, false);
                if (j > 0) {
                    const float* a = act[j].data();
                    for (int64_t q = 0; q < (int64_t)TILE * ld_in; ++q)
                        if (!(a[q] > 0.f)) d_prev[q] = 0.f;
                } else {
                    for (int r = 0; r < m; ++r)
                        std::memcpy(dx + (s0 + r) * n_in, d_prev + r * ld_in, sizeof(float) * n_in);
                }
                std::swap(d_cur, d_prev);
            }
        }
    }
    sum_thread_grads(grads, g_off, dims, n_layers, grad_params);
    LossSums total;
    for (const auto& ls : sums) {
        total.bce += ls.bce; total.depth += ls.depth; total.normal += ls.normal; total.unit += ls.unit;
    }
    loss_out[0] = total.bce * inv_b;
    loss_out[1] = total.depth * inv_hits;
    loss_out[2] = total.normal * inv_hits;
    loss_out[3] = total.unit * inv_hits;
}


// ---- Fused KMLP (networks.KMLP): one shared pair network over the k - 1 adjacent point pairs of a segment. Pair j's
// input is the window [j * D, (j + 2) * D) of the segment's k * D feature row (D = L * F), so a pair is a first-layer
// GEMM on an offset pointer into the tile's features; the deeper layers are the MLP path's.

inline float softplus(float x) { return std::fmax(x, 0.f) + std::log1p(std::exp(-std::fabs(x))); }

// The first-hit combination of networks.KMLP.decode for one segment, pair by pair: the running sum of log(1 - p_i)
// over the pairs seen and the most likely first-hit pair so far (log q_j = log p_j + sum_{i<j} log(1 - p_i), the
// first of equal ones) with its depth and normal outputs.
struct FirstHit {
    float log_none = 0.f, best = -INFINITY, raw[4] = {0.f, 0.f, 0.f, 0.f};
    int pair = 0;
    void add(int j, const float* r) {
        const float lq = -softplus(-r[0]) + log_none;
        if (lq > best) { best = lq; pair = j; std::memcpy(raw, r + 1, sizeof raw); }
        log_none -= softplus(r[0]);
    }
    // Later pairs cannot change the answer: P >= 1 - exp(log_none) > 1/2 already (a hit), and every later log q_j
    // <= log_none < best (the chosen pair stays the argmax).
    bool decided() const { return log_none < -0.69314718f && log_none < best; }
    // (hit probability, local t in [0, 1], unit normal); for a segment decided early the probability is its lower
    // bound from the pairs seen (> 1/2: the same hit decision).
    void write(int pairs, float* o) const {
        o[0] = -std::expm1(log_none);
        o[1] = (pair + 1.f / (1.f + std::exp(-raw[0]))) / pairs;
        const float n = std::fmax(std::sqrt(raw[1] * raw[1] + raw[2] * raw[2] + raw[3] * raw[3]), 1e-12f);
        o[2] = raw[1] / n; o[3] = raw[2] / n; o[4] = raw[3] / n;
    }
};

// decode 0: out (B, k - 1, n_out) raw pair outputs. decode 1 (n_out = 5): out (B, 5) = FirstHit::write, and a
// segment's remaining pairs are skipped once it is decided (its feature row moves behind the tile's live rows, so
// the next pair's GEMMs run on the live rows only).
template <int F, typename T, typename TW>
void kmlp_segments_t(const Grid& g, const float* rays_o, const float* rays_d, const int64_t* ray, const float* te,
                     const float* tx, int64_t b, int k, const float* frac, const T* table, int n_layers,
                     const int32_t* dims, const TW* params, int decode, float* out, int threads) {
    const Layers<TW> net(n_layers, dims, params, false);
    const int n_out = dims[n_layers];
    const int width = g.levels * (F > 0 ? F : g.features);
    const int64_t ldx = padded(k * width);
    const int64_t tiles = (b + TILE - 1) / TILE;
    const int pairs = k - 1;
#pragma omp parallel num_threads(threads)
    {
        const FlushDenormals ftz_guard;
        auto act = net.activations();
        std::vector<float> x((size_t)TILE * ldx, 0.f);
        std::vector<FirstHit> first(TILE);
        std::vector<int> row_of(TILE);  // tile position -> segment row (positions [0, live) still evaluated)
#pragma omp for schedule(dynamic, 4)
        for (int64_t tile = 0; tile < tiles; ++tile) {
            const int64_t s0 = tile * TILE;
            const int m = (int)((b - s0) < TILE ? (b - s0) : TILE);
            encode_tile<F>(g, rays_o, rays_d, ray, te, tx, s0, m, k, frac, table, x.data(), ldx, (float*)nullptr);
            int live = m;
            for (int r = 0; r < m; ++r) { first[r] = FirstHit(); row_of[r] = r; }
            for (int j = 0; j < pairs && live > 0; ++j) {
                net.forward(act, x.data() + j * width, ldx, decode ? live : TILE);
                const float* y = act[n_layers].data();
                if (!decode) {
                    for (int r = 0; r < m; ++r)
                        std::memcpy(out + ((s0 + r) * pairs + j) * n_out, y + r * padded(n_out), sizeof(float) * n_out);
                    continue;
                }
                for (int p = live - 1; p >= 0; --p) {  // downwards: a row swapped into p is one already seen
                    FirstHit& fh = first[row_of[p]];
                    fh.add(j, y + p * padded(n_out));
                    if (fh.decided() && p != --live) {
                        std::swap_ranges(x.begin() + p * ldx, x.begin() + (p + 1) * ldx, x.begin() + live * ldx);
                        std::swap(row_of[p], row_of[live]);
                    }
                }
            }
            if (decode)
                for (int r = 0; r < m; ++r) first[r].write(pairs, out + (s0 + r) * 5);
        }
    }
}

struct KLossSums {
    double bce = 0, ce = 0, depth = 0, normal = 0, unit = 0;
};

// Loss of networks.KMLP for rows [0, m) of raw (TILE, P, 5), P = k - 1 pairs (see its docstring: BCE of the
// leaf's hit probability in log space, the cross-entropy of the true sub-segment, masked L1s of the depth inside it
// and of its normal); d loss / d raw into d_raw (TILE, P, 5), zero rows from m on.
inline void kmlp_loss_rows(const float* raw, int P, int m, const uint8_t* hit, const float* local_t,
                           const float* normal, float inv_b, float inv_hits, float w_t, float w_n, int unoriented, float w_unit, float* d_raw,
                           KLossSums& sums) {
    std::vector<float> log_miss(P), log_q(P), prob(P);
    for (int r = 0; r < TILE; ++r) {
        float* g = d_raw + (int64_t)r * P * 5;
        for (int c = 0; c < P * 5; ++c) g[c] = 0.f;
        if (r >= m) continue;
        const float* o = raw + (int64_t)r * P * 5;
        float cum = 0.f;
        for (int i = 0; i < P; ++i) {
            const float x = o[i * 5];
            log_miss[i] = -softplus(x);
            prob[i] = 1.f / (1.f + std::exp(-x));
            cum += log_miss[i];
            log_q[i] = -softplus(-x) + (cum - log_miss[i]);  // log p_i + sum_{l<i} log(1 - p_l)
        }
        const float log_none = cum;
        const float one_minus = -std::expm1(log_none);
        const bool clamped = !(one_minus > 1e-12f);
        const float log_hit = std::log(clamped ? 1e-12f : one_minus);
        const float d_hit_d_none = clamped ? 0.f : -std::exp(log_none) / one_minus;  // d log P / d log(1 - P)
        const bool is_hit = hit[r] != 0;
        const float y = is_hit ? 1.f : 0.f;
        sums.bce += -(y * log_hit + (1.f - y) * log_none);
        float g_none = -(y * d_hit_d_none + (1.f - y)) * inv_b;  // d loss / d log_none
        int js = -1;
        float g_ce = 0.f;
        if (is_hit) {
            const float pos = local_t[r] * (float)P;
            js = (int)std::floor(pos);
            js = js < 0 ? 0 : (js > P - 1 ? P - 1 : js);
            const float ce = -(log_q[js] - log_hit);
            sums.ce += std::fabs(ce);
            g_ce = (float)((ce > 0.f) - (ce < 0.f)) * inv_hits;  // d |ce| / d ce
            g_none += g_ce * d_hit_d_none;
            float sub_t = pos - (float)js;
            sub_t = sub_t < 0.f ? 0.f : (sub_t > 1.f ? 1.f : sub_t);
            depth_normal_rows(o + js * 5, sub_t, normal + 3 * r, w_t, w_n, unoriented, w_unit, inv_hits, g + js * 5,
                              sums.depth, sums.normal, sums.unit);
        }
        // d log_none / d x_i = -p_i; d (-log q_js) / d x_i = -(1 - p_i) at i = js, +p_i before it, 0 after.
        for (int i = 0; i < P; ++i) {
            float gi = g_none * -prob[i];
            if (js >= 0 && i <= js) gi += g_ce * (i == js ? -(1.f - prob[i]) : prob[i]);
            g[i * 5] = gi;
        }
    }
}

template <int F>
void kmlp_train_t(const Grid& g, const float* rays_o, const float* rays_d, const int64_t* ray, const float* te,
                  const float* tx, int64_t b, int k, const float* frac, const float* table, int n_layers,
                  const int32_t* dims, const float* params, const uint8_t* hit, const float* local_t,
                  const float* normal, float inv_hits, float w_t, float w_n, int unoriented, float w_unit, double* loss_out, float* grad_params,
                  float* points, float* dx, float* out_raw, int threads) {
    const Layers<float> net(n_layers, dims, params, true);
    const int P = k - 1;
    const int width = g.levels * (F > 0 ? F : g.features);
    const int64_t ldx = padded(k * width);
    const std::vector<int64_t> g_off = grad_offsets(dims, n_layers);
    const int64_t tiles = (b + TILE - 1) / TILE;
    const float inv_b = 1.f / (float)b;
    const int n_threads = threads < 1 ? 1 : threads;
    const int n_out = dims[n_layers];
    std::vector<std::vector<float>> grads(n_threads);
    std::vector<KLossSums> sums(n_threads);
#pragma omp parallel num_threads(n_threads)
    {
        const FlushDenormals ftz_guard;
        const int tid = omp_get_thread_num();
        std::vector<float>& gp = grads[tid];
        gp.assign(g_off[n_layers], 0.f);
        std::vector<std::vector<std::vector<float>>> acts(P);
        for (int j = 0; j < P; ++j) acts[j] = net.activations();
        std::vector<float> x((size_t)TILE * ldx, 0.f), d_x((size_t)TILE * ldx, 0.f);
        std::vector<float> raw((size_t)TILE * P * 5, 0.f), d_raw((size_t)TILE * P * 5, 0.f);
        const int64_t ld_max = padded(net.widest());
        std::vector<float> d_a((size_t)TILE * ld_max, 0.f), d_b((size_t)TILE * ld_max, 0.f);
#pragma omp for schedule(static)
        for (int64_t tile = 0; tile < tiles; ++tile) {
            const int64_t s0 = tile * TILE;
            const int m = (int)((b - s0) < TILE ? (b - s0) : TILE);
            encode_tile<F>(g, rays_o, rays_d, ray, te, tx, s0, m, k, frac, table, x.data(), ldx, points);
            for (int j = 0; j < P; ++j) {
                net.forward(acts[j], x.data() + j * width, ldx);
                for (int r = 0; r < TILE; ++r)
                    std::memcpy(&raw[((int64_t)r * P + j) * 5], acts[j][n_layers].data() + r * padded(n_out),
                                sizeof(float) * 5);
            }
            if (out_raw)
                std::memcpy(out_raw + s0 * P * 5, raw.data(), sizeof(float) * (size_t)m * P * 5);
            kmlp_loss_rows(raw.data(), P, m, hit + s0, local_t + s0, normal + 3 * s0, inv_b, inv_hits, w_t, w_n, unoriented,
                           w_unit, d_raw.data(), sums[tid]);
            std::fill(d_x.begin(), d_x.end(), 0.f);
            for (int p = 0; p < P; ++p) {
                auto& act = acts[p];
                float* d_cur = d_a.data();
                float* d_prev = d_b.data();
                const int64_t ld5 = padded(n_out);
                for (int r = 0; r < TILE; ++r)  // zero padding: the dW GEMM runs lanes(n_out) columns
                    for (int c = 0; c < ld5; ++c) d_cur[r * ld5 + c] = c < n_out ? d_raw[((int64_t)r * P + p) * 5 + c] : 0.f;
                for (int j = n_layers - 1; j >= 0; --j) {
                    const int n_in = dims[j], no = dims[j + 1];
                    const int64_t ld_in = padded(n_in), ld_out = padded(no);
                    float* gw = gp.data() + g_off[j];
                    if (j == 0)  // the pair's input window of the tile's features, seen transposed
                        gemm(n_in, lanes(no), TILE, x.data() + p * width, 1, ldx, d_cur, ld_out, gw, ld_out, true);
                    else
                        gemm(n_in, lanes(no), TILE, act[j].data(), 1, ld_in, d_cur, ld_out, gw, ld_out, true);
                    float* gb = gw + (int64_t)n_in * ld_out;
                    for (int r = 0; r < m; ++r)
                        for (int c = 0; c < no; ++c) gb[c] += d_cur[r * ld_out + c];
                    if (j > 0) {
                        gemm(TILE, n_in, no, d_cur, ld_out, 1, net.w[j].data(), ld_in, d_prev, ld_in, false);
                        const float* a = act[j].data();
                        for (int64_t q = 0; q < (int64_t)TILE * ld_in; ++q)
                            if (!(a[q] > 0.f)) d_prev[q] = 0.f;
                        std::swap(d_cur, d_prev);
                    } else {  // overlapping windows: the pair's input gradient adds into the segment's row
                        gemm(TILE, n_in, no, d_cur, ld_out, 1, net.w[0].data(), ld_in, d_x.data() + p * width, ldx,
                             true);
                    }
                }
            }
            for (int r = 0; r < m; ++r)
                std::memcpy(dx + (s0 + r) * (int64_t)k * width, d_x.data() + r * ldx, sizeof(float) * k * width);
        }
    }
    sum_thread_grads(grads, g_off, dims, n_layers, grad_params);
    KLossSums total;
    for (const auto& ls : sums) {
        total.bce += ls.bce; total.ce += ls.ce; total.depth += ls.depth; total.normal += ls.normal; total.unit += ls.unit;
    }
    loss_out[0] = total.bce * inv_b;
    loss_out[1] = total.ce * inv_hits;
    loss_out[2] = total.depth * inv_hits;
    loss_out[3] = total.normal * inv_hits;
    loss_out[4] = total.unit * inv_hits;
}


// ---- HashVQAD's soft row table (encodings/hashvqad.py, training): S[l, e] = sum_c softmax(logits[l, e] / tau)_c *
// table[l, cand[e mod T, c]] for the entries a vertex can reach (a dense coarse level's first R^3; held compact,
// level after level, as the logits are); its backward into the rows and the logits. Entries e = m T + a share
// the candidate rows of a (T a power of two), so work goes by (level, a): the t candidate rows are loaded once and
// stay in L1 for the M = H / T entries that use them, and the backward sums their row gradients locally before one
// add per row into a per-thread gradient table (summed in thread order: deterministic).
#ifdef NBVH_AVX2
// exp(x) in 8 lanes (Cephes' expf: x = n ln2 + r, a degree-6 polynomial for exp(r), 2^n from the exponent bits):
// relative error ~2e-7, 8x the scalar libm call the softmax spent most of its time in.
inline __m256 exp8(__m256 x) {
    x = _mm256_min_ps(_mm256_max_ps(x, _mm256_set1_ps(-87.3f)), _mm256_set1_ps(88.3f));
    const __m256 n = _mm256_round_ps(_mm256_mul_ps(x, _mm256_set1_ps(1.44269504088896341f)),
                                     _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
    __m256 r = _mm256_sub_ps(x, _mm256_mul_ps(n, _mm256_set1_ps(0.693359375f)));
    r = _mm256_sub_ps(r, _mm256_mul_ps(n, _mm256_set1_ps(-2.12194440e-4f)));
    __m256 y = _mm256_set1_ps(1.9875691500E-4f);
    y = _mm256_fmadd_ps(y, r, _mm256_set1_ps(1.3981999507E-3f));
    y = _mm256_fmadd_ps(y, r, _mm256_set1_ps(8.3334519073E-3f));
    y = _mm256_fmadd_ps(y, r, _mm256_set1_ps(4.1665795894E-2f));
    y = _mm256_fmadd_ps(y, r, _mm256_set1_ps(1.6666665459E-1f));
    y = _mm256_fmadd_ps(y, r, _mm256_set1_ps(5.0000001201E-1f));
    y = _mm256_fmadd_ps(y, _mm256_mul_ps(r, r), _mm256_add_ps(r, _mm256_set1_ps(1.f)));
    const __m256i e = _mm256_slli_epi32(_mm256_add_epi32(_mm256_cvtps_epi32(n), _mm256_set1_epi32(127)), 23);
    return _mm256_mul_ps(y, _mm256_castsi256_ps(e));
}

inline float hmax8(__m256 v) {
    __m128 m = _mm_max_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps(v, 1));
    m = _mm_max_ps(m, _mm_movehl_ps(m, m));
    m = _mm_max_ss(m, _mm_shuffle_ps(m, m, 1));
    return _mm_cvtss_f32(m);
}

inline float hsum8(__m256 v) {
    __m128 m = _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps(v, 1));
    m = _mm_add_ps(m, _mm_movehl_ps(m, m));
    m = _mm_add_ss(m, _mm_shuffle_ps(m, m, 1));
    return _mm_cvtss_f32(m);
}
#endif

// softmax(lg * inv_tau) of t values into p (t a multiple of 8 on the vector path).
inline void softmax_row(const float* lg, int t, float inv_tau, float* p) {
#ifdef NBVH_AVX2
    if (t % 8 == 0 && t <= 64) {
        const __m256 s = _mm256_set1_ps(inv_tau);
        __m256 v[8];
        __m256 mx = _mm256_set1_ps(-INFINITY);
        for (int j = 0; j < t / 8; ++j) { v[j] = _mm256_mul_ps(_mm256_loadu_ps(lg + 8 * j), s); mx = _mm256_max_ps(mx, v[j]); }
        const __m256 m = _mm256_set1_ps(hmax8(mx));
        __m256 sum = _mm256_setzero_ps();
        for (int j = 0; j < t / 8; ++j) { v[j] = exp8(_mm256_sub_ps(v[j], m)); sum = _mm256_add_ps(sum, v[j]); }
        const __m256 inv = _mm256_set1_ps(1.f / hsum8(sum));
        for (int j = 0; j < t / 8; ++j) _mm256_storeu_ps(p + 8 * j, _mm256_mul_ps(v[j], inv));
        return;
    }
#endif
    float mx = lg[0] * inv_tau;
    for (int c = 1; c < t; ++c) mx = std::fmax(mx, lg[c] * inv_tau);
    float sum = 0.f;
    for (int c = 0; c < t; ++c) { p[c] = std::exp(lg[c] * inv_tau - mx); sum += p[c]; }
    const float inv = 1.f / sum;
    for (int c = 0; c < t; ++c) p[c] *= inv;
}

// The reachable entries of all levels in one index space: entry q of [0, sum reach) is entry q - start[l] of level l
// (start: L + 1 prefix sums). Unreachable entries (a dense coarse level's beyond its R^3) are skipped.
struct ReachableEntries {
    std::vector<int64_t> start;
    ReachableEntries(const int64_t* reach, int L, int64_t H) : start(L + 1, 0) {
        for (int l = 0; l < L; ++l) start[l + 1] = start[l] + std::min<int64_t>(std::max<int64_t>(reach[l], 0), H);
    }
    int64_t total() const { return start.back(); }
    // (level, entry) of q; L is small (<= 16): a scan.
    void locate(int64_t q, int* l, int64_t* i) const {
        int lv = 0;
        while (q >= start[lv + 1]) ++lv;
        *l = lv;
        *i = q - start[lv];
    }
};

// needed (R,) uint8 or null: only the entries marked are computed (a step reads a quarter of them, entries_read);
// the others' soft rows are zero and their probabilities unwritten (the backward skips them: their gradient rows
// are zero).
template <int TF>
void vqad_soft_forward_t(const float* logits, const float* table, const int64_t* cand, const int64_t* reach, int L,
                         int64_t H, int64_t T, int t, int F_dyn, float inv_tau, const uint8_t* needed, float* probs,
                         float* soft, int threads) {
    const int F = TF > 0 ? TF : F_dyn;
    const ReachableEntries entries(reach, L, H);
#pragma omp parallel num_threads(threads)
    {
    const FlushDenormals ftz_guard;
    // Entries in memory order (streaming the logits, probabilities and rows written); a level's T candidate rows
    // (T F floats) stay in L2 while its entries pass.
#pragma omp for schedule(static)
    for (int64_t q = 0; q < entries.total(); ++q) {
        int l;
        int64_t i;
        if (needed && !needed[q]) {
            std::memset(soft + q * F, 0, sizeof(float) * F);
            continue;
        }
        entries.locate(q, &l, &i);
        const int64_t a = i % T;
        float* p = probs + q * t;
        softmax_row(logits + q * t, t, inv_tau, p);
        float acc[TF > 0 ? TF : 256];
        for (int f = 0; f < F; ++f) acc[f] = 0.f;
        const int64_t* ca = cand + a * t;
        const float* lvl = table + l * T * F;
        for (int c = 0; c < t; ++c) {
            const float pc = p[c];
            const float* row = lvl + ca[c] * F;
#pragma omp simd
            for (int f = 0; f < F; ++f) acc[f] += pc * row[f];
        }
        std::memcpy(soft + q * F, acc, sizeof(float) * F);
    }
    }
}

template <int TF>
void vqad_soft_backward_t(const float* probs, const float* table, const int64_t* cand, const int64_t* reach,
                          const float* grad_soft, int L, int64_t H, int64_t T, int t, int F_dyn, float inv_tau,
                          float* grad_table, float* grad_logits, int threads) {
    const int F = TF > 0 ? TF : F_dyn;
    const int n_threads = threads < 1 ? 1 : threads;
    const ReachableEntries entries(reach, L, H);
    std::vector<std::vector<float>> local(n_threads);
#pragma omp parallel num_threads(n_threads)
    {
        const FlushDenormals ftz_guard;
        std::vector<float>& gt = local[omp_get_thread_num()];
        gt.assign((size_t)L * T * F, 0.f);  // this thread's row gradients (L2-resident), summed in thread order
#pragma omp for schedule(static)
        for (int64_t q = 0; q < entries.total(); ++q) {
            const float* gs = grad_soft + q * F;
            float* gl = grad_logits + q * t;
            // An entry no vertex of the batch read has a zero gradient row: nothing to add to the rows, and zero
            // logit gradients (exactly what the sums below give). 76% of all entries at a step's batch (bunny, T=2^9).
            bool touched = false;
            for (int f = 0; f < F && !touched; ++f) touched = gs[f] != 0.f;
            if (!touched) {
                std::memset(gl, 0, sizeof(float) * t);
                continue;
            }
            int l;
            int64_t i;
            entries.locate(q, &l, &i);
            const int64_t a = i % T;
            const float* p = probs + q * t;
            const int64_t* ca = cand + a * t;
            const float* lvl = table + l * T * F;
            float* glvl = gt.data() + l * T * F;
            float g[256];
            float mean = 0.f;
            for (int c = 0; c < t; ++c) {
                const float* row = lvl + ca[c] * F;
                float* dr = glvl + ca[c] * F;
                const float pc = p[c];
                float dot = 0.f;
#pragma omp simd reduction(+ : dot)
                for (int f = 0; f < F; ++f) { dot += gs[f] * row[f]; dr[f] += pc * gs[f]; }
                g[c] = dot;
                mean += pc * dot;
            }
            for (int c = 0; c < t; ++c) gl[c] = p[c] * (g[c] - mean) * inv_tau;
        }
    }
    const int64_t n = (int64_t)L * T * F;
    for (int th = 0; th < n_threads; ++th) {
        if (local[th].empty()) continue;
        const float* src = local[th].data();
        for (int64_t q = 0; q < n; ++q) grad_table[q] += src[q];
    }
}

void vqad_soft_forward(const float* logits, const float* table, const int64_t* cand, const int64_t* reach, int L,
                       int64_t H, int64_t T, int t, int F, float inv_tau, const uint8_t* needed, float* probs,
                       float* soft, int threads) {
    if (F == 16) vqad_soft_forward_t<16>(logits, table, cand, reach, L, H, T, t, F, inv_tau, needed, probs, soft, threads);
    else if (F == 8) vqad_soft_forward_t<8>(logits, table, cand, reach, L, H, T, t, F, inv_tau, needed, probs, soft, threads);
    else vqad_soft_forward_t<0>(logits, table, cand, reach, L, H, T, t, F, inv_tau, needed, probs, soft, threads);
}

// The entries of a soft row table (g.rows == 0: the reachable entries, level after level) that the k points of b
// segments read: needed[row] = 1 for every corner of every level (the points and corners of encode_tile, bit for
// bit). Concurrent marks store the same byte (relaxed atomics).
void mark_entries(const Grid& g, const float* rays_o, const float* rays_d, const int64_t* ray, const float* te,
                  const float* tx, int64_t b, int k, const float* frac, uint8_t* needed, int threads) {
#pragma omp parallel for schedule(static) num_threads(threads)
    for (int64_t seg = 0; seg < b; ++seg) {
        int64_t row[8];
        float w[8];
        for (int i = 0; i < k; ++i) {
            float p[3];
            segment_point(rays_o, rays_d, ray, te, tx, seg, frac[i], p);
            for (int l = 0; l < g.levels; ++l) {
                corners_any(g, l, p, row, w, fits32(g, l));
                for (int c = 0; c < 8; ++c) __atomic_store_n(needed + g.row_start[l] + row[c], (uint8_t)1, __ATOMIC_RELAXED);
            }
        }
    }
}

void vqad_soft_backward(const float* probs, const float* table, const int64_t* cand, const int64_t* reach,
                        const float* grad_soft, int L, int64_t H, int64_t T, int t, int F, float inv_tau,
                        float* grad_table, float* grad_logits, int threads) {
    if (F == 16)
        vqad_soft_backward_t<16>(probs, table, cand, reach, grad_soft, L, H, T, t, F, inv_tau, grad_table, grad_logits,
                                 threads);
    else if (F == 8)
        vqad_soft_backward_t<8>(probs, table, cand, reach, grad_soft, L, H, T, t, F, inv_tau, grad_table, grad_logits,
                                threads);
    else
        vqad_soft_backward_t<0>(probs, table, cand, reach, grad_soft, L, H, T, t, F, inv_tau, grad_table, grad_logits,
                                threads);
}

}  // namespace

// The two node formats the stream stepper reads, behind one interface: node_box(node, carried) - a node's box (lo
// xyz, hi xyz: 6 floats); child_box(child, parent_box, scratch) - a child's box; left_of / leaf_of - its links
// (leaf_of < 0: none). carries_box: each stack entry keeps its node's box (the 8-bit format has no boxes to read).
struct RecordNodes {  // the 32-byte node records, read in place: lo, hi float32, then left, leaf int32
    const float* records;
    static constexpr bool carries_box = false;
    const float* node_box(int32_t node, const float*) const { return records + 8 * (int64_t)node; }
    const float* child_box(int32_t child, const float*, float*) const { return records + 8 * (int64_t)child; }
    int32_t left_of(int32_t node) const { return reinterpret_cast<const int32_t*>(records)[8 * (int64_t)node + 6]; }
    int32_t leaf_of(int32_t node) const { return reinterpret_cast<const int32_t*>(records)[8 * (int64_t)node + 7]; }
};

// The 8-bit node format (quantize.encode_nodes) decoded during traversal: child box = parent's decoded box + codes,
// per axis lo = plo + q * ((phi - plo) / 255) (code 255: phi exactly), the float32 operations of
// quantize._decode_child in the same order, so the boxes are bit-identical to the ones training used. A child with
// q_lo > q_hi on some axis is empty and decodes as (+inf, -inf), as quantize.decode_nodes writes it.
inline void decode_box(const float* parent, const uint8_t* q, float* box) {
    bool empty = false;
    for (int a = 0; a < 3; ++a) {
        const float plo = parent[a], phi = parent[3 + a];
        const float step = (phi - plo) / 255.0f;
        const uint8_t ql = q[a], qh = q[3 + a];
        box[a] = ql >= 255 ? phi : plo + (float)ql * step;
        box[3 + a] = qh >= 255 ? phi : plo + (float)qh * step;
        empty |= ql > qh;
    }
    if (empty)
        for (int a = 0; a < 3; ++a) { box[a] = INFINITY; box[3 + a] = -INFINITY; }
}

struct CodedNodes {  // codes (M, 6) uint8 relative to the parent's box, left/leaf (M,) uint16 (65535 = none)
    const uint8_t* codes;
    const uint16_t* left;
    const uint16_t* leaf;
    static constexpr bool carries_box = true;
    const float* node_box(int32_t, const float* carried) const { return carried; }
    const float* child_box(int32_t child, const float* parent, float* scratch) const {
        decode_box(parent, codes + 6 * (int64_t)child, scratch);
        return scratch;
    }
    int32_t left_of(int32_t node) const { return left[node]; }
    int32_t leaf_of(int32_t node) const { return leaf[node] == 65535 ? -1 : leaf[node]; }
};

// One step of traversal.LeafStream.next for every ray with sp > 0: pop (nearer child first) until a leaf is
// reached. out_leaf[r] = leaf ordinal or -1 (no leaf this call), out_te, out_tx per ray.
// Stacks: stack_node (n, depth) int32, stack_t (n, depth) float32, stack_box (n, depth, 6) float32 when the format
// carries boxes (else unused), sp (n,) int32; t_max (n,) float32.
template <class Nodes>
void stream_next_t(const Nodes& nodes, const float* rays_o, const float* inv_d, int64_t n, int32_t* stack_node,
                   float* stack_t, float* stack_box, int32_t* sp_arr, const float* t_max_arr, int depth,
                   int32_t* out_leaf, float* out_te, float* out_tx, int threads) {
#pragma omp parallel for schedule(dynamic, 256) num_threads(threads)
    for (int64_t r = 0; r < n; ++r) {
        out_leaf[r] = -1;
        int32_t sp = sp_arr[r];
        if (sp == 0) continue;
        const float* o = rays_o + 3 * r;
        const float* inv = inv_d + 3 * r;
        const float t_max = t_max_arr[r];
        int32_t* st_n = stack_node + r * depth;
        float* st_t = stack_t + r * depth;
        float* st_b = Nodes::carries_box ? stack_box + r * depth * 6 : nullptr;
        while (sp > 0) {
            --sp;
            const int32_t node = st_n[sp];
            if (!(st_t[sp] <= t_max)) continue;  // entered beyond a shortened t_max: skip
            const float* box = nodes.node_box(node, Nodes::carries_box ? st_b + 6 * sp : nullptr);
            const int32_t left = nodes.left_of(node);
            if (left == 0) {
                const int32_t leaf = nodes.leaf_of(node);
                if (leaf < 0) continue;  // padding node (never entered in practice)
                float te, tx;
                ray_box(o, inv, box, box + 3, INFINITY, &te, &tx);
                out_leaf[r] = leaf;
                out_te[r] = te;
                out_tx[r] = tx;
                break;
            }
            // Both children's boxes before a push overwrites the popped entry's box.
            float scratch_l[6], scratch_r[6], te_l, tx_l, te_r, tx_r;
            const float* bl = nodes.child_box(left, box, scratch_l);
            const float* br = nodes.child_box(left + 1, box, scratch_r);
            const bool hit_l = ray_box(o, inv, bl, bl + 3, t_max, &te_l, &tx_l);
            const bool hit_r = ray_box(o, inv, br, br + 3, t_max, &te_r, &tx_r);
            const bool right_first = te_r < te_l;
            const int32_t near = right_first ? left + 1 : left, far = right_first ? left : left + 1;
            const bool near_hit = right_first ? hit_r : hit_l, far_hit = right_first ? hit_l : hit_r;
            const float near_t = right_first ? te_r : te_l, far_t = right_first ? te_l : te_r;
            const float* near_b = right_first ? br : bl;
            const float* far_b = right_first ? bl : br;
            auto push = [&](int32_t child, float t, const float* child_box) {
                st_n[sp] = child;
                st_t[sp] = t;
                if constexpr (Nodes::carries_box) std::memcpy(st_b + 6 * sp, child_box, 6 * sizeof(float));
                ++sp;
            };
            if (far_hit) push(far, far_t, far_b);
            if (near_hit) push(near, near_t, near_b);
        }
        sp_arr[r] = sp;
    }
}

extern "C" {

int nbvh_abi_version() { return 22; }

// Fused inference over B segments of an MLP (kmlp = 0: mlp_segments_t) or a KMLP (kmlp = 1: kmlp_segments_t):
// rays_o/rays_d (n_rays, 3), ray (B,) int64 ray of each segment, te/tx (B,) segment ends, frac (k,) point
// fractions; table (L, rows, F) of table_kind 0 float32, 1 float16, 2 uint8 codes (with qoffset/qscale (L, F):
// value = offset + code * scale; null otherwise); dims (n_layers + 1,) int32 layer widths (dims[0] = k L F for an
// MLP, 2 L F for a KMLP's pair); params packed as Layers reads them. out: (B, dims[n_layers]) for an MLP,
// (B, k - 1, dims[n_layers]) for a KMLP, float32 raw outputs; a KMLP with decode = 1: (B, 5) its first-hit
// combination (hit probability, local t, unit normal: networks.KMLP.decode, kmlp_segments_t), pairs after a
// segment is decided skipped. weight_kind 0: params float32; 1: float16 (the
// stored half-precision network, read by the GEMM as it is: no float32 copy).
void nbvh_net_segments(const float* rays_o, const float* rays_d, const int64_t* ray, const float* te, const float* tx,
                       int64_t b, int k, const float* frac, const void* table, int table_kind,
                       const float* qoffset, const float* qscale, int levels,
                       int features, const float* scales, const int64_t* res, const uint8_t* dense,
                       int64_t vertex_table, int64_t rows, const uint8_t* codes, int64_t code_rows, int code_bits, int kmlp,
                       int decode, int n_layers, const int32_t* dims, const void* params, int weight_kind, float* out,
                       int threads) {
    Grid g{levels, features, scales, res, dense, vertex_table, rows, codes, code_rows, code_bits};
    g.qoffset = qoffset;
    g.qscale = qscale;
    g.init_masks();
    auto run = [&](auto weights) {
        using TW = std::remove_const_t<std::remove_pointer_t<decltype(weights)>>;
        by_features(features, [&](auto F) {
            constexpr int f = decltype(F)::value;
            by_table(table_kind, table, [&](auto tab) {
                using T = std::remove_const_t<std::remove_pointer_t<decltype(tab)>>;
                if (kmlp)
                    kmlp_segments_t<f, T, TW>(g, rays_o, rays_d, ray, te, tx, b, k, frac, tab, n_layers, dims, weights,
                                              decode, out, threads);
                else
                    mlp_segments_t<f, T, TW>(g, rays_o, rays_d, ray, te, tx, b, k, frac, tab, n_layers, dims, weights,
                                             out, threads);
            });
        });
    };
    if (weight_kind == 1)
        run(static_cast<const _Float16*>(params));
    else
        run(static_cast<const float*>(params));
}

// One training step on B labelled segments of an MLP (mlp_train_t; loss_out (4,) float64 = bce, depth_l1,
// normal_l1, normal_unit; out_raw (B, 5)) or a KMLP (kmlp_train_t; loss_out (5,) = bce, segment_ce, depth_l1 on the
// sub-segment scale, normal_l1, normal_unit; out_raw (B, k - 1, 5)); grad_params packed like params; grad_table (L, rows, F) accumulated
// (zero it first). hit (B,) uint8, local_t (B,), normal (B, 3); hit_count = number of hit rows.
// Scratch: points (B * k, 3), dx (B, k L F). out_raw may be null.
void nbvh_net_train(const float* rays_o, const float* rays_d, const int64_t* ray, const float* te, const float* tx,
                    int64_t b, int k, const float* frac, const float* table, int levels, int features,
                    const float* scales, const int64_t* res, const uint8_t* dense, int64_t vertex_table, int64_t rows,
                    const uint8_t* codes, int64_t code_rows, int code_bits, int kmlp, int n_layers, const int32_t* dims,
                    const float* params, const uint8_t* hit, const float* local_t, const float* normal,
                    int64_t hit_count, float w_t, float w_n, int unoriented, float w_unit, double* loss_out, float* grad_params, float* grad_table,
                    float* points, float* dx, float* out_raw, int threads) {
    Grid g{levels, features, scales, res, dense, vertex_table, rows, codes, code_rows, code_bits};
    g.init_masks();
    const float inv_hits = 1.f / (float)(hit_count > 0 ? hit_count : 1);
    by_features(features, [&](auto F) {
        constexpr int f = decltype(F)::value;
        if (kmlp)
            kmlp_train_t<f>(g, rays_o, rays_d, ray, te, tx, b, k, frac, table, n_layers, dims, params, hit, local_t,
                            normal, inv_hits, w_t, w_n, unoriented, w_unit, loss_out, grad_params, points, dx, out_raw, threads);
        else
            mlp_train_t<f>(g, rays_o, rays_d, ray, te, tx, b, k, frac, table, n_layers, dims, params, hit, local_t,
                           normal, inv_hits, w_t, w_n, unoriented, w_unit, loss_out, grad_params, points, dx, out_raw, threads);
        encode_backward_t<f>(g, points, b * k, dx, grad_table, threads);
    });
}


// Inference with a float16 copy of the table (same arguments as nbvh_encode_forward; table is (L, rows, F) half).
void nbvh_encode_forward_f16(const float* points, int64_t n, const void* table, float* out, int levels, int features,
                             const float* scales, const int64_t* res, const uint8_t* dense, int64_t vertex_table,
                             int64_t rows, const uint8_t* codes, int64_t code_rows, int code_bits, int threads) {
    Grid g{levels, features, scales, res, dense, vertex_table, rows, codes, code_rows, code_bits};
    g.init_masks();
    const _Float16* t = static_cast<const _Float16*>(table);
    by_features(features, [&](auto F) { encode_forward_t<decltype(F)::value, _Float16>(g, points, n, t, out, threads); });
}

// HashVQAD soft row table (see vqad_soft_forward) over the reachable entries only, level after level (R = sum of
// reach): logits (R, t), table (L, T, F), cand (T, t) int64 rows, reach (L,) int64 reachable entries per level
// (entries 0..reach[l]-1 of H); soft (R, F) and probs (R, t) written. t <= 256. needed (R,) uint8 or null: only
// the marked entries computed (nbvh_mark_entries), the others' soft rows zero, their probs unwritten.
void nbvh_vqad_soft_forward(const float* logits, const float* table, const int64_t* cand, const int64_t* reach,
                            int levels, int64_t H, int64_t T, int t, int F, float inv_tau, const uint8_t* needed,
                            float* probs, float* soft, int threads) {
    vqad_soft_forward(logits, table, cand, reach, levels, H, T, t, F, inv_tau, needed, probs, soft, threads);
}

// The soft row table entries (rows = 0: R reachable entries, level after level) that the k points of B segments
// read (segments as nbvh_net_train's): needed (R,) uint8 set to 1 at each (zero it first).
void nbvh_mark_entries(const float* rays_o, const float* rays_d, const int64_t* ray, const float* te, const float* tx,
                       int64_t b, int k, const float* frac, int levels, int features, const float* scales,
                       const int64_t* res, const uint8_t* dense, int64_t vertex_table, int64_t rows,
                       const uint8_t* codes, int64_t code_rows, int code_bits, uint8_t* needed, int threads) {
    Grid g{levels, features, scales, res, dense, vertex_table, rows, codes, code_rows, code_bits};
    g.init_masks();
    mark_entries(g, rays_o, rays_d, ray, te, tx, b, k, frac, needed, threads);
}

// Its backward: grad_soft (R, F) -> grad_table (L, T, F) accumulated (zero it first), grad_logits (R, t) written.
void nbvh_vqad_soft_backward(const float* probs, const float* table, const int64_t* cand, const int64_t* reach,
                             const float* grad_soft, int levels, int64_t H, int64_t T, int t, int F, float inv_tau,
                             float* grad_table, float* grad_logits, int threads) {
    vqad_soft_backward(probs, table, cand, reach, grad_soft, levels, H, T, t, F, inv_tau, grad_table, grad_logits,
                       threads);
}

// Inference from uint8 codes (L, rows, F) with qoffset/qscale (L, F) float32 (value = offset + code * scale).
void nbvh_encode_forward_u8(const float* points, int64_t n, const uint8_t* table, const float* qoffset,
                            const float* qscale, float* out, int levels, int features, const float* scales,
                            const int64_t* res, const uint8_t* dense, int64_t vertex_table, int64_t rows,
                            const uint8_t* codes, int64_t code_rows, int code_bits, int threads) {
    Grid g{levels, features, scales, res, dense, vertex_table, rows, codes, code_rows, code_bits};
    g.qoffset = qoffset;
    g.qscale = qscale;
    g.init_masks();
    by_features(features, [&](auto F) { encode_forward_t<decltype(F)::value, uint8_t>(g, points, n, table, out, threads); });
}

// points (n, 3) float32; table (L, rows, F) float32; out (n, L * F) float32.
void nbvh_encode_forward(const float* points, int64_t n, const float* table, float* out, int levels, int features,
                         const float* scales, const int64_t* res, const uint8_t* dense, int64_t vertex_table,
                         int64_t rows, const uint8_t* codes, int64_t code_rows, int code_bits, int threads) {
    Grid g{levels, features, scales, res, dense, vertex_table, rows, codes, code_rows, code_bits};
    g.init_masks();
    by_features(features, [&](auto F) { encode_forward_t<decltype(F)::value>(g, points, n, table, out, threads); });
}

// grad_table (L, rows, F) float32 is accumulated into (zero it first).
void nbvh_encode_backward(const float* points, int64_t n, const float* grad_out, float* grad_table, int levels,
                          int features, const float* scales, const int64_t* res, const uint8_t* dense,
                          int64_t vertex_table, int64_t rows, const uint8_t* codes, int64_t code_rows, int code_bits, int threads) {
    Grid g{levels, features, scales, res, dense, vertex_table, rows, codes, code_rows, code_bits};
    g.init_masks();
    by_features(features, [&](auto F) {
        encode_backward_t<decltype(F)::value>(g, points, n, grad_out, grad_table, threads);
    });
}

// stream_next_t on the 32-byte node records (NODE_DTYPE, the model's own array, read in place).
void nbvh_stream_next(const float* rays_o, const float* inv_d, int64_t n, const float* records, int32_t* stack_node,
                      float* stack_t, int32_t* sp_arr, const float* t_max_arr, int depth, int32_t* out_leaf,
                      float* out_te, float* out_tx, int threads) {
    stream_next_t(RecordNodes{records}, rays_o, inv_d, n, stack_node, stack_t, nullptr, sp_arr, t_max_arr, depth,
                  out_leaf, out_te, out_tx, threads);
}

// stream_next_t on the stored 8-bit nodes (the model holds the file's 10 bytes per node, not decoded boxes).
void nbvh_stream_next_q(const float* rays_o, const float* inv_d, int64_t n, const uint8_t* codes,
                        const uint16_t* node_left, const uint16_t* node_leaf, int32_t* stack_node, float* stack_t,
                        float* stack_box, int32_t* sp_arr, const float* t_max_arr, int depth, int32_t* out_leaf,
                        float* out_te, float* out_tx, int threads) {
    stream_next_t(CodedNodes{codes, node_left, node_leaf}, rays_o, inv_d, n, stack_node, stack_t, stack_box, sp_arr,
                  t_max_arr, depth, out_leaf, out_te, out_tx, threads);
}

// Complete front-to-back leaf lists (traversal.leaves_along_rays) in one traversal: each thread walks a contiguous
// block of rays and appends its (node, t_enter, t_exit) runs to its own list, sorted per ray by (t_enter, t_exit,
// node) like the reference; nbvh_leaves_collect then copies the lists, in thread order (= ray order), into the
// caller's arrays and frees them. counts (n,) int64 and *total are written here.
struct LeafLists {
    std::vector<std::vector<int32_t>> node;
    std::vector<std::vector<float>> te, tx;
};

void* nbvh_leaves_traverse(const float* rays_o, const float* inv_d, int64_t n, const float* t_max_arr,
                           const float* node_lo, const float* node_hi, const int32_t* node_left,
                           const int32_t* node_leaf, int depth, int64_t* counts, int64_t* total, int threads) {
    const int n_threads = threads < 1 ? 1 : threads;
    auto* lists = new LeafLists;
    lists->node.resize(n_threads);
    lists->te.resize(n_threads);
    lists->tx.resize(n_threads);
#pragma omp parallel num_threads(n_threads)
    {
        const FlushDenormals ftz_guard;
        const int tid = omp_get_thread_num();
        auto& out_node = lists->node[tid];
        auto& out_te = lists->te[tid];
        auto& out_tx = lists->tx[tid];
        std::vector<int32_t> stack(depth + 2);
        const int nt = omp_get_num_threads();
        const int64_t r0 = n * tid / nt, r1 = n * (tid + 1) / nt;  // contiguous block: lists stay in ray order
        out_node.reserve((size_t)(r1 - r0) * 4);
        out_te.reserve((size_t)(r1 - r0) * 4);
        out_tx.reserve((size_t)(r1 - r0) * 4);
        for (int64_t r = r0; r < r1; ++r) {
            const float* o = rays_o + 3 * r;
            const float* inv = inv_d + 3 * r;
            const float t_max = t_max_arr ? t_max_arr[r] : INFINITY;
            const size_t base = out_node.size();
            int sp = 0;
            float te, tx;
            if (ray_box(o, inv, node_lo, node_hi, t_max, &te, &tx)) stack[sp++] = 0;
            while (sp > 0) {
                const int32_t node = stack[--sp];
                const int32_t left = node_left[node];
                if (left == 0) {
                    if (node_leaf[node] < 0) continue;
                    ray_box(o, inv, node_lo + 3 * node, node_hi + 3 * node, t_max, &te, &tx);
                    out_node.push_back(node);
                    out_te.push_back(te);
                    out_tx.push_back(tx);
                    // Insertion into the sorted run (runs are short: a few leaves per ray).
                    size_t j = out_node.size() - 1;
                    while (j > base) {
                        const float pe = out_te[j - 1], px = out_tx[j - 1];
                        const bool after = pe > te || (pe == te && (px > tx || (px == tx && out_node[j - 1] > node)));
                        if (!after) break;
                        out_te[j] = pe; out_tx[j] = px; out_node[j] = out_node[j - 1];
                        --j;
                    }
                    out_te[j] = te; out_tx[j] = tx; out_node[j] = node;
                    continue;
                }
                for (int c = 1; c >= 0; --c) {
                    if (ray_box(o, inv, node_lo + 3 * (left + c), node_hi + 3 * (left + c), t_max, &te, &tx))
                        stack[sp++] = left + c;
                }
            }
            counts[r] = (int64_t)(out_node.size() - base);
        }
    }
    int64_t sum = 0;
    for (const auto& v : lists->node) sum += (int64_t)v.size();
    *total = sum;
    return lists;
}

// Copies the lists of nbvh_leaves_traverse into out_node (total,) int64, out_te, out_tx (total,) float32 (or only
// frees them when out_node is null).
void nbvh_leaves_collect(void* handle, int64_t* out_node, float* out_te, float* out_tx) {
    auto* lists = static_cast<LeafLists*>(handle);
    if (out_node) {
        int64_t pos = 0;
        for (size_t t = 0; t < lists->node.size(); ++t) {
            const auto& nd = lists->node[t];
            for (size_t i = 0; i < nd.size(); ++i) out_node[pos + (int64_t)i] = nd[i];
            std::memcpy(out_te + pos, lists->te[t].data(), sizeof(float) * nd.size());
            std::memcpy(out_tx + pos, lists->tx[t].data(), sizeof(float) * nd.size());
            pos += (int64_t)nd.size();
        }
    }
    delete lists;
}

}  // extern "C"
