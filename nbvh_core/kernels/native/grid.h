// The multiresolution grid lookup (encodings/base.py, hashgrid.py, hashvqad.py): a point's cell, hashed or dense
// corner rows and trilinear weights per level, the weighted row sums (forward) and their scatter (backward).
#pragma once
#include "common.h"

namespace {

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

}  // namespace
