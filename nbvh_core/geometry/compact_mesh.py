"""A compact ray-traceable mesh (a dense-geometry layout): the strongest plain-mesh contender a model is weighed
against.

Written from the published descriptions of AMD's Dense Geometry Format (Barczak et al., HPG 2024) and compressed
wide BVHs (Ylitie et al. 2017); no code copied. Triangles are cut into clusters of at most 64 from a SAH tree; each
cluster is decodable on its own, so a tracer walks the cluster BVH and decodes only the clusters a ray reaches.

- Positions lie on one global grid (`grid_bits` per axis over the longest side of the box), stored per cluster as
  offsets from the cluster's anchor with the cluster's own bit width per axis (the span it needs): a vertex shared
  by two clusters is the same grid point in both, so there are no cracks.
- Topology is a generalised triangle strip per cluster, its vertices numbered by first use: each triangle is a
  2-bit code (restart, or continue across one of the previous triangle's two open edges, or an escape for a
  triangle wound against its neighbour), and each vertex it brings is one bit when it is the next unseen vertex,
  else one bit and a local index of ceil(log2 V) bits.
- Normals are derived from the geometry (none stored). A BVH over the clusters has child boxes of 6 u8, relative to
  the parent's decoded box, rounded outward.

    data = encode_compact(mesh)        # bytes; len(data) is the format's exact size
    decoded = decode_compact(data)     # CompactMesh: the triangles a tracer of this format would hit, its boxes

Layout (little endian):

    header   48 B   magic b"CMS2", node count, cluster count (u32 each), grid origin (3 f32), grid step (f32),
                    root box (6 f32: lo, hi, rounded outward)
    nodes    10 B each, BFS order from the root: box (6 u8: lo, hi in 1/255ths of the parent's box, floor/ceil),
                    link (u32: first child, the second follows it; or LEAF_BIT | cluster index)
    clusters 14 B each: anchor (3 u16, grid units), bit widths (u16: 5 bits per axis), vertex count - 1,
                    triangle count - 1 (u8 each), data offset (u32, from the start of the cluster data)
    data     per cluster, byte aligned: vertex offsets (x, y, z at the cluster's widths, LSB first), then the
                    strip code (LSB first)
"""
from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from .bvh import build_full_tree
from .cluster_codec import EDGE_1, ESCAPE, RESTART, cluster_payloads
from .mesh import CROSS_CHUNK, Mesh, face_cross_chunks

MAGIC = b"CMS2"
#: Triangles per cluster (at most 192 distinct vertices: the counts fit a byte).
CLUSTER_TRIANGLES = 64
#: Global grid resolution per axis over the longest side. 2^-14 of the object is 1/64 px at 256 px across: the
#: decoded bunny's image MSE against the original is below 1e-6 (tests/test_compact_mesh.py), far under any level.
GRID_BITS = 14
LEAF_BIT = 1 << 31
_HEADER = struct.Struct("<4sII3ff6f")
_CLUSTER = struct.Struct("<3HHBBI")
NODE_BYTES, CLUSTER_BYTES = 10, _CLUSTER.size


@dataclass
class CompactMesh:
    """A decoded compact mesh. vertices (V, 3) float32 (each cluster's own copy of its vertices), faces (F, 3)
    int32 into them; node_lo/node_hi (N, 3) float32 decoded boxes; node_link (N,) uint32; cluster_of_face (F,);
    grid (V, 3) int64, each vertex's global grid point; step, the grid step (object units)."""

    vertices: np.ndarray
    faces: np.ndarray
    node_lo: np.ndarray
    node_hi: np.ndarray
    node_link: np.ndarray
    cluster_of_face: np.ndarray
    grid: np.ndarray
    step: float


def _clusters(tree) -> list[np.ndarray]:
    """Each cluster's triangles (indices into the mesh), in the tree's depth-first order. The highest nodes of at
    most CLUSTER_TRIANGLES triangles, then neighbours in that order merged while they fit: a cluster holds 62 of 64
    triangles on average on the bunny where the nodes alone hold 44 (fewer records, fewer shared vertices)."""
    UNIT = CLUSTER_TRIANGLES
    ranges, stack = [], [0]
    while stack:
        node = stack.pop()
        if tree.count[node] <= UNIT or tree.left[node] < 0:
            ranges.append((int(tree.start[node]), int(tree.count[node])))
        else:
            stack += [int(tree.left[node]) + 1, int(tree.left[node])]
    ranges.sort()
    merged: list[list[int]] = []
    for start, count in ranges:
        if merged and merged[-1][1] + count <= CLUSTER_TRIANGLES:
            merged[-1][1] += count
        else:
            merged.append([start, count])
    return [tree.tri_order[s:s + c] for s, c in merged]


def _cluster_tree(n_clusters: int) -> tuple[list[int], list[tuple[int, int]]]:
    """A balanced binary tree over clusters 0..n-1 (neighbours in depth-first order are neighbours in space), in
    BFS order with siblings adjacent: (link of each node: first child, or -1 - cluster; each node's cluster range)."""
    spans, links, head = [(0, n_clusters)], [], 0
    while head < len(spans):
        lo, hi = spans[head]
        head += 1
        if hi - lo == 1:
            links.append(-1 - lo)
        else:
            links.append(len(spans))
            mid = (lo + hi) // 2
            spans += [(lo, mid), (mid, hi)]
    return links, spans


def _grid(vertices: np.ndarray, grid_bits: int) -> tuple[np.ndarray, np.float32]:
    """The global grid's origin and step: the longest side of the box spans 2^grid_bits - 1 steps."""
    origin = vertices.min(axis=0).astype(np.float32)
    extent = float((vertices.max(axis=0) - vertices.min(axis=0)).max())
    return origin, np.float32(max(extent, 1e-12) / float((1 << grid_bits) - 1))


def encode_compact(mesh: Mesh, tree=None, grid_bits: int = GRID_BITS) -> bytes:
    """`mesh` in the compact layout (module docstring). tree: the mesh's `bvh.build_full_tree` when the caller has
    one (clusters are cut from it), else one is built. grid_bits: the global grid's bits per axis (<= 16)."""
    return _encode(mesh, tree, grid_bits)[0]


def _encode(mesh: Mesh, tree=None, grid_bits: int = GRID_BITS) -> tuple[bytes, np.ndarray]:
    """(the compact layout's bytes, every vertex as the layout decodes it (V, 3) float32)."""
    if not 4 <= grid_bits <= 16:
        raise ValueError(f"grid_bits must be 4..16, got {grid_bits}")
    tree = tree if tree is not None else build_full_tree(mesh)
    tri_sets = _clusters(tree)
    origin, step = _grid(mesh.vertices, grid_bits)
    grid, decoded = _snapped(mesh.vertices, origin, step)
    payloads, widths, n_verts, grid_lo, grid_hi = cluster_payloads(mesh.faces, grid, tri_sets)
    offsets = np.concatenate(([0], np.cumsum([len(p) for p in payloads])))
    records = [_CLUSTER.pack(*map(int, grid_lo[k]), int(widths[k]), int(n_verts[k]) - 1, len(tris) - 1,
                             int(offsets[k])) for k, tris in enumerate(tri_sets)]
    # a vertex decodes to origin + grid x step (float64, then float32): monotone in the grid point, so a cluster's
    # decoded box is its grid box decoded
    cluster_lo = (origin + grid_lo * np.float64(step)).astype(np.float32)
    cluster_hi = (origin + grid_hi * np.float64(step)).astype(np.float32)
    links, _ = _cluster_tree(len(records))
    nodes = _encode_nodes(links, cluster_lo, cluster_hi)
    root_lo = np.nextafter(np.min(cluster_lo, axis=0), -np.inf).astype(np.float32)
    root_hi = np.nextafter(np.max(cluster_hi, axis=0), np.inf).astype(np.float32)
    header = _HEADER.pack(MAGIC, len(links), len(records), *origin, step, *root_lo, *root_hi)
    return header + nodes + b"".join(records) + b"".join(payloads), decoded


def _snapped(vertices: np.ndarray, origin: np.ndarray, step: float,
             with_grid: bool = True) -> tuple[np.ndarray | None, np.ndarray]:
    """Each vertex's grid point (V, 3) int64 (None without `with_grid`: a decoded copy alone needs none) and its
    decoded position (V, 3) float32, the float64 work a chunk of rows at a time (on the whole 10M-triangle lattice
    at once it peaked ~0.5 GiB over the mesh)."""
    grid = np.empty(vertices.shape, np.int64) if with_grid else None
    decoded = np.empty(vertices.shape, np.float32)
    for a in range(0, len(vertices), CROSS_CHUNK):
        g = np.rint((vertices[a:a + CROSS_CHUNK].astype(np.float64) - origin) / np.float64(step))
        if grid is not None:
            grid[a:a + CROSS_CHUNK] = g
        decoded[a:a + CROSS_CHUNK] = origin + g * np.float64(step)
    return grid, decoded


def _quantize_box(lo, hi, plo, phi) -> np.ndarray:
    """A child box as 6 u8 in 1/255ths of its parent's box, rounded outward (the decoded box contains it); any
    leading shape: (..., 3) float32 boxes give (..., 6)."""
    ext = np.maximum(phi - plo, np.float32(1e-30))
    qlo = np.clip(np.floor((lo - plo) / ext * 255.0), 0, 255)
    qhi = np.clip(np.ceil((hi - plo) / ext * 255.0), 0, 255)
    return np.concatenate((qlo, qhi), axis=-1).astype(np.uint8)


def _dequantize_box(q: np.ndarray, plo: np.ndarray, phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    ext = (phi - plo).astype(np.float64)
    lo = plo + q[..., :3] / 255.0 * ext
    hi = plo + q[..., 3:] / 255.0 * ext
    # float rounding must never shrink a box: widen by one ulp each way
    return (np.nextafter(lo.astype(np.float32), -np.inf), np.nextafter(hi.astype(np.float32), np.inf))


def _encode_nodes(links: list[int], cluster_lo: np.ndarray, cluster_hi: np.ndarray) -> bytes:
    """Node boxes (bottom-up from the decoded clusters' boxes) quantized top-down against their parents' decoded
    boxes, and their links. links: `_cluster_tree`'s (BFS order: a node's children come after it). One depth at a
    time through `_quantize_box` / `_dequantize_box` (node by node: 18 s of a 10M-triangle mesh's 825k nodes)."""
    links = np.asarray(links, np.int64)
    n = len(links)
    inner = np.flatnonzero(links >= 0)
    parent = np.full(n, -1, np.int64)
    parent[links[inner]] = inner
    parent[links[inner] + 1] = inner
    levels = [np.zeros(1, np.int64)]
    while True:
        c = links[levels[-1]]
        c = c[c >= 0]
        if not c.size:
            break
        levels.append(np.sort(np.concatenate((c, c + 1))))
    lo = np.zeros((n, 3), np.float32)
    hi = np.zeros((n, 3), np.float32)
    leaf = np.flatnonzero(links < 0)
    lo[leaf], hi[leaf] = cluster_lo[-1 - links[leaf]], cluster_hi[-1 - links[leaf]]
    for nodes in reversed(levels):
        nodes = nodes[links[nodes] >= 0]
        c = links[nodes]
        lo[nodes], hi[nodes] = np.minimum(lo[c], lo[c + 1]), np.maximum(hi[c], hi[c + 1])
    dlo, dhi = np.zeros_like(lo), np.zeros_like(hi)
    dlo[0], dhi[0] = np.nextafter(lo[0], -np.inf), np.nextafter(hi[0], np.inf)
    q = np.zeros((n, 6), np.uint8)
    for nodes in levels:
        up = np.where(nodes == 0, 0, parent[nodes])
        plo, phi = dlo[up], dhi[up]
        q[nodes] = _quantize_box(lo[nodes], hi[nodes], plo, phi)
        dlo[nodes], dhi[nodes] = _dequantize_box(q[nodes], plo, phi)
    record = np.zeros(n, np.dtype([("q", np.uint8, 6), ("link", "<u4")], align=False))
    record["q"] = q
    record["link"] = np.where(links < 0, LEAF_BIT | (-1 - links), links).astype(np.uint32)
    return record.tobytes()


def _encode_nodes_reference(links: list[int], cluster_lo: np.ndarray, cluster_hi: np.ndarray) -> bytes:
    """`_encode_nodes` node by node (the reference its test compares with)."""
    n = len(links)
    lo = np.zeros((n, 3), np.float32)
    hi = np.zeros((n, 3), np.float32)
    for i in range(n - 1, -1, -1):
        c = links[i]
        if c < 0:
            lo[i], hi[i] = cluster_lo[-1 - c], cluster_hi[-1 - c]
        else:
            lo[i], hi[i] = np.minimum(lo[c], lo[c + 1]), np.maximum(hi[c], hi[c + 1])
    dlo = np.zeros_like(lo)
    dhi = np.zeros_like(hi)
    dlo[0] = np.nextafter(lo[0], -np.inf)
    dhi[0] = np.nextafter(hi[0], np.inf)
    out = bytearray()
    parent_of = {0: -1}
    for i in range(n):
        plo, phi = (dlo[0], dhi[0]) if i == 0 else (dlo[parent_of[i]], dhi[parent_of[i]])
        q = _quantize_box(lo[i], hi[i], plo, phi)
        dlo[i], dhi[i] = _dequantize_box(q, plo, phi)
        c = links[i]
        if c >= 0:
            parent_of[c] = parent_of[c + 1] = i
        out += q.tobytes() + struct.pack("<I", LEAF_BIT | (-1 - c) if c < 0 else c)
    return bytes(out)


def decode_cluster(data: bytes, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Cluster `k` of `data` alone (what a tracer decodes when a ray reaches its box): (grid points (V, 3) int64,
    triangles (T, 3) int32 into them)."""
    _, n_nodes, n_clusters, *_ = _HEADER.unpack_from(data, 0)
    if not 0 <= k < n_clusters:
        raise ValueError(f"cluster {k} out of range (the mesh has {n_clusters})")
    at = _HEADER.size + n_nodes * NODE_BYTES + k * CLUSTER_BYTES
    ax, ay, az, widths, nv, nt, off = _CLUSTER.unpack_from(data, at)
    nv, nt = nv + 1, nt + 1
    w = [widths & 31, widths >> 5 & 31, widths >> 10 & 31]
    start = _HEADER.size + n_nodes * NODE_BYTES + n_clusters * CLUSTER_BYTES + off
    vert_bytes = (nv * sum(w) + 7) // 8
    bits = int.from_bytes(data[start:start + vert_bytes], "little")
    pts = np.empty((nv, 3), np.int64)
    pos = 0
    for i in range(nv):
        for axis in range(3):
            pts[i, axis] = bits >> pos & ((1 << w[axis]) - 1)
            pos += w[axis]
    pts += np.array([ax, ay, az], np.int64)
    code = int.from_bytes(data[start + vert_bytes:start + vert_bytes + 4 * nt * (2 + 1 + 8) // 8 + 16], "little")
    index_bits = max(1, int(nv - 1).bit_length())
    pos, seen = 0, 0

    def take(width: int) -> int:
        nonlocal pos
        v = code >> pos & ((1 << width) - 1)
        pos += width
        return v

    def ref() -> int:
        nonlocal seen
        if take(1):
            seen += 1
            return seen - 1
        return take(index_bits)

    tris = np.empty((nt, 3), np.int32)
    prev = None
    for t in range(nt):
        c = take(2)
        if c == RESTART or prev is None:
            tri = (ref(), ref(), ref())
        else:
            edge = c if c != ESCAPE else EDGE_1 + take(1)
            x, y, z = prev
            u, v = (y, z) if edge == EDGE_1 else (z, x)
            tri = (v, u, ref()) if c != ESCAPE else (u, v, ref())
        tris[t] = tri
        prev = tri
    if seen != nv or int(tris.max(initial=0)) >= nv:
        raise ValueError(f"cluster {k} is damaged (its strip names {seen} of {nv} vertices)")
    return pts, tris


def decode_compact(data: bytes) -> CompactMesh:
    """The triangles and boxes `data` holds (what a tracer of the layout would intersect)."""
    if len(data) < _HEADER.size or data[:4] != MAGIC:
        raise ValueError("not a compact mesh (.cmsh) of this version")
    _, n_nodes, n_clusters, *rest = _HEADER.unpack_from(data, 0)
    origin, step = np.asarray(rest[:3], np.float32), np.float32(rest[3])
    root = np.asarray(rest[4:10], np.float32)
    pos = _HEADER.size
    node_raw = np.frombuffer(data, np.uint8, n_nodes * NODE_BYTES, pos).reshape(n_nodes, NODE_BYTES)
    links = node_raw[:, 6:].copy().view("<u4").ravel()
    lo, hi = np.zeros((n_nodes, 3), np.float32), np.zeros((n_nodes, 3), np.float32)
    lo[0], hi[0] = _dequantize_box(node_raw[0, :6], root[:3], root[3:])
    for i in range(n_nodes):
        if not links[i] & LEAF_BIT:
            for c in (int(links[i]), int(links[i]) + 1):
                lo[c], hi[c] = _dequantize_box(node_raw[c, :6], lo[i], hi[i])
    grids, faces, owner = [], [], []
    base = 0
    for k in range(n_clusters):
        pts, tris = decode_cluster(data, k)
        grids.append(pts)
        faces.append(tris + base)
        owner.append(np.full(len(tris), k, np.int32))
        base += len(pts)
    grid = np.concatenate(grids)
    vertices = (origin + grid * np.float64(step)).astype(np.float32)
    return CompactMesh(vertices, np.concatenate(faces), lo, hi, links, np.concatenate(owner), grid, float(step))


def in_original_units(data: bytes, scale: float, offset) -> bytes:
    """The same compact mesh with its grid placed in the original coordinates (original = normalised x scale +
    offset): only the header's origin, step and root box change (cluster offsets, bit widths and child boxes are
    relative), so the bytes written are exactly the bytes the verdict counted."""
    magic, n_nodes, n_clusters, *rest = _HEADER.unpack_from(data, 0)
    origin = np.asarray(rest[:3], np.float64) * scale + np.asarray(offset, np.float64)
    root = np.asarray(rest[4:10], np.float64).reshape(2, 3) * scale + np.asarray(offset, np.float64)
    root = np.stack([np.nextafter(root[0].astype(np.float32), -np.inf), np.nextafter(root[1].astype(np.float32), np.inf)])
    header = _HEADER.pack(magic, n_nodes, n_clusters, *origin.astype(np.float32), np.float32(rest[3] * scale),
                          *root.ravel())
    return header + data[_HEADER.size:]


def compact_bytes(mesh: Mesh, tree=None) -> int:
    """The exact size of `mesh` in the compact layout (the encoder's output length: what the verdict weighs is
    what `compress` writes)."""
    return len(encode_compact(mesh, tree))


def compact_mesh(mesh: Mesh, tree=None) -> tuple[int, Mesh]:
    """(exact bytes of `mesh` in the compact layout, the decoded triangles as a Mesh in the same normalised
    coordinates, for measuring the image error of what the layout holds)."""
    # The layout's triangles are the mesh's on its vertices snapped to the grid (what decode_compact reads back:
    # tests/test_compact_mesh.py), so they are taken from the encoder instead of decoding the bytes again.
    data, snapped = _encode(mesh, tree)
    return len(data), _on_vertices(mesh, snapped)


def decoded_mesh(mesh: Mesh, grid_bits: int = GRID_BITS) -> Mesh:
    """The triangles `mesh`'s compact layout holds, without encoding it: the mesh on its vertices snapped to the
    layout's global grid, which no cluster or tree changes (compact_mesh's second part; a heavy mesh is scored
    before its tree is built)."""
    origin, step = _grid(mesh.vertices, grid_bits)
    return _on_vertices(mesh, _snapped(mesh.vertices, origin, step, with_grid=False)[1])


def _on_vertices(mesh: Mesh, snapped: np.ndarray) -> Mesh:
    # a sliver the grid collapsed to zero area is never hit (Embree skips it) and has no normal: left out
    keep = np.empty(mesh.n_triangles, bool)  # chunk by chunk: no (F, 3) float64 cross of a heavy mesh
    for a, b, cross in face_cross_chunks(snapped, mesh.faces):
        keep[a:b] = np.linalg.norm(cross, axis=1) > 0
    return Mesh(vertices=snapped, faces=mesh.faces[keep], transform=mesh.transform, name=mesh.name)
