"""A compact ray-traceable mesh: the strongest plain-mesh contender a model is measured against.

The layout follows what dense geometry formats (AMD's DGF, Barczak et al. 2024) and compressed wide BVHs (Ylitie et
al. 2017) do, written here from their published descriptions: triangles in clusters of at most 64, positions on one
global grid stored as 16-bit offsets from a per-cluster anchor (so a vertex shared by two clusters decodes to the
same point: no cracks), cluster-local 8-bit indices, normals derived from the geometry (none stored), and a BVH over
the clusters whose child boxes are 8-bit, conservative, relative to the parent's decoded box.

    data = encode_compact(mesh)        # bytes; len(data) is the format's exact size
    decoded = decode_compact(data)     # CompactMesh: the triangles a tracer of this format would hit, its boxes

Layout (little endian):

    header   52 B   magic b"CMSH", node count, cluster count (u32 each), grid origin (3 f32), grid step (f32),
                    root box (6 f32: lo, hi, rounded outward)
    nodes    10 B each, BFS order from the root: box (6 u8: lo, hi in 1/255ths of the parent's box, floor/ceil),
                    link (u32: first child, the second follows it; or LEAF_BIT | cluster index)
    clusters 18 B each: anchor (3 i32, grid units), vertex count, triangle count (u8 each, count - 1),
                    data offset (u32, from the start of the cluster data)
    data     per cluster: vertices (3 u16 offsets from the anchor each), then triangles (3 u8 local indices each)
"""
from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from .bvh import build_full_tree
from .mesh import Mesh

MAGIC = b"CMSH"
#: Triangles per cluster (and so at most 192 <= 256 distinct vertices: 8-bit local indices always suffice).
CLUSTER_TRIANGLES = 64
LEAF_BIT = 1 << 31
_HEADER = struct.Struct("<4sII3ff6f")
NODE_BYTES, CLUSTER_BYTES = 10, 18


@dataclass
class CompactMesh:
    """A decoded compact mesh. vertices (V, 3) float32 (each cluster's own copy of its vertices), faces (F, 3)
    int32 into them; node_lo/node_hi (N, 3) float32 decoded boxes; node_link (N,) uint32; cluster_of_face (F,)."""

    vertices: np.ndarray
    faces: np.ndarray
    node_lo: np.ndarray
    node_hi: np.ndarray
    node_link: np.ndarray
    cluster_of_face: np.ndarray


def _clusters(mesh: Mesh, tree) -> tuple[np.ndarray, np.ndarray]:
    """The BVH over clusters, from `tree` (a full tree of `mesh`): (kept node ids of `tree` in BFS order, whether each
    is a cluster). A cluster is the highest node of at most CLUSTER_TRIANGLES triangles."""
    order, is_cluster = [0], []
    head = 0
    while head < len(order):
        node = order[head]
        head += 1
        leaf = tree.count[node] <= CLUSTER_TRIANGLES or tree.left[node] < 0
        is_cluster.append(leaf)
        if not leaf:
            order += [int(tree.left[node]), int(tree.left[node]) + 1]
    return np.asarray(order, np.int64), np.asarray(is_cluster, bool)


def _grid(vertices: np.ndarray, spans: list[np.ndarray]) -> tuple[np.ndarray, float]:
    """The global grid's origin and step: the widest cluster spans at most 65534 steps (16-bit offsets)."""
    origin = vertices.min(axis=0).astype(np.float32)
    widest = max(float((vertices[s].max(axis=0) - vertices[s].min(axis=0)).max()) for s in spans)
    return origin, np.float32(max(widest, 1e-12) / 65534.0)


def _quantize_box(lo, hi, plo, phi) -> np.ndarray:
    """A child box as 6 u8 in 1/255ths of its parent's box, rounded outward (the decoded box contains it)."""
    ext = np.maximum(phi - plo, np.float32(1e-30))
    qlo = np.clip(np.floor((lo - plo) / ext * 255.0), 0, 255)
    qhi = np.clip(np.ceil((hi - plo) / ext * 255.0), 0, 255)
    return np.concatenate((qlo, qhi)).astype(np.uint8)


def _dequantize_box(q: np.ndarray, plo: np.ndarray, phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    ext = (phi - plo).astype(np.float64)
    lo = plo + q[:3] / 255.0 * ext
    hi = plo + q[3:] / 255.0 * ext
    # float rounding must never shrink a box: widen by one ulp each way
    return (np.nextafter(lo.astype(np.float32), -np.inf), np.nextafter(hi.astype(np.float32), np.inf))


def encode_compact(mesh: Mesh, tree=None) -> bytes:
    """`mesh` in the compact layout (module docstring). tree: the mesh's `bvh.build_full_tree` when the caller has
    one (clusters are cut from it), else one is built."""
    tree = tree if tree is not None else build_full_tree(mesh)
    order, is_cluster = _clusters(mesh, tree)
    cluster_nodes = order[is_cluster]
    tri_sets = [tree.tri_order[tree.start[n]:tree.start[n] + tree.count[n]] for n in cluster_nodes]
    vert_sets = [np.unique(mesh.faces[t]) for t in tri_sets]
    origin, step = _grid(mesh.vertices, vert_sets)
    grid = np.rint((mesh.vertices.astype(np.float64) - origin) / step).astype(np.int64)
    decoded = (origin + grid * np.float64(step)).astype(np.float32)
    clusters, data = [], []
    offset = 0
    cluster_lo, cluster_hi = [], []
    for tris, verts in zip(tri_sets, vert_sets):
        anchor = grid[verts].min(axis=0)
        local = np.searchsorted(verts, mesh.faces[tris])
        payload = (grid[verts] - anchor).astype("<u2").tobytes() + local.astype(np.uint8).tobytes()
        clusters.append(struct.pack("<3iBBI", *anchor.astype(np.int32), len(verts) - 1, len(tris) - 1, offset))
        data.append(payload)
        offset += len(payload)
        cluster_lo.append(decoded[verts].min(axis=0))
        cluster_hi.append(decoded[verts].max(axis=0))
    nodes = _encode_nodes(order, is_cluster, tree, np.asarray(cluster_lo), np.asarray(cluster_hi))
    root_lo = np.nextafter(np.min(cluster_lo, axis=0), -np.inf).astype(np.float32)
    root_hi = np.nextafter(np.max(cluster_hi, axis=0), np.inf).astype(np.float32)
    header = _HEADER.pack(MAGIC, len(order), len(clusters), *origin, step, *root_lo, *root_hi)
    return header + nodes + b"".join(clusters) + b"".join(data)


def _encode_nodes(order, is_cluster, tree, cluster_lo, cluster_hi) -> bytes:
    """Node boxes (bottom-up from the decoded clusters' boxes) quantized top-down against their parents' decoded
    boxes, and their links."""
    n = len(order)
    index = {int(node): i for i, node in enumerate(order)}
    lo = np.zeros((n, 3), np.float32)
    hi = np.zeros((n, 3), np.float32)
    cluster_index = np.cumsum(is_cluster) - 1
    for i in range(n - 1, -1, -1):
        if is_cluster[i]:
            lo[i], hi[i] = cluster_lo[cluster_index[i]], cluster_hi[cluster_index[i]]
        else:
            c = index[int(tree.left[order[i]])]
            lo[i], hi[i] = np.minimum(lo[c], lo[c + 1]), np.maximum(hi[c], hi[c + 1])
    dlo = np.zeros_like(lo)
    dhi = np.zeros_like(hi)
    dlo[0] = np.nextafter(lo[0], -np.inf)
    dhi[0] = np.nextafter(hi[0], np.inf)
    out = bytearray()
    parent_of = {}
    for i in range(n):
        plo, phi = (dlo[0], dhi[0]) if i == 0 else (dlo[parent_of[i]], dhi[parent_of[i]])
        q = _quantize_box(lo[i], hi[i], plo, phi)
        dlo[i], dhi[i] = _dequantize_box(q, plo, phi)
        if is_cluster[i]:
            link = LEAF_BIT | int(cluster_index[i])
        else:
            link = index[int(tree.left[order[i]])]
            parent_of[link] = parent_of[link + 1] = i
        out += q.tobytes() + struct.pack("<I", link)
    return bytes(out)


def decode_compact(data: bytes) -> CompactMesh:
    """The triangles and boxes `data` holds (what a tracer of the layout would intersect)."""
    magic, n_nodes, n_clusters, *rest = _HEADER.unpack_from(data, 0)
    if magic != MAGIC:
        raise ValueError("not a compact mesh")
    origin, step = np.asarray(rest[:3], np.float32), np.float32(rest[3])
    root = np.asarray(rest[4:10], np.float32)
    pos = _HEADER.size
    node_raw = np.frombuffer(data, np.uint8, n_nodes * NODE_BYTES, pos).reshape(n_nodes, NODE_BYTES)
    pos += n_nodes * NODE_BYTES
    links = node_raw[:, 6:].copy().view("<u4").ravel()
    lo, hi = np.zeros((n_nodes, 3), np.float32), np.zeros((n_nodes, 3), np.float32)
    lo[0], hi[0] = _dequantize_box(node_raw[0, :6], root[:3], root[3:])
    for i in range(n_nodes):
        if not links[i] & LEAF_BIT:
            for c in (int(links[i]), int(links[i]) + 1):
                lo[c], hi[c] = _dequantize_box(node_raw[c, :6], lo[i], hi[i])
    data_start = pos + n_clusters * CLUSTER_BYTES
    vertices, faces, owner = [], [], []
    base = 0
    for k in range(n_clusters):
        ax, ay, az, nv, nt, off = struct.unpack_from("<3iBBI", data, pos + k * CLUSTER_BYTES)
        nv, nt = nv + 1, nt + 1
        at = data_start + off
        offs = np.frombuffer(data, "<u2", nv * 3, at).reshape(nv, 3).astype(np.int64)
        local = np.frombuffer(data, np.uint8, nt * 3, at + nv * 6).reshape(nt, 3).astype(np.int32)
        grid = offs + np.array([ax, ay, az], np.int64)
        vertices.append((origin + grid * np.float64(step)).astype(np.float32))
        faces.append(local + base)
        owner.append(np.full(nt, k, np.int32))
        base += nv
    return CompactMesh(np.concatenate(vertices), np.concatenate(faces), lo, hi, links, np.concatenate(owner))


def compact_bytes(mesh: Mesh, tree=None) -> int:
    """len(encode_compact(mesh, tree)) without encoding: header, nodes, cluster records, each cluster's distinct
    vertices (6 B) and triangles (3 B). Vectorised: a 3.3M-triangle mesh in seconds, for the verdict."""
    tree = tree if tree is not None else build_full_tree(mesh)
    order, is_cluster = _clusters(mesh, tree)
    clusters = order[is_cluster]
    owner = np.empty(mesh.n_triangles, np.int64)
    for k, node in enumerate(clusters):  # tri_order ranges: one slice assignment per cluster
        owner[tree.tri_order[tree.start[node]:tree.start[node] + tree.count[node]]] = k
    pairs = np.unique(owner[:, None] * np.int64(mesh.n_vertices) + mesh.faces.astype(np.int64))
    return _HEADER.size + NODE_BYTES * len(order) + CLUSTER_BYTES * len(clusters) + 6 * len(pairs) \
        + 3 * mesh.n_triangles


def compact_mesh(mesh: Mesh, tree=None) -> tuple[int, Mesh]:
    """(exact bytes of `mesh` in the compact layout, the decoded triangles as a Mesh in the same normalised
    coordinates, for measuring the image error of what the layout holds)."""
    data = encode_compact(mesh, tree)
    dec = decode_compact(data)
    # a sliver the 16-bit grid collapsed to zero area is never hit (Embree skips it) and has no normal: left out
    tri = dec.vertices[dec.faces].astype(np.float64)
    keep = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1) > 0
    return len(data), Mesh(vertices=dec.vertices, faces=dec.faces[keep], transform=mesh.transform, name=mesh.name)
