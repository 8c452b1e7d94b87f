"""The shape table of a .nbvh file: which tensors a config stores, their shapes and kinds, and so their bytes.

One table serves three readers: the planner sizes a model before training (`payload_bytes`, `look_stored_bytes`),
the writer's components write exactly these tensors, and the reader (`header.check_header`) refuses a file whose
tensor table differs from it before anything is allocated. A kind is a numpy dtype string, 'node' (a 32-byte BVH
node, `bvh.NODE_DTYPE`) or 'packed<bits>' (codes packed as `container.pack_codes` packs them).
"""
from __future__ import annotations

import numpy as np
import torch

from .container import REACHABLE_INDEX_SINCE, SHAPE_BITS_SINCE, writer_version
from .errors import NBVHFileError
from ..geometry.bvh import NODE_DTYPE
from ..geometry.look import Material
from ..neural.appearance import AppearanceConfig, AppearanceHead, head_table_bits, map_width
from ..neural.encodings.base import code_width, level_vertex_counts
from ..neural.model import ModelConfig
from ..neural.quantize import StorageConfig

#: A texture's decoded pixels may be at most this many times its stored bytes (a flat 4k image compresses ~1300x)
#: or MIN_TEXTURE_ALLOWANCE, whichever is larger: a crafted tiny PNG cannot ask for gigabytes.
TEXTURE_INFLATION = 4096
MIN_TEXTURE_ALLOWANCE = 16 << 20


def float_dtype(bits: int):
    """The numpy type of float rows stored at `bits` (16: float16, else float32)."""
    return np.float16 if bits == 16 else np.float32


def network_shapes(cfg: ModelConfig) -> dict[str, tuple[int, ...]]:
    """state_dict shapes of the network `cfg` describes, computed on the meta device (nothing allocated)."""
    from ..neural.networks import make_network

    with torch.device("meta"):
        net = make_network(cfg.encoding.out_dim, cfg.network)
    return {name: tuple(p.shape) for name, p in net.state_dict().items()}


def expected_tensors(cfg: ModelConfig, storage: StorageConfig, n_nodes: int,
                      version: tuple[int, int] | None = None,
                      shape_only: bool = False) -> dict[str, tuple[tuple, str]]:
    """name -> (shape, numpy dtype or 'packed<bits>') of every tensor a file of this format version and config
    must hold (shape_only: its 8-bit BVH holds the tree's shape as bits, from format 2.5 on; version: the writer's
    by default)."""
    version = version or writer_version()
    enc = cfg.encoding
    L, T, F = enc.levels, enc.table_size, enc.features
    table = table_shapes("features", L, T, F, storage.table_bits)
    network = network_shapes(cfg)
    out: dict[str, tuple[tuple, str]] = {}
    if storage.node_bits == 8:
        out.update({"bvh.root": ((6,), "<f4"), "bvh.boxes": ((n_nodes, 6), "u1")})
        if shape_only and version >= SHAPE_BITS_SINCE:
            out["bvh.shape"] = ((n_nodes,), "packed1")
        else:
            out.update({"bvh.left": ((n_nodes,), "<u2"), "bvh.leaf": ((n_nodes,), "<u2")})
    else:
        out["bvh"] = ((n_nodes,), "node")
    out.update(table)
    if enc.kind == "hashvqad":
        shape = ((sum(level_vertex_counts(enc, enc.index_size)),) if version >= REACHABLE_INDEX_SINCE
                 else (L, enc.index_size))
        out["index"] = (shape, f"packed{code_width(enc.candidates)}")
    fdt = "<f4" if storage.network_bits == 32 else "<f2"
    for name, shape in network.items():
        if storage.network_bits <= 8 and name.endswith("weight") and len(shape) == 2:
            out[f"network.{name}"] = (shape, "i1" if storage.network_bits == 8 else "packed4")
            out[f"network.{name}_scale"] = ((shape[0],), "<f2")
        else:
            out[f"network.{name}"] = (shape, fdt)
    return out


def payload_bytes(cfg: ModelConfig, storage: StorageConfig, n_nodes: int) -> int:
    """Bytes of the tensors a file of this config holds for `n_nodes` nodes laid out by `bvh.layout_cut` (every
    trained tree; the 8-bit BVH as shape bits), header and checksum excluded: the reader's own shape table
    (`expected_tensors`), so the planner sizes exactly what the writer writes and the reader checks."""
    tensors = expected_tensors(cfg, storage, n_nodes, shape_only=True)
    return sum(nbytes(shape, kind) for shape, kind in tensors.values())


def table_shapes(name: str, levels: int, rows: int, features: int, bits: int) -> dict[str, tuple[tuple, str]]:
    """name -> (shape, dtype) of a feature table's stored tensors (see `table_tensors`)."""
    if bits <= 8:
        kind = "u1" if bits == 8 else f"packed{bits}"
        return {name: ((levels, rows, features), kind), f"{name}.offset": ((levels, features), "<f4"),
                f"{name}.scale": ((levels, features), "<f4")}
    return {name: ((levels, rows, features), "<f2" if bits == 16 else "<f4")}


def nbytes(shape: tuple, kind: str) -> int:
    count = int(np.prod(shape, dtype=np.int64)) if shape else 1
    if kind == "node":
        return count * NODE_DTYPE.itemsize
    if kind.startswith("packed"):
        return (count * int(kind[6:]) + 7) // 8
    return count * np.dtype(kind).itemsize


def look_expected(look, storage: StorageConfig, by_name: dict, where: str) -> dict[str, tuple[tuple, str]]:
    """name -> (shape, dtype) of the appearance head's tensors and the textures (each image's bytes as long as its
    entry says, its decoded size bounded by TEXTURE_INFLATION x its bytes)."""
    if look is None:
        return {}
    cfg, mats = look
    out: dict[str, tuple[tuple, str]] = {}
    if cfg is not None:
        out.update(table_shapes("appearance.features", cfg.levels, 1 << cfg.log2_table, cfg.features,
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


def look_stored_bytes(cfg: AppearanceConfig | None, materials: list[Material], storage: StorageConfig) -> dict[str, int]:
    """What a file stores for an asset's look, exactly: {'appearance': the head's tensors (cfg None: no head),
    'textures': each slot image as stored, `Material.stored_image`}, so a model is weighed as it ships before it is
    trained."""
    stored = {f"texture.{i}": {"nbytes": len(m.stored_image())} for i, m in enumerate(materials)
              if m.image is not None}
    look = (cfg, [m.to_dict() for m in materials])
    shapes = look_expected(look, storage, stored, "look")
    out = {"appearance": 0, "textures": 0}
    for name, (shape, kind) in shapes.items():
        out["textures" if name.startswith("texture.") else "appearance"] += nbytes(shape, kind)
    return out
