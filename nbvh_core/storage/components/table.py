"""The feature tables (the encoding's, the appearance head's) and HashVQAD's index: float rows at 32 or 16 bits, or
codes at 8 or 4 bits with a per-level, per-feature affine (`quantize.py`); the index as packed codes of log2(t)
bits, the reachable entries of each level (format 2.2; before it: all L x H entries)."""
from __future__ import annotations

import numpy as np
import torch

from ..container import REACHABLE_INDEX_SINCE, pack_codes, writer_version
from ..errors import NBVHFileError
from ..layout import float_dtype


def table_tensors(enc, name: str, component: str, bits: int, how: str) -> list[tuple[str, str, bytes, list[int]]]:
    """A feature table's stored tensors: at 8 or 4 bits its codes `name` (4-bit codes packed two to a byte) and
    float32 `name.offset`, `name.scale` (the encoding must hold codes already: `how` says what makes it so); else
    its rows at `bits`."""
    if bits <= 8:
        if not enc.quantized:
            raise ValueError(f"a {bits}-bit table must be quantized first ({how})")
        codes = enc.qcodes.cpu().numpy()
        if codes.size and int(codes.max()) >= 1 << bits:
            raise ValueError(f"the table holds codes above {bits} bits ({how} at another width)")
        data = codes.tobytes() if bits == 8 else pack_codes(codes, bits)
        out = [(name, component, data, list(enc.qcodes.shape))]
        for part, t in (("offset", enc.qoffset), ("scale", enc.qscale)):
            arr = t.detach().cpu().numpy().astype(np.float32)
            out.append((f"{name}.{part}", component, arr.tobytes(), list(arr.shape)))
        return out
    table = enc.float_rows().detach().cpu().numpy()
    return [(name, component, table.astype(float_dtype(bits)).tobytes(), list(table.shape))]


def index_tensors(enc) -> list[tuple[str, str, bytes, list[int]]]:
    """HashVQAD's index codes (the encoding must be frozen); none for an encoding without a learned index."""
    if not enc.learned_index:
        return []
    if not enc.frozen:
        raise ValueError("HashVQAD must be frozen (argmax codes) before saving")
    if writer_version() >= REACHABLE_INDEX_SINCE:  # the packed codes as held (see HashVQAD)
        return [("index", "index", enc.codes.cpu().numpy().tobytes(), [sum(enc.reachable_entries())])]
    full = enc.full_codes().cpu().numpy()  # before 2.2: all L x H entries
    return [("index", "index", pack_codes(full, enc.code_bits()), list(full.shape))]


def load_table(enc, name: str, bits: int, array, bad_scale: str) -> None:
    """Fill an encoding's feature table from the file's `name` tensors (see `table_tensors`): codes with their
    affine at 8 or 4 bits (held as uint8 codes; a scale <= 0 raises NBVHFileError(bad_scale)), else float
    rows."""
    if bits <= 8:
        scale = array(f"{name}.scale")
        if (scale <= 0).any():
            raise NBVHFileError(bad_scale)
        enc.set_quantized(torch.from_numpy(array(name)), torch.from_numpy(array(f"{name}.offset")),
                          torch.from_numpy(scale))
    else:
        enc.table = torch.nn.Parameter(torch.from_numpy(array(name).astype(np.float32)), requires_grad=False)


def load_index(enc, candidates: int, array, where: str) -> None:
    """HashVQAD's frozen codes from the file's `index` (1-D: reachable entries; 2-D: before 2.2)."""
    codes = array("index")
    if (codes >= candidates).any():
        raise NBVHFileError(f"{where}: HashVQAD codes out of range")
    codes = torch.from_numpy(codes.copy())
    enc.codes = enc.pack(codes) if codes.ndim == 1 else enc.compact_codes(codes)
    enc.logits = None
