// Fused MLP and KMLP models (neural/fused_mlp.py): inference and one training step per (ray, leaf) segment.
#include "grid.h"

namespace {

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



}  // namespace

extern "C" {

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


}  // extern "C"
