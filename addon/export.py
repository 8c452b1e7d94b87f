"""Blender object -> numpy arrays (object-local coordinates, modifiers applied, triangulated).

Read with `foreach_get` into preallocated arrays: no per-vertex Python loops.
"""
from __future__ import annotations

import numpy as np

#: Object types Blender can turn into a mesh.
CONVERTIBLE = {"MESH", "CURVE", "SURFACE", "FONT", "META", "CURVES"}


class ExportError(ValueError):
    """The object cannot be compressed; the message names it and says why."""


def evaluated_triangles(obj, depsgraph) -> tuple[np.ndarray, np.ndarray, dict, dict]:
    """(V, 3) float32 vertices, (F, 3) int32 triangle indices, `mesh_data_bytes` and the look's arrays
    (`look_arrays`: slots, coordinates, materials; {} without material slots) of `obj` as evaluated in
    `depsgraph` (one evaluation serves all).

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
        look = look_arrays(obj, mesh)
    finally:
        obj_eval.to_mesh_clear()
    verts = verts.reshape(-1, 3)
    if not np.isfinite(verts).all():
        raise ExportError(f"'{obj.name}' has {int((~np.isfinite(verts).all(1)).sum())} vertices with NaN or "
                          "infinite coordinates")
    return verts, tris.reshape(-1, 3), blender_bytes, look


def look_arrays(obj, mesh) -> dict:
    """The .npz members of an object's look (nbvh_core.geometry.look.LOOK_MEMBERS): per-triangle material slot, per-corner
    coordinates of the active UV map, per slot the base colour (linear RGBA) and the image feeding Base Color
    (uint8, row 0 at the top). {} when the object has no material slots (it keeps its single colour)."""
    slots = list(getattr(obj, "material_slots", []))
    if not slots:
        return {}
    n_t = len(mesh.loop_triangles)
    out = {}
    mat_index = np.empty(n_t, np.int32)
    mesh.loop_triangles.foreach_get("material_index", mat_index)
    out["face_slots"] = np.clip(mat_index, 0, len(slots) - 1)
    uv_layer = mesh.uv_layers.active if len(mesh.uv_layers) else None
    if uv_layer is not None:
        uv = np.empty(len(mesh.loops) * 2, np.float32)
        uv_layer.data.foreach_get("uv", uv)
        loops = np.empty(n_t * 3, np.int32)
        mesh.loop_triangles.foreach_get("loops", loops)
        out["corner_uvs"] = uv.reshape(-1, 2)[loops].reshape(n_t, 3, 2)
    colors, names = [], []
    for i, slot in enumerate(slots):
        color, image, source = material_look(slot.material)
        colors.append(color)
        names.append(slot.material.name if slot.material is not None else f"slot{i}")
        if image is not None:
            out[f"image_{i}"] = image
            if source is not None:
                out[f"image_source_{i}"] = np.frombuffer(source, np.uint8)
    out["base_colors"] = np.asarray(colors, np.float32)
    out["material_names"] = np.array(names, dtype=str)
    return out


#: Largest image side exported with a look (bigger images are left out: the slot shows its base colour).
MAX_EXPORT_SIDE = 8192


def material_look(mat) -> tuple[list[float], np.ndarray | None, bytes | None]:
    """(linear RGBA base colour, image (H, W, 3|4) uint8 sRGB or None, the image's PNG/JPEG file bytes or None) of
    a material: the Principled or Diffuse BSDF feeding the output, its Base Color's value or the Image Texture
    linked to it; the viewport colour otherwise."""
    if mat is None:
        return [0.8, 0.8, 0.8, 1.0], None, None
    color = list(mat.diffuse_color)
    if not mat.use_nodes or mat.node_tree is None:
        return color, None, None
    bsdf = next((n for n in mat.node_tree.nodes if n.type in ("BSDF_PRINCIPLED", "BSDF_DIFFUSE")), None)
    if bsdf is None:
        return color, None, None
    socket = bsdf.inputs.get("Base Color") or bsdf.inputs.get("Color")
    if socket is None:
        return color, None, None
    if socket.is_linked and socket.links[0].from_node.type == "TEX_IMAGE":
        img = socket.links[0].from_node.image
        pixels = image_pixels(img)
        return list(socket.default_value), pixels, image_file_bytes(img) if pixels is not None else None
    return list(socket.default_value), None, None


#: Largest image file carried as a texture's source (the core stores it as is only when it decodes to exactly the
#: exported pixels: `nbvh_core.geometry.look.encode_texture`).
MAX_SOURCE_BYTES = 64 << 20


def image_file_bytes(img) -> bytes | None:
    """The PNG or JPEG bytes a Blender image was loaded from (packed into the .blend, or its file on disk), or
    None (generated, another format, unreadable, too large). Read only: the user's file is never written."""
    if img is None or getattr(img, "source", "FILE") != "FILE" or img.file_format not in ("PNG", "JPEG"):
        return None
    try:
        packed = getattr(img, "packed_file", None)
        if packed is not None:
            data = bytes(packed.data)
        else:
            import os

            import bpy

            path = bpy.path.abspath(img.filepath, library=img.library)
            if not os.path.isfile(path) or os.path.getsize(path) > MAX_SOURCE_BYTES:
                return None
            with open(path, "rb") as f:
                data = f.read()
    except (OSError, ValueError, TypeError):
        return None
    return data if len(data) <= MAX_SOURCE_BYTES else None


def linear_to_srgb(rgb: np.ndarray) -> np.ndarray:
    """Linear values, clipped to [0, 1], sRGB-encoded (the standard transfer curve)."""
    rgb = np.clip(rgb, 0.0, 1.0)
    return np.where(rgb <= 0.0031308, 12.92 * rgb, 1.055 * np.power(rgb, 1 / 2.4) - 0.055)


def image_pixels(img) -> np.ndarray | None:
    """(H, W, 4) uint8 of a Blender image, row 0 at the top, sRGB-encoded (float images are encoded here), or
    (H, W, 3) when every pixel is opaque (an alpha of 255 everywhere carries nothing, and a 3-channel photograph
    may be stored as JPEG); None when it has no pixels or is over MAX_EXPORT_SIDE."""
    if img is None:
        return None
    w, h = int(img.size[0]), int(img.size[1])
    if not (0 < w <= MAX_EXPORT_SIDE and 0 < h <= MAX_EXPORT_SIDE):
        return None
    px = np.empty(w * h * 4, np.float32)
    img.pixels.foreach_get(px)
    px = px.reshape(h, w, 4)[::-1]
    if img.is_float:
        px[..., :3] = linear_to_srgb(px[..., :3])
    out = np.clip(px * 255 + 0.5, 0, 255).astype(np.uint8)
    if (out[..., 3] == 255).all():
        out = out[..., :3]
    return np.ascontiguousarray(out)


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
