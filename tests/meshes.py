"""Small meshes made in code for tests."""
import numpy as np

from nbvh_core.geometry.mesh import mesh_from_arrays


def icosphere(subdivisions=3, noise=0.0, seed=0):
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    v = np.asarray(m.vertices) + noise * np.random.default_rng(seed).normal(size=m.vertices.shape)
    return mesh_from_arrays(v, np.asarray(m.faces), name="icosphere")
