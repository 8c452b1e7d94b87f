// Fused CPU kernels of the fast path (see kernels/__init__.py). Plain C ABI, called through ctypes on the
// memory of contiguous torch tensors; OpenMP over points (forward), levels (backward) or rays (traversal).
//
// Every kernel computes exactly what the reference torch code computes (encodings/base.py, hashvqad.py,
// traversal.py) with the same float32 operations in the same order where the order matters for the result:
// grid cells, hashes and box tests are bit-identical (built with -ffp-contract=off, no fused multiply-add);
// only the order of the 8-corner sums differs (float rounding, ~1e-7 relative).
#include <cmath>
#include <cstdint>
#include <cstring>
#include <omp.h>
#include <type_traits>

namespace {

constexpr uint32_t P1 = 2654435761u;
constexpr uint32_t P2 = 805459861u;

struct Grid {
    int levels, features;
    const float* scales;      // (L,) s_l
    const int64_t* res;       // (L,) vertices per axis
    const uint8_t* dense;     // (L,) 1 when level l indexes densely
    int64_t vertex_table;     // vertex index range: T (HashGrid) or H (HashVQAD)
    int64_t rows;             // rows per level in `table`
    const uint8_t* codes;     // (L, vertex_table) frozen HashVQAD codes, or null
    int64_t code_rows;        // T: candidate rows hash2(i, code) mod T (with codes)
    uint32_t vertex_mask = 0; // vertex_table - 1 when it is a power of two <= 2^32, else 0
    uint32_t code_mask = 0;

    void init_masks() {
        auto pow2 = [](int64_t v) { return v > 0 && v <= (int64_t(1) << 32) && (v & (v - 1)) == 0; };
        vertex_mask = pow2(vertex_table) ? (uint32_t)(vertex_table - 1) : 0;
        code_mask = pow2(code_rows) ? (uint32_t)(code_rows - 1) : 0;
    }
};

// Row of `table` (within level l) and trilinear weight of the 8 corners of point x at level l.
inline void corners(const Grid& g, int l, const float* x, int64_t* row, float* w) {
    const float s = g.scales[l];
    float frac[3];
    int64_t base[3];
    for (int a = 0; a < 3; ++a) {
        float xa = x[a];
        xa = xa < 0.f ? 0.f : (xa > 1.f ? 1.f : xa);
        const float p = xa * s + 0.5f;
        const float b = std::floor(p);
        frac[a] = p - b;
        base[a] = (int64_t)b;
    }
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
        if (g.codes) {
            const uint32_t code = g.codes[(int64_t)l * g.vertex_table + idx];
            const uint32_t h = ((uint32_t)idx * P1) ^ (code * P2);
            idx = g.code_mask ? (int64_t)(h & g.code_mask) : (int64_t)(h % (uint64_t)g.code_rows);
        }
        row[c] = idx;
    }
}

// Table entries are float32, or float16 (`_Float16`, inference only: half the bytes to gather; the compiler turns
// the conversion into vcvtph2ps).
template <int F, typename T>
inline void accumulate(float* __restrict out, const T* __restrict tab, const int64_t* row, const float* w, int f_dyn) {
    const int nf = F > 0 ? F : f_dyn;
    for (int f = 0; f < nf; ++f) out[f] = 0.f;
    for (int c = 0; c < 8; ++c) {
        const T* __restrict src = tab + row[c] * nf;
        const float wc = w[c];
#pragma omp simd
        for (int f = 0; f < nf; ++f) out[f] += wc * (float)src[f];
    }
}

template <int F, typename T = float>
void encode_forward_t(const Grid& g, const float* points, int64_t n, const T* table, float* out, int threads) {
    const int L = g.levels;
    const int nf = F > 0 ? F : g.features;
#pragma omp parallel for schedule(static) num_threads(threads)
    for (int64_t i = 0; i < n; ++i) {
        int64_t row[8];
        float w[8];
        for (int l = 0; l < L; ++l) {
            corners(g, l, points + 3 * i, row, w);
            accumulate<F>(out + (i * L + l) * nf, table + (int64_t)l * g.rows * nf, row, w, nf);
        }
    }
}

template <int F>
void encode_backward_t(const Grid& g, const float* points, int64_t n, const float* grad_out, float* grad_table,
                       int threads) {
    const int L = g.levels;
    const int nf = F > 0 ? F : g.features;
    // One level per thread at a time: no two threads write the same row, and the sum order is fixed.
#pragma omp parallel for schedule(dynamic, 1) num_threads(threads)
    for (int l = 0; l < L; ++l) {
        float* gt = grad_table + (int64_t)l * g.rows * nf;
        int64_t row[8];
        float w[8];
        for (int64_t i = 0; i < n; ++i) {
            corners(g, l, points + 3 * i, row, w);
            const float* __restrict go = grad_out + (i * L + l) * nf;
            for (int c = 0; c < 8; ++c) {
                float* __restrict dst = gt + row[c] * nf;
                const float wc = w[c];
#pragma omp simd
                for (int f = 0; f < nf; ++f) dst[f] += wc * go[f];
            }
        }
    }
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

}  // namespace

extern "C" {

int nbvh_abi_version() { return 3; }

// Inference with a float16 copy of the table (same arguments as nbvh_encode_forward; table is (L, rows, F) half).
void nbvh_encode_forward_f16(const float* points, int64_t n, const void* table, float* out, int levels, int features,
                             const float* scales, const int64_t* res, const uint8_t* dense, int64_t vertex_table,
                             int64_t rows, const uint8_t* codes, int64_t code_rows, int threads) {
    Grid g{levels, features, scales, res, dense, vertex_table, rows, codes, code_rows};
    g.init_masks();
    const _Float16* t = static_cast<const _Float16*>(table);
    switch (features) {
        case 8: encode_forward_t<8, _Float16>(g, points, n, t, out, threads); break;
        case 16: encode_forward_t<16, _Float16>(g, points, n, t, out, threads); break;
        default: encode_forward_t<0, _Float16>(g, points, n, t, out, threads);
    }
}

// points (n, 3) float32; table (L, rows, F) float32; out (n, L * F) float32.
void nbvh_encode_forward(const float* points, int64_t n, const float* table, float* out, int levels, int features,
                         const float* scales, const int64_t* res, const uint8_t* dense, int64_t vertex_table,
                         int64_t rows, const uint8_t* codes, int64_t code_rows, int threads) {
    Grid g{levels, features, scales, res, dense, vertex_table, rows, codes, code_rows};
    g.init_masks();
    by_features(features, [&](auto F) { encode_forward_t<decltype(F)::value>(g, points, n, table, out, threads); });
}

// grad_table (L, rows, F) float32 is accumulated into (zero it first).
void nbvh_encode_backward(const float* points, int64_t n, const float* grad_out, float* grad_table, int levels,
                          int features, const float* scales, const int64_t* res, const uint8_t* dense,
                          int64_t vertex_table, int64_t rows, const uint8_t* codes, int64_t code_rows, int threads) {
    Grid g{levels, features, scales, res, dense, vertex_table, rows, codes, code_rows};
    g.init_masks();
    by_features(features, [&](auto F) {
        encode_backward_t<decltype(F)::value>(g, points, n, grad_out, grad_table, threads);
    });
}

// Segment points: out (B, k, 3) = o[ray] + (te + i/(k-1) (tx - te)) d[ray], as NeuralBVH.segment_points.
void nbvh_segment_points(const float* rays_o, const float* rays_d, const int64_t* ray, const float* te,
                         const float* tx, int64_t b, int k, const float* frac, float* out, int threads) {
#pragma omp parallel for schedule(static) num_threads(threads)
    for (int64_t s = 0; s < b; ++s) {
        const float* o = rays_o + 3 * ray[s];
        const float* d = rays_d + 3 * ray[s];
        const float len = tx[s] - te[s];
        for (int i = 0; i < k; ++i) {
            const float t = te[s] + frac[i] * len;
            for (int a = 0; a < 3; ++a) out[(s * k + i) * 3 + a] = o[a] + t * d[a];
        }
    }
}

// One step of traversal.LeafStream.next for every ray with sp > 0: pop (nearer child first) until a leaf is
// reached. out_leaf[r] = leaf ordinal or -1 (no leaf this call), out_node, out_te, out_tx per ray.
// Stacks: stack_node (n, depth) int32, stack_t (n, depth) float32, sp (n,) int32; t_max (n,) float32.
void nbvh_stream_next(const float* rays_o, const float* inv_d, int64_t n, const float* node_lo,
                      const float* node_hi, const int32_t* node_left, const int32_t* node_leaf, int32_t* stack_node,
                      float* stack_t, int32_t* sp_arr, const float* t_max_arr, int depth, int32_t* out_leaf,
                      float* out_te, float* out_tx, int threads) {
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
        while (sp > 0) {
            --sp;
            const int32_t node = st_n[sp];
            if (!(st_t[sp] <= t_max)) continue;  // entered beyond a shortened t_max: skip
            const int32_t left = node_left[node];
            if (left == 0) {
                if (node_leaf[node] < 0) continue;  // padding node (never entered in practice)
                float te, tx;
                ray_box(o, inv, node_lo + 3 * node, node_hi + 3 * node, INFINITY, &te, &tx);
                out_leaf[r] = node_leaf[node];
                out_te[r] = te;
                out_tx[r] = tx;
                break;
            }
            float te_l, tx_l, te_r, tx_r;
            const bool hit_l = ray_box(o, inv, node_lo + 3 * left, node_hi + 3 * left, t_max, &te_l, &tx_l);
            const bool hit_r = ray_box(o, inv, node_lo + 3 * (left + 1), node_hi + 3 * (left + 1), t_max, &te_r, &tx_r);
            const bool right_first = te_r < te_l;
            const int32_t near = right_first ? left + 1 : left, far = right_first ? left : left + 1;
            const bool near_hit = right_first ? hit_r : hit_l, far_hit = right_first ? hit_l : hit_r;
            const float near_t = right_first ? te_r : te_l, far_t = right_first ? te_l : te_r;
            if (far_hit) { st_n[sp] = far; st_t[sp] = far_t; ++sp; }
            if (near_hit) { st_n[sp] = near; st_t[sp] = near_t; ++sp; }
        }
        sp_arr[r] = sp;
    }
}

// Complete front-to-back leaf lists (traversal.leaves_along_rays) in two passes: count (out = null), then fill.
// counts (n,) int64 out of the count pass; offsets (n + 1,) from its prefix sum. Entries per ray are sorted by
// (t_enter, t_exit, node) like the reference. t_max (n,) or null.
void nbvh_leaves_along_rays(const float* rays_o, const float* inv_d, int64_t n, const float* t_max_arr,
                            const float* node_lo, const float* node_hi, const int32_t* node_left,
                            const int32_t* node_leaf, int depth, int64_t* counts, const int64_t* offsets,
                            int64_t* out_node, float* out_te, float* out_tx, int threads) {
#pragma omp parallel num_threads(threads)
    {
        int32_t* stack = new int32_t[depth + 2];
#pragma omp for schedule(dynamic, 256)
        for (int64_t r = 0; r < n; ++r) {
            const float* o = rays_o + 3 * r;
            const float* inv = inv_d + 3 * r;
            const float t_max = t_max_arr ? t_max_arr[r] : INFINITY;
            int64_t count = 0;
            int64_t base = offsets ? offsets[r] : 0;
            int sp = 0;
            float te, tx;
            if (ray_box(o, inv, node_lo, node_hi, t_max, &te, &tx)) stack[sp++] = 0;
            while (sp > 0) {
                const int32_t node = stack[--sp];
                const int32_t left = node_left[node];
                if (left == 0) {
                    if (node_leaf[node] < 0) continue;
                    if (offsets) {
                        ray_box(o, inv, node_lo + 3 * node, node_hi + 3 * node, t_max, &te, &tx);
                        // Insertion into the sorted run (runs are short: a few leaves per ray).
                        int64_t j = base + count;
                        while (j > base) {
                            const float pe = out_te[j - 1], px = out_tx[j - 1];
                            const bool after = pe > te || (pe == te && (px > tx || (px == tx && out_node[j - 1] > node)));
                            if (!after) break;
                            out_te[j] = pe; out_tx[j] = px; out_node[j] = out_node[j - 1];
                            --j;
                        }
                        out_te[j] = te; out_tx[j] = tx; out_node[j] = node;
                    }
                    ++count;
                    continue;
                }
                for (int c = 1; c >= 0; --c) {
                    if (ray_box(o, inv, node_lo + 3 * (left + c), node_hi + 3 * (left + c), t_max, &te, &tx))
                        stack[sp++] = left + c;
                }
            }
            if (!offsets) counts[r] = count;
        }
        delete[] stack;
    }
}

}  // extern "C"
