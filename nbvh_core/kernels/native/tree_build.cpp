// The full binned-SAH tree (geometry/bvh.py `build_full_tree`, whose numpy code is the reference): the same
// splits, node numbering (level by level, children of the i-th split node at n_total + 2i), triangle order and
// float32 boxes, node for node. The numpy build sorted every level's triangles (O(n log^2 n)): 10 s for a 1.2M
// lattice on 2 cores, ~100 s at 10M. The triangles' boxes move with `order`, so every pass over a node reads its
// triangles in sequence (reads through `order` made each level a scatter of random reads: 12.0 s for the 10M
// lattice's tree at 4 per leaf, 2 cores).
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

// The centroid on one axis of the box at lo/hi, as the numpy build computes it: (float64(lo) + hi) * 0.5 (exact:
// no array of them is kept, 24 B per triangle).
inline double centroid(const float* lo, const float* hi, int64_t i, int a) {
    return ((double)lo[3 * i + a] + (double)hi[3 * i + a]) * 0.5;
}

// One thread's working arrays, kept from node to node (an allocation per array per node was ~1/3 of the build).
struct Scratch {
    std::vector<char> right;
    std::vector<double> cnt, cost, lcnt;
    std::vector<float> blo, bhi, llo, lhi, spill_box;
    std::vector<int64_t> rank, spill_ids;
};

// One node's split (what one level of the numpy build decides for it): w.right[i] for its n triangles, whose
// boxes are lo/hi[i] (in the node's order). The bins of the three axes are filled in one pass.
void split_node(const float* lo, const float* hi, int64_t n, int n_bins, int median_below, Scratch& w) {
    std::vector<char>& right = w.right;
    right.assign(n, 0);
    double c_lo[3], c_hi[3], extent[3], scale[3];
    for (int a = 0; a < 3; ++a) c_lo[a] = INFINITY, c_hi[a] = -INFINITY;
    for (int64_t i = 0; i < n; ++i)
        for (int a = 0; a < 3; ++a) {
            const double c = centroid(lo, hi, i, a);
            c_lo[a] = std::min(c_lo[a], c), c_hi[a] = std::max(c_hi[a], c);
        }
    for (int a = 0; a < 3; ++a) {
        extent[a] = c_hi[a] - c_lo[a];
        scale[a] = extent[a] > 0 ? (double)n_bins / extent[a] : 0.0;
    }
    auto bin = [&](int64_t i, int a) {
        int64_t b = (int64_t)((centroid(lo, hi, i, a) - c_lo[a]) * scale[a]);
        return (int)std::min<int64_t>(std::max<int64_t>(b, 0), n_bins - 1);
    };
    double best_cost = INFINITY;
    int best_axis = 0, best_plane = 0;
    if (n > median_below) {
        // per axis a and bin b (index a * n_bins + b): the count and the box of its triangles
        std::vector<double>& cnt = w.cnt;
        std::vector<float>&blo = w.blo, &bhi = w.bhi;
        cnt.assign(3 * n_bins, 0.0), blo.assign(9 * n_bins, INFINITY), bhi.assign(9 * n_bins, -INFINITY);
        for (int64_t i = 0; i < n; ++i)
            for (int a = 0; a < 3; ++a) {
                const int b = a * n_bins + bin(i, a);
                cnt[b] += 1.0;
                for (int k = 0; k < 3; ++k)
                    blo[3 * b + k] = std::min(blo[3 * b + k], lo[3 * i + k]),
                    bhi[3 * b + k] = std::max(bhi[3 * b + k], hi[3 * i + k]);
            }
        std::vector<float>&llo = w.llo, &lhi = w.lhi;
        std::vector<double>&cost = w.cost, &lcnt = w.lcnt;
        llo.resize(3 * n_bins), lhi.resize(3 * n_bins), cost.resize(n_bins - 1), lcnt.resize(n_bins);
        for (int a = 0; a < 3; ++a) {
            const double* ac = &cnt[a * n_bins];
            const float* alo = &blo[3 * a * n_bins];
            const float* ahi = &bhi[3 * a * n_bins];
            // sweeps: bins [0..p] on the left, [p + 1..] on the right, for planes p = 0..n_bins - 2
            for (int k = 0; k < 3; ++k) llo[k] = alo[k], lhi[k] = ahi[k];
            for (int b = 1; b < n_bins; ++b)
                for (int k = 0; k < 3; ++k)
                    llo[3 * b + k] = std::min(llo[3 * (b - 1) + k], alo[3 * b + k]),
                    lhi[3 * b + k] = std::max(lhi[3 * (b - 1) + k], ahi[3 * b + k]);
            float rlo[3] = {INFINITY, INFINITY, INFINITY}, rhi[3] = {-INFINITY, -INFINITY, -INFINITY};
            double total = 0.0;
            for (int b = 0; b < n_bins; ++b) total += ac[b];
            double run = 0.0;
            for (int b = 0; b < n_bins; ++b) run += ac[b], lcnt[b] = run;
            for (int p = n_bins - 2; p >= 0; --p) {
                for (int k = 0; k < 3; ++k)
                    rlo[k] = std::min(rlo[k], alo[3 * (p + 1) + k]), rhi[k] = std::max(rhi[k], ahi[3 * (p + 1) + k]);
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
    std::vector<int64_t>& rank = w.rank;
    rank.resize(n);
    for (int64_t i = 0; i < n; ++i) rank[i] = i;
    std::stable_sort(rank.begin(), rank.end(),
                     [&](int64_t x, int64_t y) { return centroid(lo, hi, x, ax) < centroid(lo, hi, y, ax); });
    for (int64_t r = n / 2; r < n; ++r) right[rank[r]] = 1;
}

// Stable partition of n rows of ROW values each, left rows (right[i] == 0) first; returns the left count. Only
// the right rows go through `spill`.
template <int ROW, typename T>
int64_t partition_rows(T* rows, int64_t n, const std::vector<char>& right, std::vector<T>& spill) {
    int64_t n_right = 0;
    for (int64_t i = 0; i < n; ++i) n_right += right[i];
    if ((int64_t)spill.size() < ROW * n_right) spill.resize(ROW * n_right);
    int64_t kept = 0, spilt = 0;
    for (int64_t i = 0; i < n; ++i) {
        T* to = right[i] ? &spill[ROW * spilt++] : rows + ROW * kept++;  // a left row moves down (kept <= i)
        for (int k = 0; k < ROW; ++k) to[k] = rows[ROW * i + k];
    }
    if (spilt) std::memcpy(rows + ROW * kept, spill.data(), ROW * spilt * sizeof(T));  // none: data() may be null
    return kept;
}

}  // namespace

extern "C" void nbvh_build_full_tree(float* tri_lo, float* tri_hi, int64_t n, int max_leaf_size, int n_bins,
                                     int median_below, int64_t capacity, float* node_lo, float* node_hi,
                                     int64_t* left, int64_t* start, int64_t* count, int32_t* depth, int64_t* order,
                                     int64_t* n_nodes, int64_t* control, int threads) {
    // tri_lo/tri_hi are the caller's scratch: row k holds the box of triangle order[k] from here on
    for (int64_t i = 0; i < n; ++i) order[i] = i;
    for (int a = 0; a < 3; ++a) node_lo[a] = INFINITY, node_hi[a] = -INFINITY;
    for (int64_t i = 0; i < n; ++i)
        for (int a = 0; a < 3; ++a)
            node_lo[a] = std::min(node_lo[a], tri_lo[3 * i + a]), node_hi[a] = std::max(node_hi[a], tri_hi[3 * i + a]);
    left[0] = -1, start[0] = 0, count[0] = n, depth[0] = 0;
    int64_t total = 1;
    std::vector<int64_t> active = {0};
    std::vector<Scratch> scratch(std::max(threads, 1));  // kept across levels: the top levels' spills are large
    for (int level = 1; total < capacity; ++level) {
        std::vector<int64_t> splitting;
        for (int64_t id : active)
            if (count[id] > max_leaf_size) splitting.push_back(id);
        if (splitting.empty()) break;
        if (__atomic_load_n(&control[1], __ATOMIC_RELAXED)) {  // stopped: no tree
            *n_nodes = -1;
            return;
        }
        const int64_t m = (int64_t)splitting.size();
        if (total + 2 * m > capacity) break;  // never: a full tree has at most 2n - 1 nodes
#pragma omp parallel num_threads(threads)
        {
            Scratch& w = scratch[omp_get_thread_num()];
#pragma omp for schedule(dynamic, 1)
            for (int64_t i = 0; i < m; ++i) {
                const int64_t id = splitting[i], s = start[id], c = count[id];
                float* lo_s = tri_lo + 3 * s;
                float* hi_s = tri_hi + 3 * s;
                split_node(lo_s, hi_s, c, n_bins, median_below, w);
                const int64_t n_left = partition_rows<1>(order + s, c, w.right, w.spill_ids);
                partition_rows<3>(lo_s, c, w.right, w.spill_box);
                partition_rows<3>(hi_s, c, w.right, w.spill_box);
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
                            lo[a] = std::min(lo[a], tri_lo[3 * k + a]), hi[a] = std::max(hi[a], tri_hi[3 * k + a]);
                    left[ch] = -1, start[ch] = cs, count[ch] = cc, depth[ch] = level;
                }
                __atomic_fetch_add(&control[0], c, __ATOMIC_RELAXED);
            }
        }
        active.clear();
        for (int64_t k = total; k < total + 2 * m; ++k) active.push_back(k);
        total += 2 * m;
    }
    *n_nodes = total;
}
