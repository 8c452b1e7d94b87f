"""The benchmark meshes: the five bundled samples plus three made here in code (deterministic, nothing stored).

    knot   - a tube around a (2, 3) torus knot: thin parts everywhere (tube radius 3% of the box), 28.8k triangles
    spiky  - a sphere with a high-frequency displacement: dense small detail on a closed surface, 81.9k triangles
    sheet  - an open wavy sheet with round holes: open surface, boundary edges, thin (zero-thickness), ~70k triangles
    gear   - a CAD-like part: a 24-tooth spur gear with a bored hub, planar faces and sharp edges, 3.1k triangles
    lattice - the heavy one (like the paper's multi-million-triangle models): a cubic strut lattice with fine bumps
             on every strut, marching cubes at 320^3, >2M triangles (generated once, cached under ~/.cache/nbvh)

Together with blob (smooth), studs (many repeated small details), gyroid (thin walls, holes), terrain (open height
field) and bunny (a real scan with holes), they span detail levels, thin parts and open surfaces.
"""
from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent

from nbvh_core.geometry.mesh import Mesh, load_mesh, mesh_from_arrays
from nbvh_core.geometry.bundled_samples import SAMPLE_NAMES, sample_path

MADE = ("knot", "spiky", "sheet", "gear", "lattice")
BENCH_MESHES = tuple(SAMPLE_NAMES) + ("knot", "spiky", "sheet")  # the heavy lattice only where named


def _grid_faces(nu: int, nv: int, wrap_u: bool, wrap_v: bool) -> np.ndarray:
    """Two triangles per quad of an nu x nv vertex grid (indices u * nv + v)."""
    us = np.arange(nu if wrap_u else nu - 1)
    vs = np.arange(nv if wrap_v else nv - 1)
    u, v = (a.ravel() for a in np.meshgrid(us, vs, indexing="ij"))
    a = u * nv + v
    b = ((u + 1) % nu) * nv + v
    c = ((u + 1) % nu) * nv + (v + 1) % nv
    d = u * nv + (v + 1) % nv
    return np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]).astype(np.int64)


def knot(nu: int = 600, nv: int = 24, radius: float = 0.06) -> Mesh:
    t = np.linspace(0, 2 * np.pi, nu, endpoint=False)
    p, q = 2, 3
    r = np.cos(q * t) + 2
    curve = np.stack([r * np.cos(p * t), r * np.sin(p * t), -np.sin(q * t)], 1)
    tangent = np.gradient(curve, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    normal = np.cross(tangent, [0.0, 0.0, 1.0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    binormal = np.cross(tangent, normal)
    ang = np.linspace(0, 2 * np.pi, nv, endpoint=False)
    ring = np.cos(ang)[None, :, None] * normal[:, None] + np.sin(ang)[None, :, None] * binormal[:, None]
    verts = curve[:, None] + radius * 3.0 * ring  # curve spans ~6 units: tube radius ~3% of the box
    return mesh_from_arrays(verts.reshape(-1, 3), _grid_faces(nu, nv, True, True), name="knot")


def spiky(subdivisions: int = 6, amplitude: float = 0.08, frequency: float = 14.0) -> Mesh:
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=subdivisions)
    v = np.asarray(s.vertices)
    bump = np.sin(frequency * v[:, 0]) * np.sin(frequency * v[:, 1]) * np.sin(frequency * v[:, 2])
    return mesh_from_arrays(v * (1 + amplitude * bump)[:, None], np.asarray(s.faces), name="spiky")


def sheet(n: int = 200) -> Mesh:
    ax = np.linspace(-1, 1, n)
    x, y = np.meshgrid(ax, ax, indexing="ij")
    z = 0.25 * np.sin(3 * x) * np.cos(2 * y) + 0.1 * np.sin(7 * y + 2 * x)
    verts = np.stack([x.ravel(), y.ravel(), z.ravel()], 1)
    faces = _grid_faces(n, n, False, False)
    # Round holes on a 4 x 4 lattice: drop the triangles whose centroid is inside one.
    c = verts[faces].mean(1)
    cell = (c[:, :2] + 1) / 2 * 4
    d = np.linalg.norm(cell - np.floor(cell) - 0.5, axis=1)
    return mesh_from_arrays(verts, faces[d > 0.28], name="sheet")


def gear(teeth: int = 24, per_tooth: int = 16, thickness: float = 0.25, bore: float = 0.3) -> Mesh:
    """A spur gear as a CAD tool exports it: flat top and bottom, a toothed rim (trapezoidal teeth) and a round
    bore, each a ring of quads between two closed loops sampled at the same angles (so the faces are planar and
    the edges sharp, as a tessellated B-rep is)."""
    n = teeth * per_tooth
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False)
    phase = (np.arange(n) % per_tooth) / per_tooth  # position within a tooth period
    tooth = np.clip(np.minimum(phase, 1 - phase) * 4 - 0.5, 0, 1)  # 0 in the gap, 1 on the tip, ramps between
    outer = 1.0 + 0.12 * tooth
    loops = [np.stack([r * np.cos(ang), r * np.sin(ang), np.full(n, z)], 1)
             for r, z in ((outer, 0.0), (outer, thickness), (np.full(n, bore), thickness), (np.full(n, bore), 0.0))]
    verts = np.concatenate(loops)
    faces = []
    i = np.arange(n)
    j = (i + 1) % n
    for a, b in ((0, 1), (1, 2), (2, 3), (3, 0)):  # rim, top, bore, bottom: quads between consecutive loops
        pa, pb = a * n, b * n
        faces += [np.stack([pa + i, pa + j, pb + j], 1), np.stack([pa + i, pb + j, pb + i], 1)]
    return mesh_from_arrays(verts, np.concatenate(faces), name="gear")


def lattice(n: int = 320, period: float = 0.25, radius: float = 0.03) -> Mesh:
    """A cubic lattice of struts (every `period` along x, y and z inside a 1.8-wide box), each strut covered with
    bumps of 0.008 at a 0.05 wavelength: millions of triangles of fine, repeated detail. Cached (the marching
    cubes take a minute)."""
    import os

    cache = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "nbvh" / f"lattice-{n}-{period}-{radius}.npz"
    if cache.exists():
        with np.load(cache) as d:
            return mesh_from_arrays(d["vertices"], d["faces"], name="lattice")
    from skimage.measure import marching_cubes

    ax = np.linspace(-1.0, 1.0, n, dtype=np.float32)
    h = float(ax[1] - ax[0])
    x, y, z = np.meshgrid(ax, ax, ax, indexing="ij")
    fx, fy, fz = [c - np.round(c / period) * period for c in (x, y, z)]
    rods = np.minimum(np.minimum(np.sqrt(fy * fy + fz * fz), np.sqrt(fx * fx + fz * fz)), np.sqrt(fx * fx + fy * fy))
    del fx, fy, fz
    k = 2 * np.pi / 0.05
    field = rods - radius - 0.008 * np.sin(k * x) * np.sin(k * y) * np.sin(k * z)
    del rods
    box = np.maximum(np.maximum(np.abs(x), np.abs(y)), np.abs(z)) - 0.9
    field = np.maximum(field, box)
    del x, y, z, box
    verts, faces, _, _ = marching_cubes(field, level=0.0, spacing=(h, h, h))
    verts, faces = (verts - 1.0).astype(np.float32), faces[:, ::-1].astype(np.int32)
    cache.parent.mkdir(parents=True, exist_ok=True)
    np.savez(cache, vertices=verts, faces=faces)
    return mesh_from_arrays(verts, faces, name="lattice")


def bench_mesh(name: str) -> Mesh:
    """A benchmark mesh by name (see module docstring), normalised like every input."""
    if name in MADE:
        return {"knot": knot, "spiky": spiky, "sheet": sheet, "gear": gear, "lattice": lattice}[name]()
    return load_mesh(sample_path(name))


@functools.lru_cache(maxsize=None)
def bench_grid(name: str):
    """The bench mesh's grid measures (`mesh_measures.grid_measures`), taken once per process: loading and measuring the
    3.3M-triangle lattice takes seconds, and several benches choose a grid per (mesh, table size)."""
    from nbvh_core.planning.mesh_measures import grid_measures

    return grid_measures(bench_mesh(name))


if __name__ == "__main__":
    for name in BENCH_MESHES:
        m = bench_mesh(name)
        print(f"{name}: {m.n_triangles:,} triangles, {m.n_vertices:,} vertices")


def named_mesh(name: str) -> Mesh:
    """A bench mesh, or a real asset of `real_assets.REAL_ASSETS` (fetched when missing), by name."""
    if name in MADE or name in SAMPLE_NAMES:
        return bench_mesh(name)
    from nbvh_core.geometry.mesh import load_mesh
    from bench.real_assets import asset_path

    return load_mesh(asset_path(name))
