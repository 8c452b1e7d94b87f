"""One cluster of the compact mesh, encoded (`compact_mesh`'s module docstring has the layout): its vertices as
offsets on the global grid at the cluster's own bit width per axis, and its triangles as a generalised strip (2-bit
codes; each new vertex one bit when it is the next unseen one, else a local index). `cluster_payloads` encodes every
cluster, with the compiled encoder (kernels/native/mesh_codec.cpp, byte for byte the same) where it builds;
`compact_mesh.decode_cluster` reads one back."""
from __future__ import annotations

import numpy as np

#: Strip codes, 2 bits per triangle.
RESTART, EDGE_1, EDGE_2, ESCAPE = 0, 1, 2, 3


class _Bits:
    """An LSB-first bit string built field by field."""

    def __init__(self) -> None:
        self.value, self.length = 0, 0

    def put(self, v: int, width: int) -> None:
        self.value |= int(v) << self.length
        self.length += width

    def tobytes(self) -> bytes:
        return self.value.to_bytes((self.length + 7) // 8, "little")


def _strip(local: np.ndarray) -> list[tuple[int, tuple[int, int, int]]]:
    """A generalised strip over one cluster's triangles `local` (T, 3) (any vertex ids): [(code, (a, b, c))], each
    (a, b, c) the triangle in its own winding, rotated so that (a, b) is the edge shared with the previous one."""
    n = len(local)
    by_edge: dict[tuple[int, int], list[int]] = {}
    for t, (a, b, c) in enumerate(local.tolist()):
        for e in ((a, b), (b, c), (c, a)):
            by_edge.setdefault((min(e), max(e)), []).append(t)
    left = set(range(n))

    def open_neighbours(t: int) -> int:
        a, b, c = local[t].tolist()
        return sum(1 for e in ((a, b), (b, c), (c, a)) for u in by_edge[(min(e), max(e))] if u != t and u in left)

    out: list[tuple[int, tuple[int, int, int]]] = []
    prev = None
    while left:
        step = None
        if prev is not None:
            x, y, z = prev
            for code, (u, v) in ((EDGE_1, (y, z)), (EDGE_2, (z, x))):
                for t in by_edge[(min(u, v), max(u, v))]:
                    if t not in left:
                        continue
                    tri = local[t].tolist()
                    k = tri.index(v) if v in tri else -1
                    if k >= 0 and tri[(k + 1) % 3] == u:  # wound with its neighbour: (v, u, w)
                        step = (code, (v, u, tri[(k + 2) % 3]), t)
                    else:  # wound against it: (u, v, w), an escape
                        k = tri.index(u)
                        step = (ESCAPE + (code == EDGE_2) * 4, (u, v, tri[(k + 2) % 3]), t)
                    break
                if step is not None:
                    break
        if step is None:  # restart where the fewest triangles still touch: strips end less often
            t = min(left, key=open_neighbours) if len(left) <= 64 else next(iter(left))
            step = (RESTART, tuple(local[t].tolist()), t)
        code, tri, t = step
        left.discard(t)
        out.append((code, tri))
        prev = tri
    return out


def _encode_cluster(grid_pts: np.ndarray, local: np.ndarray) -> tuple[bytes, int, list[int], np.ndarray]:
    """One cluster: (payload, bit widths packed 5:5:5, anchor, vertex permutation (first use order)).
    grid_pts (V, 3) int64 the cluster's vertices on the global grid; local (T, 3) indices into them."""
    strip = _strip(local)
    first_use: dict[int, int] = {}
    code_bits = _Bits()
    n_v = len(grid_pts)
    index_bits = max(1, int(n_v - 1).bit_length())

    def ref(v: int) -> None:
        if v not in first_use:
            first_use[v] = len(first_use)
            code_bits.put(1, 1)
        else:
            code_bits.put(0, 1)
            code_bits.put(first_use[v], index_bits)

    for code, (a, b, c) in strip:
        if code == RESTART:
            code_bits.put(RESTART, 2)
            for v in (a, b, c):
                ref(v)
        else:
            code_bits.put(min(code, ESCAPE), 2)
            if code >= ESCAPE:
                code_bits.put(code // 4, 1)  # which open edge
            ref(c)
    perm = np.array(sorted(first_use, key=first_use.get), np.int64)
    pts = grid_pts[perm]
    anchor = pts.min(axis=0)
    offs = pts - anchor
    widths = [int(w) for w in np.maximum(offs.max(axis=0), 0).astype(np.int64)]
    widths = [w.bit_length() for w in widths]
    vert_bits = _Bits()
    for row in offs.tolist():
        for v, w in zip(row, widths):
            vert_bits.put(v, w)
    payload = vert_bits.tobytes() + code_bits.tobytes()
    return payload, widths[0] | widths[1] << 5 | widths[2] << 10, anchor.tolist(), perm


def payload_bound(triangles: np.ndarray) -> np.ndarray:
    """Each cluster's largest possible payload in bytes (int64, per triangle count): 3 x 16 bits per vertex (at
    most 3 per triangle) and per triangle 3 code bits and three references of 1 + 8 bits (mesh_codec.cpp's bound)."""
    t = np.asarray(triangles, np.int64)
    return (3 * t * 48 + 7) // 8 + (t * 30 + 7) // 8 + 2


#: Clusters the compiled encoder takes per call (each call's scratch: their payload bounds, ~1.4 MB at 64 triangles).
CLUSTER_BLOCK = 1024


def cluster_payloads(faces: np.ndarray, grid: np.ndarray, tri_sets: list[np.ndarray]):
    """Every cluster's payload: (payload bytes list, packed widths (C,) int64, vertex counts (C,) int64, grid boxes
    lo and hi (C, 3) int64). The compiled encoder where it builds (~1 us per triangle in Python: 65 s of a
    1.2M-triangle lattice's plan), else `_encode_cluster` per cluster."""
    from ..kernels import library

    n = len(tri_sets)
    if library.fast_enabled():  # kernels/native/mesh_codec.cpp: byte for byte `_encode_cluster`
        from ..kernels import bindings

        counts = np.array([len(t) for t in tri_sets], np.int64)
        start = np.concatenate(([0], np.cumsum(counts))).astype(np.int64)
        order = np.ascontiguousarray(np.concatenate(tri_sets), np.int64)  # the tree's int64 order: no second copy
        faces, grid = np.ascontiguousarray(faces, np.int32), np.ascontiguousarray(grid, np.int64)
        payloads, widths, n_verts = [], np.zeros(n, np.int64), np.zeros(n, np.int64)
        lo, hi = np.zeros((n, 3), np.int64), np.zeros((n, 3), np.int64)
        # CLUSTER_BLOCK clusters at a time: the encoder writes each at its bound's offset (~22 B per triangle, 6x a
        # payload), so the whole 10M-triangle lattice at once touched 0.5 GiB
        for a in range(0, n, CLUSTER_BLOCK):
            b = min(n, a + CLUSTER_BLOCK)
            out = np.zeros(int(payload_bound(counts[a:b]).sum()), np.uint8)
            offset = np.zeros(b - a + 1, np.int64)
            bindings.encode_clusters(faces=faces, grid=grid, cluster_tris=order[start[a]:start[b]],
                                     t=int(start[b] - start[a]), cluster_start=start[a:b + 1] - start[a], c=b - a,
                                     out=out, out_bytes=len(out), out_offset=offset, widths=widths[a:b],
                                     n_verts=n_verts[a:b], grid_lo=lo[a:b], grid_hi=hi[a:b])
            data = out[:offset[-1]].tobytes()
            payloads += [data[offset[k]:offset[k + 1]] for k in range(b - a)]
        return payloads, widths, n_verts, lo, hi
    payloads, widths, n_verts = [], np.zeros(n, np.int64), np.zeros(n, np.int64)
    lo, hi = np.zeros((n, 3), np.int64), np.zeros((n, 3), np.int64)
    for k, tris in enumerate(tri_sets):
        verts = np.unique(faces[tris])
        local = np.searchsorted(verts, faces[tris])
        payload, widths[k], _, _ = _encode_cluster(grid[verts], local)
        payloads.append(payload)
        n_verts[k], lo[k], hi[k] = len(verts), grid[verts].min(axis=0), grid[verts].max(axis=0)
    return payloads, widths, n_verts, lo, hi
