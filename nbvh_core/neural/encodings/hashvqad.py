"""HashVQAD: a hash grid whose vertices reach the feature rows through a learned index table.

Per level: an index table I of H entries (the grid vertex hashes into I exactly as HashGrid's vertices hash
into V) and the feature table V of T rows of F floats. Entry i may point at t candidate rows,
candidate j being row hash2(i, j) mod T with hash2(i, j) = (i * 2654435761) xor (j * 805459861) on 32 bits.

* Training (soft): entry i holds t logits; its feature is the softmax(logits / tau)-weighted sum of its t
  candidate rows. Computed for all (reachable) entries at once as a "soft row table" S (cost H * t * F per level
  per step, independent of the batch size), after which vertex lookups are the same 8-corner weighted sum as
  HashGrid's, into S. Because T is a power of two, hash2(i, j) mod T = (i * P1 mod T) xor (j * P2 mod T), and
  i * P1 mod T depends only on i mod T: the H = M * T entries split into M groups of T that share their
  candidate rows, so S is one dense batched matmul softmax (M, T, t) x rows (T, t, F) per level, forward and
  backward (no scatter over H * t candidates).
* Annealing: `temperature` is lowered (geometrically, by the trainer) so the softmax approaches a one-hot.
* Frozen (hard): `freeze()` stores argmax_j logits as one integer in [0, t) per entry (log2(t) bits each, bit
  packed in the file); a vertex then looks up row hash2(i, I[i]) mod T directly.
* Reachable entries: a coarse level indexed densely reads only its R^3 < H entries (`reachable_entries`; with the
  paper's H = 128 T most coarse levels do: at T=2^9 and N_max 64, 4,913 and 19,683 of 65,536). Only those have
  logits, soft rows (S is (R, F), R their number over all levels, level after level) and, once frozen, codes, held
  and stored (file format 2.2) level after level: the rest would train nothing. The function is the paper's; its
  bytes and the soft phase's work (softmax, its backward, Adam over the logits) are not.
Stored size per level: V = T * F floats, I = (reachable entries) * `code_bits()` (log2(t) rounded up to 1, 2, 4, 8).
"""
from __future__ import annotations


import torch
from torch import nn

from ... import kernels
from ...kernels import bindings
from .base import MASK32, PRIMES, EncodingConfig, code_width, level_vertex_counts, vertex_resolution
from .hashgrid import HashGrid, table_features_bytes


def candidate_rows(entries: torch.Tensor, candidates: torch.Tensor, table_size: int) -> torch.Tensor:
    """hash2(i, j) mod T for broadcastable int64 tensors of entries i and candidates j."""
    h = ((entries * PRIMES[1]) & MASK32) ^ ((candidates * PRIMES[2]) & MASK32)
    return h % table_size


class _SoftTable(torch.autograd.Function):
    """The soft row table S (R, F) of the R reachable entries (level after level, as the logits (R, t)) and its
    backward into the rows and the logits, by the fused kernels (`nbvh_vqad_soft_forward/backward`): one pass for
    softmax and weighted rows; the backward's row gradients summed per thread. Same values as
    `HashVQAD.reference_row_table` (tests/test_fastpath.py). needed (R,) uint8 or None: only the marked entries'
    rows computed, the others zero (their gradient rows are zero too: the backward skips them)."""

    @staticmethod
    def forward(ctx, logits, table, cand, reach, tau, index_size, needed=None):
        t = logits.shape[1]
        L, T, F = table.shape
        H = index_size
        logits_c, table_c = logits.detach().contiguous(), table.detach().contiguous()
        probs = torch.empty_like(logits_c)
        soft = torch.empty((logits.shape[0], F), dtype=torch.float32)
        bindings.vqad_soft_forward(logits=logits_c, table=table_c, cand=cand, reach=reach, levels=L, H=H, T=T, t=t,
                                   F=F, inv_tau=1.0 / tau, needed=needed, probs=probs, soft=soft)
        ctx.save_for_backward(probs, table_c, cand, reach)
        ctx.tau, ctx.index_size = tau, index_size
        return soft

    @staticmethod
    def backward(ctx, grad_soft):
        probs, table, cand, reach = ctx.saved_tensors
        t = probs.shape[1]
        L, T, F = table.shape
        H = ctx.index_size
        grad_soft = grad_soft.contiguous()
        g_table = torch.zeros_like(table)
        g_logits = torch.empty_like(probs)
        bindings.vqad_soft_backward(probs=probs, table=table, cand=cand, reach=reach, grad_soft=grad_soft, levels=L,
                                    H=H, T=T, t=t, F=F, inv_tau=1.0 / ctx.tau, grad_table=g_table,
                                    grad_logits=g_logits)
        return g_logits, g_table, None, None, None, None, None


class HashVQAD(HashGrid):
    """points (N, 3) in [0, 1]^3 -> features (N, L * F); see module docstring.

    Parameters: `table` (L, T, F) feature rows; `logits` (R, t) while soft, R = the reachable entries of all levels,
    level after level (`code_starts`: level l's are rows starts[l]:starts[l + 1]; entry i of level l is row
    starts[l] + i). Buffer `codes` uint8 after
    `freeze()`: the reachable entries' codes level after level, bit-packed as the file stores them (`code_bits()`
    each, little-endian within a byte: 4 bits at t = 16).
    """

    learned_index = True

    def __init__(self, cfg: EncodingConfig, inference: bool = False):
        super().__init__(cfg, inference)
        if cfg.candidates < 2 or cfg.candidates & (cfg.candidates - 1):
            raise ValueError(f"HashVQAD candidates t must be a power of two >= 2, got {cfg.candidates}")
        if cfg.index_factor < 1:
            raise ValueError(f"HashVQAD index factor H / T must be >= 1, got {cfg.index_factor}")
        # (L,) int64 on the CPU (the kernels read it; made explicitly there, also under a meta-device context)
        self._reach = torch.tensor(self.reachable_entries(), dtype=torch.int64, device="cpu")
        # A model built to be loaded (inference) never allocates the soft index: R * t floats, up to 128x the table.
        # Only the reachable entries have logits: the rest would train nothing and cost Adam its time.
        self.logits = None if inference else nn.Parameter(
            torch.randn(int(self._reach.sum()), cfg.candidates) * 1e-2)
        self.register_buffer("codes", torch.zeros(0, dtype=torch.uint8), persistent=True)
        self.temperature = 1.0
        self._cand_cache: torch.Tensor | None = None
        self._starts_cache: torch.Tensor | None = None

    @property
    def frozen(self) -> bool:
        return self.codes.numel() > 0

    def vertex_table_size(self) -> int:
        """H: the index's entries."""
        return self.cfg.index_size

    def reachable_entries(self) -> list[int]:
        """Per level, the index entries a grid vertex can select (`base.level_vertex_counts`): entries 0..n-1."""
        return level_vertex_counts(self.cfg, self.cfg.index_size)

    def code_starts(self) -> list[int]:
        """L + 1 offsets: level l's codes are codes[starts[l]:starts[l + 1]]."""
        starts = [0]
        for n in self.reachable_entries():
            starts.append(starts[-1] + n)
        return starts

    def pack(self, codes: torch.Tensor) -> torch.Tensor:
        """Codes (C,) (one per uint8) -> the held form: bit-packed, `code_bits()` each, little-endian in a byte."""
        bits = self.code_bits()
        per = 8 // bits
        flat = codes.to(torch.uint8).reshape(-1)
        flat = torch.cat([flat, flat.new_zeros((-flat.numel()) % per)]).view(-1, per).to(torch.int32)
        shifts = torch.arange(per, dtype=torch.int32, device=flat.device) * bits
        return (flat << shifts).sum(dim=1).to(torch.uint8).contiguous()  # the fields do not overlap: sum = or

    def unpack(self, positions: torch.Tensor) -> torch.Tensor:
        """The held codes at int64 `positions` (any shape) in the level-after-level order, as int64."""
        bits = self.code_bits()
        per = 8 // bits
        byte = self.codes.to(torch.int64)[positions // per]
        return (byte >> ((positions % per) * bits)) & ((1 << bits) - 1)

    def compact_index(self, full: torch.Tensor) -> torch.Tensor:
        """(L, H, ...) per-entry values -> (R, ...): the reachable entries', level after level (the layout of the
        logits and the codes; converts an older checkpoint's or file's full-index values)."""
        return torch.cat([full[level, :n] for level, n in enumerate(self.reachable_entries())]).contiguous()

    def compact_codes(self, full: torch.Tensor) -> torch.Tensor:
        """(L, H) codes -> the held form: the reachable entries' codes level after level, packed (`pack`)."""
        return self.pack(self.compact_index(full))

    def full_codes(self) -> torch.Tensor:
        """(L, H) uint8: the held codes spread back over the whole index, unreachable entries code 0."""
        full = torch.zeros((self.cfg.levels, self.cfg.index_size), dtype=torch.uint8, device=self.codes.device)
        starts = self.code_starts()
        for level, n in enumerate(self.reachable_entries()):
            pos = torch.arange(starts[level], starts[level] + n, device=self.codes.device)
            full[level, :n] = self.unpack(pos).to(torch.uint8)
        return full

    def _group_candidates(self) -> torch.Tensor:
        """(T, t) int64: candidate rows of entries i = 0..T-1; entry m * T + a has the same rows as entry a."""
        dev = self.table.device
        if self._cand_cache is None or self._cand_cache.device != dev:
            i = torch.arange(self.cfg.table_size, device=dev)[:, None]
            j = torch.arange(self.cfg.candidates, device=dev)[None, :]
            self._cand_cache = candidate_rows(i, j, self.cfg.table_size)
        return self._cand_cache

    def row_table(self, needed: torch.Tensor | None = None) -> torch.Tensor:
        """The rows vertices look up: the stored table once frozen, else the soft row table (R, F). needed (R,) uint8
        (fused kernel only): compute the marked entries' soft rows only, the others zero (a step's batch reads about
        a quarter of them: `fused_mlp.entries_read`)."""
        if self.frozen:
            return self.float_rows()
        if kernels.soft_table_kernel(self, self.table.device) == "fused":
            return _SoftTable.apply(self.logits, self.table, self._group_candidates().contiguous(), self._reach,
                                    float(self.temperature), self.cfg.index_size, needed)
        return self.reference_row_table()

    def reference_row_table(self) -> torch.Tensor:
        """The soft row table (R, F) in torch, one row per reachable entry, level after level (the reference the
        fused kernel is tested against)."""
        cfg = self.cfg
        n_t, n_c = cfg.table_size, cfg.candidates
        probs = torch.softmax(self.logits / self.temperature, dim=-1)  # (R, t)
        cand = self._group_candidates()  # entry i = m * T + a has the rows of a
        starts = self.code_starts()
        parts = []
        for level, n in enumerate(self.reachable_entries()):
            p = probs[starts[level]:starts[level + 1]]
            groups = -(-n // n_t)  # padded to whole groups of T entries, one batched matmul per level
            p = torch.cat([p, p.new_zeros(groups * n_t - n, n_c)]).view(groups, n_t, n_c)
            rows = self.table[level, cand]  # (T, t, F)
            parts.append(torch.einsum("mac,acf->maf", p, rows).reshape(groups * n_t, cfg.features)[:n])
        return torch.cat(parts)

    def level_row_offsets(self, table: torch.Tensor) -> torch.Tensor:
        """(L,) int64: the first row of each level in `table` viewed as (rows, F): the soft table (R, F) holds
        only the reachable entries' rows (`code_starts`), a stored (L, T, F) table T per level."""
        if table.dim() == 3:
            return super().level_row_offsets(table)
        return self._level_starts(table.device)

    def _level_starts(self, device) -> torch.Tensor:
        """(L,) int64 `code_starts()[:-1]` on `device`: level l's first entry in the reachable-entries layout that
        the logits, the soft rows and the codes share (built once per device)."""
        if self._starts_cache is None or self._starts_cache.device != torch.device(device):
            self._starts_cache = torch.tensor(self.code_starts()[:-1], dtype=torch.int64, device=device)
        return self._starts_cache

    def _reads_table(self) -> bool:
        return self.frozen  # soft: the kernels read the soft row table computed from it

    def _fused_rows(self, needed: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor | None, int]:
        if self.frozen:  # vertex -> code -> candidate row, inside the kernel
            return self.table, self.codes, self.cfg.table_size
        return self.row_table(needed), None, 0

    def triton_table(self) -> torch.Tensor:
        """The rows the Triton lookup reads: the table (L, T, F) once frozen (its index inside the kernel), else
        the soft row table (R, F) (differentiable in the logits and the table through torch)."""
        return self.table if self.frozen else self.row_table()

    def _triton_form(self) -> tuple:
        return (self.frozen, id(self.codes), self.codes._version)  # the cached geometry holds the codes: ids stay unique

    def _level_geometry(self, device: torch.device):
        """Frozen: each level's T rows, vertices through the codes; soft: the soft table's reachable entries,
        level after level (`code_starts`), read by vertex index."""
        from ...kernels.triton.hashgrid import level_geometry

        res = [vertex_resolution(s) for s in self.scales]
        starts = self.code_starts()[:-1]
        if self.frozen:
            return level_geometry(self.scales, res, self.cfg.index_size, device, rows=self.cfg.table_size,
                                  code_starts=starts, code_bits=self.code_bits(), index=self.codes)
        return level_geometry(self.scales, res, self.cfg.index_size, device, rows=self.cfg.table_size,
                              row_starts=starts)

    def vertex_rows(self, idx: torch.Tensor) -> torch.Tensor:
        if not self.frozen:
            return idx  # rows of the soft table S are the index entries themselves
        code = self.unpack(idx + self._level_starts(idx.device)[None, :, None])  # idx < the level's reachable entries
        return candidate_rows(idx, code, self.cfg.table_size)

    def schedule(self, fraction: float, cfg) -> str | None:
        """The soft index's life cycle over training (cfg: train.TrainConfig): temperature 1 until the anneal
        phase (the `anneal_fraction` before the fine-tune, or before the end without a freeze), then geometrically
        down to `tau_min`. Returns 'anneal' while annealing, else None."""
        if self.frozen or cfg.anneal_fraction <= 0:
            return None
        anneal_end = 1.0 - (cfg.finetune_fraction if cfg.freeze else 0.0)
        anneal_start = anneal_end - cfg.anneal_fraction
        if fraction < anneal_start:
            return None
        self.temperature = float(cfg.tau_min ** min(1.0, (fraction - anneal_start) / cfg.anneal_fraction))
        return "anneal"

    def freeze_due(self, fraction: float, cfg) -> bool:
        """True once the fine-tune phase (the last `finetune_fraction`) is reached with the index still soft."""
        return cfg.freeze and not self.frozen and fraction >= 1.0 - cfg.finetune_fraction

    @torch.no_grad()
    def freeze(self) -> None:
        """Replace the soft index table by the argmax codes of its reachable entries (irreversible); drops the
        logits."""
        self.codes = self.pack(self.logits.argmax(dim=-1).to(torch.uint8))  # already the reachable entries'
        self.logits = None

    def code_bits(self) -> int:
        """Bits per code as held and stored (`base.code_width`: 4 at t = 16)."""
        return code_width(self.cfg.candidates)

    def stored_bytes(self, table_bits: int = 32) -> dict[str, int]:
        """{'features': as HashGrid's, 'index': ceil(reachable entries * log2(t) / 8)} (file format 2.2)."""
        cfg = self.cfg
        return {"features": table_features_bytes(cfg, table_bits),
                "index": (sum(self.reachable_entries()) * self.code_bits() + 7) // 8}
