// The full binned-SAH tree (geometry/bvh.py `build_full_tree`, whose numpy code is the reference): the same
// splits, node numbering (level by level, children of the i-th split node at n_total + 2i), triangle order and
// float32 boxes, node for node. The numpy build sorted every level's triangles (O(n log^2 n)): 10 s for a 1.2M
// lattice on 2 cores, ~100 s at 10M.
#include "common.h"

namespace {

// Half the surface area of a box (lo, hi as float32, differences in float64), 0 for an empty one.
inline double half_area(const float* lo, const float* hi) {
    double d[3];
    for (int a = 0; a < 3; ++a) {
        double v = std::max((double)hi[a] - (double)lo[a], 0.0);
        d[a] = std::isfinite(v) ? v : 0.0;
    }
    return d[0] * d[1] + d[1] * d[2] + d[2] * d[0];
}

// One node's split (what one level of the numpy build decides for it): go_right per triangle of order[s, s + n).
void split_node(const int64_t* tris, int64_t n, const float* tri_lo, const float* tri_hi, const double* centroid,
                int n_bins, int median_below, std::vector<char>& right) {
    right.assign(n, 0);
    double c_lo[3], c_hi[3], extent[3], scale[3];
    for (int a = 0; a < 3; ++a) c_lo[a] = INFINITY, c_hi[a] = -INFINITY;
    for (int64_t i = 0; i < n; ++i)
        for (int a = 0; a < 3; ++a) {
            const double c = centroid[3 * tris[i] + a];
            c_lo[a] = std::min(c_lo[a], c), c_hi[a] = std::max(c_hi[a], c);
        }
    for (int a = 0; a < 3; ++a) {
        extent[a] = c_hi[a] - c_lo[a];
        scale[a] = extent[a] > 0 ? (double)n_bins / extent[a] : 0.0;
    }
    auto bin = [&](int64_t i, int a) {
        int64_t b = (int64_t)((centroid[3 * tris[i] + a] - c_lo[a]) * scale[a]);
        return (int)std::min<int64_t>(std::max<int64_t>(b, 0), n_bins - 1);
    };
    double best_cost = INFINITY;
    int best_axis = 0, best_plane = 0;
    if (n > median_below) {
        std::vector<double> cnt(n_bins);
        std::vector<float> blo(3 * n_bins), bhi(3 * n_bins), llo(3 * n_bins), lhi(3 * n_bins);
        for (int a = 0; a < 3; ++a) {
            std::fill(cnt.begin(), cnt.end(), 0.0);
            std::fill(blo.begin(), blo.end(), INFINITY);
            std::fill(bhi.begin(), bhi.end(), -INFINITY);
            for (int64_t i = 0; i < n; ++i) {
                const int b = bin(i, a);
                cnt[b] += 1.0;
                for (int k = 0; k < 3; ++k) {
                    blo[3 * b + k] = std::min(blo[3 * b + k], tri_lo[3 * tris[i] + k]);
                    bhi[3 * b + k] = std::max(bhi[3 * b + k], tri_hi[3 * tris[i] + k]);
                }
            }
            // sweeps: bins [0..p] on the left, [p + 1..] on the right, for planes p = 0..n_bins - 2
            for (int k = 0; k < 3; ++k) llo[k] = blo[k], lhi[k] = bhi[k];
            for (int b = 1; b < n_bins; ++b)
                for (int k = 0; k < 3; ++k)
                    llo[3 * b + k] = std::min(llo[3 * (b - 1) + k], blo[3 * b + k]),
                    lhi[3 * b + k] = std::max(lhi[3 * (b - 1) + k], bhi[3 * b + k]);
            float rlo[3] = {INFINITY, INFINITY, INFINITY}, rhi[3] = {-INFINITY, -INFINITY, -INFINITY};
            std::vector<double> cost(n_bins - 1);
            double total = 0.0;
            for (int b = 0; b < n_bins; ++b) total += cnt[b];
            std::vector<double> lcnt(n_bins);
            double run = 0.0;
            for (int b = 0; b < n_bins; ++b) run += cnt[b], lcnt[b] = run;
            for (int p = n_bins - 2; p >= 0; --p) {
                for (int k = 0; k < 3; ++k)
                    rlo[k] = std::min(rlo[k], blo[3 * (p + 1) + k]), rhi[k] = std::max(rhi[k], bhi[3 * (p + 1) + k]);
                const double l = lcnt[p], r = total - l;
                const double c = half_area(&llo[3 * p], &lhi[3 * p]) * l + half_area(rlo, rhi) * r;
                cost[p] = (l > 0 && r > 0) ? c : INFINITY;
            }
            int plane = 0;
            for (int p = 1; p < n_bins - 1; ++p)
                if (cost[p] < cost[plane]) plane = p;
            if (cost[plane] < best_cost) best_cost = cost[plane], best_axis = a, best_plane = plane;
        }
    }
    if (std::isfinite(best_cost)) {
        for (int64_t i = 0; i < n; ++i) right[i] = bin(i, best_axis) > best_plane;
        return;
    }
    // small nodes, and nodes SAH cannot split: the upper half along the longest centroid axis (stable)
    int ax = 0;
    for (int a = 1; a < 3; ++a)
        if (extent[a] > extent[ax]) ax = a;
    std::vector<int64_t> rank(n);
    for (int64_t i = 0; i < n; ++i) rank[i] = i;
    std::stable_sort(rank.begin(), rank.end(), [&](int64_t x, int64_t y) {
        return centroid[3 * tris[x] + ax] < centroid[3 * tris[y] + ax];
    });
    for (int64_t r = n / 2; r < n; ++r) right[rank[r]] = 1;
}

}  // namespace

extern "C" void nbvh_build_full_tree(const float* tri_lo, const float* tri_hi, const double* centroid, int64_t n,
                                     int max_leaf_size, int n_bins, int median_below, int64_t capacity,
                                     float* node_lo, float* node_hi, int64_t* left, int64_t* start, int64_t* count,
                                     int32_t* depth, int64_t* order, int64_t* n_nodes, int threads) {
    for (int64_t i = 0; i < n; ++i) order[i] = i;
    for (int a = 0; a < 3; ++a) node_lo[a] = INFINITY, node_hi[a] = -INFINITY;
    for (int64_t i = 0; i < n; ++i)
        for (int a = 0; a < 3; ++a)
            node_lo[a] = std::min(node_lo[a], tri_lo[3 * i + a]), node_hi[a] = std::max(node_hi[a], tri_hi[3 * i + a]);
    left[0] = -1, start[0] = 0, count[0] = n, depth[0] = 0;
    int64_t total = 1;
    std::vector<int64_t> active = {0};
    for (int level = 1; total < capacity; ++level) {
        std::vector<int64_t> splitting;
        for (int64_t id : active)
            if (count[id] > max_leaf_size) splitting.push_back(id);
        if (splitting.empty()) break;
        const int64_t m = (int64_t)splitting.size();
        if (total + 2 * m > capacity) break;  // never: a full tree has at most 2n - 1 nodes
#pragma omp parallel for schedule(dynamic, 1) num_threads(threads)
        for (int64_t i = 0; i < m; ++i) {
            const int64_t id = splitting[i], s = start[id], c = count[id];
            std::vector<char> right;
            split_node(order + s, c, tri_lo, tri_hi, centroid, n_bins, median_below, right);
            std::vector<int64_t> part;
            part.reserve(c);
            for (int64_t k = 0; k < c; ++k)
                if (!right[k]) part.push_back(order[s + k]);
            const int64_t n_left = (int64_t)part.size();
            for (int64_t k = 0; k < c; ++k)
                if (right[k]) part.push_back(order[s + k]);
            std::memcpy(order + s, part.data(), c * sizeof(int64_t));
            const int64_t kid = total + 2 * i;
            left[id] = kid;
            const int64_t ranges[2][2] = {{s, n_left}, {s + n_left, c - n_left}};
            for (int side = 0; side < 2; ++side) {
                const int64_t ch = kid + side, cs = ranges[side][0], cc = ranges[side][1];
                float* lo = node_lo + 3 * ch;
                float* hi = node_hi + 3 * ch;
                for (int a = 0; a < 3; ++a) lo[a] = INFINITY, hi[a] = -INFINITY;
                for (int64_t k = cs; k < cs + cc; ++k)
                    for (int a = 0; a < 3; ++a)
                        lo[a] = std::min(lo[a], tri_lo[3 * order[k] + a]), hi[a] = std::max(hi[a], tri_hi[3 * order[k] + a]);
                left[ch] = -1, start[ch] = cs, count[ch] = cc, depth[ch] = level;
            }
        }
        active.clear();
        for (int64_t k = total; k < total + 2 * m; ++k) active.push_back(k);
        total += 2 * m;
    }
    *n_nodes = total;
}
