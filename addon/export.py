"""Blender object -> numpy arrays (object-local coordinates, modifiers applied, triangulated).

Read with `foreach_get` into preallocated arrays: no per-vertex Python loops.
"""
from __future__ import annotations

import numpy as np

#: Object types Blender can turn into a mesh.
CONVERTIBLE = {"MESH", "CURVE", "SURFACE", "FONT", "META", "CURVES"}


class ExportError(ValueError):
    """The object cannot be compressed; the message names it and says why."""


def evaluated_triangles(obj, depsgraph) -> tuple[np.ndarray, np.ndarray, dict]:
    """(V, 3) float32 vertices, (F, 3) int32 triangle indices and `mesh_data_bytes` of `obj` as evaluated in
    `depsgraph` (one evaluation serves both).

    Coordinates are object-local (the world matrix is applied by the previews, so the result sits on the
    original). Raises ExportError for objects that have no surface.
    """
    if obj.type not in CONVERTIBLE:
        kind = obj.type.lower()
        article = "an" if kind[0] in "aeiou" else "a"
        raise ExportError(f"'{obj.name}' is {article} {kind}, which has no surface to compress "
                          "(select meshes, curves, surfaces, text or metaballs)")
    obj_eval = obj.evaluated_get(depsgraph)
    try:
        mesh = obj_eval.to_mesh()
    except RuntimeError as exc:
        raise ExportError(f"'{obj.name}' cannot be converted to a mesh: {exc}") from None
    if mesh is None:
        raise ExportError(f"'{obj.name}' cannot be converted to a mesh")
    try:
        mesh.calc_loop_triangles()
        n_v, n_t = len(mesh.vertices), len(mesh.loop_triangles)
        if n_v == 0 or n_t == 0:
            raise ExportError(f"'{obj.name}' has an empty mesh ({n_v} vertices, {n_t} triangles)")
        verts = np.empty(n_v * 3, np.float32)
        mesh.vertices.foreach_get("co", verts)
        tris = np.empty(n_t * 3, np.int32)
        mesh.loop_triangles.foreach_get("vertices", tris)
        blender_bytes = mesh_data_bytes(mesh)
    finally:
        obj_eval.to_mesh_clear()
    verts = verts.reshape(-1, 3)
    if not np.isfinite(verts).all():
        raise ExportError(f"'{obj.name}' has {int((~np.isfinite(verts).all(1)).sum())} vertices with NaN or "
                          "infinite coordinates")
    return verts, tris.reshape(-1, 3), blender_bytes


def asset_textures(obj) -> tuple[dict, int]:
    """({image name: report.texture_bytes}, material slot count) of the images the object's materials read
    through Image Texture nodes (each image once)."""
    from .report import texture_bytes

    images = {}
    for slot in getattr(obj, "material_slots", []):
        mat = slot.material
        if mat is None or not mat.use_nodes or mat.node_tree is None:
            continue
        for node in mat.node_tree.nodes:
            img = getattr(node, "image", None) if node.type == "TEX_IMAGE" else None
            if img is not None and img.name not in images:
                w, h = img.size
                images[img.name] = texture_bytes(int(w), int(h), int(img.channels), bool(img.is_float))
    return images, len(getattr(obj, "material_slots", []))


def mesh_data_bytes(mesh) -> dict:
    """Bytes of a Blender mesh as Blender stores them: positions, edges, face corners, faces, normals, UVs and
    other attributes (by data type), so the report compares like with like."""
    sizes = {"FLOAT": 4, "INT": 4, "FLOAT_VECTOR": 12, "FLOAT_COLOR": 16, "BYTE_COLOR": 4, "BOOLEAN": 1,
             "FLOAT2": 8, "INT8": 1, "INT32_2D": 8, "QUATERNION": 16, "FLOAT4X4": 64, "STRING": 0, "INT16_2D": 4}
    domain_len = {"POINT": len(mesh.vertices), "EDGE": len(mesh.edges), "CORNER": len(mesh.loops),
                  "FACE": len(mesh.polygons)}
    out = {"positions": len(mesh.vertices) * 12, "edges": len(mesh.edges) * 8,
           "corner_verts": len(mesh.loops) * 4, "corner_edges": len(mesh.loops) * 4,
           "face_offsets": (len(mesh.polygons) + 1) * 4}
    if hasattr(mesh, "attributes"):
        for attr in mesh.attributes:
            if attr.name in ("position", ".edge_verts", ".corner_vert", ".corner_edge") or attr.name.startswith("."):
                continue
            n = domain_len.get(attr.domain, 0) * sizes.get(attr.data_type, 4)
            key = "uv" if attr.data_type == "FLOAT2" else f"attribute:{attr.name}"
            out[key] = out.get(key, 0) + n
    if not any(k == "uv" for k in out) and hasattr(mesh, "uv_layers"):
        n_uv = len(mesh.uv_layers) * len(mesh.loops) * 8
        if n_uv:
            out["uv"] = n_uv
    # Normals a renderer keeps: one per corner (split normals) or per vertex.
    out["normals"] = len(mesh.vertices) * 12
    out["total"] = sum(out.values())
    return out
