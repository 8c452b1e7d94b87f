"""The benchmark meshes: the five bundled samples plus three made here in code (deterministic, nothing stored).

    knot   - a tube around a (2, 3) torus knot: thin parts everywhere (tube radius 3% of the box), 28.8k triangles
    spiky  - a sphere with a high-frequency displacement: dense small detail on a closed surface, 81.9k triangles
    sheet  - an open wavy sheet with round holes: open surface, boundary edges, thin (zero-thickness), ~70k triangles

Together with blob (smooth), studs (many repeated small details), gyroid (thin walls, holes), terrain (open height
field) and bunny (a real scan with holes), they span detail levels, thin parts and open surfaces.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from nbvh_core.mesh import Mesh, load_mesh, mesh_from_arrays  # noqa: E402
from nbvh_core.samples_dir import SAMPLE_NAMES, sample_path  # noqa: E402

MADE = ("knot", "spiky", "sheet")
BENCH_MESHES = tuple(SAMPLE_NAMES) + MADE


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


def bench_mesh(name: str) -> Mesh:
    """A benchmark mesh by name (see module docstring), normalised like every input."""
    if name in MADE:
        return {"knot": knot, "spiky": spiky, "sheet": sheet}[name]()
    return load_mesh(sample_path(name))


if __name__ == "__main__":
    for name in BENCH_MESHES:
        m = bench_mesh(name)
        print(f"{name}: {m.n_triangles:,} triangles, {m.n_vertices:,} vertices")
