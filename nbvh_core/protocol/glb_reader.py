"""Reads back the .glb files this product writes (`geometry.glb`), with numpy alone (so it sits with what the add-on
and the job share): the add-on builds a kept decimation's mesh data from it inside Blender, where there is no torch
and no trimesh. Only the layout the writer makes is accepted (one mesh, triangle primitives sharing float32 POSITION / NORMAL / TEXCOORD_0, uint32 indices);
anything else is refused in one line (ValueError). A file is data: nothing in it is run."""
from __future__ import annotations

import json
import struct

import numpy as np

#: The largest .glb read back (a 20M-triangle decimation with its textures is well under it).
MAX_GLB_BYTES = 2 << 30
_COMPONENTS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3}


def _chunks(data: bytes, where: str) -> tuple[dict, bytes]:
    if len(data) > MAX_GLB_BYTES or len(data) < 20:
        raise ValueError(f"{where}: not a glTF binary of a readable size ({len(data):,} B)")
    magic, version, total = struct.unpack_from("<4sII", data, 0)
    if magic != b"glTF" or version != 2 or total != len(data):
        raise ValueError(f"{where}: not a glTF 2.0 binary (or truncated)")
    n_json, kind = struct.unpack_from("<I4s", data, 12)
    if kind != b"JSON" or 20 + n_json > len(data):
        raise ValueError(f"{where}: its JSON chunk is missing or truncated")
    try:
        doc = json.loads(data[20:20 + n_json])
    except ValueError:
        raise ValueError(f"{where}: its JSON chunk does not parse") from None
    at = 20 + n_json
    blob = b""
    if at + 8 <= len(data):
        n_bin, kind = struct.unpack_from("<I4s", data, at)
        if kind != b"BIN\0" or at + 8 + n_bin > len(data):
            raise ValueError(f"{where}: its binary chunk is truncated")
        blob = data[at + 8:at + 8 + n_bin]
    return doc, blob


def _accessor(doc: dict, blob: bytes, index: int, where: str) -> np.ndarray:
    try:
        acc = doc["accessors"][index]
        view = doc["bufferViews"][acc["bufferView"]]
        width = _COMPONENTS[acc["type"]]
        dtype = {5126: np.float32, 5125: np.uint32}[acc["componentType"]]
        start, count = int(view.get("byteOffset", 0)), int(acc["count"])
    except (KeyError, IndexError, TypeError):
        raise ValueError(f"{where}: accessor {index} is not of the layout this product writes") from None
    n = count * width * np.dtype(dtype).itemsize
    if start < 0 or count < 0 or start + n > len(blob) or n > int(view["byteLength"]):
        raise ValueError(f"{where}: accessor {index} reaches past its buffer")
    return np.frombuffer(blob, dtype, count * width, start).reshape(count, width) if width > 1 else \
        np.frombuffer(blob, dtype, count, start)


def read_glb(data: bytes, where: str = "glb") -> dict:
    """The mesh of a .glb this product wrote, as arrays: positions (W, 3) float32, normals (W, 3) float32 or None,
    uvs (W, 2) float32 with v = 0 at the image's bottom (Blender's convention) or None, faces (F, 3) int64 into
    them, face_material (F,) int64 (the material slot each triangle uses), material_names [str]."""
    doc, blob = _chunks(data, where)
    try:
        primitives = doc["meshes"][0]["primitives"]
        attributes = primitives[0]["attributes"]
    except (KeyError, IndexError, TypeError):
        raise ValueError(f"{where}: no mesh in it") from None
    positions = _accessor(doc, blob, attributes["POSITION"], where)
    normals = _accessor(doc, blob, attributes["NORMAL"], where) if "NORMAL" in attributes else None
    uvs = None
    if "TEXCOORD_0" in attributes:
        raw = _accessor(doc, blob, attributes["TEXCOORD_0"], where)
        uvs = np.stack([raw[:, 0], 1.0 - raw[:, 1]], 1).astype(np.float32)
    faces, slots = [], []
    for p in primitives:
        if p.get("attributes") != attributes or p.get("mode", 4) != 4:
            raise ValueError(f"{where}: primitives that do not share one vertex buffer of triangles")
        idx = _accessor(doc, blob, p["indices"], where).astype(np.int64)
        if idx.size % 3 or (idx.size and idx.max() >= len(positions)):
            raise ValueError(f"{where}: indices out of range")
        faces.append(idx.reshape(-1, 3))
        slots.append(np.full(idx.size // 3, int(p.get("material", 0)), np.int64))
    names = [str(m.get("name", "")) for m in doc.get("materials", [])]
    return {"positions": positions, "normals": normals, "uvs": uvs, "faces": np.concatenate(faces),
            "face_material": np.concatenate(slots), "material_names": names}
