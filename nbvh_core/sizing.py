"""Is neural compression worth it for this mesh? Sizes a ray tracer would hold, compared before training.

A ray tracer keeps float32 vertices, int32 indices, float32 vertex normals and a BVH with <= 4 triangles per
leaf (32-byte nodes) resident before it traces one ray; the .nbvh model is traced as stored. When the model
that `settings` would build is not smaller than that, compressing gains nothing, and the result says so
(`Assessment.worth_compressing`). Choosing sizes automatically is issue 6's work; this only compares.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

from .bvh import build_full_tree, resident_bvh_nodes
from .mesh import Mesh


def mesh_resident_bytes(mesh: Mesh) -> dict:
    """Bytes a ray tracer holds for `mesh`: vertices, indices, normals, bvh (<= 4 triangles per leaf), total."""
    nodes = resident_bvh_nodes(build_full_tree(mesh), 4)
    out = {"vertices": mesh.n_vertices * 12, "indices": mesh.n_triangles * 12, "normals": mesh.n_vertices * 12,
           "bvh": nodes * 32}
    out["total"] = sum(out.values())
    return out


@dataclass
class Assessment:
    """model_bytes: the .nbvh size (exact payload + typical header); resident: `mesh_resident_bytes(mesh)`."""

    model_bytes: int
    resident: dict
    worth_compressing: bool
    message: str

    def to_dict(self) -> dict:
        return asdict(self)


def assess(mesh: Mesh, settings) -> Assessment:
    """Compare the model `settings` (a pipeline.Settings, already resolved) would write with the mesh's resident
    bytes. worth_compressing is False when the model is not smaller."""
    from .pipeline import estimate_file_bytes

    model = estimate_file_bytes(settings)
    resident_bytes = mesh_resident_bytes(mesh)
    resident = resident_bytes["total"]
    worth = model < resident
    if worth:
        msg = f"model ~{model:,} B vs the mesh as a ray tracer holds it {resident:,} B ({resident / model:.1f}x smaller)"
    else:
        msg = (f"not worth compressing: the mesh as a ray tracer holds it ({resident:,} B) is already smaller than "
               f"this model (~{model:,} B); keep the mesh, or ask for a smaller model (--budget-kb)")
    return Assessment(model_bytes=model, resident=resident_bytes, worth_compressing=worth, message=msg)
