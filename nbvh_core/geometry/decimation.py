"""Decimation: the mesh a user could ship instead of a model, simplified the way engines simplify (meshoptimizer's
attribute-aware quadric simplifier, as gltfpack uses it), with the asset's look kept.

The simplifier works on *wedges*: one vertex per distinct (position, material slot, texture coordinate), the way a
glTF file holds them. Where two wedges share a position (a UV seam, a slot boundary) the simplifier sees a seam
and only collapses along it, so seams stay closed and slots keep their borders; texture coordinates are weighed in
the error (UV_WEIGHT), so islands are not stretched. Open borders only collapse along themselves. The
simplifier moves no vertex (every kept vertex is an input vertex), so the result maps back onto the input's
positions, slots and coordinates exactly, and the same call gives the same mesh again.

    dec = decimate(mesh, 12_000)        # Mesh with ~12k triangles, its look (slots, UVs, materials) kept

Why meshoptimizer: scored by the product's metric (16 held-out views, 256 px image MSE) this decimation reads
1.09-10.6x lower MSE than fast-simplification at equal requested triangles on 16 of 18 points of six assets, 1.04x
and 1.11x higher on two coarse ones (bench/results/decimators.md).
"""
from __future__ import annotations

import numpy as np

from .look import Look
from .mesh import Mesh, face_cross

#: Weight of the texture coordinates against positions in the simplifier's error (positions are measured in the
#: mesh's extent, coordinates in texture space). 0.5 is a starting value, not tuned: no asset of
#: bench/results/decimators.md has coordinates; the textured Fuze scan kept at it read FLIP 0.0065
#: (bench/results/textured_keep.md).
UV_WEIGHT = 0.5
#: The simplifier stops at the target count, not at an error bound: the curve asks for counts.
UNBOUNDED_ERROR = 1e9
#: When the simplifier stops above this multiple of the count asked (every further collapse would cross the border
#: of one of many parts: a CAD assembly), it runs again allowed to drop whole small parts. On the engine asked for
#: 2,206 triangles: 3,588 at MSE 0.0085 plain, 1,031 at 0.0139 pruning (fast-simplification: 2,205 at 0.0157).
PRUNE_ABOVE = 1.2


class DecimationUnavailable(RuntimeError):
    """The simplifier (PyPI `meshoptimizer`) is not installed: no decimation can be measured or written."""


def simplifier_missing() -> str | None:
    """None when the decimation can run, else one line saying why it cannot (what to install)."""
    try:
        import meshoptimizer  # noqa: F401
    except ImportError:
        return "meshoptimizer is not installed (pip install meshoptimizer): no decimation was measured"
    return None


def unique_rows(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """np.unique(keys, axis=0, return_index=True, return_inverse=True) for an (N, K) integer array, by one stable
    lexsort (np.unique sorts rows as opaque records: 1.6 s per call on a 1.2M-triangle mesh's corners, most of
    its decimation's time). Returns (unique rows (U, K) in ascending row order, the first index of each (U,),
    each row's unique index (N,))."""
    keys = np.asarray(keys)
    order = np.lexsort(keys.T[::-1])
    ranked = keys[order]
    new = np.ones(len(keys), bool)
    new[1:] = (ranked[1:] != ranked[:-1]).any(axis=1)
    group = np.cumsum(new) - 1
    inverse = np.empty(len(keys), np.int64)
    inverse[order] = group
    return ranked[new], order[new], inverse


def wedges(mesh: Mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """The mesh as a glTF-style vertex buffer: one wedge per distinct (position, slot, texture coordinate).

    Vertices are welded by position first: a triangle soup (an STL file reads as one: three vertices per triangle)
    or a CAD part split at its hard edges would otherwise be all seams, and nothing could collapse.
    Returns (wedge_vertex (W,) int64 index into mesh.vertices (the first vertex at its position), corners (F, 3)
    wedge per corner (int64; uint32 for a bare shape), wedge_slot (W,) int32 or None without several slots,
    wedge_uv (W, 2) float32 or None without coordinates)."""
    look = mesh.look
    bits = np.ascontiguousarray(mesh.vertices, np.float32).view(np.int32)
    _, first_vertex, position = unique_rows(bits)
    welded = position.astype(np.int32)[mesh.faces]  # int32: (F, 3) indices of at most V < 2^31 positions
    slots = None if look is None or look.n_slots <= 1 else look.face_slots
    uvs = None if look is None else look.corner_uvs
    if slots is None and uvs is None:  # a bare shape: a wedge per used position, no rows to sort
        return _position_wedges(first_vertex, welded)
    cols = [welded.reshape(-1).astype(np.int64)]
    if slots is not None:
        cols.append(np.repeat(slots.astype(np.int64), 3))
    if uvs is not None:  # exact float bits: equal coordinates are one wedge, any difference is a seam
        uv_bits = np.ascontiguousarray(uvs.reshape(-1, 2), np.float32).view(np.int32).astype(np.int64)
        cols += [uv_bits[:, 0], uv_bits[:, 1]]
    keys = np.stack(cols, axis=1)
    unique, first, inverse = unique_rows(keys)
    corners = inverse.reshape(-1, 3)
    wedge_vertex = first_vertex[unique[:, 0]].astype(np.int64)
    wedge_slot = None if slots is None else unique[:, 1].astype(np.int32)
    wedge_uv = None if uvs is None else uvs.reshape(-1, 2)[first].astype(np.float32)
    return wedge_vertex, corners, wedge_slot, wedge_uv


def _position_wedges(first_vertex: np.ndarray, welded: np.ndarray) -> tuple:
    """`wedges` of a shape without slots or coordinates: the used positions in ascending order (what sorting the
    corners' rows gives, without the sort: at 10M triangles the rows' sort peaked 1.4 GiB over the mesh), corners
    (F, 3) uint32, the simplifier's own index type."""
    used = np.zeros(len(first_vertex), bool)
    used[welded.reshape(-1)] = True
    rank = np.cumsum(used, dtype=np.int64) - 1
    corners = rank.astype(np.uint32)[welded]
    return first_vertex[np.flatnonzero(used)].astype(np.int64), corners, None, None


def _with_attributes():
    """meshoptimizer's `meshopt_simplifyWithAttributes`, declared here: the PyPI wrapper (0.2.30a0) declares no
    argument types for it, so its own call cannot pass the target error (a float). Its own library handle, so the
    wrapper's declarations are left as they are."""
    import ctypes

    from meshoptimizer import _loader

    fn = ctypes.CDLL(_loader.lib._name).meshopt_simplifyWithAttributes
    u32p, f32p, size = ctypes.POINTER(ctypes.c_uint), ctypes.POINTER(ctypes.c_float), ctypes.c_size_t
    fn.argtypes = [u32p, u32p, size, f32p, size, size, f32p, size, f32p, size, ctypes.POINTER(ctypes.c_ubyte), size,
                   ctypes.c_float, ctypes.c_uint, f32p]
    fn.restype = size
    return fn


def simplify_indices(positions: np.ndarray, corners: np.ndarray, triangles: int,
                     attributes: np.ndarray | None = None, weights: np.ndarray | None = None) -> np.ndarray:
    """meshoptimizer's simplifier to at most `triangles` triangles.

    positions: (W, 3) float32; corners: (F, 3) int indices into positions; attributes: (W, A) float32 weighed by
    weights (A,) float32, or None. Returns (F', 3) uint32: F' <= triangles unless the simplifier stops early (every
    remaining collapse would break a seam or a border; past PRUNE_ABOVE it may drop whole small parts instead)."""
    missing = simplifier_missing()
    if missing:
        raise DecimationUnavailable(missing)
    import meshoptimizer

    pos = np.ascontiguousarray(positions, np.float32)
    idx = np.ascontiguousarray(corners.reshape(-1), np.uint32)
    out = np.zeros(idx.size, np.uint32)
    target = int(max(triangles, 1)) * 3
    n = _simplify(meshoptimizer, out, idx, pos, target, attributes, weights, 0)
    if n > PRUNE_ABOVE * target:  # stuck at the borders of many parts: let it drop whole small parts
        pruned = np.zeros_like(out)
        m = _simplify(meshoptimizer, pruned, idx, pos, target, attributes, weights, meshoptimizer.SIMPLIFY_PRUNE)
        if m > 0:  # never every part: a decimation of nothing is no alternative
            out, n = pruned, m
    return out[:n].reshape(-1, 3).copy()  # uint32, the simplifier's own: a heavy mesh's chain levels are held


def _simplify(meshoptimizer, out, idx, pos, target, attributes, weights, options: int) -> int:
    """One simplifier call into `out`; returns the index count."""
    if attributes is None:
        return meshoptimizer.simplify(out, idx, pos, target_index_count=target, target_error=UNBOUNDED_ERROR,
                                      options=options)
    import ctypes

    attr = np.ascontiguousarray(attributes, np.float32)
    w = np.ascontiguousarray(weights, np.float32)
    u32p, f32p = ctypes.POINTER(ctypes.c_uint), ctypes.POINTER(ctypes.c_float)
    return _with_attributes()(out.ctypes.data_as(u32p), idx.ctypes.data_as(u32p), idx.size, pos.ctypes.data_as(f32p),
                              len(pos), 12, attr.ctypes.data_as(f32p), attr.shape[1] * 4, w.ctypes.data_as(f32p),
                              w.size, None, target, UNBOUNDED_ERROR, options, None)


#: The chain's levels (triangles, x4 apart): a decimation to N triangles is simplified from the chain's level just
#: above N (itself from the level above it, the top from the mesh), not from the whole mesh: one pass over a heavy
#: mesh serves every count of the alternative's curve (`Decimator`).
CHAIN_LEVELS = (250, 1_000, 4_000, 16_000, 64_000, 256_000, 1_024_000, 4_096_000, 16_384_000)


class Decimator:
    """One mesh's decimations at any counts, its look kept. The wedges are built once; a count is simplified from
    the decimation at the next CHAIN_LEVELS level above it (kept once made), so every count costs a pass over a
    mesh at most 4x its size, and only the chain's top pass reads the whole mesh. The chain depends on the count
    alone: the same mesh and count give the same decimation, whatever was asked before.

    chained=False simplifies every count from the whole mesh (`decimate`)."""

    def __init__(self, mesh: Mesh, chained: bool = True):
        self.mesh, self.chained = mesh, chained
        self._wedges: tuple | None = None
        self._levels: dict[int, np.ndarray] = {}

    def _wedge_data(self, corners: bool = False) -> tuple:
        """(wedge_vertex, corners, wedge_slot, wedge_uv, positions); corners: the whole mesh's wedge corners are
        needed (rebuilt after `drop_mesh_corners`)."""
        if self._wedges is None or (corners and self._wedges[1] is None):
            wedge_vertex, corners, wedge_slot, wedge_uv = wedges(self.mesh)
            vertices = self.mesh.vertices
            same = len(wedge_vertex) == len(vertices) and np.array_equal(wedge_vertex, np.arange(len(vertices)))
            # a wedge per vertex, in order (a welded bare shape): the mesh's own positions, not a copy
            self._wedges = (wedge_vertex, corners, wedge_slot, wedge_uv, vertices if same else vertices[wedge_vertex])
        return self._wedges

    def drop_mesh_corners(self) -> None:
        """Let the whole mesh's wedge corners go (12 B per triangle): once the chain's top level is made only a count
        above it reads them, and they are rebuilt for one. The plan drops them before the whole mesh's tree is built
        (its memory peak on a heavy mesh, bench/results/heavy.md)."""
        if self._wedges is not None:
            self._wedges = self._wedges[:1] + (None,) + self._wedges[2:]

    def source_level(self, triangles: int) -> int | None:
        """The chain level a decimation to `triangles` is simplified from (None: the whole mesh)."""
        if not self.chained:
            return None
        return next((lv for lv in CHAIN_LEVELS if triangles < lv < self.mesh.n_triangles), None)

    def pending_triangles(self, triangles: int) -> int:
        """About how many triangles the simplifier reads to make the decimation to `triangles` now: its source and
        every chain level above it not made yet (0 for a level made). What a measurement's time is predicted from."""
        if triangles in self._levels:
            return 0
        level = self.source_level(triangles)
        if level is None:
            return self.mesh.n_triangles
        return level + self.pending_triangles(level)

    def kept_corners(self, triangles: int) -> np.ndarray:
        """(F', 3) uint32 wedge corners of the decimation to `triangles` (F' <= triangles unless the simplifier
        stops early: `simplify_indices`)."""
        if triangles in self._levels:  # a chain level made as another count's source
            return self._levels[triangles]
        level = self.source_level(triangles)
        wedge_vertex, corners, _, wedge_uv, positions = self._wedge_data(corners=level is None)
        if level is not None and level not in self._levels:
            self._levels[level] = self.kept_corners(level)
        source = corners if level is None else self._levels[level]
        if wedge_uv is None:
            kept = simplify_indices(positions, source, triangles)
        else:
            kept = simplify_indices(positions, source, triangles, wedge_uv, np.full(2, UV_WEIGHT, np.float32))
        if self.chained and triangles in CHAIN_LEVELS:  # the alternative's ladder asks for the levels themselves
            self._levels[triangles] = kept
        return kept

    def __call__(self, triangles: int) -> Mesh:
        """The decimation to about `triangles` triangles (< the mesh's) as a Mesh: the input's positions
        (normalised coordinates, same transform), each kept triangle with its slot and its corners' coordinates.
        Raises DecimationUnavailable without meshoptimizer."""
        wedge_vertex, _, wedge_slot, wedge_uv, _ = self._wedge_data()
        kept = self.kept_corners(triangles)
        mesh = self.mesh
        faces = wedge_vertex[kept]
        used, faces = np.unique(faces.reshape(-1), return_inverse=True)
        faces = faces.reshape(-1, 3).astype(np.int32)
        look = None
        if mesh.look is not None:
            slots = (np.zeros(len(kept), np.int32) if wedge_slot is None else wedge_slot[kept[:, 0]])
            look = Look(slots, None if wedge_uv is None else wedge_uv[kept], mesh.look.materials)
        # Distinct vertices at one position (a globe's pole, welded CAD parts) can meet in a triangle of no area:
        # dropped, as the mesh reader drops them (else the file written would read back with fewer triangles).
        keep = np.linalg.norm(face_cross(mesh.vertices[used], faces), axis=1) > 0
        if look is not None and not keep.all():
            look = look.subset(keep)
        return Mesh(vertices=mesh.vertices[used], faces=faces[keep], transform=mesh.transform, name=mesh.name,
                    look=look)


def decimate(mesh: Mesh, triangles: int, chained: bool = True) -> Mesh:
    """`mesh` simplified to about `triangles` triangles (< mesh.n_triangles), its look kept (`Decimator`: the
    same result as a Decimator of the mesh gives for that count). chained=False: simplified from the whole mesh.
    Deterministic. Raises DecimationUnavailable without meshoptimizer."""
    return Decimator(mesh, chained)(triangles)
