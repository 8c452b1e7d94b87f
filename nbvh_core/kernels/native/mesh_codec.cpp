// The compact mesh's cluster payloads (geometry/compact_mesh.py, whose `_strip` and `_encode_cluster` are the
// reference): the same strip, the same first-use numbering and the same bits, byte for byte. Python's encoder
// spent ~1 us per triangle on the strip (65 s of a 1.2M-triangle lattice's 121 s plan, 2 cores).
#include "common.h"

namespace {

constexpr int RESTART = 0, EDGE_1 = 1, EDGE_2 = 2, ESCAPE = 3;

// An LSB-first bit string written into `out` (zeroed first by the caller's bound).
struct BitWriter {
    uint8_t* out;
    int64_t length = 0;
    void put(uint64_t v, int width) {
        for (int i = 0; i < width; ++i, ++length)
            if (v >> i & 1) out[length >> 3] |= uint8_t(1u << (length & 7));
    }
    int64_t bytes() const { return (length + 7) >> 3; }
};

inline int bit_length(int64_t v) {
    int n = 0;
    while (v > 0) { ++n; v >>= 1; }
    return n;
}

// The upper bound of one cluster's payload: 3 x 16 bits per vertex (V <= 3T), and per triangle 3 code bits and
// three references of 1 + 8 bits.
inline int64_t payload_bound(int64_t t) { return (3 * t * 48 + 7) / 8 + (t * 30 + 7) / 8 + 2; }

// One cluster: local (T, 3) vertex ids 0..V-1 (numbered by ascending global id), its V grid points. Writes the
// vertex bits then the strip bits (each byte aligned) at `out`; returns the payload's bytes.
int64_t encode_cluster(const int32_t* local, int T, const int64_t* pts, int V, uint8_t* out, int64_t* widths_out,
                       int64_t* lo_out, int64_t* hi_out) {
    // by_edge: (key, t) in insertion order, sorted stably by key: the triangles on an edge in ascending t
    struct EdgeRef { int32_t key, t; };
    std::vector<EdgeRef> refs;
    refs.reserve(3 * T);
    auto key_of = [](int a, int b) { return std::min(a, b) * 65536 + std::max(a, b); };
    for (int t = 0; t < T; ++t) {
        const int32_t* tri = local + 3 * t;
        for (int e = 0; e < 3; ++e) refs.push_back({key_of(tri[e], tri[(e + 1) % 3]), t});
    }
    std::stable_sort(refs.begin(), refs.end(), [](const EdgeRef& x, const EdgeRef& y) { return x.key < y.key; });
    auto range = [&](int key) {
        auto lo = std::lower_bound(refs.begin(), refs.end(), key, [](const EdgeRef& r, int k) { return r.key < k; });
        auto hi = std::upper_bound(refs.begin(), refs.end(), key, [](int k, const EdgeRef& r) { return k < r.key; });
        return std::make_pair(lo, hi);
    };
    std::vector<char> left(T, 1);
    int n_left = T;
    auto open_neighbours = [&](int t) {
        const int32_t* tri = local + 3 * t;
        int count = 0;
        for (int e = 0; e < 3; ++e) {
            auto r = range(key_of(tri[e], tri[(e + 1) % 3]));
            for (auto it = r.first; it != r.second; ++it) count += it->t != t && left[it->t];
        }
        return count;
    };
    auto index_of = [](const int32_t* tri, int v) { return tri[0] == v ? 0 : tri[1] == v ? 1 : tri[2] == v ? 2 : -1; };

    std::vector<int> first_use(V, -1);
    int seen = 0;
    const int index_bits = std::max(1, bit_length(V - 1));
    // the strip's bits go to a scratch buffer first: the vertex bits (whose order is the strip's) come before them
    std::vector<uint8_t> code_buf((T * 30 + 7) / 8 + 2, 0);
    BitWriter code{code_buf.data()};
    auto ref = [&](int v) {
        if (first_use[v] < 0) {
            first_use[v] = seen++;
            code.put(1, 1);
        } else {
            code.put(0, 1);
            code.put(first_use[v], index_bits);
        }
    };
    bool has_prev = false;
    int prev[3] = {0, 0, 0};
    while (n_left > 0) {
        int step_code = -1, step_t = -1, tri_out[3] = {0, 0, 0};
        if (has_prev) {
            const int x = prev[0], y = prev[1], z = prev[2];
            const int cand[2][3] = {{EDGE_1, y, z}, {EDGE_2, z, x}};
            for (int c = 0; c < 2 && step_code < 0; ++c) {
                const int edge = cand[c][0], u = cand[c][1], v = cand[c][2];
                auto r = range(key_of(u, v));
                for (auto it = r.first; it != r.second; ++it) {
                    const int t = it->t;
                    if (!left[t]) continue;
                    const int32_t* tri = local + 3 * t;
                    int k = index_of(tri, v);
                    if (k >= 0 && tri[(k + 1) % 3] == u) {  // wound with its neighbour: (v, u, w)
                        step_code = edge;
                        tri_out[0] = v, tri_out[1] = u, tri_out[2] = tri[(k + 2) % 3];
                    } else {  // wound against it: (u, v, w), an escape
                        k = index_of(tri, u);
                        step_code = ESCAPE + (edge == EDGE_2) * 4;
                        tri_out[0] = u, tri_out[1] = v, tri_out[2] = tri[(k + 2) % 3];
                    }
                    step_t = t;
                    break;
                }
            }
        }
        if (step_code < 0) {  // restart where the fewest triangles still touch (ties: the lowest index)
            int best = -1, best_count = 0;
            for (int t = 0; t < T; ++t) {
                if (!left[t]) continue;
                if (n_left > 64) { best = t; break; }
                const int count = open_neighbours(t);
                if (best < 0 || count < best_count) best = t, best_count = count;
            }
            step_code = RESTART, step_t = best;
            for (int i = 0; i < 3; ++i) tri_out[i] = local[3 * best + i];
        }
        left[step_t] = 0;
        --n_left;
        if (step_code == RESTART) {
            code.put(RESTART, 2);
            for (int i = 0; i < 3; ++i) ref(tri_out[i]);
        } else {
            code.put(std::min(step_code, ESCAPE), 2);
            if (step_code >= ESCAPE) code.put(step_code / 4, 1);
            ref(tri_out[2]);
        }
        for (int i = 0; i < 3; ++i) prev[i] = tri_out[i];
        has_prev = true;
    }
    // the vertices in first-use order, as offsets from the cluster's anchor at the cluster's widths
    std::vector<int> perm(seen);
    for (int v = 0; v < V; ++v)
        if (first_use[v] >= 0) perm[first_use[v]] = v;
    int64_t lo[3], hi[3];
    for (int a = 0; a < 3; ++a) {
        lo[a] = hi[a] = pts[3 * perm[0] + a];
        for (int i = 1; i < seen; ++i) lo[a] = std::min(lo[a], pts[3 * perm[i] + a]), hi[a] = std::max(hi[a], pts[3 * perm[i] + a]);
    }
    int w[3];
    for (int a = 0; a < 3; ++a) w[a] = bit_length(hi[a] - lo[a]), lo_out[a] = lo[a], hi_out[a] = hi[a];
    BitWriter verts{out};
    for (int i = 0; i < seen; ++i)
        for (int a = 0; a < 3; ++a) verts.put(uint64_t(pts[3 * perm[i] + a] - lo[a]), w[a]);
    const int64_t vb = verts.bytes(), cb = code.bytes();
    std::memcpy(out + vb, code_buf.data(), cb);
    *widths_out = w[0] | w[1] << 5 | w[2] << 10;
    return vb + cb;
}

}  // namespace

extern "C" void nbvh_encode_clusters(const int32_t* faces, const int64_t* grid, const int64_t* cluster_tris,
                                     int64_t t, const int64_t* cluster_start, int64_t c, uint8_t* out,
                                     int64_t out_bytes, int64_t* out_offset, int64_t* widths, int64_t* n_verts,
                                     int64_t* grid_lo, int64_t* grid_hi, int threads) {
    (void)t;
    // each cluster at its bound's offset (in parallel), then moved down to the previous one's end (in order)
    std::vector<int64_t> bound_at(c + 1, 0), length(c, 0);
    for (int64_t k = 0; k < c; ++k) bound_at[k + 1] = bound_at[k] + payload_bound(cluster_start[k + 1] - cluster_start[k]);
    if (bound_at[c] > out_bytes) return;  // the caller sized `out` with nbvh's bound: never reached
    std::memset(out, 0, bound_at[c]);
#pragma omp parallel for schedule(dynamic, 64) num_threads(threads)
    for (int64_t k = 0; k < c; ++k) {
        const int T = int(cluster_start[k + 1] - cluster_start[k]);
        std::vector<int32_t> global(3 * T), local(3 * T);
        for (int i = 0; i < T; ++i)
            for (int j = 0; j < 3; ++j) global[3 * i + j] = faces[3 * cluster_tris[cluster_start[k] + i] + j];
        std::vector<int32_t> verts(global);
        std::sort(verts.begin(), verts.end());
        verts.erase(std::unique(verts.begin(), verts.end()), verts.end());
        for (int i = 0; i < 3 * T; ++i)
            local[i] = int32_t(std::lower_bound(verts.begin(), verts.end(), global[i]) - verts.begin());
        const int V = int(verts.size());
        std::vector<int64_t> pts(3 * V);
        for (int v = 0; v < V; ++v)
            for (int a = 0; a < 3; ++a) pts[3 * v + a] = grid[3 * int64_t(verts[v]) + a];
        n_verts[k] = V;
        length[k] = encode_cluster(local.data(), T, pts.data(), V, out + bound_at[k], widths + k, grid_lo + 3 * k,
                                   grid_hi + 3 * k);
    }
    int64_t at = 0;
    for (int64_t k = 0; k < c; ++k) {
        out_offset[k] = at;
        if (at != bound_at[k]) std::memmove(out + at, out + bound_at[k], length[k]);
        at += length[k];
    }
    out_offset[c] = at;
}
