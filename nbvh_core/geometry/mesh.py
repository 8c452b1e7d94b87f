"""Mesh input: load, validate and normalise a triangle mesh.

Everything downstream (BVH, rays, model) works in *normalised* coordinates: the mesh is scaled uniformly so
that its longest bounding-box side is 1 and centred at (0.5, 0.5, 0.5), i.e. it lies in the unit box [0, 1]^3.
`Mesh.transform` keeps the mapping back to the original coordinates (`original = normalised * scale + offset`),
so distances, points and images can be reported in the user's units.
"""
from __future__ import annotations

import gc
import io
import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .look import Look, LookError, Material, check_look, image_from_pil

#: File extensions `load_mesh` reads (a trailing `.gz` is decompressed first).
SUPPORTED_EXTENSIONS = (".obj", ".ply", ".stl", ".off", ".glb", ".gltf")
#: The largest mesh file (or decompressed .gz, or file a glTF/OBJ refers to) `load_mesh` reads: a 20M-triangle
#: binary PLY is ~0.5 GB.
MAX_MESH_BYTES = 8 << 30
#: A .gz whose content would be more than this many times its size is refused before it is inflated (meshes
#: compress 2-6x; a decompression bomb 1000x).
MAX_GZIP_RATIO = 200


#: The largest |coordinate| accepted: squares of extents and areas stay finite in float64 far beyond it, and no
#: real asset comes near it (1e15 m is 7,000 astronomical units).
MAX_COORDINATE = 1e15


class MeshError(ValueError):
    """A mesh that cannot be used: the message says what is wrong and with which input."""


class MeshWarning(UserWarning):
    """Something was repaired (e.g. degenerate triangles dropped); the message says what and how many."""


@dataclass(frozen=True)
class Transform:
    """Uniform scale + offset: `original = normalised * scale + offset` (scale > 0, offset (3,) float64)."""

    scale: float
    offset: np.ndarray

    def to_original(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) normalised points -> (N, 3) float64 original coordinates."""
        return np.asarray(points, dtype=np.float64) * self.scale + self.offset

    def to_normalised(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) original points -> (N, 3) float64 normalised coordinates."""
        return (np.asarray(points, dtype=np.float64) - self.offset) / self.scale

    def distance_to_original(self, distance: np.ndarray | float) -> np.ndarray | float:
        """A length in normalised units -> the same length in original units."""
        return distance * self.scale

    def to_dict(self) -> dict:
        return {"scale": float(self.scale), "offset": [float(v) for v in self.offset]}

    @staticmethod
    def from_dict(d: dict) -> "Transform":
        return Transform(float(d["scale"]), np.asarray(d["offset"], dtype=np.float64))


@dataclass(frozen=True)
class Mesh:
    """A validated triangle mesh in normalised coordinates.

    vertices: (V, 3) float32 inside [0, 1]^3; faces: (F, 3) int32, every index in [0, V), no degenerate triangle.
    look: the faces' material slots, texture coordinates and materials (`look.Look`), or None (a bare shape).
    """

    vertices: np.ndarray
    faces: np.ndarray
    transform: Transform
    name: str = "mesh"
    #: Repairs made while loading, as readable sentences (also emitted as `MeshWarning`).
    repairs: tuple[str, ...] = field(default=())
    look: Look | None = None

    @property
    def n_triangles(self) -> int:
        return int(self.faces.shape[0])

    @property
    def n_vertices(self) -> int:
        return int(self.vertices.shape[0])

    def triangles(self) -> np.ndarray:
        """(F, 3, 3) float32 corner positions."""
        return self.vertices[self.faces]

    def face_normals(self, tri: np.ndarray | None = None) -> np.ndarray:
        """(F, 3) float32 unit geometric normals, right-handed winding (v1 - v0) x (v2 - v0); with `tri` (K,) int
        triangle ids, (K, 3): the same values for those triangles only."""
        faces = self.faces if tri is None else self.faces[tri]
        out = np.empty((len(faces), 3), np.float32)
        for a, b, n in face_cross_chunks(self.vertices, faces):
            out[a:b] = n / np.linalg.norm(n, axis=1, keepdims=True)
        return out

    def surface_area(self) -> float:
        """Total area in normalised units squared."""
        return float(0.5 * np.linalg.norm(face_cross(self.vertices, self.faces), axis=1).sum())


#: Triangles per chunk of float64 work on a whole mesh: the temporaries stay bounded (a 10M-triangle mesh's
#: (F, 3, 3) float64 corner copy alone was 720 MB).
CROSS_CHUNK = 1 << 20


def face_cross_chunks(vertices: np.ndarray, faces: np.ndarray):
    """Yields (start, stop, (v1 - v0) x (v2 - v0) in float64 (stop - start, 3)) over CROSS_CHUNK triangles at a time
    (vertices (V, 3), faces (F, 3)): the same values as on the whole array at once."""
    for a in range(0, len(faces), CROSS_CHUNK):
        tri = vertices[faces[a:a + CROSS_CHUNK]].astype(np.float64)
        yield a, a + len(tri), np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])


def face_cross(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, 3) float64 (v1 - v0) x (v2 - v0) per triangle (length: twice its area), computed in chunks."""
    out = np.empty((len(faces), 3), np.float64)
    for a, b, c in face_cross_chunks(vertices, faces):
        out[a:b] = c
    return out


def _checked_arrays(vertices: np.ndarray, faces: np.ndarray, name: str) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3) float64 vertices and (F, 3) int64 faces, or a `MeshError` naming the first problem (no copies
    where the input already has those types)."""
    try:
        v = np.asarray(vertices, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise MeshError(f"{name}: vertices are not numeric: {exc}") from None
    f = np.asarray(faces)
    if v.size == 0 or f.size == 0:
        raise MeshError(f"{name}: the mesh is empty ({v.reshape(-1, 3).shape[0] if v.size % 3 == 0 else v.size} "
                        f"vertices, {0 if f.size == 0 else len(f)} faces); nothing to compress")
    if v.ndim != 2 or v.shape[1] != 3:
        raise MeshError(f"{name}: vertices must have shape (V, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3:
        shape = f.shape if f.dtype != object else f"{len(f)} ragged faces"
        raise MeshError(f"{name}: faces must be triangles with shape (F, 3), got {shape}; "
                        "triangulate polygons (e.g. Blender's Triangulate modifier) first")
    if not np.issubdtype(f.dtype, np.integer):
        if np.issubdtype(f.dtype, np.floating) and np.all(np.isfinite(f)) and np.all(f == np.round(f)):
            f = f.astype(np.int64)
        else:
            raise MeshError(f"{name}: face indices must be integers, got dtype {f.dtype}")
    bad = ~np.isfinite(v).all(axis=1)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise MeshError(f"{name}: {int(bad.sum())} of {len(v)} vertices have NaN or infinite coordinates "
                        f"(first: vertex {first} = {v[first].tolist()})")
    big = float(np.abs(v).max())
    if big > MAX_COORDINATE:
        raise MeshError(f"{name}: coordinates reach {big:.3g}; beyond +-{MAX_COORDINATE:g} areas and extents overflow "
                        "(rescale the mesh)")
    f = f.astype(np.int64, copy=False)  # a reader's int64 faces as they are: no second copy of a heavy mesh
    lo, hi = int(f.min()), int(f.max())
    if lo < 0 or hi >= len(v):
        n_bad = int(((f < 0) | (f >= len(v))).any(axis=1).sum())
        raise MeshError(f"{name}: {n_bad} faces index vertices out of range (indices span [{lo}, {hi}], "
                        f"but there are {len(v)} vertices)")
    return v, f


def mesh_from_arrays(vertices: np.ndarray, faces: np.ndarray, name: str = "mesh", look: Look | None = None) -> Mesh:
    """Validate raw arrays and normalise them into the unit box.

    vertices: (V, 3) float, any units; faces: (F, 3) integer indices into vertices; look: per-face slots,
    per-corner texture coordinates and materials aligned with `faces` (checked; `LookError` is a `MeshError`'s
    sibling ValueError naming the problem), kept aligned when faces are dropped.
    Raises `MeshError` for an empty mesh, NaN/inf coordinates, out-of-range indices or non-triangle faces.
    Degenerate triangles (repeated index or zero area) are dropped with a `MeshWarning` that gives the count.
    The input arrays are never modified.
    """
    v, f = _checked_arrays(vertices, faces, name)
    if look is not None:
        try:
            look = check_look(look, len(f), name)
        except LookError as exc:
            raise MeshError(str(exc)) from None
    repairs: list[str] = []
    area2 = np.empty(len(f), np.float64)  # twice each area, chunk by chunk: no (F, 3) float64 cross kept
    for a, b, c in face_cross_chunks(v, f):
        area2[a:b] = np.linalg.norm(c, axis=1)
    extent = float((v.max(axis=0) - v.min(axis=0)).max())
    # Zero area relative to the mesh size: repeated indices, collinear or coincident corners.
    degenerate = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2]) | (area2 <= (1e-12 * extent) ** 2)
    n_degenerate = int(degenerate.sum())
    if n_degenerate == len(f):
        raise MeshError(f"{name}: all {len(f)} triangles are degenerate (zero area); nothing to compress")
    if n_degenerate:
        msg = f"{name}: dropped {n_degenerate} degenerate (zero-area) triangles of {len(f)}"
        repairs.append(msg)
        warnings.warn(msg, MeshWarning, stacklevel=2)
        f = f[~degenerate]
        look = look.subset(~degenerate) if look is not None else None

    used = np.zeros(len(v), bool)  # a mask, not np.unique's sorted copy of every index (~50 B per triangle)
    used[f.reshape(-1)] = True
    box_lo, box_hi = v[used].min(axis=0), v[used].max(axis=0)
    scale = float((box_hi - box_lo).max())
    if not scale > 0:
        raise MeshError(f"{name}: the mesh has zero extent")
    # Centre the box at 0.5 so the longest side spans exactly [0, 1].
    offset = (box_lo + box_hi) / 2 - 0.5 * scale
    transform = Transform(scale, offset)
    vn = v - offset  # Transform.to_normalised's arithmetic, in place: one float64 temporary, not three
    vn /= scale
    np.clip(vn, 0.0, 1.0, out=vn)
    padded = np.zeros((len(vn) + 1, 3), np.float32)  # a spare row: Embree's shared buffer reads 4 B past the last
    padded[:-1] = vn                                  # vertex (embree_scene.padded_vertices), no copy needed there
    return Mesh(vertices=padded[:-1], faces=f.astype(np.int32), transform=transform, name=name, repairs=tuple(repairs),
                look=None if look is None or _says_nothing(look) else look)


def _says_nothing(look: Look) -> bool:
    """One slot, no image, the default grey: what a file without materials loads as (kept as a bare shape)."""
    m = look.materials[0]
    return look.n_slots == 1 and m.image is None and np.allclose(m.base_color, Material().base_color, atol=0.02)


def _read_bytes(path: Path) -> tuple[bytes, str]:
    """File contents (decompressed if `.gz`, at most MAX_GZIP_RATIO x the file and MAX_MESH_BYTES) and the mesh
    extension (e.g. '.ply')."""
    import zlib

    suffixes = [s.lower() for s in path.suffixes]
    size = path.stat().st_size
    if size > MAX_MESH_BYTES:
        raise MeshError(f"{path}: {size} bytes is more than the {MAX_MESH_BYTES} a mesh file may have")
    data = path.read_bytes()
    if suffixes and suffixes[-1] == ".gz":
        limit = min(MAX_MESH_BYTES, max(1 << 20, MAX_GZIP_RATIO * len(data)))
        inflate = zlib.decompressobj(wbits=16 + zlib.MAX_WBITS)
        try:
            out = inflate.decompress(data, limit)
            if inflate.unconsumed_tail:
                raise MeshError(f"{path}: decompresses to more than {limit} bytes (over {MAX_GZIP_RATIO}x its size): "
                                "refused as a decompression bomb")
            if not inflate.eof:
                raise MeshError(f"{path}: damaged gzip file: truncated")
        except zlib.error as exc:
            raise MeshError(f"{path}: damaged gzip file: {exc}") from None
        data = out
        suffixes = suffixes[:-1]
    ext = suffixes[-1] if suffixes else ""
    return data, ext


def _confined_resolver(path: Path):
    """trimesh's resolver for the files a glTF or OBJ names (buffers, textures, material libraries): only regular
    files inside the mesh's own folder (trimesh refuses names that escape it), each at most MAX_MESH_BYTES, so a
    name cannot make the reader wait on a pipe or device or read a huge file."""
    from trimesh.resolvers import FilePathResolver

    class ConfinedResolver(FilePathResolver):
        def get(self, name: str) -> bytes:
            for candidate in (name.strip(), name.strip().lstrip("/"), os.path.split(name)[-1]):
                try:
                    target = self.absolute(candidate)
                except ValueError:
                    continue
                if target.is_file() and target.stat().st_size <= MAX_MESH_BYTES:
                    return target.read_bytes()
            raise ValueError(f"{name[:80]!r} is not a regular file of at most {MAX_MESH_BYTES} bytes beside the mesh")

    return ConfinedResolver(str(path))


def load_mesh(path: str | os.PathLike) -> Mesh:
    """Load OBJ, PLY, STL, OFF or GLB/glTF (optionally gzip-compressed, `name.ply.gz`) and validate it.

    Scenes (glTF with several nodes) are flattened with their node transforms applied. Polygons are
    triangulated by the reader. Files are data: only regular files are read, a .gz is inflated to at most
    MAX_GZIP_RATIO x its size, and the files a glTF/OBJ names must be regular files in the mesh's folder
    (`_confined_resolver`). Raises `MeshError` with the path and the reason on any failure.
    """
    path = Path(path)
    if not path.exists():
        raise MeshError(f"{path}: no such file")
    if path.is_dir():
        raise MeshError(f"{path}: is a folder, not a mesh file")
    if not path.is_file():
        raise MeshError(f"{path}: not a regular file (a pipe or device is never read)")
    data, ext = _read_bytes(path)
    if ext not in SUPPORTED_EXTENSIONS:
        raise MeshError(f"{path}: unsupported format {ext or '(no extension)'!r}; "
                        f"supported: {', '.join(SUPPORTED_EXTENSIONS)} (optionally .gz)")
    if len(data) == 0:
        raise MeshError(f"{path}: the file is empty")
    import trimesh  # local: trimesh import is slow and only loading needs it

    try:
        # Plain files load by path so that glTF finds its external buffers; .gz ones from memory.
        if path.suffix.lower() == ".gz":
            loaded = trimesh.load(io.BytesIO(data), file_type=ext[1:], process=False)
        else:
            loaded = trimesh.load(io.BytesIO(data), file_type=ext[1:], process=False,
                                  resolver=_confined_resolver(path))
        parts = [g for g in (loaded.dump(concatenate=False) if isinstance(loaded, trimesh.Scene) else [loaded])
                 if isinstance(g, trimesh.Trimesh) and len(g.faces)]
    except Exception as exc:  # trimesh raises many types for broken files
        raise MeshError(f"{path}: could not read as {ext[1:].upper()}: {type(exc).__name__}: {exc}") from None
    if not parts:
        raise MeshError(f"{path}: contains no triangles (a point cloud, lines or an empty scene?)")
    vertices, faces, look = _joined(parts)
    name = path.name.split(".")[0]
    if ext == ".obj" and path.suffix.lower() != ".gz":
        _read_mtl_images(path, data, look)
    if ext in (".glb", ".gltf"):  # the images' own bytes, which trimesh does not keep (`gltf_images`)
        from .gltf_images import material_images

        files = material_images(data, ext, None if path.suffix.lower() == ".gz" else _confined_resolver(path))
        for m in look.materials:
            if m.image is not None and m.source is None:
                m.source = files.get(m.name)
    # The file's bytes and the reader's objects are not needed past here. trimesh's objects hold reference cycles
    # (their caches point back at them), so only a collection frees them: without it the 10M-triangle lattice's
    # load left 0.7 GiB of them resident into the plan (1.18 GiB after loading, 0.49 GiB after a collection).
    del data, loaded, parts
    gc.collect()
    return mesh_from_arrays(vertices, faces, name=name, look=look)


def _read_mtl_images(path: Path, data: bytes, look: Look) -> None:
    """The images an OBJ's MTL names (map_Kd), after the reader loaded them: one that was read keeps its file's
    bytes as its source (`Material.source`: a file stores them as they are when they are exact and smallest); one
    that could not be read - missing, outside the mesh's folder, or not an image - loads with its base colour alone
    (the reader drops it silently): say so, one line per material, as a MeshWarning. Nothing else is lost."""
    resolver = _confined_resolver(path)
    named: dict[str, str] = {}
    for line in data.decode("utf-8", "replace").splitlines():
        if line.strip().startswith("mtllib "):
            try:
                mtl = resolver.get(line.strip()[7:].strip()).decode("utf-8", "replace")
            except ValueError:
                continue  # no material library: the reader said so, or it has no materials to lose
            current = None
            for entry in mtl.splitlines():
                words = entry.strip().split(maxsplit=1)
                if len(words) == 2 and words[0] == "newmtl":
                    current = words[1].strip()
                elif len(words) == 2 and words[0] == "map_Kd" and current is not None:
                    named[current] = words[1].split()[-1]
    for m in look.materials:
        if m.image is None and m.name in named:
            warnings.warn(f"{path.name}: material {m.name!r}: its image {named[m.name][:80]!r} could not be read "
                          "(missing, outside the mesh's folder, or not an image); the slot shows its base colour",
                          MeshWarning, stacklevel=3)
        elif m.image is not None and m.name in named:
            try:
                m.source = resolver.get(named[m.name])
            except ValueError:
                pass  # the reader found it and this lookup did not: the image is re-encoded


def _joined(parts: list) -> tuple[np.ndarray, np.ndarray, Look]:
    """trimesh geometries (transforms applied) -> one vertex array, one face array and their look: one slot per
    distinct material, texture coordinates where every part has them."""
    vertices, faces, slots, uvs, materials, keys = [], [], [], [], [], {}
    base = 0
    for g in parts:
        visual = getattr(g, "visual", None)
        material = getattr(visual, "material", None)
        key = id(material) if material is not None else None
        if key not in keys:
            keys[key] = len(materials)
            materials.append(_material_of(material, len(materials)))
        uv = getattr(visual, "uv", None)
        uvs.append(np.asarray(uv, np.float32)[np.asarray(g.faces)] if uv is not None and len(uv) == len(g.vertices)
                   else None)
        vertices.append(np.asarray(g.vertices))
        faces.append(np.asarray(g.faces) + base if base else np.asarray(g.faces))
        slots.append(np.full(len(g.faces), keys[key], np.int32))
        base += len(g.vertices)
    def joined(arrays: list) -> np.ndarray:  # one part: its arrays as read (a heavy scan is one part: no copies)
        return arrays[0] if len(arrays) == 1 else np.concatenate(arrays)

    corner_uvs = joined(uvs) if all(u is not None for u in uvs) else None
    return joined(vertices), joined(faces), Look(joined(slots), corner_uvs, materials)


def _material_of(material, index: int) -> Material:
    """A trimesh material (PBR from glTF, Simple from OBJ's MTL) -> `Material`: base colour (linear) and image."""
    from .look import srgb_to_linear

    if material is None:
        return Material(name=f"slot{index}")
    name = str(getattr(material, "name", None) or f"slot{index}")[:64]
    color = getattr(material, "baseColorFactor", None)
    image = getattr(material, "baseColorTexture", None)
    if color is not None:  # glTF: the factor is linear, in 0..255 or 0..1 by trimesh version
        c = np.asarray(color, np.float64)
        c = c / 255.0 if c.max() > 1.0 else c
    else:
        d = getattr(material, "diffuse", None)  # MTL Kd is sRGB-ish 0..255 in trimesh
        c = np.asarray(d if d is not None else [204, 204, 204, 255], np.float64) / 255.0
        c = np.concatenate([srgb_to_linear(c[:3]), c[3:4] if len(c) > 3 else [1.0]])
        image = getattr(material, "image", None)
    c = np.resize(c, 4) if len(c) != 4 else c
    return Material(name=name, base_color=np.clip(c, 0, 1).astype(np.float32), image=image_from_pil(image))


def mesh_like(mesh: Mesh, vertices: np.ndarray, faces: np.ndarray) -> Mesh:
    """Another triangulation of `mesh` (a decimation, a Draco-decoded copy) in the same normalised coordinates:
    no re-normalisation, triangles with a repeated index dropped."""
    f = np.asarray(faces, np.int32).reshape(-1, 3)
    keep = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    return Mesh(vertices=np.asarray(vertices, np.float32), faces=f[keep], transform=mesh.transform, name=mesh.name)


def mesh_file_bytes(mesh: Mesh) -> bytes:
    """`mesh` in its original coordinates as a binary PLY (what a user imports back into Blender)."""
    import trimesh

    original = mesh.transform.to_original(mesh.vertices)
    return trimesh.Trimesh(original, mesh.faces, process=False).export(file_type="ply", encoding="binary")
