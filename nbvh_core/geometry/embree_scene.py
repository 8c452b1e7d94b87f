"""An Embree 4 scene on the mesh's own arrays, queried by the kernel library (`native/embree_rays.cpp`).

embreex (the Python binding `exact.ExactTracer` otherwise uses) copies the vertices and indices into Embree's
buffers in Python-level loops and builds Embree's default BVH: on the 10,087,988-triangle lattice (2-core VM)
6.2 s to fill the buffers, 193 MiB of copies and 653 MiB of BVH. Here the scene reads the mesh's arrays where
they lie (Embree's shared buffers), is built compact on large meshes (`COMPACT_FROM_TRIANGLES`; 343 MiB there, built in
1.9 s instead of 2.6 s), and the rays are spread over OpenMP threads instead of Python threads.

The Embree library is the one embreex's wheel ships (its `embreex.libs` folder); where it, or the kernel library,
is missing (or the reference path is chosen), `open_scene` returns None and the tracer keeps embreex.
"""
from __future__ import annotations

import ctypes
import weakref
from pathlib import Path

import numpy as np

# rtcore_common.h / rtcore_buffer.h / rtcore_scene.h (Embree 4's documented enum values)
_GEOMETRY_TYPE_TRIANGLE = 0
_BUFFER_TYPE_INDEX, _BUFFER_TYPE_VERTEX = 0, 1
_FORMAT_UINT3, _FORMAT_FLOAT3 = 0x5003, 0x9003
_SCENE_FLAG_NONE, _SCENE_FLAG_COMPACT = 0, 1 << 1
_BUILD_QUALITY_MEDIUM = 1

#: From this many triangles the scene is built compact: Embree's BVH at about half the bytes (10M lattice: 343
#: against 651 MiB) for rays ~30% slower (32k random rays: 25.5 against 19.3 ms there; the bunny 5.2 against 3.8).
#: Below it the memory is small beside the rest of the run and the training's labels are worth the speed.
COMPACT_FROM_TRIANGLES = 1 << 21

_embree: ctypes.CDLL | None = None
_embree_tried = False


def embree_library() -> ctypes.CDLL | None:
    """The Embree 4 library embreex loads (None where it cannot be found), its entry points typed."""
    global _embree, _embree_tried
    if _embree_tried:
        return _embree
    _embree_tried = True
    try:
        import embreex
    except ImportError:
        return None
    found = sorted((Path(embreex.__file__).resolve().parent.parent / "embreex.libs").glob("libembree4*"))
    if not found:
        return None
    try:
        lib = ctypes.CDLL(str(found[0]))
    except OSError:
        return None
    vp, size = ctypes.c_void_p, ctypes.c_size_t
    for name, restype, argtypes in (
            ("rtcNewDevice", vp, [ctypes.c_char_p]), ("rtcReleaseDevice", None, [vp]),
            ("rtcGetDeviceError", ctypes.c_int, [vp]), ("rtcNewScene", vp, [vp]),
            ("rtcSetSceneFlags", None, [vp, ctypes.c_int]), ("rtcSetSceneBuildQuality", None, [vp, ctypes.c_int]),
            ("rtcNewGeometry", vp, [vp, ctypes.c_int]),
            ("rtcSetSharedGeometryBuffer", None, [vp, ctypes.c_int, ctypes.c_uint, ctypes.c_int,
                                                  np.ctypeslib.ndpointer(flags="C_CONTIGUOUS"), size, size, size]),
            ("rtcCommitGeometry", None, [vp]), ("rtcAttachGeometry", ctypes.c_uint, [vp, vp]),
            ("rtcReleaseGeometry", None, [vp]), ("rtcCommitScene", None, [vp]), ("rtcReleaseScene", None, [vp])):
        fn = getattr(lib, name, None)
        if fn is None:
            return None
        fn.restype, fn.argtypes = restype, argtypes
    if getattr(lib, "rtcIntersect1", None) is None:
        return None
    _embree = lib
    return lib


def _byte_bounds(a: np.ndarray) -> tuple[int, int]:
    """(first, one past the last) byte address of `a`: numpy 1's np.byte_bounds, numpy 2's array_utils (a lent
    card's Python has numpy 2.5)."""
    bounds = getattr(np, "byte_bounds", None)
    if bounds is None:
        from numpy.lib.array_utils import byte_bounds as bounds
    return bounds(a)


def padded_vertices(vertices: np.ndarray) -> np.ndarray:
    """`vertices` (V, 3) float32 when 4 readable bytes follow its last row (Embree reads each vertex with one
    16-byte load, so a shared vertex buffer must have them: `mesh.mesh_from_arrays` allocates a spare row), else
    a copy that has them (12 B per vertex)."""
    v = np.ascontiguousarray(vertices, dtype=np.float32)
    base = v.base if isinstance(v.base, np.ndarray) else None
    if base is not None and base.flags.c_contiguous and v.size:
        (lo, hi), (v_lo, v_hi) = _byte_bounds(base), _byte_bounds(v)
        if lo <= v_lo and v_hi + 4 <= hi:
            return v
    padded = np.zeros((v.shape[0] + 1, 3), np.float32)
    padded[:-1] = v
    return padded[:-1]


class EmbreeScene:
    """A committed Embree scene over vertices (V, 3) float32 and faces (F, 3) int32 (held, not copied)."""

    def __init__(self, lib: ctypes.CDLL, vertices: np.ndarray, faces: np.ndarray, compact: bool | None = None):
        """compact: Embree's compact BVH (None: from COMPACT_FROM_TRIANGLES triangles on)."""
        self.compact = faces.shape[0] >= COMPACT_FROM_TRIANGLES if compact is None else compact
        self._vertices = padded_vertices(vertices)
        self._faces = np.ascontiguousarray(faces, dtype=np.int32)
        self._intersect = ctypes.cast(lib.rtcIntersect1, ctypes.c_void_p).value
        device = lib.rtcNewDevice(None)
        if not device:
            raise RuntimeError("Embree: no device")
        scene = lib.rtcNewScene(device)
        self._finalizer = weakref.finalize(self, _release, lib, device, scene)
        lib.rtcSetSceneFlags(scene, _SCENE_FLAG_COMPACT if self.compact else _SCENE_FLAG_NONE)
        lib.rtcSetSceneBuildQuality(scene, _BUILD_QUALITY_MEDIUM)
        geometry = lib.rtcNewGeometry(device, _GEOMETRY_TYPE_TRIANGLE)
        lib.rtcSetSharedGeometryBuffer(geometry, _BUFFER_TYPE_VERTEX, 0, _FORMAT_FLOAT3, self._vertices,
                                       0, 12, self._vertices.shape[0])
        lib.rtcSetSharedGeometryBuffer(geometry, _BUFFER_TYPE_INDEX, 0, _FORMAT_UINT3, self._faces, 0,
                                       12, self._faces.shape[0])
        lib.rtcCommitGeometry(geometry)
        lib.rtcAttachGeometry(scene, geometry)
        lib.rtcReleaseGeometry(geometry)
        lib.rtcCommitScene(scene)
        error = lib.rtcGetDeviceError(device)
        if error:
            self._finalizer()
            raise RuntimeError(f"Embree: the scene was not built (error {error})")
        self._scene = scene

    def intersect(self, rays_o: np.ndarray, rays_d: np.ndarray, t_max: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest hits with 0 <= t <= t_max. rays_o, rays_d: (N, 3) float32; t_max: (N,) float32. Returns
        (t (N,) float32: t_max on a miss, triangle (N,) int32: -1 on a miss)."""
        from ..kernels import bindings

        n = rays_o.shape[0]
        t, prim = np.empty(n, np.float32), np.empty(n, np.int32)
        bindings.embree_first_hits(intersect=self._intersect, scene=self._scene,
                                   rays_o=np.ascontiguousarray(rays_o, np.float32),
                                   rays_d=np.ascontiguousarray(rays_d, np.float32),
                                   t_max=np.ascontiguousarray(t_max, np.float32), n=n, out_t=t, out_prim=prim)
        return t, prim


def _release(lib: ctypes.CDLL, device: int, scene: int) -> None:
    lib.rtcReleaseScene(scene)
    lib.rtcReleaseDevice(device)


def open_scene(vertices: np.ndarray, faces: np.ndarray) -> EmbreeScene | None:
    """The scene over the mesh's arrays, or None where Embree's library or the kernel library is missing (or Embree
    refused the scene): the caller keeps embreex."""
    from ..kernels import library

    lib = embree_library()
    if lib is None or not library.fast_enabled() or faces.shape[0] == 0:
        return None
    try:
        return EmbreeScene(lib, vertices, faces)
    except RuntimeError:
        return None
