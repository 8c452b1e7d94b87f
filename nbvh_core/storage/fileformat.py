"""The .nbvh file: a compact, versioned, checksummed container of one trained NeuralBVH; writing, reading, info.

Its parts, one concern per file beside it: `container.py` (the byte layout: prefix, header bytes, alignment,
checksum, format versions), `header.py` (what a header must say; the checked `Header`), `layout.py` (which
tensors a config stores, their shapes and bytes: the table the planner, the writer and the reader share) and
`components/` (each component's tensors written and read back: bvh, table, network, look).

Tensors of format 2 (`storage` in the header says which form each component takes, see `quantize.py`):
* bvh, 32-bit nodes: `bvh` (M x 32-byte nodes, the bytes `bvh.NODE_DTYPE` describes); 8-bit nodes: `bvh.root`
  (6 float32), `bvh.boxes` (M x 6 uint8, relative to the parent's decoded box) and the tree's shape: `bvh.shape`
  (format 2.5: M bits, 1 for an internal node, when the tree is laid out as `bvh.layout_cut` lays it out: links and
  leaf ordinals follow from the bits, `quantize.links_from_shape`), else `bvh.left`, `bvh.leaf` (M uint16).
* features (L x T x F): float32 or float16 `features`; 8 bits: `features` uint8 codes + `features.offset`,
  `features.scale` (L x F float32).
* `index` (HashVQAD only: codes of log2(t) bits, packed little-endian within each byte; format 2.2: the reachable
  entries of each level (`HashVQAD.reachable_entries`), level after level; before 2.2: all L x H entries).
* the network's parameters in `state_dict` order (`network.NAME`, float32 or float16; 8 bits (format 2.1): each
  Linear's `network.N.weight` as int8 rows and `network.N.weight_scale` (rows,) float16, biases float16; 4 bits
  (format 2.4): the same with each code c stored as the nibble c + 8, packed two to a byte).
* the look (format 2.3): `appearance.*` (the head) and `texture.N` (each slot image's PNG or JPEG bytes).
Format 1 files (float32/float16 everywhere, `float_bytes` in the header) still load.

Allocations are bounded by the file's own size (the tensors must be in it) and by the header's limits. `save_nbvh`
writes to a temporary file beside the target and renames it into place only when complete, so a crash or a full
disk never leaves a partial file under the final name.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from .components.bvh import bvh_tensors, read_nodes
from .components.look import load_look, look_header, look_tensors
from .components.network import load_network, network_tensors
from .components.table import index_tensors, load_index, load_table, table_tensors
from .container import PREFIX, assemble, read_prefix, tensor_table, unpack_codes
from .errors import NBVHFileError  # noqa: F401  (raised here; callers import it from this module)
from .header import Header, check_header
from .packed import is_packed, unpack
from ..geometry.bvh import NODE_DTYPE
from ..geometry.look import texture_format
from ..geometry.mesh import Transform
from ..neural.model import NeuralBVH
from ..protocol.outputs import write_atomic  # noqa: F401  (re-exported: callers write files through it)
from ..neural.quantize import StorageConfig


@dataclass
class FileInfo:
    """What `read_info` tells without building the model: sizes by component (bytes), header, metadata."""

    path: str
    total_bytes: int  # the traceable file: what a tracer holds, read in place
    components: dict
    header: Header
    stored_bytes: int = 0  # the file on disk: total_bytes, or less for the storage variant (packed.py)
    textures: dict = field(default_factory=dict)  # slot -> {"format": "png" | "jpeg", "bytes": int}

    @property
    def metadata(self) -> dict:
        return self.header.metadata

    @property
    def storage(self) -> StorageConfig:
        return self.header.storage


# ------------------------------------------------------------------------------------------------ writing
def _tensors(model: NeuralBVH, storage: StorageConfig) -> list[tuple[str, str, bytes, list[int]]]:
    """(name, component, bytes, shape) of every stored tensor, in file order."""
    return (bvh_tensors(model, storage)
            + table_tensors(model.encoding, "features", "features", storage.table_bits, "model.finalize_storage")
            + index_tensors(model.encoding) + network_tensors(model, storage) + look_tensors(model, storage))


def encode_nbvh(model: NeuralBVH, metadata: dict | None = None, storage: StorageConfig | None = None) -> bytes:
    """The complete file contents for `model` (see module docstring); storage defaults to float32 everywhere."""
    storage = storage or StorageConfig.float32()
    tensors = _tensors(model, storage)
    header = {"format": "nbvh", "config": model.cfg.to_dict(), "transform": model.transform.to_dict(),
              "storage": storage.to_dict(), "tensors": tensor_table(tensors), "metadata": metadata or {}}
    look = look_header(model)
    if look is not None:
        header["appearance"] = look
    return assemble(header, [data for _, _, data, _ in tensors])


def component_bytes(data: bytes) -> dict[str, int]:
    """Bytes of the file by component: header, bvh, features, [index], network, padding, checksum (sums to
    the file size)."""
    return _components(parse(data, "<bytes>"), len(data))


def _components(header: Header, total: int) -> dict[str, int]:
    comps: dict[str, int] = {"header": PREFIX.size + header.header_len}
    for t in header.tensors:
        comps[t["component"]] = comps.get(t["component"], 0) + t["nbytes"]
    comps["padding"] = total - 4 - sum(comps.values())
    comps["checksum"] = 4
    return comps


# ------------------------------------------------------------------------------------------------ reading
def parse(data: bytes, where: str) -> Header:
    """Prefix, checksum, header JSON and the tensor table, all validated; nothing allocated beyond the header."""
    fields, version, header_len = read_prefix(data, where)
    return check_header(fields, version, header_len, len(data) - 4 - PREFIX.size - header_len, where)


def _finite(arr: np.ndarray, what: str, where: str) -> np.ndarray:
    if arr.dtype.kind == "f" and not np.isfinite(arr).all():
        raise NBVHFileError(f"{where}: {what} holds NaN or infinite values")
    return arr


def decode_nbvh(data: bytes, where: str = "<bytes>", device: str | torch.device = "cpu") -> NeuralBVH:
    """Build the model stored in `data` (inference-ready: HashVQAD frozen, 8-bit tables kept as codes)."""
    return _decode(data, parse(data, where), where, device)


def _decode(data: bytes, header: Header, where: str, device: str | torch.device = "cpu") -> NeuralBVH:
    """`decode_nbvh` for a header `parse` has already checked."""
    cfg, storage, expected = header.config, header.storage, header.expected
    start = header.payload_start
    by_name = {t["name"]: t for t in header.tensors}

    def array(name: str) -> np.ndarray:
        t = by_name[name]
        shape, kind = expected[name]
        raw = data[start + t["offset"]:start + t["offset"] + t["nbytes"]]
        if kind == "node":
            return np.frombuffer(raw, NODE_DTYPE).copy()
        if kind.startswith("packed"):
            return unpack_codes(raw, int(kind[6:]), int(np.prod(shape))).reshape(shape)
        return _finite(np.frombuffer(raw, kind).reshape(shape).copy(), name, where)

    nodes, compact = read_nodes(array, storage, expected, where)
    try:
        model = NeuralBVH(nodes, cfg, Transform.from_dict(header.fields["transform"]), inference=True)
    except (ValueError, TypeError) as exc:
        raise NBVHFileError(f"{where}: inconsistent .nbvh contents: {exc}") from None
    with torch.no_grad():
        load_table(model.encoding, "features", storage.table_bits, array, f"{where}: feature scales must be > 0")
        if cfg.encoding.kind == "hashvqad":
            load_index(model.encoding, cfg.encoding.candidates, array, where)
        load_network(model, storage.network_bits, array, [n for n in expected if n.startswith("network.")])
        if compact is not None:
            model.hold_nodes_compact(compact)
        if header.look is not None:
            load_look(model, header.look, storage.table_bits, array, where)
    model.metadata = header.metadata
    model.storage = storage
    return model.to(device).eval()


def save_nbvh(model: NeuralBVH, path: str | os.PathLike, metadata: dict | None = None,
              storage: StorageConfig | None = None) -> int:
    """Write `model` to `path` atomically (temporary file + rename); returns the file size in bytes.

    On any error (e.g. disk full) the temporary file is removed and an existing file at `path` is untouched.
    """
    return write_atomic(path, encode_nbvh(model, metadata, storage))


def read_model_bytes(path: Path) -> bytes:
    """The traceable file's bytes: as they are on disk, or decoded from the storage variant (`packed.py`)."""
    try:
        if path.is_dir():
            raise NBVHFileError(f"{path}: is a folder, not an .nbvh file")
        data = path.read_bytes()
    except OSError as exc:
        raise NBVHFileError(f"{path}: cannot read: {exc.strerror or exc}") from None
    return unpack(data, str(path)) if is_packed(data) else data


def load_nbvh(path: str | os.PathLike, device: str | torch.device = "cpu") -> NeuralBVH:
    """Read a .nbvh file (see `decode_nbvh`); raises `NBVHFileError` for anything that is not a valid model."""
    path = Path(path)
    return decode_nbvh(read_model_bytes(path), str(path), device)


def read_info(path: str | os.PathLike) -> FileInfo:
    """Header, metadata and bytes by component of a .nbvh file (validated as completely as `load_nbvh` does: a file
    `info` accepts is one `render` can load)."""
    path = Path(path)
    data = read_model_bytes(path)
    header = parse(data, str(path))
    _decode(data, header, str(path))
    textures = {}
    for t in header.tensors:
        if t["name"].startswith("texture."):
            at = header.payload_start + t["offset"]  # the image's signature: its first 8 bytes, not a copy of the rest
            textures[int(t["name"].split(".")[1])] = {"format": texture_format(data[at:at + 8]), "bytes": t["nbytes"]}
    return FileInfo(path=str(path), total_bytes=len(data), components=_components(header, len(data)), header=header,
                    stored_bytes=path.stat().st_size, textures=textures)
