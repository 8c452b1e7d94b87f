"""The failure classes the product is tested and measured on (tests/test_pipeline.py, bench/robustness/bench_failures.py):
meshes where methods break, and training conditions that break them. Deterministic, made in code.

Mesh classes: `failure_mesh(name)` -> (vertices (V, 3) float64, faces (F, 3) int64), from the bundled blob where
a class needs a shape. Training conditions (`CONDITIONS`) run on the blob: a learning rate x10 or x100, 4-bit
tables, a divergence injected late (`bench_recovery.diverges_once`).
"""
from __future__ import annotations

import numpy as np

#: The classes the tests run through compress_mesh at small sizes (each a few seconds).
TESTED = ("thin walls", "huge offset (1e6)", "tiny scale (1e-6)", "inside-out", "every face twice", "1000 pieces",
          "one triangle", "zero-thickness plane", "long slivers", "non-manifold edges")
#: Mesh classes of the matrix: the tested ones, and the ones that need a larger mesh or a bench shape.
MESH_CLASSES = (*TESTED, "open sheet", "dense repeated detail", "1M+ triangles")
CONDITIONS = ("learning rate x10", "learning rate x100", "4-bit tables", "divergence injected late")


def _blob():
    from nbvh_core.geometry.bundled_samples import sample_path
    from nbvh_core.geometry.mesh import load_mesh

    mesh = load_mesh(sample_path("blob"))
    return mesh.transform.to_original(mesh.vertices).astype(np.float64), mesh.faces.astype(np.int64)


def _thin_box(thickness: float = 0.004) -> tuple[np.ndarray, np.ndarray]:
    """A closed box shell of the given wall thickness (outer box outward, inner box inward), 24 triangles."""
    import trimesh

    outer = trimesh.creation.box((1.0, 1.0, 1.0))
    inner = trimesh.creation.box((1.0 - 2 * thickness,) * 3)
    return (np.concatenate([outer.vertices, inner.vertices]),
            np.concatenate([outer.faces, inner.faces[:, ::-1] + len(outer.vertices)]))


def _fins(v: np.ndarray, f: np.ndarray, count: int = 200) -> tuple[np.ndarray, np.ndarray]:
    """The mesh with a third triangle (a fin, pointing outward) on `count` of its edges: non-manifold edges."""
    rng = np.random.default_rng(0)
    picked = f[rng.choice(len(f), count, replace=False)]
    a, b = picked[:, 0], picked[:, 1]
    centre = v.mean(axis=0)
    mid = 0.5 * (v[a] + v[b])
    tip = mid + 0.1 * (mid - centre) / np.linalg.norm(mid - centre, axis=1, keepdims=True)
    tips = len(v) + np.arange(count)
    return np.concatenate([v, tip]), np.concatenate([f, np.stack([a, b, tips], axis=1)])


def failure_mesh(name: str) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, faces) of mesh class `name` (MESH_CLASSES)."""
    import trimesh

    if name == "thin walls":
        return _thin_box()
    if name in ("open sheet", "dense repeated detail", "1M+ triangles"):
        from bench.meshes import bench_mesh, lattice

        mesh = {"open sheet": lambda: bench_mesh("sheet"), "dense repeated detail": lambda: lattice(60),
                "1M+ triangles": lambda: lattice(180)}[name]()
        return mesh.vertices.astype(np.float64), mesh.faces.astype(np.int64)
    v, f = _blob()
    if name == "huge offset (1e6)":
        return v + np.array([1e6, -2e6, 3e6]), f
    if name == "tiny scale (1e-6)":
        return v * 1e-6, f
    if name == "inside-out":
        return v, f[:, ::-1]
    if name == "every face twice":
        return v, np.concatenate([f, f])
    if name == "non-manifold edges":
        return _fins(v, f)
    if name == "1000 pieces":
        ball, rng = trimesh.creation.icosphere(1), np.random.default_rng(0)
        return (np.concatenate([ball.vertices * 0.01 + rng.random(3) for _ in range(1000)]),
                np.concatenate([ball.faces + i * len(ball.vertices) for i in range(1000)]))
    plane = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    return {"one triangle": (plane[:3], np.array([[0, 1, 2]])),
            "zero-thickness plane": (plane, np.array([[0, 1, 2], [0, 2, 3]])),
            "long slivers": (np.array([[0, 0, 0], [1, 0, 0], [0.5, 1e-4, 0], [0.5, -1e-4, 0]], float),
                             np.array([[0, 1, 2], [0, 3, 1]]))}[name]
