"""Regenerate the bundled sample meshes in this folder (deterministic; needs scikit-image and pymeshfix).

    .venv/bin/python assets/make_samples.py

Each sample has its own character (see assets/README.md). Procedural ones are marching cubes of signed fields,
written as gzip-compressed binary PLY so that all of them fit in a few MB. `bunny` is the Stanford bunny as
shipped inside the `pymeshfix` wheel (see README for source and licence).
"""
from __future__ import annotations

import gzip
import io
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


def _grid(n: int, lo: float = -1.0, hi: float = 1.0):
    ax = np.linspace(lo, hi, n, dtype=np.float32)
    return np.meshgrid(ax, ax, ax, indexing="ij"), (hi - lo) / (n - 1)


def _marching_cubes(field: np.ndarray, spacing: float, lo: float = -1.0):
    from skimage.measure import marching_cubes

    verts, faces, _, _ = marching_cubes(field, level=0.0, spacing=(spacing,) * 3)
    # skimage winds triangles so that normals point toward decreasing field values; fields here are negative
    # inside, so flip to get outward normals.
    return (verts + lo).astype(np.float32), faces[:, ::-1].astype(np.int32)


def blob(n: int = 72):
    """Smooth organic shape: a soft union of metaballs (smooth everywhere, no sharp detail)."""
    (x, y, z), h = _grid(n)
    centres = np.array([[0, 0, 0], [0.45, 0.2, 0.1], [-0.4, 0.25, -0.1], [0.1, -0.45, 0.2], [-0.1, 0.1, 0.5],
                        [0.2, 0.35, -0.4]], np.float32)
    radii = np.array([0.45, 0.3, 0.32, 0.28, 0.25, 0.22], np.float32)
    s = np.zeros_like(x)
    for c, r in zip(centres, radii):
        s += np.exp(-((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2) / (r * r))
    return _marching_cubes(0.6 - s, h)


def studs(n: int = 200):
    """Many small repeated details (cf. the paper's Fig. 7): a rounded box covered with a lattice of small studs."""
    (x, y, z), h = _grid(n)
    # Rounded box (signed distance).
    b = np.array([0.55, 0.4, 0.3], np.float32)
    qx, qy, qz = np.abs(x) - b[0], np.abs(y) - b[1], np.abs(z) - b[2]
    outside = np.sqrt(np.maximum(qx, 0) ** 2 + np.maximum(qy, 0) ** 2 + np.maximum(qz, 0) ** 2)
    box = outside + np.minimum(np.maximum(qx, np.maximum(qy, qz)), 0) - 0.12
    # Studs: a bump of radius 0.035 every 0.1 units, on every face (periodic field near the surface).
    period = 0.1
    fx, fy, fz = [(c / period - np.round(c / period)) * period for c in (x, y, z)]
    stud = np.minimum(np.minimum(np.sqrt(fx ** 2 + fy ** 2), np.sqrt(fy ** 2 + fz ** 2)), np.sqrt(fx ** 2 + fz ** 2))
    bumps = np.clip(0.035 - stud, 0, None) * 1.2
    return _marching_cubes(box - bumps, h)


def gyroid(n: int = 66):
    """Thin parts and holes: a thin gyroid sheet clipped to a sphere (walls ~0.05 thick, tunnels everywhere)."""
    (x, y, z), h = _grid(n)
    k = 2 * np.pi * 1.5
    g = np.sin(k * x) * np.cos(k * y) + np.sin(k * y) * np.cos(k * z) + np.sin(k * z) * np.cos(k * x)
    sheet = np.abs(g) / k - 0.025  # thickness ~0.05 in the field's units
    sphere = np.sqrt(x ** 2 + y ** 2 + z ** 2) - 0.85
    return _marching_cubes(np.maximum(sheet, sphere), h)


def terrain(n: int = 110):
    """An open (non-watertight) surface: a rippled height field with a boundary, seen from both sides."""
    u = np.linspace(-1, 1, n, dtype=np.float32)
    x, y = np.meshgrid(u, u, indexing="ij")
    z = 0.18 * np.sin(3 * x) * np.cos(2.5 * y) + 0.08 * np.sin(9 * x + 4 * y) + 0.3 * np.exp(-4 * (x ** 2 + y ** 2))
    verts = np.stack((x, y, z), axis=-1).reshape(-1, 3)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate((np.stack((a, b, c), 1), np.stack((a, c, d), 1)))
    return verts.astype(np.float32), faces.astype(np.int32)


def bunny():
    """The Stanford bunny scan shipped in the pymeshfix wheel (holes, non-manifold edges)."""
    import pymeshfix
    import trimesh

    path = Path(pymeshfix.__file__).parent / "examples" / "StanfordBunny.ply"
    m = trimesh.load(path, process=False, force="mesh")
    return np.asarray(m.vertices, np.float32), np.asarray(m.faces, np.int32)


SAMPLES = {"blob": blob, "studs": studs, "gyroid": gyroid, "terrain": terrain, "bunny": bunny}


def write_ply_gz(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Binary little-endian PLY, gzip level 9."""
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(vertices)}\n"
              "property float x\nproperty float y\nproperty float z\n"
              f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n").encode()
    face_rec = np.empty(len(faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    face_rec["n"] = 3
    face_rec["i"] = faces
    buf = io.BytesIO()
    buf.write(header)
    buf.write(np.ascontiguousarray(vertices, "<f4").tobytes())
    buf.write(face_rec.tobytes())
    path.write_bytes(gzip.compress(buf.getvalue(), compresslevel=9, mtime=0))


def main() -> None:
    for name, make in SAMPLES.items():
        v, f = make()
        out = HERE / f"{name}.ply.gz"
        write_ply_gz(out, v, f)
        print(f"{out.name}: {len(v)} vertices, {len(f)} triangles, {out.stat().st_size / 1e6:.2f} MB")


if __name__ == "__main__":
    main()
