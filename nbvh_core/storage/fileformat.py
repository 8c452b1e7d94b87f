"""The .nbvh file: a compact, versioned, checksummed container of one trained NeuralBVH.

Layout (little endian):

    offset  size  field
    0       8     magic b"NBVH\\x00\\r\\n\\x1a" (catches text-mode transfers and truncation at the first bytes)
    8       2     format major version (this reader reads 1 and 2; writes 2)
    10      2     format minor version (additions a reader may ignore)
    12      4     header length H (bytes of UTF-8 JSON)
    16      H     header: JSON (format 2.4: zlib-compressed JSON, zero-padded), holding the model config, transform,
                  storage (bits per component), the tensor table (name, component, shape, offset, nbytes) and
                  free-form metadata (training, quality, source mesh)
    16+H    ...   payload: the tensors back to back in table order, each 8-byte aligned (zero padding)
    end-4   4     CRC-32 of every byte before it

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
Format 1 files (float32/float16 everywhere, `float_bytes` in the header) still load.

The reader trusts nothing: `_check_header` validates every header field's type and range, derives the exact
shape and size of every tensor from the config *before anything is allocated*, and refuses a table that
disagrees; `_check_nodes` refuses a BVH whose child links are out of range or do not point forward (so traversal
cannot loop), whose leaf ordinals are out of range or repeated, or whose boxes are not finite. Every refusal is an
`NBVHFileError` (a ValueError) with one line saying which file and why. Allocations are bounded by the file's own
size (the tensors must be in it) and by the config limits below.

`save_nbvh` writes to a temporary file beside the target and renames it into place only when complete, so a
crash or a full disk never leaves a partial file under the final name.
"""
from __future__ import annotations

import json
import math
import os
import struct
import zlib
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np
import torch

from .errors import NBVHFileError  # noqa: F401  (raised here; callers import it from this module)
from .packed import is_packed, unpack
from ..geometry.bvh import MAX_NODES, NODE_DTYPE
from ..neural.encodings import ENCODINGS, EncodingConfig
from ..neural.appearance import TARGETS, AppearanceConfig, AppearanceHead, head_table_bits, map_width
from ..neural.encodings.base import code_width, level_vertex_counts
from ..geometry.look import MAX_SLOTS, MAX_TEXTURE_SIDE, LookError, Material, decode_texture, texture_format
from ..geometry.mesh import Transform
from ..neural.model import ModelConfig, NeuralBVH
from ..neural.networks import NETWORKS, NetworkConfig
from ..protocol.outputs import write_atomic  # noqa: F401  (re-exported: callers write files through it)
from ..neural.quantize import (NONE16, StorageConfig, decode_nodes, encode_nodes, links_from_shape, quantize_rows,
                               shape_bits)

MAGIC = b"NBVH\x00\r\n\x1a"
#: A 4-bit network weight code c in [-7, 7] is stored as the unsigned nibble c + 8.
NETWORK_CODE_OFFSET4 = 8
VERSION_MAJOR = 2
VERSION_MINOR = 5  # 2.1: network_bits 8 (a 2.0 reader refuses such a file by its storage field); 2.2: HashVQAD's
#                    index holds its reachable entries only (a 2.1 reader refuses such a file by the index's shape);
#                    2.3: the asset's look (header `appearance`, tensors appearance.* and texture.*; a 2.2 reader
#                    refuses such a file by its tensors); 2.4: the header zlib-compressed (4.8 KB of JSON in 1.7 KB
#                    on the bunny's default model) and 4-bit network rows (a 2.3 reader refuses such a file: its
#                    header is not JSON); 2.5: the BVH's shape as one bit per node (`bvh.shape`; a 2.4 reader
#                    refuses such a file by its tensors)
REACHABLE_INDEX_SINCE = (2, 2)
APPEARANCE_SINCE = (2, 3)
COMPRESSED_HEADER_SINCE = (2, 4)
SHAPE_BITS_SINCE = (2, 5)
#: A texture's decoded pixels may be at most this many times its stored bytes (a flat 4k image compresses ~1300x)
#: or MIN_TEXTURE_ALLOWANCE, whichever is larger: a crafted tiny PNG cannot ask for gigabytes.
TEXTURE_INFLATION = 4096
MIN_TEXTURE_ALLOWANCE = 16 << 20
#: Most patches an appearance head may tell apart (its slots are stored as uint16).
MAX_PATCHES = 65535
READABLE_MAJORS = (1, 2)
_PREFIX = struct.Struct("<8sHHI")
_ALIGN = 8
#: The reader's limits on header fields (far above any real model; they bound what a crafted header can ask).
LIMITS = {"levels": (1, 16), "n_min": (1, 1 << 16), "n_max": (1, 1 << 16), "features": (1, 64),
          "log2_table": (1, 24), "index_factor": (1, 1024), "candidates": (2, 256), "k": (2, 64),
          "hidden": (0, 16), "width": (1, 1024)}
MAX_HEADER_BYTES = 1 << 20



def pack_codes(codes: np.ndarray, bits: int) -> bytes:
    """Pack unsigned integer codes (< 2^bits, bits in 1..8) densely as one little-endian bit stream: code i holds
    stream bits [i * bits, (i + 1) * bits), byte k stream bits [8k, 8k + 8) from its least significant bit (so at 1,
    2, 4 bits each byte holds whole codes; at 6 bits four codes fill three bytes)."""
    if not 1 <= bits <= 8:
        raise ValueError(f"code width {bits} bits is not supported (1 to 8)")
    flat = np.asarray(codes, np.uint8).ravel()
    if bits == 8:
        return flat.tobytes()
    stream = np.unpackbits(flat[:, None], axis=1, count=bits, bitorder="little")
    return np.packbits(stream.ravel(), bitorder="little").tobytes()


def unpack_codes(data: bytes, bits: int, count: int) -> np.ndarray:
    """Inverse of `pack_codes`: the first `count` codes as uint8 (ValueError when `data` holds fewer)."""
    if not 1 <= bits <= 8:
        raise ValueError(f"code width {bits} bits is not supported (1 to 8)")
    raw = np.frombuffer(data, np.uint8)
    if raw.size * 8 < count * bits:
        raise ValueError(f"{raw.size} bytes hold fewer than {count} codes of {bits} bits")
    if bits == 8:
        return raw[:count].copy()
    stream = np.unpackbits(raw, count=count * bits, bitorder="little").reshape(count, bits)
    return np.packbits(stream, axis=1, bitorder="little").ravel()


@dataclass
class FileInfo:
    """What `read_info` tells without building the model: sizes by component (bytes), header, metadata."""

    path: str
    total_bytes: int  # the traceable file: what a tracer holds, read in place
    components: dict
    header: dict
    stored_bytes: int = 0  # the file on disk: total_bytes, or less for the storage variant (packed.py)
    textures: dict = field(default_factory=dict)  # slot -> {"format": "png" | "jpeg", "bytes": int}

    @property
    def metadata(self) -> dict:
        return self.header.get("metadata", {})

    @property
    def storage(self) -> StorageConfig:
        return self.header["_storage"]


# ------------------------------------------------------------------------------------------------ writing
def _float_dtype(bits: int):
    return np.float16 if bits == 16 else np.float32


def _tensors(model: NeuralBVH, storage: StorageConfig) -> list[tuple[str, str, bytes, list[int]]]:
    """(name, component, bytes, shape) of every stored tensor, in file order."""
    enc = model.encoding
    nodes = np.ascontiguousarray(model.nodes, NODE_DTYPE)
    out = []
    packed = None
    if storage.node_bits == 8:  # the format the model holds, as it is; else encoded from its nodes
        packed = model.compact_nodes if model.compact_nodes is not None else encode_nodes(nodes)
    if storage.node_bits == 8 and packed is None:
        raise ValueError("the BVH's boxes cannot be quantized relative to their parents (a child outside its "
                         "parent box); save with node_bits=32")
    if packed is None:
        out.append(("bvh", "bvh", nodes.tobytes(), [len(nodes)]))
    else:
        shape = (shape_bits(packed["left"], packed["leaf"]) if (VERSION_MAJOR, VERSION_MINOR) >= SHAPE_BITS_SINCE
                 else None)
        for part in ("root", "boxes"):
            out.append((f"bvh.{part}", "bvh", packed[part].tobytes(), list(packed[part].shape)))
        if shape is not None:  # 1 bit a node in place of 4 bytes of links (the bunny's 2,047 nodes: 8.2 KB -> 256 B)
            out.append(("bvh.shape", "bvh", pack_codes(shape, 1), [len(shape)]))
        else:
            out += [(f"bvh.{part}", "bvh", packed[part].tobytes(), list(packed[part].shape))
                    for part in ("left", "leaf")]
    out += _table_tensors(enc, "features", "features", storage.table_bits, "model.finalize_storage")
    if enc.learned_index:
        if not enc.frozen:
            raise ValueError("HashVQAD must be frozen (argmax codes) before saving")
        if (VERSION_MAJOR, VERSION_MINOR) >= REACHABLE_INDEX_SINCE:  # the packed codes as held (see HashVQAD)
            out.append(("index", "index", enc.codes.cpu().numpy().tobytes(), [sum(enc.reachable_entries())]))
        else:  # before 2.2: all L x H entries
            full = enc.full_codes().cpu().numpy()
            out.append(("index", "index", pack_codes(full, enc.code_bits()), list(full.shape)))
    for name, arr in _network_arrays(model, storage.network_bits):
        data = (pack_codes(arr.astype(np.int16) + NETWORK_CODE_OFFSET4, 4)
                if storage.network_bits == 4 and arr.dtype == np.int8 else arr.tobytes())
        out.append((f"network.{name}", "network", data, list(arr.shape)))
    return out + _look_tensors(model, storage)


def _look_tensors(model: NeuralBVH, storage: StorageConfig) -> list[tuple[str, str, bytes, list[int]]]:
    """The appearance head's table and network, then every slot image as PNG or JPEG bytes
    (`Material.stored_image`; file format 2.3: a reader that knows PNG only refuses a JPEG texture in one line)."""
    out = []
    head = model.appearance
    if head is not None:
        out += _table_tensors(head.encoding, "appearance.features", "appearance", head_table_bits(storage.table_bits),
                              "appearance.finalize_head")
        fdt = np.float32 if storage.network_bits == 32 else np.float16
        for name, p in head.network.state_dict().items():
            arr = p.detach().cpu().numpy().astype(fdt)
            out.append((f"appearance.network.{name}", "appearance", arr.tobytes(), list(arr.shape)))
        affine = head.affine.cpu().numpy().astype(np.float32)[:head.cfg.stored_maps]
        patch_slot = head.patch_slot.cpu().numpy().astype(np.uint16)
        if len(affine):
            out.append(("appearance.affine", "appearance", affine.tobytes(), list(affine.shape)))
        out.append(("appearance.patch_slot", "appearance", patch_slot.tobytes(), list(patch_slot.shape)))
    for i, m in enumerate(model.materials):
        if m.image is not None:
            data = m.stored_image()
            out.append((f"texture.{i}", "textures", data, [len(data)]))
    return out


def _look_header(model: NeuralBVH) -> dict | None:
    if not model.materials:
        return None
    return {"config": None if model.appearance is None else model.appearance.cfg.to_dict(),
            "materials": [m.to_dict() for m in model.materials]}


def _table_tensors(enc, name: str, component: str, bits: int, how: str) -> list[tuple[str, str, bytes, list[int]]]:
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
    return [(name, component, table.astype(_float_dtype(bits)).tobytes(), list(table.shape))]


def _network_arrays(model: NeuralBVH, bits: int) -> list[tuple[str, np.ndarray]]:
    """The network's stored arrays in file order: every state_dict entry at `bits` (32/16), or at 8 or 4 bits each
    weight as int8 codes followed by its float16 row scales (held ones as they are, else quantized now)."""
    from torch import nn

    if bits > 8:
        fdt = _float_dtype(bits)
        return [(n, p.detach().cpu().numpy().astype(fdt)) for n, p in model.network.state_dict().items()
                if not n.endswith(".weight_scale")]
    out = []
    for name, m in model.network.named_modules():
        if not isinstance(m, nn.Linear):
            continue
        if m.weight.dtype == torch.int8:
            codes, scale = m.weight.cpu().numpy(), m.weight_scale.cpu().numpy()
        else:
            codes, scale = quantize_rows(m.weight.detach().float().cpu().numpy(), bits)
        out += [(f"{name}.weight", codes.astype(np.int8)), (f"{name}.weight_scale", scale.astype(np.float16)),
                (f"{name}.bias", m.bias.detach().cpu().numpy().astype(np.float16))]
    return out


def encode_nbvh(model: NeuralBVH, metadata: dict | None = None, storage: StorageConfig | None = None) -> bytes:
    """The complete file contents for `model` (see module docstring); storage defaults to float32 everywhere."""
    storage = storage or StorageConfig.float32()
    tensors = _tensors(model, storage)
    table, offset = [], 0
    for name, comp, data, shape in tensors:
        table.append({"name": name, "component": comp, "shape": shape, "offset": offset, "nbytes": len(data)})
        offset += len(data) + (-len(data)) % _ALIGN
    header = {"format": "nbvh", "config": model.cfg.to_dict(), "transform": model.transform.to_dict(),
              "storage": storage.to_dict(), "tensors": table, "metadata": metadata or {}}
    look = _look_header(model)
    if look is not None:
        header["appearance"] = look
    hdr = header_bytes(header)
    parts = [_PREFIX.pack(MAGIC, VERSION_MAJOR, VERSION_MINOR, len(hdr)), hdr]
    for _, _, data, _ in tensors:
        parts += [data, b"\0" * ((-len(data)) % _ALIGN)]
    body = b"".join(parts)
    return body + struct.pack("<I", zlib.crc32(body))


def component_bytes(data: bytes) -> dict[str, int]:
    """Bytes of the file by component: header, bvh, features, [index], network, padding, checksum (sums to
    the file size)."""
    return _components(_parse(data, "<bytes>"), len(data))


def _components(header: dict, total: int) -> dict[str, int]:
    comps: dict[str, int] = {"header": _PREFIX.size + header["_header_len"]}
    for t in header["tensors"]:
        comps[t["component"]] = comps.get(t["component"], 0) + t["nbytes"]
    comps["padding"] = total - 4 - sum(comps.values())
    comps["checksum"] = 4
    return comps


# ------------------------------------------------------------------------------------------------ checking
def _int_field(d: dict, key: str, where: str, lo: int, hi: int) -> int:
    v = d.get(key)
    if not isinstance(v, int) or isinstance(v, bool) or not lo <= v <= hi:
        raise NBVHFileError(f"{where}: header field {key!r} must be an integer in [{lo}, {hi}], got {v!r:.40}")
    return v


def _config_from(d, cls, where: str, what: str):
    """A dataclass config from a header dict: known fields only, each of its default's type, ints in LIMITS."""
    if not isinstance(d, dict):
        raise NBVHFileError(f"{where}: header field {what!r} must be an object")
    known = {f.name: f for f in fields(cls)}
    unknown = set(d) - set(known)
    if unknown:
        raise NBVHFileError(f"{where}: unknown {what} field(s) {', '.join(sorted(map(str, unknown)))[:80]}")
    kw = {}
    default = cls()
    for name, v in d.items():
        want = type(getattr(default, name))
        if want is type(None) and v is not None:  # an optional count (None: its default meaning)
            want = int
        if want is int:
            lo, hi = LIMITS.get(name, (-(1 << 31), 1 << 31))
            kw[name] = _int_field(d, name, where, lo, hi)
        elif want is float:
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v):
                raise NBVHFileError(f"{where}: {what} field {name!r} must be a finite number, got {v!r:.40}")
            kw[name] = float(v)
        elif not isinstance(v, want):
            raise NBVHFileError(f"{where}: {what} field {name!r} must be a {want.__name__}, got {v!r:.40}")
        else:
            kw[name] = v
    try:  # the config's own checks (a loss or kind it does not know): still the reader's one-line refusal
        return cls(**kw)
    except ValueError as exc:
        raise NBVHFileError(f"{where}: {what}: {exc}") from None


def _model_config(header: dict, where: str) -> ModelConfig:
    cfg = header.get("config")
    if not isinstance(cfg, dict):
        raise NBVHFileError(f"{where}: header field 'config' must be an object")
    enc = _config_from(cfg.get("encoding"), EncodingConfig, where, "encoding")
    net = _config_from(cfg.get("network"), NetworkConfig, where, "network")
    if enc.kind not in ENCODINGS or net.kind not in NETWORKS:
        raise NBVHFileError(f"{where}: unknown encoding {enc.kind!r:.20} or network {net.kind!r:.20}")
    if enc.kind == "hashvqad" and enc.candidates & (enc.candidates - 1):
        raise NBVHFileError(f"{where}: HashVQAD candidates must be a power of two, got {enc.candidates}")
    if enc.n_max < enc.n_min:
        raise NBVHFileError(f"{where}: n_max {enc.n_max} < n_min {enc.n_min}")
    return ModelConfig(enc, net)


def _storage(header: dict, major: int, where: str) -> StorageConfig:
    if major == 1:
        fb = header.get("float_bytes")
        if fb not in (2, 4) or isinstance(fb, bool):
            raise NBVHFileError(f"{where}: header field 'float_bytes' must be 2 or 4, got {fb!r:.40}")
        bits = 8 * fb
        return StorageConfig(table_bits=bits, network_bits=bits, node_bits=32)
    st = header.get("storage")
    if not isinstance(st, dict) or set(st) != {"table_bits", "network_bits", "node_bits"}:
        raise NBVHFileError(f"{where}: header field 'storage' must name table_bits, network_bits and node_bits")
    try:
        return StorageConfig(**st)
    except (TypeError, ValueError) as exc:
        raise NBVHFileError(f"{where}: bad storage: {exc}") from None


def _network_shapes(cfg: ModelConfig) -> dict[str, tuple[int, ...]]:
    """state_dict shapes of the network `cfg` describes, computed on the meta device (nothing allocated)."""
    from ..neural.networks import make_network

    with torch.device("meta"):
        net = make_network(cfg.encoding.out_dim, cfg.network)
    return {name: tuple(p.shape) for name, p in net.state_dict().items()}


def _expected_tensors(cfg: ModelConfig, storage: StorageConfig, n_nodes: int,
                      version: tuple[int, int] = (VERSION_MAJOR, VERSION_MINOR),
                      shape_only: bool = False) -> dict[str, tuple[tuple, str]]:
    """name -> (shape, numpy dtype or 'packed<bits>') of every tensor a file of this format version and config
    must hold (shape_only: its 8-bit BVH holds the tree's shape as bits, from format 2.5 on)."""
    enc = cfg.encoding
    L, T, F = enc.levels, enc.table_size, enc.features
    out: dict[str, tuple[tuple, str]] = {}
    if storage.node_bits == 8:
        out.update({"bvh.root": ((6,), "<f4"), "bvh.boxes": ((n_nodes, 6), "u1")})
        if shape_only and version >= SHAPE_BITS_SINCE:
            out["bvh.shape"] = ((n_nodes,), "packed1")
        else:
            out.update({"bvh.left": ((n_nodes,), "<u2"), "bvh.leaf": ((n_nodes,), "<u2")})
    else:
        out["bvh"] = ((n_nodes,), "node")
    out.update(_table_shapes("features", L, T, F, storage.table_bits))
    if enc.kind == "hashvqad":
        shape = ((sum(level_vertex_counts(enc, enc.index_size)),) if version >= REACHABLE_INDEX_SINCE
                 else (L, enc.index_size))
        out["index"] = (shape, f"packed{code_width(enc.candidates)}")
    fdt = "<f4" if storage.network_bits == 32 else "<f2"
    for name, shape in _network_shapes(cfg).items():
        if storage.network_bits <= 8 and name.endswith("weight") and len(shape) == 2:
            out[f"network.{name}"] = (shape, "i1" if storage.network_bits == 8 else "packed4")
            out[f"network.{name}_scale"] = ((shape[0],), "<f2")
        else:
            out[f"network.{name}"] = (shape, fdt)
    return out


def payload_bytes(cfg: ModelConfig, storage: StorageConfig, n_nodes: int) -> int:
    """Bytes of the tensors a file of this config holds for `n_nodes` nodes laid out by `bvh.layout_cut` (every
    trained tree; the 8-bit BVH as shape bits), header and checksum excluded: the reader's own shape table
    (`_expected_tensors`), so the planner sizes exactly what the writer writes and the reader checks."""
    tensors = _expected_tensors(cfg, storage, n_nodes, shape_only=True)
    return sum(_nbytes(shape, kind) for shape, kind in tensors.values())


def _table_shapes(name: str, levels: int, rows: int, features: int, bits: int) -> dict[str, tuple[tuple, str]]:
    """name -> (shape, dtype) of a feature table's stored tensors (see `_table_tensors`)."""
    if bits <= 8:
        kind = "u1" if bits == 8 else f"packed{bits}"
        return {name: ((levels, rows, features), kind), f"{name}.offset": ((levels, features), "<f4"),
                f"{name}.scale": ((levels, features), "<f4")}
    return {name: ((levels, rows, features), "<f2" if bits == 16 else "<f4")}


def _nbytes(shape: tuple, kind: str) -> int:
    count = int(np.prod(shape, dtype=np.int64)) if shape else 1
    if kind == "node":
        return count * NODE_DTYPE.itemsize
    if kind.startswith("packed"):
        return (count * int(kind[6:]) + 7) // 8
    return count * np.dtype(kind).itemsize


def header_bytes(header: dict, version: tuple[int, int] | None = None) -> bytes:
    """A header as a file of `version` (default: the writer's) stores it: JSON, zlib-compressed from 2.4 on, padded
    so the payload that follows starts 8-byte aligned (zeros after compressed bytes, spaces after plain JSON)."""
    version = version or (VERSION_MAJOR, VERSION_MINOR)
    text = json.dumps(header, separators=(",", ":"), sort_keys=True, allow_nan=False).encode()
    if version >= COMPRESSED_HEADER_SINCE:
        text = zlib.compress(text, 9)
        return text + b"\0" * ((-(_PREFIX.size + len(text))) % _ALIGN)
    return text + b" " * ((-(_PREFIX.size + len(text))) % _ALIGN)


def header_json(raw: bytes, version: tuple[int, int], where: str) -> bytes:
    """The JSON text of a stored header (inverse of `header_bytes`): a compressed one is inflated to at most
    MAX_HEADER_BYTES, and nothing but its alignment padding may follow it. Raises NBVHFileError (one line)."""
    if version < COMPRESSED_HEADER_SINCE:
        return raw
    inflate = zlib.decompressobj()
    try:
        text = inflate.decompress(raw, MAX_HEADER_BYTES)
    except zlib.error as exc:
        raise NBVHFileError(f"{where}: unreadable header (not zlib data: {str(exc)[:60]})") from None
    if not inflate.eof:
        raise NBVHFileError(f"{where}: header does not inflate within {MAX_HEADER_BYTES} bytes (truncated or too "
                            "large)")
    if len(inflate.unused_data) >= _ALIGN or inflate.unused_data.strip(b"\0"):
        raise NBVHFileError(f"{where}: bytes after the compressed header")
    return text


def _parse(data: bytes, where: str) -> dict:
    """Prefix, checksum, header JSON and the tensor table, all validated; nothing allocated beyond the header."""
    if len(data) < _PREFIX.size + 4:
        raise NBVHFileError(f"{where}: too short to be an .nbvh file ({len(data)} bytes)")
    magic, major, minor, hlen = _PREFIX.unpack_from(data, 0)
    if magic != MAGIC:
        raise NBVHFileError(f"{where}: not an .nbvh file (wrong magic bytes {magic[:8]!r})")
    if major not in READABLE_MAJORS:
        raise NBVHFileError(f"{where}: .nbvh format version {major}.{minor} is not supported "
                            f"(this reader reads {', '.join(f'{m}.x' for m in READABLE_MAJORS)})")
    stored_crc = struct.unpack_from("<I", data, len(data) - 4)[0]
    if zlib.crc32(memoryview(data)[:-4]) != stored_crc:
        raise NBVHFileError(f"{where}: damaged or truncated file (checksum mismatch)")
    if hlen > min(MAX_HEADER_BYTES, len(data) - _PREFIX.size - 4):
        raise NBVHFileError(f"{where}: header length {hlen} does not fit the file ({len(data)} bytes)")
    try:
        header = json.loads(header_json(bytes(data[_PREFIX.size:_PREFIX.size + hlen]), (major, minor), where))
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise NBVHFileError(f"{where}: unreadable header: {str(exc)[:80]}") from None
    if not isinstance(header, dict):
        raise NBVHFileError(f"{where}: the header must be a JSON object, not {type(header).__name__}")
    header["_header_len"] = hlen
    header["_payload_start"] = _PREFIX.size + hlen
    header["_major"], header["_minor"] = major, minor
    _check_header(header, len(data) - 4 - _PREFIX.size - hlen, where)
    return header


def _check_header(header: dict, payload: int, where: str) -> None:
    """Every field the reader uses: types, ranges, and a tensor table that matches the config exactly."""
    cfg = _model_config(header, where)
    storage = _storage(header, header["_major"], where)
    tf = header.get("transform")
    if (not isinstance(tf, dict) or not isinstance(tf.get("scale"), (int, float)) or isinstance(tf.get("scale"), bool)
            or not (math.isfinite(tf["scale"]) and tf["scale"] > 0) or not isinstance(tf.get("offset"), list)
            or len(tf["offset"]) != 3
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                       for v in tf["offset"])):
        raise NBVHFileError(f"{where}: header field 'transform' must be {{scale > 0, offset: 3 finite numbers}}")
    meta = header.get("metadata", {})
    if not isinstance(meta, dict):
        raise NBVHFileError(f"{where}: header field 'metadata' must be an object")
    _check_metadata(meta, where)
    tensors = header.get("tensors")
    if not isinstance(tensors, list):
        raise NBVHFileError(f"{where}: header field 'tensors' must be a list")
    by_name = {}
    for t in tensors:
        if not isinstance(t, dict) or not isinstance(t.get("name"), str) or not isinstance(t.get("component"), str):
            raise NBVHFileError(f"{where}: every tensor entry needs a name and a component")
        for key in ("offset", "nbytes"):
            _int_field(t, key, where, 0, payload)
        # a dimension cannot exceed the payload's bits (packed codes: down to 1 bit each); the exact size per
        # tensor is checked against the config below
        if not isinstance(t.get("shape"), list) or not all(isinstance(v, int) and not isinstance(v, bool) and
                                                          0 <= v <= 8 * payload for v in t["shape"]):
            raise NBVHFileError(f"{where}: tensor {t['name'][:40]!r} has a bad shape")
        if t["offset"] % _ALIGN or t["offset"] + t["nbytes"] > payload:
            raise NBVHFileError(f"{where}: tensor {t['name'][:40]!r} extends past the end of the file or is "
                                "misaligned")
        if t["name"] in by_name:
            raise NBVHFileError(f"{where}: tensor {t['name'][:40]!r} appears twice")
        by_name[t["name"]] = t
    node_tensor = by_name.get("bvh" if storage.node_bits == 32 else "bvh.boxes")
    if node_tensor is None or not node_tensor["shape"] or not 1 <= node_tensor["shape"][0] <= MAX_NODES:
        raise NBVHFileError(f"{where}: the BVH tensor is missing or its node count is not in [1, {MAX_NODES}]")
    expected = _expected_tensors(cfg, storage, node_tensor["shape"][0], (header["_major"], header["_minor"]),
                                 shape_only="bvh.shape" in by_name)
    look = _look_spec(header, where)
    expected.update(_look_expected(look, storage, by_name, where))
    if set(expected) != set(by_name):
        missing, extra = sorted(set(expected) - set(by_name)), sorted(set(by_name) - set(expected))
        raise NBVHFileError(f"{where}: tensors do not match the config (missing {missing[:3]}, unexpected "
                            f"{[e[:40] for e in extra[:3]]})")
    end = 0
    for t in tensors:  # in file order, non-overlapping
        shape, kind = expected[t["name"]]
        if tuple(t["shape"]) != shape or t["nbytes"] != _nbytes(shape, kind):
            raise NBVHFileError(f"{where}: tensor {t['name']!r} is {t['shape']} / {t['nbytes']} B; the config "
                                f"says {list(shape)} / {_nbytes(shape, kind)} B")
        if t["offset"] < end:
            raise NBVHFileError(f"{where}: tensor {t['name']!r} overlaps the one before it")
        end = t["offset"] + t["nbytes"]
    header["_config"], header["_storage"], header["_expected"] = cfg, storage, expected
    header["_look"] = look


def _look_spec(header: dict, where: str) -> tuple[AppearanceConfig | None, list[dict]] | None:
    """The header's `appearance` (format 2.3), checked: (head config or None, materials), or None when absent."""
    look = header.get("appearance")
    if look is None:
        return None
    if (header["_major"], header["_minor"]) < APPEARANCE_SINCE:
        raise NBVHFileError(f"{where}: an 'appearance' field in a format {header['_major']}.{header['_minor']} file")
    if not isinstance(look, dict) or set(look) != {"config", "materials"}:
        raise NBVHFileError(f"{where}: header field 'appearance' must hold exactly 'config' and 'materials'")
    mats = look["materials"]
    if not isinstance(mats, list) or not 1 <= len(mats) <= MAX_SLOTS:
        raise NBVHFileError(f"{where}: appearance.materials must be a list of 1 to {MAX_SLOTS} materials")
    for m in mats:
        color = m.get("base_color") if isinstance(m, dict) else None
        image = m.get("image") if isinstance(m, dict) else None
        if (not isinstance(m, dict) or set(m) != {"name", "base_color", "image"} or not isinstance(m["name"], str)
                or len(m["name"]) > 256 or not isinstance(color, list) or len(color) != 4
                or not all(isinstance(c, (int, float)) and not isinstance(c, bool) and 0 <= c <= 1 for c in color)):
            raise NBVHFileError(f"{where}: a material needs a name and a base_color of 4 numbers in [0, 1]")
        if image is not None and not (isinstance(image, list) and len(image) == 3 and all(
                isinstance(v, int) and not isinstance(v, bool) for v in image) and 1 <= image[0] <= MAX_TEXTURE_SIDE
                and 1 <= image[1] <= MAX_TEXTURE_SIDE and image[2] in (3, 4)):
            raise NBVHFileError(f"{where}: material {m['name'][:40]!r}: image must be [height, width, 3|4] with "
                                f"sides up to {MAX_TEXTURE_SIDE}")
    cfg = None
    if look["config"] is not None:
        cfg = _config_from(look["config"], AppearanceConfig, where, "appearance config")
        if (cfg.slots != len(mats) or not 1 <= cfg.patches <= MAX_PATCHES or cfg.outputs == 0
                or cfg.patch_degree not in (1, 2, 3) or cfg.target not in TARGETS
                or not (cfg.mapped_patches is None or (isinstance(cfg.mapped_patches, int)
                                                       and 0 <= cfg.mapped_patches <= cfg.patches))):
            raise NBVHFileError(f"{where}: the appearance head's {cfg.slots} slots and {cfg.patches} patches do not "
                                f"match {len(mats)} materials (1 to {MAX_PATCHES} patches)")
    return cfg, mats


def _look_expected(look, storage: StorageConfig, by_name: dict, where: str) -> dict[str, tuple[tuple, str]]:
    """name -> (shape, dtype) of the appearance head's tensors and the textures (each image's bytes as long as its
    entry says, its decoded size bounded by TEXTURE_INFLATION x its bytes)."""
    if look is None:
        return {}
    cfg, mats = look
    out: dict[str, tuple[tuple, str]] = {}
    if cfg is not None:
        out.update(_table_shapes("appearance.features", cfg.levels, 1 << cfg.log2_table, cfg.features,
                                 head_table_bits(storage.table_bits)))
        with torch.device("meta"):
            head = AppearanceHead(cfg, inference=True)
        fdt = "<f4" if storage.network_bits == 32 else "<f2"
        out.update({f"appearance.network.{n}": (tuple(p.shape), fdt) for n, p in head.network.state_dict().items()})
        if cfg.stored_maps:  # the maps of the first patches (image slots'); the others are zero
            out["appearance.affine"] = ((cfg.stored_maps, 2, map_width(cfg.patch_degree)), "<f4")
        out["appearance.patch_slot"] = ((cfg.patches,), "<u2")
    for i, m in enumerate(mats):
        if m["image"] is None:
            continue
        entry = by_name.get(f"texture.{i}")
        nbytes = entry["nbytes"] if entry is not None else 0
        h, w, c = m["image"]
        if h * w * c > max(MIN_TEXTURE_ALLOWANCE, TEXTURE_INFLATION * nbytes):
            raise NBVHFileError(f"{where}: texture {i} declares {w}x{h}x{c} pixels from {nbytes} bytes of image")
        out[f"texture.{i}"] = ((nbytes,), "u1")
    return out


def _check_metadata(meta: dict, where: str) -> None:
    """The metadata fields tools print must have the types they print."""
    def number(v):
        return v is None or (isinstance(v, (int, float)) and not isinstance(v, bool))

    for key in ("source", "quality", "training", "settings", "assessment"):
        if key in meta and meta[key] is not None and not isinstance(meta[key], dict):
            raise NBVHFileError(f"{where}: metadata field {key!r} must be an object")
    q = meta.get("quality") or {}
    for key in ("mse", "silhouette_iou", "depth_error"):
        if key in q and not number(q[key]):
            raise NBVHFileError(f"{where}: metadata quality.{key} must be a number")
    s = meta.get("source") or {}
    if "triangles" in s and not (isinstance(s["triangles"], int) and not isinstance(s["triangles"], bool)):
        raise NBVHFileError(f"{where}: metadata source.triangles must be an integer")
    if "name" in s and not isinstance(s["name"], str):
        raise NBVHFileError(f"{where}: metadata source.name must be a string")
    tr = meta.get("training") or {}
    for key in ("steps", "seconds", "samples", "samples_per_s", "final_loss"):
        if key in tr and not number(tr[key]):
            raise NBVHFileError(f"{where}: metadata training.{key} must be a number")


def _check_nodes(nodes: np.ndarray, where: str) -> None:
    """Links in range and pointing forward (no cycle), leaf ordinals 0..n-1 each once, boxes finite or empty."""
    _check_nodes_links(nodes, where)
    left = nodes["left"].astype(np.int64)
    leaf = nodes["leaf"].astype(np.int64)
    internal = left != 0
    if (leaf[internal] != -1).any():
        raise NBVHFileError(f"{where}: BVH internal node with a leaf ordinal")
    leaves = leaf[~internal]
    real = leaves[leaves >= 0]
    if (leaves < -1).any() or real.size == 0 or (np.sort(real) != np.arange(real.size)).any():
        raise NBVHFileError(f"{where}: BVH leaf ordinals must be 0..{max(real.size - 1, 0)} once each")
    lo, hi = nodes["lo"], nodes["hi"]
    empty = (lo > hi).any(axis=1)
    if np.isnan(lo).any() or np.isnan(hi).any() or not (np.isfinite(lo[~empty]).all() and
                                                         np.isfinite(hi[~empty]).all()):
        raise NBVHFileError(f"{where}: BVH boxes must be finite (or empty)")
    if (~internal & (leaf == -1) & ~empty).any():
        raise NBVHFileError(f"{where}: BVH node marked unused has a non-empty box")


def _finite(arr: np.ndarray, what: str, where: str) -> np.ndarray:
    if arr.dtype.kind == "f" and not np.isfinite(arr).all():
        raise NBVHFileError(f"{where}: {what} holds NaN or infinite values")
    return arr


# ------------------------------------------------------------------------------------------------ reading
def decode_nbvh(data: bytes, where: str = "<bytes>", device: str | torch.device = "cpu") -> NeuralBVH:
    """Build the model stored in `data` (inference-ready: HashVQAD frozen, 8-bit tables kept as codes)."""
    return _decode(data, _parse(data, where), where, device)


def _decode(data: bytes, header: dict, where: str, device: str | torch.device = "cpu") -> NeuralBVH:
    """`decode_nbvh` for a header `_parse` has already checked."""
    cfg, storage, expected = header["_config"], header["_storage"], header["_expected"]
    start = header["_payload_start"]

    def array(name: str) -> np.ndarray:
        t = next(t for t in header["tensors"] if t["name"] == name)
        shape, kind = expected[name]
        raw = data[start + t["offset"]:start + t["offset"] + t["nbytes"]]
        if kind == "node":
            return np.frombuffer(raw, NODE_DTYPE).copy()
        if kind.startswith("packed"):
            return unpack_codes(raw, int(kind[6:]), int(np.prod(shape))).reshape(shape)
        return _finite(np.frombuffer(raw, kind).reshape(shape).copy(), name, where)

    if storage.node_bits == 8:
        root = array("bvh.root")
        if "bvh.shape" in expected:
            try:
                left, leaf = links_from_shape(array("bvh.shape"))
            except ValueError as exc:
                raise NBVHFileError(f"{where}: the BVH's shape bits are not a tree ({exc})") from None
            left, leaf = left.astype(np.uint16), np.where(leaf < 0, NONE16, leaf).astype(np.uint16)
        else:
            left, leaf = array("bvh.left"), array("bvh.leaf")
        pre = np.zeros(len(left), NODE_DTYPE)
        pre["left"], pre["leaf"] = left, np.where(leaf == NONE16, -1, leaf.astype(np.int64))
        pre["lo"], pre["hi"] = root[:3], root[3:]  # structure check first (decode walks the links)
        _check_nodes_links(pre, where)
        if (root[:3] > root[3:]).any():
            raise NBVHFileError(f"{where}: BVH root box is empty")
        compact = {"root": root, "boxes": array("bvh.boxes"), "left": left, "leaf": leaf}
        nodes = decode_nodes(root, compact["boxes"], left, leaf)
    else:
        compact = None
        nodes = array("bvh")
    _check_nodes(nodes, where)
    try:
        transform = Transform.from_dict(header["transform"])
        model = NeuralBVH(nodes, cfg, transform, inference=True)
    except (ValueError, TypeError) as exc:
        raise NBVHFileError(f"{where}: inconsistent .nbvh contents: {exc}") from None
    enc = model.encoding
    with torch.no_grad():
        _load_table(enc, "features", storage.table_bits, array, f"{where}: feature scales must be > 0")
        if cfg.encoding.kind == "hashvqad":
            codes = array("index")
            if (codes >= cfg.encoding.candidates).any():
                raise NBVHFileError(f"{where}: HashVQAD codes out of range")
            codes = torch.from_numpy(codes.copy())
            enc.codes = enc.pack(codes) if codes.ndim == 1 else enc.compact_codes(codes)  # 2-D: before 2.2
            enc.logits = None
        _load_network(model, storage.network_bits, array, [n for n in expected if n.startswith("network.")])
        if compact is not None:
            model.hold_nodes_compact(compact)
        if header.get("_look") is not None:
            _load_look(model, header["_look"], storage.table_bits, array, where)
    model.metadata = header.get("metadata", {})
    model.storage = storage
    return model.to(device).eval()


def _load_table(enc, name: str, bits: int, array, bad_scale: str) -> None:
    """Fill an encoding's feature table from the file's `name` tensors (see `_table_tensors`): codes with their
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


def _load_look(model: NeuralBVH, look: tuple, table_bits: int, array, where: str) -> None:
    """The materials (textures decoded from their PNG or JPEG bytes) and the appearance head, held as stored."""
    cfg, mats = look
    materials = []
    for i, m in enumerate(mats):
        image = None
        if m["image"] is not None:
            try:
                image = decode_texture(array(f"texture.{i}").tobytes(), tuple(m["image"]), where)
            except LookError as exc:
                raise NBVHFileError(str(exc)) from None
        materials.append(Material(m["name"], np.asarray(m["base_color"], np.float32), image))
    model.materials = materials
    if cfg is None:
        return
    head = AppearanceHead(cfg, inference=True)
    _load_table(head.encoding, "appearance.features", head_table_bits(table_bits), array,
                f"{where}: appearance feature scales must be > 0")
    state = {n: torch.from_numpy(array(f"appearance.network.{n}").astype(np.float32))
             for n in head.network.state_dict()}
    head.network.load_state_dict(state)
    patch_slot = array("appearance.patch_slot").astype(np.int64)
    if (patch_slot >= len(materials)).any():
        raise NBVHFileError(f"{where}: appearance patches name slots beyond the {len(materials)} materials")
    if cfg.stored_maps:
        head.affine[:cfg.stored_maps] = torch.from_numpy(array("appearance.affine"))
    head.patch_slot.copy_(torch.from_numpy(patch_slot))
    head.requires_grad_(False)
    model.appearance = head.eval()


def _load_network(model: NeuralBVH, bits: int, array, names: list[str]) -> None:
    """Fill the model's network from the file's arrays and hold it as stored (float16, or int8 rows + scales)."""
    from ..neural.quantize import dequantize_rows

    if bits > 8:
        model.network.load_state_dict({n[len("network."):]: torch.from_numpy(array(n).astype(np.float32))
                                       for n in names})
        if bits == 16:
            model.hold_network_half()  # resident as stored
        return
    rows, state = {}, {}
    for n in names:
        key = n[len("network."):]
        if key.endswith(".weight_scale"):
            continue
        if f"{n}_scale" in names:
            codes, scale = array(n), array(f"{n}_scale")
            if bits == 4:  # stored offset by 8 (0..15); code -8 is never written, and reads as itself
                codes = (codes.astype(np.int16) - NETWORK_CODE_OFFSET4).astype(np.int8)
            if not np.isfinite(scale.astype(np.float32)).all():
                raise NBVHFileError(f"network scales must be finite ({n})")
            rows[key] = (codes, scale)
            state[key] = torch.from_numpy(dequantize_rows(codes, scale).astype(np.float32))
        else:
            state[key] = torch.from_numpy(array(n).astype(np.float32))
    model.network.load_state_dict(state)
    model.hold_network_int8(rows, bits)


def _check_nodes_links(nodes: np.ndarray, where: str) -> None:
    """The link part of `_check_nodes` (before quantized boxes are decoded along the links)."""
    m = len(nodes)
    left = nodes["left"].astype(np.int64)
    internal = left != 0
    if (left < 0).any() or (internal & ((left <= np.arange(m)) | (left + 1 >= m))).any():
        raise NBVHFileError(f"{where}: BVH child links out of range or not after their parent (a cycle or a "
                            "dangling node)")


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
    header = _parse(data, str(path))
    _decode(data, header, str(path))
    start = header["_payload_start"]
    textures = {}
    for t in header["tensors"]:
        if t["name"].startswith("texture."):
            at = start + t["offset"]  # the image's signature: its first 8 bytes, not a copy of the rest
            textures[int(t["name"].split(".")[1])] = {"format": texture_format(data[at:at + 8]), "bytes": t["nbytes"]}
    return FileInfo(path=str(path), total_bytes=len(data), components=_components(header, len(data)), header=header,
                    stored_bytes=path.stat().st_size, textures=textures)


def look_stored_bytes(cfg: AppearanceConfig | None, materials: list[Material], storage: StorageConfig) -> dict[str, int]:
    """What a file stores for an asset's look, exactly: {'appearance': the head's tensors (cfg None: no head),
    'textures': each slot image as stored, `Material.stored_image`}, so a model is weighed as it ships before it is
    trained."""
    stored = {f"texture.{i}": {"nbytes": len(m.stored_image())} for i, m in enumerate(materials)
              if m.image is not None}
    look = (cfg, [m.to_dict() for m in materials])
    shapes = _look_expected(look, storage, stored, "look")
    out = {"appearance": 0, "textures": 0}
    for name, (shape, kind) in shapes.items():
        out["textures" if name.startswith("texture.") else "appearance"] += _nbytes(shape, kind)
    return out
