"""The hash-grid lookup as one Triton kernel per block of points, and its backward; the reference is
`neural.encodings.base.corner_indices` + `gather_weighted_sum` (`HashGrid.reference_forward`).

Per point and level l: p = x * s_l + 0.5 (float32, as the reference computes it), corner c = floor(p) + {0, 1}^3,
weight = product of frac or 1 - frac per axis (x, then y, then z), index = c_x + c_y R + c_z R^2 when the level's
R^3 vertices fit the T rows, else Instant-NGP's hash (c_x * 1) ^ (c_y * 2654435761) ^ (c_z * 805459861) on 32 bits,
mod T (T a power of two). out[n, l F + f] = sum over the 8 corners of weight * table[l, index, f].
The backward adds weight * grad into the table's gradient with atomics (on a GPU the order of the adds varies:
float32 sums agree to rounding, not bit for bit).

    out = grid_encode(points, table, geometry)             # (N, L*F); differentiable in `table`
    out = grid_encode_codes(points, codes, offset, scale, geometry)   # a shipped file's uint8 rows
"""
from __future__ import annotations

import torch
import triton
import triton.language as tl

#: Points per program. 64 keeps the 8 gathered (BLOCK, F) tiles of a level in registers for F = 16.
BLOCK = 64


@triton.jit
def _corner(x, y, z, scale, res, dense, T: tl.constexpr, cx: tl.constexpr, cy: tl.constexpr, cz: tl.constexpr):
    """Row index and trilinear weight of corner (cx, cy, cz) of each point's cell on one level."""
    px, py, pz = x * scale + 0.5, y * scale + 0.5, z * scale + 0.5
    bx, by, bz = tl.floor(px), tl.floor(py), tl.floor(pz)
    fx, fy, fz = px - bx, py - by, pz - bz
    wx = fx if cx == 1 else 1.0 - fx
    wy = fy if cy == 1 else 1.0 - fy
    wz = fz if cz == 1 else 1.0 - fz
    ix = bx.to(tl.int32) + cx
    iy = by.to(tl.int32) + cy
    iz = bz.to(tl.int32) + cz
    dense_index = ix + iy * res + iz * res * res
    h = (ix.to(tl.uint32) * 1) ^ (iy.to(tl.uint32) * 2654435761) ^ (iz.to(tl.uint32) * 805459861)
    hashed = (h & (T - 1)).to(tl.int32)
    return tl.where(dense != 0, dense_index, hashed), wx * wy * wz


@triton.jit
def _points(points_ptr, rows, live):
    """The block's points, clamped to [0, 1]^3 as the reference clamps them."""
    x = tl.minimum(tl.maximum(tl.load(points_ptr + rows * 3 + 0, mask=live, other=0.0), 0.0), 1.0)
    y = tl.minimum(tl.maximum(tl.load(points_ptr + rows * 3 + 1, mask=live, other=0.0), 0.0), 1.0)
    z = tl.minimum(tl.maximum(tl.load(points_ptr + rows * 3 + 2, mask=live, other=0.0), 0.0), 1.0)
    return x, y, z


@triton.jit
def _encode_forward(points_ptr, table_ptr, scales_ptr, res_ptr, dense_ptr, out_ptr, n, offset_ptr, scale_ptr,
                    L: tl.constexpr, T: tl.constexpr, F: tl.constexpr, BLOCK_N: tl.constexpr, CODES: tl.constexpr):
    rows = tl.program_id(0) * BLOCK_N + tl.arange(0, BLOCK_N)
    live = rows < n
    feats = tl.arange(0, F)
    x, y, z = _points(points_ptr, rows, live)
    for level in tl.static_range(L):
        scale = tl.load(scales_ptr + level)
        res = tl.load(res_ptr + level)
        dense = tl.load(dense_ptr + level)
        acc = tl.zeros((BLOCK_N, F), dtype=tl.float32)
        if CODES:  # uint8 codes: value = offset + code * scale per (level, feature), as `HashGrid.float_rows`
            q_off = tl.load(offset_ptr + level * F + feats)[None, :]
            q_scale = tl.load(scale_ptr + level * F + feats)[None, :]
        for c in tl.static_range(8):
            idx, w = _corner(x, y, z, scale, res, dense, T, c & 1, (c >> 1) & 1, (c >> 2) & 1)
            base = (level * T + idx).to(tl.int64) * F
            row = tl.load(table_ptr + base[:, None] + feats[None, :], mask=live[:, None], other=0)
            if CODES:
                row = q_off + row.to(tl.float32) * q_scale
            acc += w[:, None] * row
        tl.store(out_ptr + rows[:, None].to(tl.int64) * (L * F) + level * F + feats[None, :], acc, mask=live[:, None])


@triton.jit
def _encode_backward(points_ptr, grad_ptr, scales_ptr, res_ptr, dense_ptr, grad_table_ptr, n,
                     L: tl.constexpr, T: tl.constexpr, F: tl.constexpr, BLOCK_N: tl.constexpr):
    rows = tl.program_id(0) * BLOCK_N + tl.arange(0, BLOCK_N)
    live = rows < n
    feats = tl.arange(0, F)
    x, y, z = _points(points_ptr, rows, live)
    for level in tl.static_range(L):
        scale = tl.load(scales_ptr + level)
        res = tl.load(res_ptr + level)
        dense = tl.load(dense_ptr + level)
        g = tl.load(grad_ptr + rows[:, None].to(tl.int64) * (L * F) + level * F + feats[None, :], mask=live[:, None],
                    other=0.0)
        for c in tl.static_range(8):
            idx, w = _corner(x, y, z, scale, res, dense, T, c & 1, (c >> 1) & 1, (c >> 2) & 1)
            base = (level * T + idx).to(tl.int64) * F
            tl.atomic_add(grad_table_ptr + base[:, None] + feats[None, :], w[:, None] * g, mask=live[:, None])


def level_geometry(scales: list[float], resolutions: list[int], table_size: int,
                   device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(scales (L,) float32, vertex resolution R (L,) int32, dense (L,) int32) of a grid's levels, as the kernels
    read them: `scales` and `resolutions` (R per level, `neural.encodings.base.vertex_resolution`) from the
    encoding; a level is dense when R^3 <= T."""
    res = list(resolutions)
    return (torch.tensor(scales, dtype=torch.float32, device=device),
            torch.tensor(res, dtype=torch.int32, device=device),
            torch.tensor([int(r ** 3 <= table_size) for r in res], dtype=torch.int32, device=device))


def _launch(kernel, points, data, geometry, out, table_shape, **extra):
    levels, rows, features = table_shape
    n = points.shape[0]
    kernel[(triton.cdiv(n, BLOCK),)](points, data, *geometry, out, n, L=levels, T=rows, F=features, BLOCK_N=BLOCK,
                                     **extra)


class _GridEncode(torch.autograd.Function):
    @staticmethod
    def forward(ctx, points, table, geometry):
        points = points.contiguous().float()
        out = torch.empty(points.shape[0], table.shape[0] * table.shape[2], device=points.device)
        _launch(_encode_forward, points, table.contiguous(), geometry, out, table.shape, offset_ptr=out,
                scale_ptr=out, CODES=False)
        ctx.save_for_backward(points)
        ctx.geometry, ctx.shape = geometry, table.shape
        return out

    @staticmethod
    def backward(ctx, grad):
        (points,) = ctx.saved_tensors
        grad_table = torch.zeros(ctx.shape, device=points.device)
        _launch(_encode_backward, points, grad.contiguous().float(), ctx.geometry, grad_table, ctx.shape)
        return None, grad_table, None


def grid_encode_codes(points: torch.Tensor, codes: torch.Tensor, offset: torch.Tensor, scale: torch.Tensor,
                      geometry: tuple) -> torch.Tensor:
    """The lookup of a table held as uint8 codes (L, T, F) with (L, F) float32 offset and scale (a shipped file's
    rows, `HashGrid.set_quantized`): (N, L*F) float32, inference only."""
    points = points.contiguous().float()
    out = torch.empty(points.shape[0], codes.shape[0] * codes.shape[2], device=points.device)
    _launch(_encode_forward, points, codes.contiguous(), geometry, out, codes.shape,
            offset_ptr=offset.contiguous().float(), scale_ptr=scale.contiguous().float(), CODES=True)
    return out


def grid_encode(points: torch.Tensor, table: torch.Tensor, geometry: tuple) -> torch.Tensor:
    """points (N, 3) float32 in [0, 1]^3 (clamped), table (L, T, F) float32 (T a power of two, F a power of two
    >= 16 for the GPU's tiles), geometry: `level_geometry(...)` -> (N, L*F) float32, level-major. Differentiable in
    `table` (the backward's atomics)."""
    return _GridEncode.apply(points, table, geometry)
