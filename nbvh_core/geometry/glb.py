"""A mesh with its look as a glTF 2.0 binary (.glb): what a user gets when a decimation wins, and what Blender,
engines and viewers open as it is.

One primitive per material slot in use, all sharing one vertex buffer of wedges (a vertex per distinct position,
normal and texture coordinate: seams stay split exactly where the asset split them; normals smooth across gentle
edges and split at hard ones, CREASE_DEGREES). Materials are
metallic-roughness with the slot's base colour (linear, as glTF's factor is) and, where the slot has an image, its
texture as the product stores it (`Material.stored_image`: the asset's own PNG/JPEG bytes when exact). Positions
are in the asset's original units. glTF puts v = 0 at the top of an image; the product's coordinates put it at the
bottom (Blender's convention), so v is flipped on the way out, as glTF importers flip it on the way in.

    data = encode_glb(mesh)       # bytes, deterministic
"""
from __future__ import annotations

import json
import struct

import numpy as np

from .look import texture_format
from .mesh import Mesh

_FLOAT, _UINT = 5126, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963


#: Faces meeting at a vertex at more than this angle keep their own normals there (a hard edge, as a CAD part's or
#: a box's); below it the vertex is shaded smooth (a scan's surface). 45 degrees: the engine's machined edges are
#: 90, a 100k-triangle scan's neighbouring faces stay under 30.
CREASE_DEGREES = 45.0


def corner_normals(mesh: Mesh, crease_degrees: float = CREASE_DEGREES) -> np.ndarray:
    """(F, 3, 3) float32 unit normal per corner: the area-weighted sum of the normals of the faces around the corner's
    vertex that lie within `crease_degrees` of the corner's own face (smooth across gentle edges, split at hard
    ones; every corner of a smooth vertex gets bit-identical sums, so it stays one vertex in the file)."""
    tri = mesh.triangles().astype(np.float64)
    weighted = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # length = 2 x area
    unit = weighted / np.maximum(np.linalg.norm(weighted, axis=1, keepdims=True), 1e-300)
    vertex = mesh.faces.reshape(-1).astype(np.int64)
    face = np.repeat(np.arange(mesh.n_triangles), 3)
    order = np.argsort(vertex, kind="stable")
    starts = np.searchsorted(vertex[order], vertex[order], side="left")
    sizes = np.bincount(vertex, minlength=mesh.n_vertices)[vertex[order]]
    # every (corner, corner at the same vertex) pair, the corners sorted by vertex: sum(valence^2) pairs
    i = np.repeat(np.arange(len(order)), sizes)
    j = starts[i] + (np.arange(len(i)) - np.repeat(np.cumsum(sizes) - sizes, sizes))
    fi, fj = face[order][i], face[order][j]
    keep = np.einsum("ij,ij->i", unit[fi], unit[fj]) >= np.cos(np.radians(crease_degrees))
    out = np.zeros((len(order), 3))
    np.add.at(out, i[keep], weighted[fj[keep]])
    normals = np.empty_like(out)
    normals[order] = out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-300)
    return normals.reshape(-1, 3, 3).astype(np.float32)


def _wedge_buffer(mesh: Mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray]:
    """(positions (W, 3) float32 original units, normals (W, 3), uvs (W, 2) glTF-flipped or None, corners (F, 3)):
    one wedge per distinct (vertex, normal, texture coordinate)."""
    textured = mesh.look is not None and mesh.look.textured
    normals = corner_normals(mesh).reshape(-1, 3)
    cols = [mesh.faces.reshape(-1).astype(np.int64)]
    cols += list(np.ascontiguousarray(normals).view(np.int32).astype(np.int64).T)  # exact bits: equal is one
    uv = mesh.look.corner_uvs.reshape(-1, 2) if textured else None
    if uv is not None:
        cols += list(np.ascontiguousarray(uv, np.float32).view(np.int32).astype(np.int64).T)
    _, first, inverse = np.unique(np.stack(cols, 1), axis=0, return_index=True, return_inverse=True)
    positions = mesh.transform.to_original(mesh.vertices[cols[0][first]]).astype(np.float32)
    uvs = None if uv is None else np.stack([uv[first, 0], 1.0 - uv[first, 1]], 1).astype(np.float32)
    return positions, normals[first], uvs, inverse.reshape(-1, 3).astype(np.uint32)


class _Binary:
    """The GLB's binary chunk, built view by view (each 4-byte aligned)."""

    def __init__(self):
        self.data, self.views, self.accessors = bytearray(), [], []

    def view(self, payload: bytes, target: int | None = None) -> int:
        self.data += b"\0" * (-len(self.data) % 4)
        view = {"buffer": 0, "byteOffset": len(self.data), "byteLength": len(payload)}
        if target is not None:
            view["target"] = target
        self.data += payload
        self.views.append(view)
        return len(self.views) - 1

    def accessor(self, array: np.ndarray, kind: str, target: int, bounds: bool = False) -> int:
        array = np.ascontiguousarray(array)
        acc = {"bufferView": self.view(array.tobytes(), target), "componentType": _UINT if kind == "SCALAR" else _FLOAT,
               "count": int(array.shape[0]), "type": kind}
        if bounds:
            acc["min"], acc["max"] = array.min(0).tolist(), array.max(0).tolist()
        self.accessors.append(acc)
        return len(self.accessors) - 1


def _materials(mesh: Mesh, binary: _Binary) -> tuple[list, list, list]:
    """glTF materials, textures and images of the mesh's slots (one default material for a bare shape)."""
    if mesh.look is None:
        return [{"name": "material", "pbrMetallicRoughness": {"metallicFactor": 0.0, "roughnessFactor": 0.5}}], [], []
    materials, textures, images = [], [], []
    for m in mesh.look.materials:
        pbr = {"baseColorFactor": [float(c) for c in m.base_color], "metallicFactor": 0.0, "roughnessFactor": 0.5}
        data = m.stored_image() if mesh.look.corner_uvs is not None else None
        if data is not None:
            pbr["baseColorFactor"] = [1.0, 1.0, 1.0, float(m.base_color[3])]  # the image is the colour, as read
            images.append({"bufferView": binary.view(data), "mimeType": f"image/{texture_format(data)}"})
            textures.append({"source": len(images) - 1})
            pbr["baseColorTexture"] = {"index": len(textures) - 1}
        materials.append({"name": m.name, "pbrMetallicRoughness": pbr})
    return materials, textures, images


def encode_glb(mesh: Mesh) -> bytes:
    """`mesh` with its look as a .glb (see the module docstring). Deterministic: the same mesh gives the same bytes."""
    positions, normals, uvs, corners = _wedge_buffer(mesh)
    binary = _Binary()
    attributes = {"POSITION": binary.accessor(positions, "VEC3", _ARRAY_BUFFER, bounds=True),
                  "NORMAL": binary.accessor(normals, "VEC3", _ARRAY_BUFFER)}
    if uvs is not None:
        attributes["TEXCOORD_0"] = binary.accessor(uvs, "VEC2", _ARRAY_BUFFER)
    slots = np.zeros(mesh.n_triangles, np.int64) if mesh.look is None else mesh.look.face_slots
    materials, textures, images = _materials(mesh, binary)
    primitives = []
    for s in np.unique(slots):
        idx = corners[slots == s].reshape(-1)
        primitives.append({"attributes": attributes, "material": int(s), "mode": 4,
                           "indices": binary.accessor(idx, "SCALAR", _ELEMENT_ARRAY_BUFFER)})
    doc = {"asset": {"version": "2.0", "generator": "nbvh_core"}, "scene": 0, "scenes": [{"nodes": [0]}],
           "nodes": [{"mesh": 0, "name": mesh.name}], "meshes": [{"name": mesh.name, "primitives": primitives}],
           "materials": materials, "buffers": [{"byteLength": len(binary.data)}], "bufferViews": binary.views,
           "accessors": binary.accessors}
    if images:
        doc["images"], doc["textures"] = images, textures
    text = json.dumps(doc, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    blob = bytes(binary.data) + b"\0" * (-len(binary.data) % 4)
    total = 12 + 8 + len(text) + 8 + len(blob)
    return (struct.pack("<4sII", b"glTF", 2, total) + struct.pack("<I4s", len(text), b"JSON") + text
            + struct.pack("<I4s", len(blob), b"BIN\0") + blob)
