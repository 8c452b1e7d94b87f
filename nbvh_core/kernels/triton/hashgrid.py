"""The hash-grid lookup as one Triton kernel per block of points, and its backward; the reference is
`neural.encodings.base.corner_indices` + `gather_weighted_sum` (`HashGrid.reference_forward`, and HashVQAD's).

Per point and level l: p = x * s_l + 0.5 (float32, as the reference computes it), corner c = floor(p) + {0, 1}^3,
weight = product of frac or 1 - frac per axis (x, then y, then z), vertex i = c_x + c_y R + c_z R^2 when the level's
R^3 vertices fit the H vertex entries, else Instant-NGP's hash (c_x * 1) ^ (c_y * 2654435761) ^ (c_z * 805459861) on
32 bits, mod H (a power of two). The row the vertex reads: row_base[l] + i for a HashGrid (H = T rows per level) and
for HashVQAD's soft row table (row_base = the level's first reachable entry); for a frozen HashVQAD (`code_bits` > 0)
row_base[l] + hash2(i, code) mod T, the code read from the bit-packed index at code_start[l] + i (hash2(i, j) =
(i * 2654435761) xor (j * 805459861) on 32 bits, `hashvqad.candidate_rows`).
out[n, l F + f] = sum over the 8 corners of weight * table[row, f].
The backward adds weight * grad into the table's gradient with atomics (on a GPU the order of the adds varies:
float32 sums agree to rounding, not bit for bit).

    out = grid_encode(points, table, geometry)             # (N, L*F); differentiable in `table`
    out = grid_encode_codes(points, codes, offset, scale, geometry)   # a shipped file's uint8 rows
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import triton
import triton.language as tl

#: Points per program. 64 keeps the 8 gathered (BLOCK, F) tiles of a level in registers for F = 16.
BLOCK = 64


@dataclass(frozen=True)
class LevelGeometry:
    """A grid's levels as the kernels read them (`level_geometry`): per level (L,) the scale (float32), the vertex
    resolution R (int32), dense (int32: R^3 <= H), the first row (int32, rows of the table viewed as (rows, F)) and
    the first code of a learned index (int32); `vertex_table` H (vertex hashes mod H), `rows` T (the rows per level
    a code selects among), `listed` (the first rows are not l * T: read from `row_base`), `code_bits` (0: vertices
    read their rows directly; else HashVQAD's frozen index, bits per code) and `index` (the bit-packed codes (C,)
    uint8, or None). What is not needed is not read: the kernels' registers are the ray query's limit."""

    scales: torch.Tensor
    resolution: torch.Tensor
    dense: torch.Tensor
    row_base: torch.Tensor
    code_start: torch.Tensor
    vertex_table: int
    rows: int
    listed: bool = False
    code_bits: int = 0
    index: torch.Tensor | None = None

    @property
    def levels(self) -> int:
        return self.scales.numel()

    def pointers(self) -> tuple:
        """The per-level tensors and the index, in the kernels' argument order (the index: a placeholder when
        there is none, never read)."""
        index = self.index if self.index is not None else self.code_start
        return self.scales, self.resolution, self.dense, self.row_base, self.code_start, index

    def constants(self) -> dict:
        return dict(H=self.vertex_table, T=self.rows, LISTED=self.listed, BITS=self.code_bits)


@triton.jit
def _corner(x, y, z, scale, res, dense, H: tl.constexpr, cx: tl.constexpr, cy: tl.constexpr, cz: tl.constexpr):
    """Vertex index (in [0, H)) and trilinear weight of corner (cx, cy, cz) of each point's cell on one level."""
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
    hashed = (h & (H - 1)).to(tl.int32)
    return tl.where(dense != 0, dense_index, hashed), wx * wy * wz


@triton.jit
def _level_starts(base_ptr, start_ptr, level, T: tl.constexpr, LISTED: tl.constexpr, BITS: tl.constexpr):
    """The level's first row (int32) and first code (int32; 0 without an index), loaded only where needed."""
    if LISTED:
        row_base = tl.load(base_ptr + level)
    else:
        row_base = level * T
    if BITS > 0:
        code_start = tl.load(start_ptr + level)
    else:
        code_start = level * 0
    return row_base, code_start


@triton.jit
def _corner_row(x, y, z, scale, res, dense, row_base, code_start, index_ptr, live, H: tl.constexpr,
                T: tl.constexpr, BITS: tl.constexpr, cx: tl.constexpr, cy: tl.constexpr, cz: tl.constexpr):
    """Row (int64, of the table viewed as (rows, F)) and trilinear weight of corner (cx, cy, cz): the vertex's own
    row, or through a frozen learned index (BITS > 0) the candidate row its code names (module docstring)."""
    vertex, w = _corner(x, y, z, scale, res, dense, H, cx, cy, cz)
    row = vertex
    if BITS > 0:
        pos = code_start + vertex
        byte = tl.load(index_ptr + pos // (8 // BITS), mask=live, other=0).to(tl.int32)
        code = (byte >> ((pos % (8 // BITS)) * BITS)) & ((1 << BITS) - 1)
        h = (vertex.to(tl.uint32) * 2654435761) ^ (code.to(tl.uint32) * 805459861)
        row = (h & (T - 1)).to(tl.int32)
    return (row_base + row).to(tl.int64), w


@triton.jit
def _points(points_ptr, rows, live):
    """The block's points, clamped to [0, 1]^3 as the reference clamps them."""
    x = tl.minimum(tl.maximum(tl.load(points_ptr + rows * 3 + 0, mask=live, other=0.0), 0.0), 1.0)
    y = tl.minimum(tl.maximum(tl.load(points_ptr + rows * 3 + 1, mask=live, other=0.0), 0.0), 1.0)
    z = tl.minimum(tl.maximum(tl.load(points_ptr + rows * 3 + 2, mask=live, other=0.0), 0.0), 1.0)
    return x, y, z


@triton.jit
def _encode_forward(points_ptr, table_ptr, scales_ptr, res_ptr, dense_ptr, base_ptr, start_ptr, index_ptr, out_ptr,
                    n, offset_ptr, scale_ptr, L: tl.constexpr, H: tl.constexpr, T: tl.constexpr, F: tl.constexpr,
                    LISTED: tl.constexpr, BITS: tl.constexpr, BLOCK_N: tl.constexpr, CODES: tl.constexpr):
    rows = tl.program_id(0) * BLOCK_N + tl.arange(0, BLOCK_N)
    live = rows < n
    feats = tl.arange(0, F)
    x, y, z = _points(points_ptr, rows, live)
    for level in tl.static_range(L):
        scale = tl.load(scales_ptr + level)
        res = tl.load(res_ptr + level)
        dense = tl.load(dense_ptr + level)
        row_base, code_start = _level_starts(base_ptr, start_ptr, level, T, LISTED, BITS)
        acc = tl.zeros((BLOCK_N, F), dtype=tl.float32)
        if CODES:  # uint8 codes: value = offset + code * scale per (level, feature), as `HashGrid.float_rows`
            q_off = tl.load(offset_ptr + level * F + feats)[None, :]
            q_scale = tl.load(scale_ptr + level * F + feats)[None, :]
        for c in tl.static_range(8):
            at, w = _corner_row(x, y, z, scale, res, dense, row_base, code_start, index_ptr, live, H, T, BITS,
                                c & 1, (c >> 1) & 1, (c >> 2) & 1)
            row = tl.load(table_ptr + at[:, None] * F + feats[None, :], mask=live[:, None], other=0)
            if CODES:
                row = q_off + row.to(tl.float32) * q_scale
            acc += w[:, None] * row
        tl.store(out_ptr + rows[:, None].to(tl.int64) * (L * F) + level * F + feats[None, :], acc, mask=live[:, None])


@triton.jit
def _encode_backward(points_ptr, grad_ptr, scales_ptr, res_ptr, dense_ptr, base_ptr, start_ptr, index_ptr,
                     grad_table_ptr, n, L: tl.constexpr, H: tl.constexpr, T: tl.constexpr, F: tl.constexpr,
                     LISTED: tl.constexpr, BITS: tl.constexpr, BLOCK_N: tl.constexpr):
    rows = tl.program_id(0) * BLOCK_N + tl.arange(0, BLOCK_N)
    live = rows < n
    feats = tl.arange(0, F)
    x, y, z = _points(points_ptr, rows, live)
    for level in tl.static_range(L):
        scale = tl.load(scales_ptr + level)
        res = tl.load(res_ptr + level)
        dense = tl.load(dense_ptr + level)
        row_base, code_start = _level_starts(base_ptr, start_ptr, level, T, LISTED, BITS)
        g = tl.load(grad_ptr + rows[:, None].to(tl.int64) * (L * F) + level * F + feats[None, :], mask=live[:, None],
                    other=0.0)
        for c in tl.static_range(8):
            at, w = _corner_row(x, y, z, scale, res, dense, row_base, code_start, index_ptr, live, H, T, BITS,
                                c & 1, (c >> 1) & 1, (c >> 2) & 1)
            tl.atomic_add(grad_table_ptr + at[:, None] * F + feats[None, :], w[:, None] * g, mask=live[:, None])


def level_geometry(scales: list[float], resolutions: list[int], vertex_table: int, device, rows: int | None = None,
                   row_starts: list[int] | None = None, code_starts: list[int] | None = None, code_bits: int = 0,
                   index: torch.Tensor | None = None) -> LevelGeometry:
    """A grid's levels as the kernels read them: `scales` and `resolutions` (R per level,
    `neural.encodings.base.vertex_resolution`) from the encoding; a level is dense when R^3 <= `vertex_table` (H,
    a power of two). rows: T, the rows per level (default H); row_starts: each level's first row (default l * T);
    code_starts, code_bits, index: a frozen learned index (HashVQAD: its codes' level offsets, bits per code and the
    bit-packed codes), else none."""
    res = list(resolutions)
    rows = vertex_table if rows is None else rows
    starts = [level * rows for level in range(len(res))] if row_starts is None else list(row_starts)
    codes = [0] * len(res) if code_starts is None else list(code_starts)
    if vertex_table & (vertex_table - 1) or rows & (rows - 1):
        raise ValueError(f"the kernels hash into powers of two, not H = {vertex_table}, T = {rows}")
    return LevelGeometry(torch.tensor(scales, dtype=torch.float32, device=device),
                         torch.tensor(res, dtype=torch.int32, device=device),
                         torch.tensor([int(r ** 3 <= vertex_table) for r in res], dtype=torch.int32, device=device),
                         torch.tensor(starts, dtype=torch.int32, device=device),
                         torch.tensor(codes, dtype=torch.int32, device=device),
                         vertex_table, rows, row_starts is not None, code_bits,
                         None if index is None else index.to(device).contiguous())


def _launch(kernel, points, data, geometry: LevelGeometry, out, features: int, **extra):
    n = points.shape[0]
    kernel[(triton.cdiv(n, BLOCK),)](points, data, *geometry.pointers(), out, n, L=geometry.levels, F=features,
                                     BLOCK_N=BLOCK, **geometry.constants(), **extra)


class _GridEncode(torch.autograd.Function):
    @staticmethod
    def forward(ctx, points, table, geometry):
        points = points.contiguous().float()
        features = table.shape[-1]
        out = torch.empty(points.shape[0], geometry.levels * features, device=points.device)
        _launch(_encode_forward, points, table.contiguous(), geometry, out, features, offset_ptr=out,
                scale_ptr=out, CODES=False)
        ctx.save_for_backward(points)
        ctx.geometry, ctx.shape = geometry, table.shape
        return out

    @staticmethod
    def backward(ctx, grad):
        (points,) = ctx.saved_tensors
        grad_table = torch.zeros(ctx.shape, device=points.device)
        _launch(_encode_backward, points, grad.contiguous().float(), ctx.geometry, grad_table, ctx.shape[-1])
        return None, grad_table, None


def grid_encode_codes(points: torch.Tensor, codes: torch.Tensor, offset: torch.Tensor, scale: torch.Tensor,
                      geometry: LevelGeometry) -> torch.Tensor:
    """The lookup of a table held as uint8 codes (L, T, F) with (L, F) float32 offset and scale (a shipped file's
    rows, `HashGrid.set_quantized`): (N, L*F) float32, inference only."""
    points = points.contiguous().float()
    out = torch.empty(points.shape[0], geometry.levels * codes.shape[-1], device=points.device)
    _launch(_encode_forward, points, codes.contiguous(), geometry, out, codes.shape[-1],
            offset_ptr=offset.contiguous().float(), scale_ptr=scale.contiguous().float(), CODES=True)
    return out


def grid_encode(points: torch.Tensor, table: torch.Tensor, geometry: LevelGeometry) -> torch.Tensor:
    """points (N, 3) float32 in [0, 1]^3 (clamped), table (L, T, F) or (rows, F) float32 (F a power of two),
    geometry: `level_geometry(...)` -> (N, L*F) float32, level-major. Differentiable in `table` (the backward's
    atomics)."""
    return _GridEncode.apply(points, table, geometry)
