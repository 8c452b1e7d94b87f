"""Quantized storage of a model (numpy only): BVH boxes relative to their parent, feature tables in 8 bits.

**Nodes** (`node_bits=8`): the root box is kept exact (6 float32); every other node's box is stored as 6 uint8
codes relative to its parent's *decoded* box, per axis `lo = plo + q_lo * ((phi - plo) / 255)` (code 255: phi exactly; float32, the one
formula `decode_nodes` uses). Rounding is conservative: the encoder picks the largest q_lo whose decoded value is
<= the exact lo and the smallest q_hi whose decoded value is >= the exact hi, checked with the decoder's own float32
arithmetic, so a decoded box always contains its exact box and traversal never misses a leaf. The child link and
the leaf ordinal are uint16 (the node budget is <= 65535; 65535 stands for "none"). 10 bytes per node instead
of 32. A box that cannot be contained (a child outside its parent) makes `encode_nodes` return None: the file
then keeps the exact float32 nodes.

`snap_nodes` returns the decoded boxes: the pipeline trains on them, so the model is trained on exactly the
boxes the file stores (no mismatch between training and the loaded model).

**Feature tables** (`table_bits=8`): per level and feature an affine map `value = offset + code * scale` with
(offset, scale) from the min and max over the level's rows; codes uint8. The fused kernels read the codes
directly (`kernels`: accumulate the 8 corners' codes, then one multiply-add per feature, exact because the
trilinear weights sum to 1), so no float copy of the table is resident.

**Network weights** (`network_bits=8` or 4): each Linear layer's weight rows (one per output unit) as signed codes
with one float16 scale per row, symmetric (`w = code * scale`, scale = max |w| of the row / 127 at 8 bits, / 7 at 4
bits, so the largest weight is exact); biases float16. 4-bit codes are stored two to a byte and held as int8 codes
in [-7, 7]; training ends through them (`training.train.NetworkQuantization`: the straight-through estimator). A weight's value is float16(code * scale) on every path (the reference and the fused
kernels agree bit for bit). Measured on the bunny (default preset, 60 s): image MSE 0.000840 with float16 weights,
0.000847 with int8 rows (+0.9%; 6 bits: +9%), so no fine-tuning is needed for it.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ..geometry.bvh import NODE_DTYPE

NONE16 = 65535
#: Bits per stored feature value: float32, float16, or codes (8, 6, 4) on a per (level, feature) affine grid.
TABLE_BITS = (32, 16, 8, 6, 4)
#: Bits per stored network weight: float32, float16, or signed codes (8, 4) with a float16 scale per row.
NETWORK_BITS = (32, 16, 8, 4)
#: Bits per BVH box coordinate: float32, or 8-bit codes relative to the parent box.
NODE_BITS = (32, 8)
#: Below 8 bits a table's grid spans its rows between this percentile and its mirror per (level, feature): a few
#: outlying rows would otherwise leave most rows two or three codes. Measured after a 60 s bunny training (default
#: preset, 16 held-out views at 256 px): rounding to 4 bits over the full range read 4.9x the float model's MSE,
#: clipped at 1% 2.2x (6 bits: 1.24x; 8 bits over the full range: 1.03x).
LOW_BITS_CLIP_PERCENT = 1.0
_Q = np.float32(255.0)


@dataclass(frozen=True)
class StorageConfig:
    """Bits per stored value: table_bits in TABLE_BITS (8, 6 and 4: codes on a per level and feature affine grid,
    6- and 4-bit codes packed as one bit stream), network_bits in NETWORK_BITS, node_bits in {32, 8}."""

    table_bits: int = 8
    network_bits: int = 16
    node_bits: int = 8

    def __post_init__(self):
        for name, allowed in (("table_bits", TABLE_BITS), ("network_bits", NETWORK_BITS), ("node_bits", NODE_BITS)):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v not in allowed:
                raise ValueError(f"{name} must be one of {allowed}, got {v!r}")

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def float32() -> "StorageConfig":
        return StorageConfig(32, 32, 32)


# ---------------------------------------------------------------------------------------------------- nodes
def _decode_child(plo: np.ndarray, phi: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(n, 3) float32 parent bounds, (n, 3) codes -> (n, 3) float32 decoded bounds (the one decode formula)."""
    with np.errstate(over="ignore", invalid="ignore"):  # a crafted root box may overflow: the reader refuses it
        step = (phi - plo) / _Q
        out = (plo + q.astype(np.float32) * step).astype(np.float32)
    return np.where(q >= 255, phi, out).astype(np.float32)  # the top code is the parent's bound exactly


def _frontier_order(left: np.ndarray):
    """Yield arrays of internal nodes, parents before children (breadth first from the root)."""
    frontier = np.array([0], np.int64)
    while frontier.size:
        internal = frontier[left[frontier] != 0]
        if internal.size == 0:
            return
        yield internal
        kids = left[internal].astype(np.int64)
        frontier = np.concatenate((kids, kids + 1))


def encode_nodes(nodes: np.ndarray) -> dict | None:
    """NODE_DTYPE nodes -> {'root': (6,) f32, 'boxes': (M, 6) u8, 'left': (M,) u16, 'leaf': (M,) u16}, or None
    when some box cannot be contained in its parent's decoded box (then keep float32 nodes)."""
    m = len(nodes)
    if m == 0 or m > NONE16:
        return None
    left = nodes["left"].astype(np.int64)
    lo, hi = nodes["lo"].astype(np.float32), nodes["hi"].astype(np.float32)
    dec_lo, dec_hi = np.full((m, 3), np.inf, np.float32), np.full((m, 3), -np.inf, np.float32)
    dec_lo[0], dec_hi[0] = lo[0], hi[0]
    boxes = np.zeros((m, 6), np.uint8)
    boxes[:, :3] = 255  # unreached nodes (the padding node) decode as empty (q_lo > q_hi)
    for parents in _frontier_order(left):
        kids = np.concatenate((left[parents], left[parents] + 1))
        plo, phi = np.tile(dec_lo[parents], (2, 1)), np.tile(dec_hi[parents], (2, 1))
        clo, chi = lo[kids], hi[kids]
        empty = (clo > chi).any(axis=1)
        ext = (phi - plo) / _Q
        with np.errstate(divide="ignore", invalid="ignore"):
            q_lo = np.where(ext > 0, np.floor((clo - plo) / np.where(ext > 0, ext, 1)), 0)
            q_hi = np.where(ext > 0, np.ceil((chi - plo) / np.where(ext > 0, ext, 1)), 255)
        q_lo = np.clip(np.nan_to_num(q_lo, nan=0, posinf=255, neginf=0), 0, 255).astype(np.int64)
        q_hi = np.clip(np.nan_to_num(q_hi, nan=255, posinf=255, neginf=0), 0, 255).astype(np.int64)
        # Make the rounding exact in the decoder's arithmetic: largest q_lo decoding <= lo, smallest q_hi >= hi.
        for _ in range(4):
            over = (_decode_child(plo, phi, q_lo) > clo) & (q_lo > 0)
            q_lo -= over
            up = (q_lo < 255) & (_decode_child(plo, phi, np.minimum(q_lo + 1, 255)) <= clo)
            q_lo += up
            under = (_decode_child(plo, phi, q_hi) < chi) & (q_hi < 255)
            q_hi += under
            down = (q_hi > 0) & (_decode_child(plo, phi, np.maximum(q_hi - 1, 0)) >= chi)
            q_hi -= down
        # A parent thinner than 255 float32 steps decodes runs of codes to one value: the search can then pass
        # q_lo beyond q_hi on a flat child, which the decoder reads as empty. Both decode to the flat face there
        # (decoding is monotonic in q), so equal codes hold it.
        q_lo = np.minimum(q_lo, q_hi)
        d_lo, d_hi = _decode_child(plo, phi, q_lo), _decode_child(plo, phi, q_hi)
        ok = empty | ((d_lo <= clo) & (d_hi >= chi)).all(axis=1)
        if not ok.all():
            return None
        q_lo[empty], q_hi[empty] = 255, 0
        boxes[kids, :3], boxes[kids, 3:] = q_lo, q_hi
        d_lo[empty], d_hi[empty] = np.inf, -np.inf
        dec_lo[kids], dec_hi[kids] = d_lo, d_hi
    leaf = nodes["leaf"].astype(np.int64)
    return {"root": np.concatenate((lo[0], hi[0])).astype(np.float32), "boxes": boxes,
            "left": left.astype(np.uint16), "leaf": np.where(leaf < 0, NONE16, leaf).astype(np.uint16)}


def decode_nodes(root: np.ndarray, boxes: np.ndarray, left: np.ndarray, leaf: np.ndarray) -> np.ndarray:
    """Inverse of `encode_nodes` (the caller has validated the structure: every child index > its parent's)."""
    m = len(left)
    nodes = np.zeros(m, NODE_DTYPE)
    left64 = left.astype(np.int64)
    dec_lo, dec_hi = np.full((m, 3), np.inf, np.float32), np.full((m, 3), -np.inf, np.float32)
    dec_lo[0], dec_hi[0] = root[:3], root[3:]
    for parents in _frontier_order(left64):
        kids = np.concatenate((left64[parents], left64[parents] + 1))
        plo, phi = np.tile(dec_lo[parents], (2, 1)), np.tile(dec_hi[parents], (2, 1))
        q = boxes[kids].astype(np.int64)
        d_lo, d_hi = _decode_child(plo, phi, q[:, :3]), _decode_child(plo, phi, q[:, 3:])
        empty = (q[:, :3] > q[:, 3:]).any(axis=1)
        d_lo[empty], d_hi[empty] = np.inf, -np.inf
        dec_lo[kids], dec_hi[kids] = d_lo, d_hi
    nodes["lo"], nodes["hi"] = dec_lo, dec_hi
    nodes["left"] = left64
    nodes["leaf"] = np.where(leaf.astype(np.int64) == NONE16, -1, leaf.astype(np.int64))
    return nodes


def stored_node_bytes(n_nodes: int, node_bits: int, shape_only: bool = True) -> int:
    """Bytes a file spends on n_nodes BVH nodes: 32 each as float32 records, else the exact root (6 float32) and
    per node 6 uint8 box codes (`encode_nodes`) plus the tree's shape: one bit per node when the nodes are laid
    out as `bvh.layout_cut` lays them (`shape_bits`; shape_only), else a uint16 link and a uint16 leaf ordinal."""
    if node_bits == 32:
        return n_nodes * NODE_DTYPE.itemsize
    return 6 * 4 + n_nodes * 6 + ((n_nodes + 7) // 8 if shape_only else n_nodes * 4)


def shape_bits(left: np.ndarray, leaf: np.ndarray) -> np.ndarray | None:
    """(M,) uint8 0/1: 1 where node i is internal, or None when the links and leaf ordinals are not the ones
    `links_from_shape` derives from those bits (a tree not laid out breadth first with sibling pairs in order,
    the padding node at 1 when M is even, leaves numbered in node order): then a file keeps the links."""
    left, leaf = np.asarray(left, np.int64), np.asarray(leaf, np.int64)
    bits = (left != 0).astype(np.uint8)
    if len(left) % 2 == 0 and len(left) > 1:
        bits[1] = 0
    try:
        d_left, d_leaf = links_from_shape(bits)
    except ValueError:
        return None
    leaf = np.where(leaf == NONE16, -1, leaf)
    return bits if np.array_equal(d_left, left) and np.array_equal(d_leaf, leaf) else None


def links_from_shape(bits: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(M,) 0/1 internal flags -> (left (M,) int64, leaf (M,) int64; -1 for internal nodes and the padding node),
    as `bvh.layout_cut` lays a tree out: root 0, the padding node 1 when M is even (a binary tree has an odd node
    count), then each internal node's two children at the next free pair in node order, leaves numbered in node
    order. Raises ValueError when the bits are not such a tree (the count of internal nodes, a child before its
    parent)."""
    bits = np.asarray(bits).astype(bool)
    m = len(bits)
    padded = m % 2 == 0 and m > 1
    real = np.ones(m, bool)
    if padded:
        if bits[1]:
            raise ValueError("the padding node cannot be internal")
        real[1] = False
    n_real = m - int(padded)
    if m == 0 or int(bits.sum()) != (n_real - 1) // 2:
        raise ValueError(f"{int(bits.sum())} internal nodes cannot make a binary tree of {n_real} nodes")
    first_child = 2 if padded else 1
    before = np.cumsum(bits) - bits  # internal nodes before each node
    left = np.where(bits, first_child + 2 * before, 0).astype(np.int64)
    is_leaf = real & ~bits
    leaf = np.where(is_leaf, np.cumsum(is_leaf) - 1, -1).astype(np.int64)
    if (bits & (left <= np.arange(m))).any():
        raise ValueError("a child comes before its parent")
    return left, leaf


def snap_nodes(nodes: np.ndarray) -> np.ndarray:
    """The boxes a quantized file stores (each contains its exact box), or `nodes` when they cannot be quantized."""
    enc = encode_nodes(nodes)
    if enc is None:
        return nodes
    return decode_nodes(enc["root"], enc["boxes"], enc["left"], enc["leaf"])


# ---------------------------------------------------------------------------------------------------- tables
def table_affine(table: np.ndarray, bits: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Per (level, feature) (offset, scale), each (L, F) float32, of a (L, T, F) float32 table: the grid spans the
    rows' range at 8 bits, below 8 bits the range between LOW_BITS_CLIP_PERCENT and its mirror (the tails clipped),
    for the quantization-aware phase and for a table stored without one alike."""
    levels = (1 << bits) - 1
    clip_percent = LOW_BITS_CLIP_PERCENT if bits < 8 else 0.0
    if clip_percent > 0:
        mn = np.percentile(table, clip_percent, axis=1).astype(np.float32)
        mx = np.percentile(table, 100.0 - clip_percent, axis=1).astype(np.float32)
    else:
        mn = table.min(axis=1).astype(np.float32)
        mx = table.max(axis=1).astype(np.float32)
    scale = ((mx - mn) / np.float32(levels)).astype(np.float32)
    scale = np.where(scale > 0, scale, np.float32(1e-12)).astype(np.float32)
    return mn, scale


def quantize_table(table: np.ndarray, offset: np.ndarray, scale: np.ndarray, bits: int = 8) -> np.ndarray:
    """(L, T, F) float32 -> (L, T, F) uint8 codes (< 2^bits), round to nearest of `offset + code * scale`."""
    levels = (1 << bits) - 1
    q = np.rint((table - offset[:, None, :]) / scale[:, None, :])
    return np.clip(q, 0, levels).astype(np.uint8)


def dequantize_table(codes: np.ndarray, offset: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """(L, T, F) uint8 -> float32 values (the formula the kernels use per looked-up row)."""
    return (offset[:, None, :] + codes.astype(np.float32) * scale[:, None, :]).astype(np.float32)


# ---------------------------------------------------------------------------------------------------- network
def code_limit(bits: int) -> int:
    """The largest signed code of a `bits`-bit weight row (127 at 8 bits, 7 at 4): codes lie in [-limit, limit]."""
    return (1 << (bits - 1)) - 1


def quantize_rows(weight: np.ndarray, bits: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """(out, in) float weights -> (out, in) int8 codes in [-code_limit(bits), code_limit(bits)] and (out,) float16
    scales (symmetric per row; a zero row gets scale 1). The scale is rounded to float16 first and the codes computed
    against it, so the stored pair is exactly what `dequantize_rows` reads."""
    w = np.asarray(weight, np.float32)
    limit = code_limit(bits)
    amax = np.abs(w).max(axis=1) if w.size else np.zeros(w.shape[0], np.float32)
    scale = np.where(amax > 0, amax / limit, 1.0).astype(np.float16)
    scale = np.where(scale > 0, scale, np.float16(1.0)).astype(np.float16)  # a row too small for float16's range
    codes = np.clip(np.rint(w / scale.astype(np.float32)[:, None]), -limit, limit).astype(np.int8)
    return codes, scale


def dequantize_rows(codes: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """(out, in) int8, (out,) float16 -> (out, in) float16 weights: float16(code * scale)."""
    return (codes.astype(np.float32) * scale.astype(np.float32)[:, None]).astype(np.float16)
