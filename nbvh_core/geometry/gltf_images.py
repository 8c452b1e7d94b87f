"""The image files a glTF or GLB material samples, as the file holds them (PNG or JPEG bytes), by material name.

trimesh decodes a glTF's textures into pixels and keeps no bytes, so a kept mesh's `.glb` (and a model's file) would
re-encode them. Read here from the container itself - the GLB's binary chunk, a `.gltf`'s data URIs or the files it
names beside it (through the reader's confined resolver) - each becomes its material's `Material.source`;
`look.encode_texture` still stores it only when it decodes exactly to the pixels read and is no larger than PNG.
A material whose name is missing or shared, or an image that cannot be found, keeps no source (re-encoded, as
before): nothing here can fail a load.
"""
from __future__ import annotations

import base64
import json
import struct

_GLB_MAGIC, _JSON_CHUNK, _BIN_CHUNK = b"glTF", 0x4E4F534A, 0x004E4942


def _glb_chunks(data: bytes) -> tuple[dict, bytes]:
    """A GLB's JSON document and its binary chunk (b'' when it has none); ValueError on a broken container."""
    if data[:4] != _GLB_MAGIC or len(data) < 20:
        raise ValueError("not a GLB container")
    doc, binary, at = None, b"", 12
    while at + 8 <= len(data):
        length, kind = struct.unpack_from("<II", data, at)
        chunk = data[at + 8:at + 8 + length]
        if kind == _JSON_CHUNK and doc is None:
            doc = json.loads(chunk.decode("utf-8"))
        elif kind == _BIN_CHUNK and not binary:
            binary = chunk
        at += 8 + length + (-length % 4)
    if not isinstance(doc, dict):
        raise ValueError("a GLB without its JSON chunk")
    return doc, binary


def _image_bytes(doc: dict, image: dict, binary: bytes, resolver) -> bytes:
    """One glTF image's bytes: from its buffer view, a data URI or a file the resolver finds (ValueError if not)."""
    if "bufferView" in image:
        view = doc["bufferViews"][int(image["bufferView"])]
        buffer = doc["buffers"][int(view.get("buffer", 0))]
        data = binary if "uri" not in buffer else _uri_bytes(buffer["uri"], resolver)
        start = int(view.get("byteOffset", 0))
        return data[start:start + int(view["byteLength"])]
    return _uri_bytes(image["uri"], resolver)


def _uri_bytes(uri: str, resolver) -> bytes:
    if uri.startswith("data:"):
        return base64.b64decode(uri.split(",", 1)[1])
    if resolver is None:
        raise ValueError("an external file, and no folder to read it from")
    return resolver.get(uri)


def material_images(data: bytes, ext: str, resolver=None) -> dict[str, bytes]:
    """{material name: the bytes of the image its base colour samples} of a '.glb' or '.gltf' file's contents
    (`resolver`: the reader's confined resolver for files beside a .gltf, or None). Names that several materials
    share are left out (which image is whose would be a guess); any part that cannot be read is left out."""
    try:
        doc, binary = _glb_chunks(data) if ext == ".glb" else (json.loads(data.decode("utf-8")), b"")
        materials, textures, images = doc.get("materials", []), doc.get("textures", []), doc.get("images", [])
    except (ValueError, UnicodeDecodeError, AttributeError, RecursionError):  # RecursionError: nesting too deep
        return {}
    names = [m.get("name") for m in materials if isinstance(m, dict)]
    out: dict[str, bytes] = {}
    for m in materials:
        try:
            name = m.get("name")
            if not name or names.count(name) > 1:
                continue
            texture = textures[int(m["pbrMetallicRoughness"]["baseColorTexture"]["index"])]
            out[str(name)[:64]] = _image_bytes(doc, images[int(texture["source"])], binary, resolver)
        except (KeyError, IndexError, TypeError, ValueError, AttributeError):
            continue
    return out
