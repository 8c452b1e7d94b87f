"""Fused grid lookup (the fast path of `HashGrid.forward` / `HashVQAD.forward`): one C++ pass per point computes
the cells, hashes, trilinear weights and the weighted row sums of all levels; see `nbvh_core.kernels`.

Same answer as `corner_indices` + `gather_weighted_sum` (tested in tests/test_fastpath.py).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from ...kernels import bindings
from .base import EncodingConfig, code_width, level_scales, vertex_resolution


class GridSpec:
    """The constant per-level geometry the kernel needs, as contiguous CPU tensors.

    vertex_table: the range of vertex indices (T for HashGrid, H for HashVQAD); levels whose (R)^3 vertices fit
    it are indexed densely (as `corner_indices`).
    """

    def __init__(self, cfg: EncodingConfig, vertex_table: int):
        scales = level_scales(cfg)
        res = [vertex_resolution(s) for s in scales]
        self.cfg = cfg
        self.vertex_table = vertex_table
        self.scales = torch.tensor(scales, dtype=torch.float32)
        self.res = torch.tensor(res, dtype=torch.int64)
        self.dense = torch.tensor([r ** 3 <= vertex_table for r in res], dtype=torch.uint8)
        self.code_bits = code_width(cfg.candidates)  # of frozen HashVQAD codes, when a lookup has them

    def args(self, rows: int, codes: torch.Tensor | None, code_rows: int) -> dict:
        """The grid's keyword arguments of a kernel call (nbvh_kernels.h): `rows` per level of the table (0: a
        soft table of the reachable entries), frozen `codes` or None and the `code_rows` they select from."""
        return dict(levels=self.cfg.levels, features=self.cfg.features, scales=self.scales, res=self.res,
                    dense=self.dense, vertex_table=self.vertex_table, rows=rows, codes=codes, code_rows=code_rows,
                    code_bits=self.code_bits)


def level_rows(table: torch.Tensor) -> int:
    """The kernels' `rows` argument for a row table: R of an (L, R, F) table, 0 for an (R, F) table that holds only
    the reachable entries' rows, level after level (HashVQAD's soft table; level l's first row is its first code's
    index, Grid.code_start in the kernel)."""
    return table.shape[1] if table.dim() == 3 else 0


@dataclass
class FusedLookup:
    """What a fused kernel reads: rows (L, R, F) of `kind` 'f32' | 'f16' | 'u8' (codes: value = offset + code *
    scale, offset/scale (L, F) float32), the level geometry, frozen HashVQAD codes or None, rows they select from."""

    rows: torch.Tensor
    kind: str
    spec: GridSpec
    codes: torch.Tensor | None
    code_rows: int
    offset: torch.Tensor | None = None
    scale: torch.Tensor | None = None

    #: The kernels' table type argument.
    KIND_ARG = {"f32": 0, "f16": 1, "u8": 2}

    def kernel_args(self) -> dict:
        """The table's keyword arguments of nbvh_net_segments."""
        return dict(table=self.rows, table_kind=self.KIND_ARG[self.kind], qoffset=self.offset, qscale=self.scale)


class _FusedEncode(torch.autograd.Function):
    @staticmethod
    def forward(ctx, points, table, spec, codes, code_rows):
        levels, feats = spec.cfg.levels, table.shape[-1]
        points = points.detach().contiguous()
        table_c = table.detach().contiguous()
        out = torch.empty((points.shape[0], levels * feats), dtype=torch.float32)
        args = spec.args(level_rows(table), codes, code_rows)
        bindings.encode_forward(points=points, n=points.shape[0], table=table_c, out=out, **args)
        ctx.save_for_backward(points)
        ctx.spec, ctx.codes, ctx.code_rows, ctx.table_shape = spec, codes, code_rows, table.shape
        return out

    @staticmethod
    def backward(ctx, grad):
        if not ctx.needs_input_grad[1]:
            return None, None, None, None, None
        (points,) = ctx.saved_tensors
        grad = grad.contiguous()
        g_table = torch.zeros(ctx.table_shape, dtype=torch.float32)
        args = ctx.spec.args(level_rows(g_table), ctx.codes, ctx.code_rows)
        bindings.encode_backward(points=points, n=points.shape[0], grad_out=grad, grad_table=g_table, **args)
        return None, g_table, None, None, None


def fused_encode(points: torch.Tensor, table: torch.Tensor, spec: GridSpec, codes: torch.Tensor | None = None,
                 code_rows: int = 0) -> torch.Tensor:
    """points (N, 3) float32 CPU in [0, 1]^3 (clamped); table (L, R, F) float32 rows (or (R, F): `level_rows`); codes uint8 frozen
    HashVQAD codes of the reachable entries, level after level, bit-packed (`spec.code_bits` each; rows =
    hash2(vertex, code) mod code_rows), or None (rows = vertex indices).
    Returns (N, L * F) float32, differentiable in `table`."""
    if codes is not None:
        codes = codes.contiguous()
    return _FusedEncode.apply(points.to(torch.float32), table, spec, codes, code_rows)


@torch.no_grad()
def fused_encode_half(points: torch.Tensor, table_half: torch.Tensor, spec: GridSpec,
                      codes: torch.Tensor | None = None, code_rows: int = 0) -> torch.Tensor:
    """Inference only: as `fused_encode` with a float16 copy of the table (L, R, F); accumulates in float32."""
    points = points.to(torch.float32).contiguous()
    out = torch.empty((points.shape[0], table_half.shape[0] * table_half.shape[2]), dtype=torch.float32)
    codes = None if codes is None else codes.contiguous()
    bindings.encode_forward_f16(points=points, n=points.shape[0], table=table_half, out=out,
                                **spec.args(table_half.shape[1], codes, code_rows))
    return out


@torch.no_grad()
def fused_encode_u8(points: torch.Tensor, look: FusedLookup) -> torch.Tensor:
    """Inference only: the lookup from uint8 rows (look.kind == 'u8'), dequantized per feature after the 8-corner
    sum (offset + scale * sum_c w_c code_c: exact, the weights sum to 1). Returns (N, L * F) float32."""
    points = points.to(torch.float32).contiguous()
    levels, rows, feats = look.rows.shape
    out = torch.empty((points.shape[0], levels * feats), dtype=torch.float32)
    bindings.encode_forward_u8(points=points, n=points.shape[0], table=look.rows, qoffset=look.offset,
                               qscale=look.scale, out=out, **look.spec.args(rows, look.codes, look.code_rows))
    return out
