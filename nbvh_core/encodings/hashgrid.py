"""HashGrid: Instant-NGP's multiresolution hash encoding (L levels, T rows of F floats each, trilinear)."""
from __future__ import annotations

import torch
from torch import nn

from .. import kernels
from .base import EncodingConfig, corner_indices, gather_weighted_sum, level_scales
from .fused import GridSpec, fused_encode, fused_encode_half


class HashGrid(nn.Module):
    """points (N, 3) in [0, 1]^3 -> features (N, L * F), level-major.

    Parameters: `table` (L, T, F). The 8 corner lookups and the trilinear sum of all levels run as one
    `gather_weighted_sum` (gather + weighted sum; its backward scatters with index_add_, no sort) on the reference
    path, and as one fused C++ pass (`fused.fused_encode`) on the fast path (`nbvh_core.kernels`).
    """

    def __init__(self, cfg: EncodingConfig):
        super().__init__()
        self.cfg = cfg
        self.scales = level_scales(cfg)
        t = cfg.table_size
        self.table = nn.Parameter(torch.empty(cfg.levels, t, cfg.features).uniform_(-cfg.init_scale, cfg.init_scale))
        self._spec: GridSpec | None = None
        #: Inference with a float16 copy of the feature rows (fast path, no grad): half the bytes to gather.
        self.half_tables = False
        self._half: tuple | None = None

    @property
    def out_dim(self) -> int:
        return self.cfg.out_dim

    def row_table(self) -> torch.Tensor:
        """(L, T, F): the feature rows that vertices look up (for HashGrid, the table itself)."""
        return self.table

    def vertex_rows(self, idx: torch.Tensor) -> torch.Tensor:
        """Map per-level vertex indices (N, L, 8) to rows of `row_table()` (identity for HashGrid)."""
        return idx

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        if kernels.fast_enabled(points.device) and self.table.dtype == torch.float32:
            return self._fused_forward(points)
        return self.reference_forward(points)

    def _fused_forward(self, points: torch.Tensor) -> torch.Tensor:
        table, half, spec, codes, code_rows = self.fused_lookup()
        if half:
            return fused_encode_half(points, table, spec, codes, code_rows)
        return fused_encode(points, table, spec, codes, code_rows)

    def fused_lookup(self) -> tuple[torch.Tensor, bool, GridSpec, torch.Tensor | None, int]:
        """What a fused kernel reads: (rows (L, R, F) float32 or float16, is_half, geometry, frozen codes or None,
        rows the codes select from)."""
        rows, codes, code_rows = self._fused_rows()
        codes = None if codes is None else codes.contiguous()
        # The float16 copy is of the stored rows only (a soft HashVQAD table is recomputed every step).
        if self.half_tables and not torch.is_grad_enabled() and rows is self.table:
            return self._half_table(), True, self.grid_spec(), codes, code_rows
        return rows, False, self.grid_spec(), codes, code_rows

    def grid_spec(self) -> GridSpec:
        """The constant level geometry the fused kernels read (built once)."""
        if self._spec is None:
            self._spec = GridSpec(self.cfg, self._vertex_table_size())
        return self._spec

    def _fused_rows(self) -> tuple[torch.Tensor, torch.Tensor | None, int]:
        """What the kernel reads: the (L, R, F) rows, the frozen codes (or None) and the rows codes select from."""
        return self.table, None, 0

    def _half_table(self) -> torch.Tensor:
        """float16 copy of `table`, refreshed whenever the table changes (its version counter)."""
        key = (self.table.data_ptr(), self.table._version)
        if self._half is None or self._half[0] != key:
            self._half = (key, self.table.detach().to(torch.float16).contiguous())
        return self._half[1]

    def reference_forward(self, points: torch.Tensor) -> torch.Tensor:
        """The pure torch lookup (the reference the fused kernel is tested against)."""
        cfg = self.cfg
        idx, w = corner_indices(points, self.scales, self._vertex_table_size())
        rows = self.vertex_rows(idx)
        table = self.row_table()
        n_rows = table.shape[1]
        flat_rows = rows + (torch.arange(cfg.levels, device=rows.device) * n_rows)[None, :, None]
        out = gather_weighted_sum(table.reshape(-1, cfg.features), flat_rows.reshape(-1, 8),
                                  w.reshape(-1, 8).to(table.dtype))
        return out.reshape(points.shape[0], cfg.levels * cfg.features)

    def _vertex_table_size(self) -> int:
        return self.cfg.table_size

    def stored_bytes(self, float_bytes: int = 4) -> dict[str, int]:
        """Bytes of the stored tensors: {'features': L * T * F * float_bytes}."""
        return {"features": self.table.numel() * float_bytes}
