"""HashGrid: Instant-NGP's multiresolution hash encoding (L levels, T rows of F floats each, trilinear)."""
from __future__ import annotations

import torch
from torch import nn

from ... import kernels
from .base import (Encoding, EncodingConfig, corner_indices, gather_weighted_sum, level_scales, spatial_hash,
                   vertex_resolution)
from .fused import FusedLookup, GridSpec, fused_encode, fused_encode_half, fused_encode_u8


class HashGrid(Encoding):
    """points (N, 3) in [0, 1]^3 -> features (N, L * F), level-major.

    Parameters: `table` (L, T, F). After `quantize_()` the rows live as uint8 codes (buffers `qcodes` (L, T, F),
    `qoffset`, `qscale` (L, F): value = offset + code * scale) and `table` is empty: the fast path reads the codes
    directly; the reference path (and CUDA) dequantizes per call. The 8 corner lookups and the trilinear sum of all levels run as one
    `gather_weighted_sum` (gather + weighted sum; its backward scatters with index_add_, no sort) on the reference
    path, and as one fused C++ pass (`fused.fused_encode`) on the fast path (`nbvh_core.kernels`).
    """

    grid_lookup = True

    def __init__(self, cfg: EncodingConfig, inference: bool = False):
        super().__init__()
        self.cfg = cfg
        self.scales = level_scales(cfg)
        t = cfg.table_size
        if inference:  # to be filled by the file reader (float rows or uint8 codes): nothing allocated here
            self.table = nn.Parameter(torch.zeros(0), requires_grad=False)
        else:
            self.table = nn.Parameter(torch.empty(cfg.levels, t, cfg.features).uniform_(-cfg.init_scale,
                                                                                        cfg.init_scale))
        self.register_buffer("qcodes", torch.zeros(0, dtype=torch.uint8), persistent=False)
        self.register_buffer("qoffset", torch.zeros(0), persistent=False)
        self.register_buffer("qscale", torch.zeros(0), persistent=False)
        #: (offset, scale) (L, F) float32 numpy the quantization-aware phase snapped the table to (train.py).
        self.qat_affine: tuple | None = None
        self._spec: GridSpec | None = None
        self._triton_geometry: tuple | None = None
        #: Inference with a float16 copy of the feature rows (fast path, no grad): half the bytes to gather.
        self.half_tables = False
        self._half: tuple | None = None

    @property
    def out_dim(self) -> int:
        return self.cfg.out_dim

    @property
    def quantized(self) -> bool:
        """True when the rows are held as uint8 codes (see `quantize_`)."""
        return self.qcodes.numel() > 0

    def float_rows(self) -> torch.Tensor:
        """(L, T, F) float32 feature rows (dequantized when quantized: a transient copy)."""
        if self.quantized:
            return self.qoffset[:, None, :] + self.qcodes.to(torch.float32) * self.qscale[:, None, :]
        return self.table

    @torch.no_grad()
    def quantize_(self, bits: int = 8) -> None:
        """Hold the rows as `bits`-bit codes from now on (inference only; irreversible). Uses the affine map the
        quantization-aware phase trained with when there was one (then the codes reproduce the trained values)."""
        from ..quantize import quantize_table, table_affine

        if self.quantized:
            return
        table = self.table.detach().cpu().numpy()
        offset, scale = self.qat_affine if self.qat_affine is not None else table_affine(table, bits)
        codes = quantize_table(table, offset, scale, bits)
        self.set_quantized(torch.from_numpy(codes), torch.from_numpy(offset), torch.from_numpy(scale))

    @torch.no_grad()
    def hold_as_stored(self, bits: int) -> None:
        """Hold the rows as a file with `bits`-bit features stores them: codes (8 or 4 bits, held one per uint8),
        rows rounded to float16 (16, unless already codes), as they are (32). Inference only; irreversible."""
        if bits <= 8:
            self.quantize_(bits)
        elif bits == 16 and not self.quantized:
            self.table.copy_(self.table.half().float())

    def set_quantized(self, codes: torch.Tensor, offset: torch.Tensor, scale: torch.Tensor) -> None:
        """Install uint8 codes (L, T, F) and their (L, F) float32 offset/scale; drops the float table."""
        dev = self.table.device
        self.qcodes = codes.to(dev, torch.uint8).contiguous()
        self.qoffset = offset.to(dev, torch.float32).contiguous()
        self.qscale = scale.to(dev, torch.float32).contiguous()
        self.table = nn.Parameter(torch.zeros(0, device=dev), requires_grad=False)
        self._half = None

    def can_grow(self) -> bool:
        """True while the table can double without changing what it encodes (`grow`): a HashGrid's float rows
        before quantization (HashVQAD's learned index, codes, or a quantization-aware table do not grow)."""
        return type(self) is HashGrid and not self.quantized and self.qat_affine is None and self.table.dim() == 3

    def grown_like(self, rows: torch.Tensor) -> torch.Tensor:
        """`rows` laid out like the table (L, T, F), as the table twice as large lays them out (`grown_rows`)."""
        return grown_rows(rows, self.scales, 2 * self.cfg.table_size)

    @torch.no_grad()
    def grow(self) -> nn.Parameter:
        """Double T, every point encoded exactly as before (`grown_rows`): training continues with twice the rows.
        Returns the new `table` parameter (the old one is no longer the encoding's)."""
        import dataclasses

        if not self.can_grow():
            raise ValueError("only a HashGrid's float table can grow")
        rows = self.grown_like(self.table.data)
        self.cfg = dataclasses.replace(self.cfg, log2_table=self.cfg.log2_table + 1)
        self.table = nn.Parameter(rows, requires_grad=self.table.requires_grad)
        self._spec, self._half, self._triton_geometry = None, None, None
        return self.table

    def row_table(self) -> torch.Tensor:
        """(L, T, F): the feature rows that vertices look up (for HashGrid, the table itself; see
        `level_row_offsets` for a table held in another layout)."""
        return self.float_rows()

    def vertex_rows(self, idx: torch.Tensor) -> torch.Tensor:
        """Map per-level vertex indices (N, L, 8) to rows of `row_table()` (identity for HashGrid)."""
        return idx

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        kind = kernels.encoding_kernel(self, points.device)
        if kind.startswith("triton"):
            return self._triton_forward(points)
        if kind != "torch":
            return self._fused_forward(points)
        return self.reference_forward(points)

    def _triton_forward(self, points: torch.Tensor) -> torch.Tensor:
        """The Triton lookup (`kernels.triton.hashgrid`; differentiable in `table` through its atomic backward; a
        shipped table's uint8 codes read as they are held)."""
        from ...kernels.triton.hashgrid import grid_encode, grid_encode_codes

        geometry = self.triton_geometry(points.device)
        if self.quantized:
            return grid_encode_codes(points, self.qcodes, self.qoffset, self.qscale, geometry)
        return grid_encode(points, self.triton_table(), geometry)

    def triton_table(self) -> torch.Tensor:
        """The float32 rows the Triton lookup reads (and its backward adds into): the table (L, T, F)."""
        return self.table

    def triton_geometry(self, device: torch.device):
        """The levels as the Triton kernels read them (`hashgrid.LevelGeometry`), built once per device and form."""
        key = (torch.device(device), *self._triton_form())
        if self._triton_geometry is None or self._triton_geometry[0] != key:
            self._triton_geometry = (key, self._level_geometry(torch.device(device)))
        return self._triton_geometry[1]

    def _triton_form(self) -> tuple:
        """What the geometry depends on besides the device (a HashVQAD's index)."""
        return ()

    def _level_geometry(self, device: torch.device):
        from ...kernels.triton.hashgrid import level_geometry

        return level_geometry(self.scales, [vertex_resolution(s) for s in self.scales], self.vertex_table_size(),
                              device, rows=self.cfg.table_size)

    def triton_rows(self, device: torch.device):
        """What the Triton ray query reads (`ray_query.GridRows`): the uint8 codes with their affine when the table
        is held as a file stores it, else the float32 table."""
        from ...kernels.triton.ray_query import GridRows

        geometry = self.triton_geometry(device)
        if self.quantized:
            return GridRows(self.qcodes, geometry, self.qoffset, self.qscale)
        return GridRows(self.triton_table().detach(), geometry)

    def _fused_forward(self, points: torch.Tensor) -> torch.Tensor:
        look = self.fused_lookup()
        if look.kind == "f16":
            return fused_encode_half(points, look.rows, look.spec, look.codes, look.code_rows)
        if look.kind == "u8":
            return fused_encode_u8(points, look)
        return fused_encode(points, look.rows, look.spec, look.codes, look.code_rows)

    def fused_lookup(self) -> FusedLookup:
        """What a fused kernel reads (see `FusedLookup`)."""
        rows, codes, code_rows = self._fused_rows()
        codes = None if codes is None else codes.contiguous()
        spec = self.grid_spec()
        if self.quantized:
            return FusedLookup(self.qcodes, "u8", spec, codes, code_rows, self.qoffset, self.qscale)
        if self.uses_half_rows():
            return FusedLookup(self._half_table(), "f16", spec, codes, code_rows)
        return FusedLookup(rows, "f32", spec, codes, code_rows)

    def uses_half_rows(self) -> bool:
        """True when inference reads the float16 copy of the rows (`half_tables`, no grad); the copy is of the
        stored rows only (a soft HashVQAD table is recomputed every step)."""
        return self.half_tables and not self.quantized and not torch.is_grad_enabled() and self._reads_table()

    def _reads_table(self) -> bool:
        """True when the kernels read `table` itself (not rows computed from it)."""
        return True

    def grid_spec(self) -> GridSpec:
        """The constant level geometry the fused kernels read (built once)."""
        if self._spec is None:
            self._spec = GridSpec(self.cfg, self.vertex_table_size())
        return self._spec

    def _fused_rows(self, needed: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor | None, int]:
        """What the kernel reads: the rows ((L, R, F), or (R, F) reachable rows level after level: `fused.level_rows`),
        the frozen codes (or None) and the rows codes select from. needed: the entries of a computed row table that
        will be read (`HashVQAD.row_table`); a stored table ignores it."""
        return self.table, None, 0

    def _half_table(self) -> torch.Tensor:
        """float16 copy of `table`, refreshed whenever the table changes (its version counter)."""
        table = self.table
        if self._half is None or self._half[0] is not table or self._half[1] != table._version:
            self._half = (table, table._version, table.detach().to(torch.float16).contiguous())
        return self._half[2]

    def reference_forward(self, points: torch.Tensor) -> torch.Tensor:
        """The pure torch lookup (the reference the fused kernel is tested against)."""
        cfg = self.cfg
        idx, w = corner_indices(points, self.scales, self.vertex_table_size())
        rows = self.vertex_rows(idx)
        table = self.row_table()
        flat_rows = rows + self.level_row_offsets(table).to(rows.device)[None, :, None]
        out = gather_weighted_sum(table.reshape(-1, cfg.features), flat_rows.reshape(-1, 8),
                                  w.reshape(-1, 8).to(table.dtype))
        return out.reshape(points.shape[0], cfg.levels * cfg.features)

    def level_row_offsets(self, table: torch.Tensor) -> torch.Tensor:
        """(L,) int64: the first row of each level in `table` (L, R, F) viewed as (L * R, F)."""
        return torch.arange(self.cfg.levels, device=table.device) * table.shape[1]

    def vertex_table_size(self) -> int:
        """H: the entries grid vertices index (dense or hashed mod H): T for a HashGrid."""
        return self.cfg.table_size

    def stored_bytes(self, table_bits: int = 32) -> dict[str, int]:
        """Bytes of the stored tensors: {'features': L * T * F * bits / 8 (+ the (L, F) offset and scale float32
        pairs of an 8-bit table)}."""
        return {"features": table_features_bytes(self.cfg, table_bits)}


def table_features_bytes(cfg: EncodingConfig, table_bits: int) -> int:
    """Stored bytes of a (L, T, F) table at `table_bits` per value (8 bits adds the per (level, feature) offset
    and scale, float32)."""
    n = cfg.levels * cfg.table_size * cfg.features
    extra = 2 * 4 * cfg.levels * cfg.features if table_bits <= 8 else 0
    return (n * table_bits + 7) // 8 + extra


@torch.no_grad()
def grown_rows(rows: torch.Tensor, scales: list[float], new_table_size: int) -> torch.Tensor:
    """The rows of the same grid with `new_table_size` (> T) rows per level that encode every point exactly as
    `rows` (L, T, F) do: for each new row, the old row its vertices read. A hashed level that stays hashed reads
    row hash mod T' = j, whose vertices read hash mod T = j mod T before (T' a multiple of T); a level the larger
    table indexes densely gets each vertex's old row; a dense level keeps its rows. Returns (L, T', F), the rows no
    vertex reads zero. Works on any tensor laid out like the table (Adam's moments too)."""
    levels, old_size, features = rows.shape
    if new_table_size <= old_size or new_table_size % old_size:
        raise ValueError(f"a table grows to a multiple of its {old_size} rows, not {new_table_size}")
    out = rows.new_zeros((levels, new_table_size, features))
    for level, scale in enumerate(scales):
        res = vertex_resolution(scale)
        if res ** 3 <= old_size:  # dense before and after: the same rows
            out[level, :res ** 3] = rows[level, :res ** 3]
        elif res ** 3 <= new_table_size:  # dense from now on: each vertex's old (hashed) row
            r = torch.arange(res, device=rows.device)
            grid = torch.stack(torch.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)[:, [2, 1, 0]]
            out[level, :res ** 3] = rows[level, spatial_hash(grid) % old_size]
        else:  # hashed before and after
            out[level] = rows[level, torch.arange(new_table_size, device=rows.device) % old_size]
    return out
