// The kernels' C ABI: every entry point declared once, here. kernels/bindings.py reads this file to call them, so
// each pointer parameter carries its contract in a comment: /* (shape) dtypes null */
//   shape   dimensions in the entry's scalar parameters (`b * k`, `levels`), integers, or ? (any);
//           the caller's array must have exactly that many elements (with a ?: a multiple of the rest)
//   dtypes  for `void*` data only: the element types it may hold (f32 f16 u8)
//   null    the pointer may be null (the argument None)
// The ABI version is this file's hash: bindings.py compares it with `nbvh_abi_hash()` of the library it loads.
// Tables: (levels, rows, features) rows per level, or with rows = 0 the reachable entries' rows only, level after
// level (HashVQAD's soft table). Grid geometry: scales (levels,) s_l, res (levels,) vertices per axis, dense
// (levels,) 1 for a densely indexed level, vertex_table T (HashGrid) or H (HashVQAD), codes the frozen HashVQAD
// codes bit-packed at code_bits each (null: rows are vertex indices), code_rows T. threads: OpenMP threads.
#pragma once
#include <cstdint>

extern "C" {

// The hash of this header the library was built from (-DNBVH_ABI_HASH, computed by kernels/library.py).
uint64_t nbvh_abi_hash();

// ---- encode.cpp: the fused grid lookup, out (n, levels * features) float32 ----
void nbvh_encode_forward(const float* points /* (n, 3) */, int64_t n, const float* table /* (?, features) */,
                         float* out /* (n, levels * features) */, int levels, int features,
                         const float* scales /* (levels) */, const int64_t* res /* (levels) */,
                         const uint8_t* dense /* (levels) */, int64_t vertex_table, int64_t rows,
                         const uint8_t* codes /* (?) null */, int64_t code_rows, int code_bits, int threads);

// With a float16 copy of the table; accumulates in float32.
void nbvh_encode_forward_f16(const float* points /* (n, 3) */, int64_t n, const void* table /* (?, features) f16 */,
                             float* out /* (n, levels * features) */, int levels, int features,
                             const float* scales /* (levels) */, const int64_t* res /* (levels) */,
                             const uint8_t* dense /* (levels) */, int64_t vertex_table, int64_t rows,
                             const uint8_t* codes /* (?) null */, int64_t code_rows, int code_bits, int threads);

// From uint8 codes: value = qoffset + code * qscale per level and feature.
void nbvh_encode_forward_u8(const float* points /* (n, 3) */, int64_t n, const uint8_t* table /* (?, features) */,
                            const float* qoffset /* (levels, features) */, const float* qscale /* (levels, features) */,
                            float* out /* (n, levels * features) */, int levels, int features,
                            const float* scales /* (levels) */, const int64_t* res /* (levels) */,
                            const uint8_t* dense /* (levels) */, int64_t vertex_table, int64_t rows,
                            const uint8_t* codes /* (?) null */, int64_t code_rows, int code_bits, int threads);

// grad_table is accumulated into (zero it first).
void nbvh_encode_backward(const float* points /* (n, 3) */, int64_t n, const float* grad_out /* (n, levels * features) */,
                          float* grad_table /* (?, features) */, int levels, int features,
                          const float* scales /* (levels) */, const int64_t* res /* (levels) */,
                          const uint8_t* dense /* (levels) */, int64_t vertex_table, int64_t rows,
                          const uint8_t* codes /* (?) null */, int64_t code_rows, int code_bits, int threads);

// ---- networks.cpp: a whole MLP (kmlp = 0) or KMLP (kmlp = 1) per (ray, leaf) segment ----
// Segment s is the part [te[s], tx[s]] of ray ray[s]; its k points sit at fractions frac. dims: the n_layers + 1
// layer widths; params: the layers packed (weights transposed, then bias) as float32 (weight_kind 0) or float16
// (1). table_kind 0 f32, 1 f16, 2 u8 (with qoffset/qscale). out: the raw outputs, (b, dims[n_layers]) for an MLP,
// (b, k - 1, dims[n_layers]) for a KMLP, or with decode = 1 a KMLP's first hit (b, 5): probability, local t,
// unit normal (pairs after a segment is decided are skipped).
void nbvh_net_segments(const float* rays_o /* (?, 3) */, const float* rays_d /* (?, 3) */,
                       const int64_t* ray /* (b) */, const float* te /* (b) */, const float* tx /* (b) */,
                       int64_t b, int k, const float* frac /* (k) */,
                       const void* table /* (?, features) f32 f16 u8 */, int table_kind,
                       const float* qoffset /* (levels, features) null */,
                       const float* qscale /* (levels, features) null */, int levels, int features,
                       const float* scales /* (levels) */, const int64_t* res /* (levels) */,
                       const uint8_t* dense /* (levels) */, int64_t vertex_table, int64_t rows,
                       const uint8_t* codes /* (?) null */, int64_t code_rows, int code_bits, int kmlp, int decode,
                       int n_layers, const int32_t* dims /* (n_layers + 1) */, const void* params /* (?) f32 f16 */,
                       int weight_kind, float* out /* (b, ?) */, int threads);

// One training step on b labelled segments: hit (b,), local_t (b,) in [0, 1], normal (b, 3); hit_count = hit rows.
// loss_out: bce, depth_l1, normal_l1, normal_unit (an MLP) or bce, segment_ce, depth_l1, normal_l1, normal_unit (a
// KMLP); grad_params packed like params, grad_table accumulated (zero it first); points and dx are scratch;
// out_raw the raw outputs when not null.
void nbvh_net_train(const float* rays_o /* (?, 3) */, const float* rays_d /* (?, 3) */,
                    const int64_t* ray /* (b) */, const float* te /* (b) */, const float* tx /* (b) */,
                    int64_t b, int k, const float* frac /* (k) */, const float* table /* (?, features) */,
                    int levels, int features, const float* scales /* (levels) */, const int64_t* res /* (levels) */,
                    const uint8_t* dense /* (levels) */, int64_t vertex_table, int64_t rows,
                    const uint8_t* codes /* (?) null */, int64_t code_rows, int code_bits, int kmlp, int n_layers,
                    const int32_t* dims /* (n_layers + 1) */, const float* params /* (?) */,
                    const uint8_t* hit /* (b) */, const float* local_t /* (b) */, const float* normal /* (b, 3) */,
                    int64_t hit_count, float w_t, float w_n, int unoriented, float w_unit,
                    double* loss_out /* (4 + kmlp) */, float* grad_params /* (?) */,
                    float* grad_table /* (?, features) */, float* points /* (b * k, 3) */, float* dx /* (b, ?) */,
                    float* out_raw /* (b, ?) null */, int threads);

// ---- vqad.cpp: HashVQAD's soft row table over the R reachable entries (R = sum of reach) ----
// soft[e] = sum_c softmax(logits[e] * inv_tau)_c table[level(e), cand[e mod T, c]]; t <= 256. needed: only the
// marked entries are computed (the others' soft rows zero, their probs unwritten).
void nbvh_vqad_soft_forward(const float* logits /* (?, t) */, const float* table /* (levels, T, F) */,
                            const int64_t* cand /* (T, t) */, const int64_t* reach /* (levels) */, int levels,
                            int64_t H, int64_t T, int t, int F, float inv_tau, const uint8_t* needed /* (?) null */,
                            float* probs /* (?, t) */, float* soft /* (?, F) */, int threads);

// Its backward: grad_table accumulated (zero it first), grad_logits written.
void nbvh_vqad_soft_backward(const float* probs /* (?, t) */, const float* table /* (levels, T, F) */,
                             const int64_t* cand /* (T, t) */, const int64_t* reach /* (levels) */,
                             const float* grad_soft /* (?, F) */, int levels, int64_t H, int64_t T, int t, int F,
                             float inv_tau, float* grad_table /* (levels, T, F) */, float* grad_logits /* (?, t) */,
                             int threads);

// needed[e] = 1 for every soft-table entry the k points of b segments (as nbvh_net_train's) read (zero it first).
void nbvh_mark_entries(const float* rays_o /* (?, 3) */, const float* rays_d /* (?, 3) */,
                       const int64_t* ray /* (b) */, const float* te /* (b) */, const float* tx /* (b) */,
                       int64_t b, int k, const float* frac /* (k) */, int levels, int features,
                       const float* scales /* (levels) */, const int64_t* res /* (levels) */,
                       const uint8_t* dense /* (levels) */, int64_t vertex_table, int64_t rows,
                       const uint8_t* codes /* (?) null */, int64_t code_rows, int code_bits,
                       uint8_t* needed /* (?) */, int threads);

// ---- traversal.cpp: BVH traversal of n rays (inv_d = 1 / direction) ----
// The next leaf of each live ray (traversal.LeafStream), popping its own stack (stack_node, stack_t, sp_arr: the
// state between calls); out_leaf -1 where the ray has none. Nodes: the 32-byte records (lo, hi float32, left, leaf
// int32) read in place.
void nbvh_stream_next(const float* rays_o /* (n, 3) */, const float* inv_d /* (n, 3) */, int64_t n,
                      const float* records /* (?, 8) */, int32_t* stack_node /* (n, depth) */,
                      float* stack_t /* (n, depth) */, int32_t* sp_arr /* (n) */, const float* t_max_arr /* (n) */,
                      int depth, int32_t* out_leaf /* (n) */, float* out_te /* (n) */, float* out_tx /* (n) */,
                      int threads);

// The same on the stored 8-bit nodes: codes relative to the parent's box, links 65535 = none; each stack entry
// carries its node's box.
void nbvh_stream_next_q(const float* rays_o /* (n, 3) */, const float* inv_d /* (n, 3) */, int64_t n,
                        const uint8_t* codes /* (?, 6) */, const uint16_t* node_left /* (?) */,
                        const uint16_t* node_leaf /* (?) */, int32_t* stack_node /* (n, depth) */,
                        float* stack_t /* (n, depth) */, float* stack_box /* (n, depth, 6) */,
                        int32_t* sp_arr /* (n) */, const float* t_max_arr /* (n) */, int depth,
                        int32_t* out_leaf /* (n) */, float* out_te /* (n) */, float* out_tx /* (n) */, int threads);

// Every ray's complete front-to-back leaf list, sorted by (t_enter, t_exit, node), held by the returned handle:
// counts per ray and the total are written; nbvh_leaves_collect copies the lists out and frees them.
void* nbvh_leaves_traverse(const float* rays_o /* (n, 3) */, const float* inv_d /* (n, 3) */, int64_t n,
                           const float* t_max_arr /* (n) null */, const float* node_lo /* (?, 3) */,
                           const float* node_hi /* (?, 3) */, const int32_t* node_left /* (?) */,
                           const int32_t* node_leaf /* (?) */, int depth, int64_t* counts /* (n) */,
                           int64_t* total /* (1) */, int threads);

// Copies the lists into out_node, out_te, out_tx (total,) each, ray after ray, and frees them (only frees them when
// out_node is null).
void nbvh_leaves_collect(void* handle, int64_t* out_node /* (?) null */, float* out_te /* (?) null */,
                         float* out_tx /* (?) null */);

// ---- mesh_codec.cpp: the compact mesh's cluster payloads (geometry/compact_mesh.py's encoder, byte for byte) ----
// Cluster k is faces[cluster_tris[cluster_start[k]:cluster_start[k + 1]]] (at most 64) on the global grid points
// `grid`; its payload is out[out_offset[k]:out_offset[k + 1]]. `out` holds at least the bound
// compact_mesh.payload_bound gives; per cluster: packed bit widths, vertex count, grid box (lo, hi).
void nbvh_encode_clusters(const int32_t* faces /* (?, 3) */, const int64_t* grid /* (?, 3) */,
                          const int64_t* cluster_tris /* (t) */, int64_t t, const int64_t* cluster_start /* (c + 1) */,
                          int64_t c, uint8_t* out /* (out_bytes) */, int64_t out_bytes,
                          int64_t* out_offset /* (c + 1) */, int64_t* widths /* (c) */, int64_t* n_verts /* (c) */,
                          int64_t* grid_lo /* (c, 3) */, int64_t* grid_hi /* (c, 3) */, int threads);

// ---- tree_build.cpp: the full binned-SAH tree (geometry/bvh.py build_full_tree's numpy code, node for node) ----
// Triangles' boxes in (centroids are their midpoints in float64; the arrays are scratch: left permuted as `order`);
// the tree's arrays out (capacity >= 2n - 1 rows), n_nodes[0] the rows used. control[0]: triangles split so far
// (the build's progress, written as it goes); control[1] != 0 (set by another thread) stops it before its next
// level, with n_nodes[0] = -1.
void nbvh_build_full_tree(float* tri_lo /* (n, 3) */, float* tri_hi /* (n, 3) */,
                          int64_t n, int max_leaf_size, int n_bins,
                          int median_below, int64_t capacity, float* node_lo /* (capacity, 3) */,
                          float* node_hi /* (capacity, 3) */, int64_t* left /* (capacity) */,
                          int64_t* start /* (capacity) */, int64_t* count /* (capacity) */,
                          int32_t* depth /* (capacity) */, int64_t* order /* (n) */, int64_t* n_nodes /* (1) */,
                          int64_t* control /* (2) */, int threads);

// ---- embree_rays.cpp: nearest hits in an Embree 4 scene the caller built (geometry/embree_scene.py) ----
// intersect: the library's rtcIntersect1, scene: its committed RTCScene (both handles from that library). Per
// ray: the nearest hit with 0 <= t <= t_max[i]; out_t the hit's t (t_max[i] on a miss), out_prim its triangle
// (-1 on a miss).
void nbvh_embree_first_hits(void* intersect, void* scene, const float* rays_o /* (n, 3) */,
                            const float* rays_d /* (n, 3) */, const float* t_max /* (n) */, int64_t n,
                            float* out_t /* (n) */, int32_t* out_prim /* (n) */, int threads);

}  // extern "C"
