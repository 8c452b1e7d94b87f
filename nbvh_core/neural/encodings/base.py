"""What every encoding shares: the config, the multiresolution grid geometry and the spatial hash.

Grid geometry follows tiny-cuda-nn: level l has scale s_l = N_min * b^l - 1 with b = (N_max / N_min)^(1/(L-1)),
a point x in [0, 1]^3 sits at p = s_l * x + 0.5 in grid units, its cell corner is floor(p) and the trilinear
weights come from p - floor(p). Grid vertices have integer coordinates 0..ceil(s_l) + 1 per axis. A vertex is
indexed densely (x + y*R + z*R^2) when the level's (R)^3 vertices fit the table, and otherwise by the spatial
hash of Instant-NGP: (x * 1) xor (y * 2654435761) xor (z * 805459861), taken on 32 bits, modulo the table size.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import ClassVar

import torch
import torch.nn.functional as F
from torch import nn

PRIMES = (1, 2654435761, 805459861)
MASK32 = 0xFFFFFFFF


@dataclass
class EncodingConfig:
    """kind: 'hashgrid' | 'hashvqad'. Paper defaults: L=4, N_min=16, N_max=128, F=16, H = T * 2^7, t=16.

    log2_table: log2 of T, the rows of F floats per level (the one size knob). index_factor: H / T (HashVQAD).
    candidates: t, the rows each HashVQAD index entry may choose from (stored in log2(t) bits).
    """

    kind: str = "hashvqad"
    levels: int = 4
    n_min: int = 16
    n_max: int = 128
    features: int = 16
    log2_table: int = 9
    index_factor: int = 128
    candidates: int = 16
    init_scale: float = 1e-4

    @property
    def table_size(self) -> int:
        return 1 << self.log2_table

    @property
    def index_size(self) -> int:
        return self.table_size * self.index_factor

    @property
    def out_dim(self) -> int:
        return self.levels * self.features

    def to_dict(self) -> dict:
        return asdict(self)


class Encoding(nn.Module):
    """The contract every encoding keeps (what the model, the trainer, the kernels' planner and the file use).

    * `forward(points (N, 3) float32 in [0, 1]^3) -> (N, out_dim) float32`; `out_dim`; `stored_bytes(table_bits)
      -> {component: bytes}` (what the file holds).
    * Capability flags, read instead of probing for methods: `grid_lookup` - a multiresolution grid the fused
      kernels read (`fused_lookup()`, `grid_spec()`; `kernels.plan` decides whether they do); `learned_index` - a
      soft index that is trained, annealed and frozen into integer codes (`schedule`, `freeze`, `frozen`).
    * Life cycle hooks the trainer calls (no-ops for a plain table): `schedule(fraction, cfg)` once per step with
      the training fraction in [0, 1] (sets e.g. the softmax temperature; returns the name of the phase it is in,
      or None for none of its own), `freeze_due(fraction, cfg)`, `freeze()`; `frozen` is True once the encoding is in the
      form the file stores.
    """

    grid_lookup: ClassVar[bool] = False
    learned_index: ClassVar[bool] = False

    @property
    def out_dim(self) -> int:
        raise NotImplementedError

    @property
    def frozen(self) -> bool:
        return True

    def schedule(self, fraction: float, cfg) -> str | None:
        return None

    def freeze_due(self, fraction: float, cfg) -> bool:
        return False

    def freeze(self) -> None:
        pass

    def can_grow(self) -> bool:
        """True when the encoding can double its table without changing what it encodes (HashGrid.grow)."""
        return False

    def stored_bytes(self, table_bits: int = 32) -> dict[str, int]:
        raise NotImplementedError


def level_scales(cfg: EncodingConfig) -> list[float]:
    """s_l per level (see module docstring)."""
    if cfg.levels == 1:
        return [cfg.n_min - 1.0]
    b = math.exp((math.log(cfg.n_max) - math.log(cfg.n_min)) / (cfg.levels - 1))
    return [cfg.n_min * b ** level - 1.0 for level in range(cfg.levels)]


def vertex_resolution(scale: float) -> int:
    """Grid vertices per axis of a level with scale s_l: coordinates 0..ceil(s_l) + 1 (module docstring)."""
    return int(math.ceil(scale)) + 2


def code_width(candidates: int) -> int:
    """Bits per HashVQAD code as held and stored: the smallest of 1, 2, 4, 8 that holds log2(t) (whole codes per
    byte, so a kernel reads one with a shift and a mask)."""
    need = max(1, math.ceil(math.log2(candidates)))
    return next(b for b in (1, 2, 4, 8) if b >= need)


def level_vertex_counts(cfg: EncodingConfig, vertex_table: int) -> list[int]:
    """How many distinct vertex indices each level can produce (the table entries it can ever read): R^3 on a
    level indexed densely (its R^3 vertices fit the vertex_table entries; R = `vertex_resolution`),
    else vertex_table (every hash value). Coarse levels of a large table reach only a part of it."""
    counts = []
    for s in level_scales(cfg):
        res = vertex_resolution(s)
        counts.append(res ** 3 if res ** 3 <= vertex_table else vertex_table)
    return counts


def spatial_hash(corner: torch.Tensor) -> torch.Tensor:
    """(..., 3) int64 vertex coordinates -> (...,) int64 32-bit hash."""
    h = (corner[..., 0] * PRIMES[0]) & MASK32
    h = h ^ ((corner[..., 1] * PRIMES[1]) & MASK32)
    h = h ^ ((corner[..., 2] * PRIMES[2]) & MASK32)
    return h


_CORNERS = torch.tensor([[(c >> 0) & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], dtype=torch.int64)


def corner_indices(points: torch.Tensor, scales: list[float], table_size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Table indices and trilinear weights of the 8 cell corners of every point at every level.

    points: (N, 3) float in [0, 1] (clamped). Returns index (N, L, 8) int64 in [0, table_size) and weight
    (N, L, 8) of points.dtype, summing to 1 over the corners.
    """
    x = points.clamp(0.0, 1.0)
    corners = _CORNERS.to(points.device)
    idx_levels, w_levels = [], []
    for s in scales:
        p = x * s + 0.5
        base = torch.floor(p)
        frac = p - base
        c = base.to(torch.int64)[:, None, :] + corners[None]  # (N, 8, 3)
        w3 = torch.where(corners[None].bool(), frac[:, None, :], 1.0 - frac[:, None, :])
        w = w3.prod(dim=-1)
        res = vertex_resolution(s)
        if res ** 3 <= table_size:
            idx = c[..., 0] + c[..., 1] * res + c[..., 2] * res * res
        else:
            idx = spatial_hash(c) % table_size
        idx_levels.append(idx)
        w_levels.append(w)
    return torch.stack(idx_levels, 1), torch.stack(w_levels, 1)


class _GatherWeightedSum(torch.autograd.Function):
    """out[b] = sum_c w[b, c] * table[idx[b, c]].

    Forward: embedding_bag's fused gather + weighted sum (never materialises the B x C gathered rows; 25x
    faster than index_select + einsum here). Backward: index_add_ (embedding_bag's own backward sorts the
    indices, which made HashVQAD's soft table 50x slower)."""

    @staticmethod
    def forward(ctx, table: torch.Tensor, idx: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(table, idx, w)
        return F.embedding_bag(idx, table, per_sample_weights=w, mode="sum")

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        table, idx, w = ctx.saved_tensors
        g_table = g_w = None
        if ctx.needs_input_grad[0]:
            g_table = torch.zeros_like(table)
            g_table.index_add_(0, idx.reshape(-1), (w[:, :, None] * grad[:, None, :]).reshape(-1, table.shape[1]))
        if ctx.needs_input_grad[2]:
            rows = table.index_select(0, idx.reshape(-1)).view(idx.shape[0], idx.shape[1], table.shape[1])
            g_w = torch.einsum("bcf,bf->bc", rows, grad)
        return g_table, None, g_w


def gather_weighted_sum(table: torch.Tensor, idx: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """table (R, F), idx (B, C) int64 rows, w (B, C) -> (B, F): the weighted sum of the C rows of each b.

    Differentiable in `table` and `w`. Same result as F.embedding_bag(mode='sum', per_sample_weights=w).
    """
    return _GatherWeightedSum.apply(table, idx, w)
