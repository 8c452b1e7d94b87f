// The fused grid lookup's entries (encodings/fused.py): forward from float32, float16 or uint8 rows, backward.
#include "grid.h"

extern "C" {

// Inference with a float16 copy of the table (same arguments as nbvh_encode_forward; table is (L, rows, F) half).
void nbvh_encode_forward_f16(const float* points, int64_t n, const void* table, float* out, int levels, int features,
                             const float* scales, const int64_t* res, const uint8_t* dense, int64_t vertex_table,
                             int64_t rows, const uint8_t* codes, int64_t code_rows, int code_bits, int threads) {
    Grid g{levels, features, scales, res, dense, vertex_table, rows, codes, code_rows, code_bits};
    g.init_masks();
    const _Float16* t = static_cast<const _Float16*>(table);
    by_features(features, [&](auto F) { encode_forward_t<decltype(F)::value, _Float16>(g, points, n, t, out, threads); });
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

}  // extern "C"
