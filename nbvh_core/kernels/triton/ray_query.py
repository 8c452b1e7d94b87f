"""A model's whole ray query as one Triton kernel: per ray, front-to-back BVH traversal with its stack in
registers, each leaf's segment points, the hash-grid lookup at the stored precision (a HashVQAD's through its
index), the network through `tl.dot`, decode, stop at the first hit. The reference is `NeuralBVH.query` on the
torch path (`traversal.LeafStream` + `NeuralBVH.forward` + `Network.decode`); tests/test_triton_kernels.py holds
them equal under the interpreter.

Per program, BLOCK_R rays walk together in rounds: every ray with nodes left pops its stack (nearer child first,
ties to the left, as `LeafStream`) until it reaches its next leaf; then the block's rays that reached one run the
network on their segment together; a ray whose segment predicts a hit stops. A ray's stack is a (BLOCK_R, DEPTH)
register tile; the query never shortens a ray (it stops at the first predicted hit), so entries carry no t.

The network's first layer reads the segment's features 16 columns at a time, straight from the grid (column c of a
point's L*F features is level c // F, feature c % F), so every layer is a `tl.dot` of 16-column tiles whatever F
is. The output's normals are unit length but not yet turned to face the ray (the caller does, as the reference).

    hits = first_hits(rays_o, rays_d, inv_d, records, frac, grid, layers, kind="mlp")
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import triton
import triton.language as tl

from .bvh_walk import _box, _next_leaf, _xyz, stack_depth
from .hashgrid import LevelGeometry, _corner_row, _level_starts
from .mlp import PackedMLP

#: Rays per program and warps per program. Compiled for sm_90a on the CPU and read with `ptxas -v` at the default
#: preset's shape (bench/speed/kernel_registers.py): 32 rays on 8 warps with TF32 products spill nothing (MLP 224
#: registers, KMLP 254, the MLP through a HashVQAD's index 235; the KMLP over a training table's float32 rows spills
#: 96-116 B as the code around it moves); on 4 warps the KMLP spills 64 B; float32 ('ieee') or 'tf32x3' products
#: spill 0.6-0.9 KB. Not yet timed on a card.
BLOCK_R, WARPS = 32, 8
#: tl.dot's input precision on a card: 'tf32' (~1e-3 relative: a logit that close to its threshold may decide
#: otherwise than in float32) or 'ieee' (float32; agreement tests on a card). The interpreter multiplies in float32.
PRECISION = "tf32"


@dataclass(frozen=True)
class GridRows:
    """The hash grid as the kernel reads it: `rows` (L, T, F) or (R, F) float32, or uint8 codes with (L, F)
    float32 `offset` and `scale` (value = offset + code * scale, a shipped file's rows); `geometry` from
    `hashgrid.level_geometry` (the levels, and a HashVQAD's frozen index)."""

    rows: torch.Tensor
    geometry: LevelGeometry
    offset: torch.Tensor | None = None
    scale: torch.Tensor | None = None

    @property
    def codes(self) -> bool:
        return self.rows.dtype == torch.uint8


@dataclass(frozen=True)
class FirstHits:
    """hit (N,) bool; t (N,) float32 (inf on a miss); normal (N, 3) float32 unit (0 on a miss, not yet facing the
    ray); segments (N,) int32: the (ray, leaf) segments the network evaluated for each ray."""

    hit: torch.Tensor
    t: torch.Tensor
    normal: torch.Tensor
    segments: torch.Tensor


@triton.jit
def _features(grid_args, px, py, pz, col0, live, L: tl.constexpr, H: tl.constexpr, T: tl.constexpr,
              LISTED: tl.constexpr, F: tl.constexpr, BITS: tl.constexpr, CODES: tl.constexpr):
    """Columns col0 .. col0 + 15 of each point's L*F features (level-major): (BLOCK_R, 16) float32, 0 past L*F."""
    table_ptr, offset_ptr, scale_ptr, scales_ptr, res_ptr, dense_ptr, base_ptr, start_ptr, index_ptr = grid_args
    cols = col0 + tl.arange(0, 16)
    valid = cols < L * F
    level = tl.where(valid, cols // F, 0)
    feat = cols % F
    scale = tl.load(scales_ptr + level)[None, :]
    res = tl.load(res_ptr + level)[None, :]
    dense = tl.load(dense_ptr + level)[None, :]
    row_base, code_start = _level_starts(base_ptr, start_ptr, level, T, LISTED, BITS)
    row_base = row_base[None, :]
    code_start = code_start[None, :]
    mask = live[:, None] & valid[None, :]
    acc = tl.zeros((px.shape[0], 16), tl.float32)
    for c in tl.static_range(8):
        at, w = _corner_row(px[:, None], py[:, None], pz[:, None], scale, res, dense, row_base, code_start,
                            index_ptr, mask, H, T, BITS, c & 1, (c >> 1) & 1, (c >> 2) & 1)
        at = at * F + feat[None, :]
        row = tl.load(table_ptr + at, mask=mask, other=0)
        if CODES:  # uint8 codes: offset + code * scale per (level, feature), as `HashGrid.float_rows`
            row = (tl.load(offset_ptr + level * F + feat)[None, :]
                   + row.to(tl.float32) * tl.load(scale_ptr + level * F + feat)[None, :])
        acc += w * row
    return tl.where(mask, acc, 0.0)


@triton.jit
def _point(ox, oy, oz, dx, dy, dz, te, tx, frac):
    """A segment point t = t_enter + frac (t_exit - t_enter), clamped to the grid's [0, 1]^3 as the lookup does."""
    t = te + frac * (tx - te)
    px = tl.minimum(tl.maximum(ox + t * dx, 0.0), 1.0)
    py = tl.minimum(tl.maximum(oy + t * dy, 0.0), 1.0)
    pz = tl.minimum(tl.maximum(oz + t * dz, 0.0), 1.0)
    return px, py, pz


@triton.jit
def _first_layer_part(grid_args, px, py, pz, live, w_in_ptr, w_col0, acc, K_PAD: tl.constexpr, W: tl.constexpr,
                      L: tl.constexpr, H: tl.constexpr, T: tl.constexpr, LISTED: tl.constexpr, F: tl.constexpr,
                      BITS: tl.constexpr, CODES: tl.constexpr, PRECISION: tl.constexpr):
    """acc + one point's features times the first layer's columns w_col0 .. w_col0 + L*F - 1: (BLOCK_R, W)."""
    cols_w = tl.arange(0, W)
    for col0 in range(0, L * F, 16):  # a loop, not unrolled: unrolled, the loads of every tile were hoisted (spills)
        feats = _features(grid_args, px, py, pz, col0, live, L, H, T, LISTED, F, BITS, CODES)
        ks = col0 + tl.arange(0, 16)
        wk = tl.load(w_in_ptr + cols_w[None, :] * K_PAD + (w_col0 + ks)[:, None],
                     mask=(ks < L * F)[:, None], other=0.0)  # (16, W): W_in's columns, transposed
        acc += tl.dot(feats, wk, input_precision=PRECISION)
    return acc


@triton.jit
def _rest(pre, layers, W: tl.constexpr, HIDDEN: tl.constexpr, OUT_PAD: tl.constexpr, PRECISION: tl.constexpr):
    """The network after the first layer's product: (BLOCK_R, OUT_PAD) raw outputs."""
    b_in_ptr, w_hid_ptr, b_hid_ptr, w_out_ptr, b_out_ptr = layers
    cols_w = tl.arange(0, W)
    h = tl.maximum(pre + tl.load(b_in_ptr + cols_w)[None, :], 0.0)
    for layer in tl.static_range(HIDDEN):
        w = tl.load(w_hid_ptr + layer * W * W + cols_w[None, :] * W + cols_w[:, None])  # (W_in, W_out)
        h = tl.maximum(tl.dot(h, w, input_precision=PRECISION) + tl.load(b_hid_ptr + layer * W + cols_w)[None, :],
                       0.0)
    cols_o = tl.arange(0, OUT_PAD)
    w = tl.load(w_out_ptr + cols_o[None, :] * W + cols_w[:, None])  # (W, OUT_PAD)
    return tl.dot(h, w, input_precision=PRECISION) + tl.load(b_out_ptr + cols_o)[None, :]


@triton.jit
def _column(y, c: tl.constexpr):
    """Column c of a (rows, OUT_PAD) tile: (rows,)."""
    cols = tl.arange(0, y.shape[1])
    return tl.sum(tl.where(cols[None, :] == c, y, 0.0), axis=1)


@triton.jit
def _unit(x, y, z):
    """F.normalize: v / max(|v|, 1e-12)."""
    norm = tl.maximum(tl.sqrt(x * x + y * y + z * z), 1e-12)
    return x / norm, y / norm, z / norm


@triton.jit
def _softplus(x):
    return tl.maximum(x, 0.0) + tl.log(1.0 + tl.exp(-tl.abs(x)))


@triton.jit
def _mlp_segment(ray_args, te, tx, live, frac_ptr, grid_args, w_in_ptr, layers, K: tl.constexpr,
                 K_PAD: tl.constexpr, W: tl.constexpr, HIDDEN: tl.constexpr, OUT_PAD: tl.constexpr,
                 L: tl.constexpr, H: tl.constexpr, T: tl.constexpr, LISTED: tl.constexpr, F: tl.constexpr,
                 BITS: tl.constexpr, CODES: tl.constexpr, PRECISION: tl.constexpr):
    """`MLP.decode(forward(...))` of each ray's segment: (hit, local t, normal x, y, z)."""
    ox, oy, oz, dx, dy, dz = ray_args
    acc = tl.zeros((te.shape[0], W), tl.float32)
    for k in range(K):
        px, py, pz = _point(ox, oy, oz, dx, dy, dz, te, tx, tl.load(frac_ptr + k))
        acc = _first_layer_part(grid_args, px, py, pz, live, w_in_ptr, k * L * F, acc, K_PAD, W, L, H, T, LISTED,
                                F, BITS, CODES, PRECISION)
    y = _rest(acc, layers, W, HIDDEN, OUT_PAD, PRECISION)
    prob = 1.0 / (1.0 + tl.exp(-_column(y, 0)))
    local_t = 1.0 / (1.0 + tl.exp(-_column(y, 1)))
    nx, ny, nz = _unit(_column(y, 2), _column(y, 3), _column(y, 4))
    return prob > 0.5, local_t, nx, ny, nz


@triton.jit
def _kmlp_segment(ray_args, te, tx, live, frac_ptr, grid_args, w_in_ptr, layers, K: tl.constexpr,
                  K_PAD: tl.constexpr, W: tl.constexpr, HIDDEN: tl.constexpr, OUT_PAD: tl.constexpr,
                  L: tl.constexpr, H: tl.constexpr, T: tl.constexpr, LISTED: tl.constexpr, F: tl.constexpr,
                  BITS: tl.constexpr, CODES: tl.constexpr, PRECISION: tl.constexpr):
    """`KMLP.decode(forward(...))`: the pairs (point j, point j + 1) through the shared network, the first-hit
    distribution accumulated pair by pair (log q_j = log p_j + sum_{i<j} log(1 - p_i); the first argmax kept).
    Each pair looks its two points up afresh (inner points twice): carried between pairs, the first layer's half
    product spilled registers (ptxas, sm_90a)."""
    ox, oy, oz, dx, dy, dz = ray_args
    log_none = tl.zeros(te.shape, tl.float32)
    best = tl.full(te.shape, float("-inf"), tl.float32)
    best_j = tl.zeros(te.shape, tl.float32)
    best_t = tl.zeros(te.shape, tl.float32)
    bx = tl.zeros(te.shape, tl.float32)
    by = tl.zeros(te.shape, tl.float32)
    bz = tl.zeros(te.shape, tl.float32)
    for j in range(K - 1):
        pre = tl.zeros((te.shape[0], W), tl.float32)
        for half in range(2):  # point j against the first L*F input columns, point j + 1 against the next
            px, py, pz = _point(ox, oy, oz, dx, dy, dz, te, tx, tl.load(frac_ptr + j + half))
            pre = _first_layer_part(grid_args, px, py, pz, live, w_in_ptr, half * L * F, pre, K_PAD, W, L, H, T,
                                    LISTED, F, BITS, CODES, PRECISION)
        y = _rest(pre, layers, W, HIDDEN, OUT_PAD, PRECISION)
        logit = _column(y, 0)
        log_q = -_softplus(-logit) + log_none
        log_none += -_softplus(logit)
        better = log_q > best
        best = tl.where(better, log_q, best)
        best_j = tl.where(better, j * 1.0, best_j)
        best_t = tl.where(better, _column(y, 1), best_t)
        bx = tl.where(better, _column(y, 2), bx)
        by = tl.where(better, _column(y, 3), by)
        bz = tl.where(better, _column(y, 4), bz)
    local_t = (best_j + 1.0 / (1.0 + tl.exp(-best_t))) / (K - 1)
    nx, ny, nz = _unit(bx, by, bz)
    return 1.0 - tl.exp(log_none) > 0.5, local_t, nx, ny, nz


@triton.jit
def _ray_query(o_ptr, d_ptr, inv_ptr, n, rec_f_ptr, rec_i_ptr, frac_ptr,
               table_ptr, offset_ptr, scale_ptr, scales_ptr, res_ptr, dense_ptr, base_ptr, start_ptr, index_ptr,
               w_in_ptr, b_in_ptr, w_hid_ptr, b_hid_ptr, w_out_ptr, b_out_ptr,
               hit_ptr, t_ptr, normal_ptr, segments_ptr,
               L: tl.constexpr, H: tl.constexpr, T: tl.constexpr, LISTED: tl.constexpr, F: tl.constexpr,
               BITS: tl.constexpr, CODES: tl.constexpr, K: tl.constexpr,
               K_PAD: tl.constexpr, W: tl.constexpr, HIDDEN: tl.constexpr, OUT_PAD: tl.constexpr,
               KMLP: tl.constexpr, DEPTH: tl.constexpr, BR: tl.constexpr, PRECISION: tl.constexpr):
    rows = tl.program_id(0) * BR + tl.arange(0, BR)
    live = rows < n
    ox, oy, oz = _xyz(o_ptr, rows, live, 0.0)
    dx, dy, dz = _xyz(d_ptr, rows, live, 0.0)
    ix, iy, iz = _xyz(inv_ptr, rows, live, 1.0)
    ray_args = (ox, oy, oz, dx, dy, dz)
    grid_args = (table_ptr, offset_ptr, scale_ptr, scales_ptr, res_ptr, dense_ptr, base_ptr, start_ptr, index_ptr)
    layers = (b_in_ptr, w_hid_ptr, b_hid_ptr, w_out_ptr, b_out_ptr)
    slots = tl.arange(0, DEPTH)
    stack = tl.zeros((BR, DEPTH), tl.int32)  # slot 0: the root, node 0
    entered, _, _ = _box(rec_f_ptr, tl.zeros((BR,), tl.int32), live, ox, oy, oz, ix, iy, iz)
    sp = (live & entered).to(tl.int32)
    hit = sp < 0
    t_hit = tl.full((BR,), float("inf"), tl.float32)
    nx = tl.zeros((BR,), tl.float32)
    ny = tl.zeros((BR,), tl.float32)
    nz = tl.zeros((BR,), tl.float32)
    segments = tl.zeros((BR,), tl.int32)
    while tl.max(sp, axis=0) > 0:
        stack, sp, at_leaf, te, tx = _next_leaf(rec_f_ptr, rec_i_ptr, stack, sp, slots, ox, oy, oz, ix, iy, iz)
        if KMLP:
            is_hit, local_t, sx, sy, sz = _kmlp_segment(ray_args, te, tx, at_leaf, frac_ptr, grid_args, w_in_ptr,
                                                        layers, K, K_PAD, W, HIDDEN, OUT_PAD, L, H, T, LISTED, F,
                                                        BITS, CODES, PRECISION)
        else:
            is_hit, local_t, sx, sy, sz = _mlp_segment(ray_args, te, tx, at_leaf, frac_ptr, grid_args, w_in_ptr,
                                                       layers, K, K_PAD, W, HIDDEN, OUT_PAD, L, H, T, LISTED, F,
                                                       BITS, CODES, PRECISION)
        segments += at_leaf.to(tl.int32)
        new_hit = at_leaf & is_hit
        hit = hit | new_hit
        t_hit = tl.where(new_hit, te + local_t * (tx - te), t_hit)
        nx = tl.where(new_hit, sx, nx)
        ny = tl.where(new_hit, sy, ny)
        nz = tl.where(new_hit, sz, nz)
        sp = tl.where(new_hit, 0, sp)
    tl.store(hit_ptr + rows, hit.to(tl.int8), mask=live)
    tl.store(t_ptr + rows, t_hit, mask=live)
    tl.store(normal_ptr + rows * 3 + 0, nx, mask=live)
    tl.store(normal_ptr + rows * 3 + 1, ny, mask=live)
    tl.store(normal_ptr + rows * 3 + 2, nz, mask=live)
    tl.store(segments_ptr + rows, segments, mask=live)


def first_hits(rays_o: torch.Tensor, rays_d: torch.Tensor, records: torch.Tensor, max_depth: int,
               frac: torch.Tensor, grid: GridRows, layers: PackedMLP, kind: str,
               precision: str | None = None) -> FirstHits:
    """The first predicted hit of every ray, in one kernel launch.

    rays_o, rays_d: (N, 3) float32 (unit directions) on the model's device; records: (M, 8) float32 node records
    (`traversal.TorchBVH.records`: lo, hi, then left and leaf bit-cast int32), max_depth: the tree's depth;
    frac: (k,) float32 segment-point fractions (`torch.linspace(0, 1, k)`, as the reference); grid: the encoding's
    rows; layers: the network packed by `mlp.pack_mlp` (first layer's input: k points' features for 'mlp', a pair's
    for 'kmlp'); precision: tl.dot's input precision on a card (default `PRECISION`)."""
    n = rays_o.shape[0]
    dev = rays_o.device
    rays_o = rays_o.contiguous().float()
    rays_d = rays_d.contiguous().float()
    inv_d = (1.0 / rays_d).contiguous()  # 1/0 = inf: the slab test handles it, as `traversal.ray_box`
    records = records.contiguous()
    hit = torch.zeros(n, dtype=torch.int8, device=dev)
    t = torch.empty(n, dtype=torch.float32, device=dev)
    normal = torch.empty(n, 3, dtype=torch.float32, device=dev)
    segments = torch.empty(n, dtype=torch.int32, device=dev)
    if n == 0:
        return FirstHits(hit.bool(), t, normal, segments)
    features = grid.rows.shape[-1]
    offset = grid.offset if grid.codes else t  # unread unless codes
    scale = grid.scale if grid.codes else t
    _ray_query[(triton.cdiv(n, BLOCK_R),)](
        rays_o, rays_d, inv_d, n, records, records.view(torch.int32), frac.contiguous().float(),
        grid.rows.contiguous(), offset.contiguous().float(), scale.contiguous().float(), *grid.geometry.pointers(),
        layers.w_in, layers.b_in, layers.w_hidden, layers.b_hidden, layers.w_out, layers.b_out,
        hit, t, normal, segments,
        L=grid.geometry.levels, F=features, CODES=grid.codes, **grid.geometry.constants(), K=int(frac.numel()), K_PAD=layers.w_in.shape[1],
        W=layers.width, HIDDEN=layers.hidden, OUT_PAD=layers.w_out.shape[0], KMLP=kind == "kmlp",
        DEPTH=stack_depth(max_depth), BR=BLOCK_R, PRECISION=precision or PRECISION,
        num_warps=WARPS)
    return FirstHits(hit.bool(), t, normal, segments)
