"""The BVH component: 32-byte nodes, or 8-bit boxes relative to their parents with the tree's shape as one bit per
node (format 2.5; before it, uint16 links and leaf ordinals). The reader refuses a tree whose child links are out of
range or do not point forward (so traversal cannot loop), whose leaf ordinals are out of range or repeated, or
whose boxes are not finite."""
from __future__ import annotations

import numpy as np

from ..container import SHAPE_BITS_SINCE, pack_codes, writer_version
from ..errors import NBVHFileError
from ...geometry.bvh import NODE_DTYPE
from ...neural.quantize import NONE16, StorageConfig, decode_nodes, encode_nodes, links_from_shape, shape_bits


def bvh_tensors(model, storage: StorageConfig) -> list[tuple[str, str, bytes, list[int]]]:
    """(name, component, bytes, shape) of the BVH's stored tensors at `storage.node_bits`."""
    nodes = np.ascontiguousarray(model.nodes, NODE_DTYPE)
    packed = None
    if storage.node_bits == 8:  # the format the model holds, as it is; else encoded from its nodes
        packed = model.compact_nodes if model.compact_nodes is not None else encode_nodes(nodes)
    if storage.node_bits == 8 and packed is None:
        raise ValueError("the BVH's boxes cannot be quantized relative to their parents (a child outside its "
                         "parent box); save with node_bits=32")
    if packed is None:
        return [("bvh", "bvh", nodes.tobytes(), [len(nodes)])]
    out = []
    shape = shape_bits(packed["left"], packed["leaf"]) if writer_version() >= SHAPE_BITS_SINCE else None
    for part in ("root", "boxes"):
        out.append((f"bvh.{part}", "bvh", packed[part].tobytes(), list(packed[part].shape)))
    if shape is not None:  # 1 bit a node in place of 4 bytes of links (the bunny's 2,047 nodes: 8.2 KB -> 256 B)
        out.append(("bvh.shape", "bvh", pack_codes(shape, 1), [len(shape)]))
    else:
        out += [(f"bvh.{part}", "bvh", packed[part].tobytes(), list(packed[part].shape)) for part in ("left", "leaf")]
    return out


def read_nodes(array, storage: StorageConfig, expected: dict, where: str) -> tuple[np.ndarray, dict | None]:
    """(nodes as `NODE_DTYPE`, the 8-bit form as stored or None) from the file's tensors (`array(name)`), checked."""
    if storage.node_bits != 8:
        nodes = array("bvh")
        check_nodes(nodes, where)
        return nodes, None
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
    check_nodes_links(pre, where)
    if (root[:3] > root[3:]).any():
        raise NBVHFileError(f"{where}: BVH root box is empty")
    compact = {"root": root, "boxes": array("bvh.boxes"), "left": left, "leaf": leaf}
    nodes = decode_nodes(root, compact["boxes"], left, leaf)
    check_nodes(nodes, where)
    return nodes, compact


def check_nodes(nodes: np.ndarray, where: str) -> None:
    """Links in range and pointing forward (no cycle), leaf ordinals 0..n-1 each once, boxes finite or empty."""
    check_nodes_links(nodes, where)
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


def check_nodes_links(nodes: np.ndarray, where: str) -> None:
    """The link part of `check_nodes` (before quantized boxes are decoded along the links)."""
    m = len(nodes)
    left = nodes["left"].astype(np.int64)
    internal = left != 0
    if (left < 0).any() or (internal & ((left <= np.arange(m)) | (left + 1 >= m))).any():
        raise NBVHFileError(f"{where}: BVH child links out of range or not after their parent (a cycle or a "
                            "dangling node)")
