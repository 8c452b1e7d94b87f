// HashVQAD's soft row table (encodings/hashvqad.py): softmax-weighted candidate rows, their backward, and the
// entries a batch reads.
#include "grid.h"

namespace {

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

extern "C" {

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

}  // extern "C"
