// BVH traversal (geometry/traversal.py): the front-to-back leaf stream with early termination, and complete
// sorted leaf lists per ray.
#include "common.h"

namespace {

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

}  // namespace

extern "C" {

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
