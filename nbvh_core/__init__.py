"""nbvh_core: neural BVH geometry (N-BVH + HashVQAD + KMLP + consistent training rays). Pure Python + PyTorch.

Data flows one way: mesh -> BVH -> training samples -> model -> .nbvh file -> render / points / report.
"""
from .geometry.mesh import Mesh, MeshError, MeshWarning, Transform, load_mesh, mesh_from_arrays

__all__ = ["Mesh", "MeshError", "MeshWarning", "Transform", "load_mesh", "mesh_from_arrays"]
__version__ = "0.1.0"
