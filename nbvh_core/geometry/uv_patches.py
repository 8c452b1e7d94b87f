"""An asset's UV islands cut into patches the appearance head tells apart, each with a low-degree map from surface
position to texture coordinates (`uv_patches`), and its seams (`seam_edges`, `seam_distance`).

Seams are handled by classification, not regression: a patch never straddles a seam (its coordinates jump there),
so the head names a patch and the patch's map gives coordinates that stay continuous inside it.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from .look import Look

def _edge_pairs(ends: np.ndarray, corner_uvs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where two triangles share an edge. ends (F, 3): a key per corner (vertex index, or welded position);
    half-edge k runs from corner k % 3 to corner (k + 1) % 3 of triangle k // 3. Returns (i, j, gap): the two
    half-edges of each shared edge and the largest difference of the coordinates their ends carry."""
    a, b = ends[:, [0, 1, 2]].reshape(-1), ends[:, [1, 2, 0]].reshape(-1)
    ua, ub = corner_uvs[:, [0, 1, 2]].reshape(-1, 2), corner_uvs[:, [1, 2, 0]].reshape(-1, 2)
    swap = a > b  # each edge as (lower key, higher key), its coordinates in that order
    lo, hi = np.where(swap, b, a), np.where(swap, a, b)
    ulo, uhi = np.where(swap[:, None], ub, ua), np.where(swap[:, None], ua, ub)
    order = np.lexsort((hi, lo))
    k = np.nonzero((lo[order][1:] == lo[order][:-1]) & (hi[order][1:] == hi[order][:-1]))[0]
    i, j = order[k], order[k + 1]
    gap = np.maximum(np.abs(ulo[i] - ulo[j]).max(1), np.abs(uhi[i] - uhi[j]).max(1))
    return i, j, gap


def uv_charts(faces: np.ndarray, corner_uvs: np.ndarray) -> np.ndarray:
    """(F,) int chart id: faces joined across every edge whose two corners carry the same coordinates on both
    sides (a UV island); an edge where they differ is a seam."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(faces)
    i, j, gap = _edge_pairs(faces, corner_uvs)
    joined = gap < 1e-6
    graph = coo_matrix((np.ones(int(joined.sum())), (i[joined] // 3, j[joined] // 3)), shape=(n, n))
    return connected_components(graph, directed=False)[1].astype(np.int32)


#: Basis terms of a patch map by degree: 1 affine (4), 2 quadratic (10), 3 cubic (20).
PATCH_BASIS_SIZE = {1: 4, 2: 10, 3: 20}


def patch_basis(points, degree: int):
    """(N, B) basis of a patch map at points (N, 3) (numpy or torch): degree 1: x, y, z, 1 (B = 4); degree 2: also
    x^2, y^2, z^2, xy, yz, zx (B = 10); degree 3: also the ten cubic monomials (B = 20)."""
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    cols = [x, y, z, x * 0 + 1]
    if degree >= 2:
        cols += [x * x, y * y, z * z, x * y, y * z, z * x]
    if degree >= 3:
        cols += [x * x * x, y * y * y, z * z * z, x * x * y, x * x * z, y * y * x, y * y * z, z * z * x, z * z * y,
                 x * y * z]
    shape = (points.shape[0], len(cols))
    # torch tensors fill a tensor of their own kind (this module stays free of torch for the add-on)
    out = points.new_empty(shape) if hasattr(points, "new_empty") else np.empty(shape, np.float64)
    for i, c in enumerate(cols):
        out[:, i] = c
    return out


def uv_patches(vertices: np.ndarray, faces: np.ndarray, look: Look, tolerance: float, max_patches: int,
               degree: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split the surface into patches on each of which the coordinates are a polynomial of position (`degree` 1:
    affine, 2: quadratic, 3: cubic).

    Starts from one patch per (UV island, slot) for slots that sample an image, and one patch per slot for the
    others (a flat colour needs no coordinates: an artist's 81 plain slots are 81 patches, not one per island of
    every slot: 26,674 patches and 4.2 MB of head on a building). While a patch's fit misses the coordinates by more
    than `tolerance` at a fitting sample (corners, edge midpoints, centre: a triangle's coordinates are linear across
    it, a polynomial is not) and fewer than `max_patches` exist, the patch with the most surface area outside the
    tolerance is cut in two at the median of its face centres along its longest side: the area ranks the cuts by the
    hits they mend (the worst corner would spend the cap on slivers at a sphere's poles, where an equirectangular
    map has no polynomial; measured on the globe, 64 cubic patches fitted at the corners, faces sampled uniformly:
    82% within half a 512 px texel cutting at the worst corner, 90% cutting the most area). Islands made by planar
    projection (Blender's Smart UV Project, box and cube maps) fit exactly and never split; curved maps split until
    they fit or the cap is reached.
    Returns face_patch (F,) int32, maps (P, 2, B + 1) float32 (uv = maps[:, :, :B] @ patch_basis(p), p in
    normalised coordinates; maps[:, :, B]: the fit's largest |error| per coordinate at a fitting sample; the
    patches of slots that sample an image come first, the others' maps are zero) and patch_slot (P,) int32.
    """
    n = len(faces)
    if look.corner_uvs is None:
        slots = np.unique(look.face_slots)
        face_patch = np.searchsorted(slots, look.face_slots).astype(np.int32)
        return face_patch, np.zeros((len(slots), 2, PATCH_BASIS_SIZE[degree] + 1), np.float32), slots.astype(np.int32)
    textured = look.image_slots
    if not textured.any():
        return uv_patches(vertices, faces, replace(look, corner_uvs=None), tolerance, max_patches, degree)
    charts = np.where(textured[look.face_slots], uv_charts(faces, look.corner_uvs), -1)
    groups = np.unique(np.stack([charts, look.face_slots], 1), axis=0, return_inverse=True)[1].reshape(-1)
    members = [np.nonzero(groups == g)[0] for g in range(groups.max() + 1)]
    corners = np.asarray(vertices, np.float64)[faces]
    centres = corners.mean(1)
    areas = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    fits = [_fit(corners[m], look.corner_uvs[m], degree) if textured[look.face_slots[m[0]]] else _flat(degree, len(m))
            for m in members]

    def area_outside(i: int) -> float:
        return float(areas[members[i]][fits[i][2] > tolerance].sum())

    while len(members) < max_patches:
        outside = [area_outside(i) for i in range(len(members))]
        worst = int(np.argmax(outside))
        if outside[worst] <= 0 or len(members[worst]) < 2:
            break
        m = members[worst]
        c = centres[m]
        axis = int(np.argmax(c.max(0) - c.min(0)))
        order = np.argsort(c[:, axis], kind="stable")
        halves = [m[order[:len(m) // 2]], m[order[len(m) // 2:]]]
        members[worst:worst + 1] = halves
        fits[worst:worst + 1] = [_fit(corners[h], look.corner_uvs[h], degree) for h in halves]
    # patches of slots that sample an image first: a file stores the maps of those alone (`mapped_patches`)
    first = sorted(range(len(members)), key=lambda i: not textured[look.face_slots[members[i][0]]])
    members, fits = [members[i] for i in first], [fits[i] for i in first]
    face_patch = np.empty(n, np.int32)
    for i, m in enumerate(members):
        face_patch[m] = i
    affine = np.stack([np.concatenate([f[0], f[1][:, None]], 1) for f in fits]).astype(np.float32)
    patch_slot = np.array([look.face_slots[m[0]] for m in members], np.int32)
    return face_patch, affine, patch_slot


def _flat(degree: int, faces: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The map of a patch whose slot samples no image: zero coordinates, no error (never split)."""
    return np.zeros((2, PATCH_BASIS_SIZE[degree])), np.zeros(2), np.zeros(faces)


#: Corners are also fitted at this offset (normalised units) along their face's normal, with the same
#: coordinates: a hit a little off the surface (a model's depth error) reads the coordinates of the surface below
#: it, and a planar patch's fit is well-posed.
NORMAL_OFFSET = 0.01


#: Where a face is fitted and checked, as barycentric weights: its corners, edge midpoints and centre.
FIT_SAMPLES = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [.5, .5, 0], [0, .5, .5], [.5, 0, .5],
                        [1 / 3, 1 / 3, 1 / 3]])


def _fit(corners: np.ndarray, uvs: np.ndarray, degree: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares map (`patch_basis` of `degree`) from face corners (K, 3, 3) and their coordinates (K, 3, 2),
    fitted at each face's FIT_SAMPLES: (2, B), the largest |error| per coordinate (2,) and per face (K,) at a
    sample on the surface."""
    nrm = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-30)
    points = np.einsum("sk,nkd->nsd", FIT_SAMPLES, corners)
    on = points.reshape(-1, 3)
    off = (points + NORMAL_OFFSET * nrm[:, None]).reshape(-1, 3)
    x = patch_basis(np.concatenate([on, off, 2 * on - off]), degree)
    y = np.tile(np.einsum("sk,nkd->nsd", FIT_SAMPLES, np.asarray(uvs, np.float64)).reshape(-1, 2), (3, 1))
    sol = np.linalg.lstsq(x, y, rcond=None)[0]  # (B, 2)
    err = np.abs(x[:len(on)] @ sol - y[:len(on)])
    if not len(on):
        return sol.T, np.zeros(2), np.zeros(0)
    return sol.T, err.max(0), err.max(1).reshape(len(corners), -1).max(1)


def seam_edges(vertices: np.ndarray, faces: np.ndarray, corner_uvs: np.ndarray) -> np.ndarray:
    """(E, 2, 3) end points of every UV seam: an edge (vertices welded by position) whose two faces give its ends
    different coordinates."""
    key = np.round(np.asarray(vertices, np.float64) * 1e6).astype(np.int64)
    weld = np.unique(key, axis=0, return_inverse=True)[1].reshape(-1)[faces]
    i, _, gap = _edge_pairs(weld, corner_uvs)
    seam = i[gap > 1e-6]
    start, end = faces[:, [0, 1, 2]].reshape(-1)[seam], faces[:, [1, 2, 0]].reshape(-1)[seam]
    return np.stack([vertices[start], vertices[end]], axis=1).astype(np.float32)


def seam_distance(points: np.ndarray, seams: np.ndarray, spacing: float = 1e-3) -> np.ndarray:
    """(N,) distance (normalised units) from each point to the nearest seam (`seam_edges`), to within `spacing`;
    inf when there is no seam."""
    if len(seams) == 0:
        return np.full(len(points), np.inf)
    from scipy.spatial import cKDTree

    length = np.linalg.norm(seams[:, 1] - seams[:, 0], axis=1)
    n = np.maximum(2, np.ceil(length / spacing).astype(np.int64) + 1)
    idx = np.repeat(np.arange(len(seams)), n)
    frac = np.concatenate([np.linspace(0, 1, k) for k in n])[:, None]
    samples = seams[idx, 0] * (1 - frac) + seams[idx, 1] * frac
    return cKDTree(samples).query(np.asarray(points, np.float64))[0]
