"""Mesh arrays as data: a mesh .npz (the add-on's export, library assets, the render engine's meshes) read without
pickles or allocations beyond the file, and the mesh (with its look) built from it."""
from __future__ import annotations

import math
import os

import numpy as np


def read_mesh_arrays(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """`vertices`, `faces` and the look's members (`look.LOOK_MEMBERS`, `image_I`, `image_source_I`) of a mesh .npz
    as data: each member's .npy header is read first and refused unless it is a numeric (names: unicode) array whose
    declared size fits the member's own bytes (no pickles, nothing allocated beyond the file); other members are
    ignored.
    Raises MeshError (one line)."""
    import zipfile

    from .look import LOOK_MEMBERS
    from .mesh import MeshError

    out = {}
    try:
        with zipfile.ZipFile(path) as z:
            present = {n[:-4] for n in z.namelist() if n.endswith(".npy")}
            optional = [k for k in sorted(present) if k in LOOK_MEMBERS or
                        (k.startswith("image_") and k[6:].isdigit() and len(k) <= 10) or
                        (k.startswith("image_source_") and k[13:].isdigit() and len(k) <= 17)]
            for key in ("vertices", "faces", *optional):
                info = z.getinfo(f"{key}.npy")
                with z.open(info) as f:
                    version = np.lib.format.read_magic(f)
                    # the public header readers (numpy 1.x and 2.x both have them; 2.x dropped the private one)
                    header = {(1, 0): np.lib.format.read_array_header_1_0,
                              (2, 0): np.lib.format.read_array_header_2_0}.get(version)
                    if header is None:
                        raise MeshError(f"{path}: {key} is a .npy of version {version}, not 1.0 or 2.0")
                    shape, fortran, dtype = header(f)
                    if dtype.hasobject or dtype.kind not in ("iufU" if key == "material_names" else "iuf"):
                        raise MeshError(f"{path}: {key} must be a numeric array, not {dtype}")
                    if math.prod(shape) * dtype.itemsize > info.file_size:
                        raise MeshError(f"{path}: {key} declares {shape} but holds {info.file_size} bytes")
                with z.open(info) as f:
                    out[key] = np.lib.format.read_array(f, allow_pickle=False)
    except MeshError:
        raise
    except Exception as exc:  # zipfile, numpy's header parser and reader raise many kinds for a damaged file
        raise MeshError(f"{path}: not a mesh array file ({type(exc).__name__}: {str(exc)[:100]})") from None
    return out


def mesh_from_npz(path: str | os.PathLike, name: str = "mesh"):
    """The mesh (and its look, when the archive carries one: `look.LOOK_MEMBERS`) of a mesh .npz, read as data
    (`read_mesh_arrays`). Raises MeshError (one line)."""
    from .look import LookError, look_from_arrays
    from .mesh import MeshError, mesh_from_arrays

    arrays = read_mesh_arrays(path)
    try:
        look = look_from_arrays(arrays, str(path))
    except LookError as exc:
        raise MeshError(str(exc)) from None
    return mesh_from_arrays(arrays["vertices"], arrays["faces"], name=name, look=look)
