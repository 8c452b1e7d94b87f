"""Render a scene of neural models and meshes the way Blender places them (the NBVH render engine's compute).

Each object is an .nbvh model or a mesh (traced exactly by Embree) at its own object-to-world matrix; a pixel
shows the nearest hit over all objects. Shading, per `SceneSpec.shading`:

* "lambert": the scene's lights (point, spot: power in W; sun: strength in W/m^2; colour), Lambertian albedo
  per object, radiance = albedo / pi * irradiance (Cycles' units, so a shot reads as bright as in Blender), plus
  the world colour as uniform ambient light; shadow rays are traced through every object, neural or exact.
* "cosine": the paper's shading (max(0, cos(normal, direction to the first light)), white, no shadows; with no
  light, a head light at the camera), to compare with the numbers the paper reports.

Coordinates are Blender's world space. A camera is the inverse of its view-projection matrix (NDC -> world), so
perspective, orthographic, lens shift and sensor fit all come from Blender's own matrices. Images are (H, W, 4)
float32 linear RGBA with row 0 at the *bottom* (Blender's render result and texture order).
The scene itself is `scene_spec.SceneSpec` (plain JSON the add-on writes without torch).
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from ..protocol.process import Cancelled
from .scene_spec import Light, SceneSpec

#: Shadow-ray start offset along the normal, in units of the hit object's world diagonal: a neural hit is only as
#: exact as its model (2% removed nearly all self-shadowing specks on the preview preset), a mesh hit is exact.
SHADOW_BIAS = {"neural": 0.02, "mesh": 1e-4}


# ---------------------------------------------------------------------------------------------- shapes
class NeuralShape:
    """An .nbvh model, queried in its normalised frame. kind = "neural"."""

    kind = "neural"

    def __init__(self, model):
        self.model = model
        self.transform = model.transform
        if model.compact_nodes is not None:
            root = np.asarray(model.compact_nodes["root"], np.float64)
            self.box = (root[:3], root[3:])
        else:
            self.box = (model.nodes["lo"][0].astype(np.float64), model.nodes["hi"][0].astype(np.float64))

    def first_hit(self, rays_o: np.ndarray, rays_d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """rays_o, rays_d: (N, 3) float32 normalised, unit directions -> hit (N,) bool, t (N,), normal (N, 3)."""
        import torch

        q = self.model.query(torch.from_numpy(rays_o), torch.from_numpy(rays_d))
        return q.hit.cpu().numpy(), q.t.cpu().numpy(), q.normal.cpu().numpy()

    def albedo(self, rays_o: np.ndarray, rays_d: np.ndarray, t: np.ndarray) -> np.ndarray | None:
        """(N, 3) linear albedo at the hits t (N,) of normalised rays (the model's look), or None (bare shape)."""
        return self.model.albedo_at(np.clip(rays_o + t[:, None] * rays_d, 0.0, 1.0))


class MeshShape:
    """A mesh traced exactly (Embree), in the same normalised frame as a model of it. kind = "mesh"."""

    kind = "mesh"

    def __init__(self, mesh):
        from ..geometry.exact import ExactTracer

        self.tracer = ExactTracer(mesh)
        self.mesh = mesh
        self.transform = mesh.transform
        self.box = (mesh.vertices.min(0).astype(np.float64), mesh.vertices.max(0).astype(np.float64))

    def first_hit(self, rays_o: np.ndarray, rays_d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        fh = self.tracer.first_hit(rays_o, rays_d)
        return fh.hit, fh.t, fh.normal

    def albedo(self, rays_o: np.ndarray, rays_d: np.ndarray, t: np.ndarray) -> np.ndarray | None:
        """The exact look at the hits (the hit triangle's slot and interpolated coordinates), or None."""
        from ..geometry.look import hit_albedo

        look = self.mesh.look
        if look is None:
            return None
        fh = self.tracer.first_hit(rays_o, rays_d)  # the triangles (traced again: only hit pixels, once a frame)
        ok = fh.hit
        out = np.tile(np.asarray(look.materials[0].base_color[:3], np.float32), (len(t), 1))
        p = rays_o[ok] + fh.t[ok, None] * rays_d[ok]
        out[ok] = hit_albedo(look, self.mesh.vertices, self.mesh.faces, fh.tri[ok], p)
        return out


def load_shape(path: str, kind: str):
    """A NeuralShape from an .nbvh (kind "model": on the card when there is one, its rays answered by the Triton
    ray query, else on the CPU) or a MeshShape from an .npz (kind "mesh"). Raises ValueError (NBVHFileError,
    MeshError) or OSError with a message naming the file."""
    if kind == "model":
        from ..storage.fileformat import load_nbvh
        from ..training.train import pick_device

        return NeuralShape(load_nbvh(path, pick_device("auto")))
    from ..geometry.mesh_arrays import mesh_from_npz

    return MeshShape(mesh_from_npz(path, Path(path).stem))


class Placed:
    """A shape at an object's place: world rays in, world hits out."""

    def __init__(self, name: str, shape, matrix: np.ndarray, color: np.ndarray):
        s, off = float(shape.transform.scale), np.asarray(shape.transform.offset, np.float64)
        frame = np.eye(4)
        frame[:3, :3] *= s
        frame[:3, 3] = off
        self.name, self.shape, self.color = name, shape, np.asarray(color, np.float64)
        self.to_world = np.asarray(matrix, np.float64) @ frame  # normalised -> world
        if abs(np.linalg.det(self.to_world[:3, :3])) < 1e-18:
            raise ValueError(f"{name}: its transform is degenerate (a zero scale)")
        self.to_shape = np.linalg.inv(self.to_world)
        self.normal_to_world = np.linalg.inv(self.to_world[:3, :3]).T
        lo, hi = shape.box
        corners = np.array([[x, y, z, 1.0] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        world = corners @ self.to_world.T
        self.world_lo, self.world_hi = world[:, :3].min(0), world[:, :3].max(0)
        self.diagonal = float(np.linalg.norm(self.world_hi - self.world_lo))
        self.bias = SHADOW_BIAS[shape.kind] * self.diagonal

    def candidates(self, rays_o: np.ndarray, rays_d: np.ndarray, t_max: np.ndarray) -> np.ndarray:
        """Indices of the rays that enter the object's world box before t_max (a slab test)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / rays_d
            t0 = (self.world_lo - rays_o) * inv
            t1 = (self.world_hi - rays_o) * inv
        near = np.nanmax(np.minimum(t0, t1), axis=1)
        far = np.nanmin(np.maximum(t0, t1), axis=1)
        return np.nonzero((far >= np.maximum(near, 0.0)) & (near <= t_max))[0]

    def trace(self, rays_o: np.ndarray, rays_d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World rays (N, 3) float64, unit directions -> hit (N,) bool, t (N,) world distance, normal (N, 3) unit
        world (as the shape gives it, not yet flipped toward the viewer)."""
        o, d, length = self._local(rays_o, rays_d)
        hit, t, normal = self.shape.first_hit(o, d)
        n = normal.astype(np.float64) @ self.normal_to_world.T
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-20)
        return hit, np.where(hit, t / length, np.inf), n

    def albedo(self, rays_o: np.ndarray, rays_d: np.ndarray, t: np.ndarray) -> np.ndarray:
        """(N, 3) linear albedo where world rays hit this object at world distances t (N,): the shape's look,
        else the object's colour."""
        o, d, length = self._local(rays_o, rays_d)
        look = self.shape.albedo(o, d, (t * length).astype(np.float32))
        return np.tile(self.color, (len(t), 1)) if look is None else look.astype(np.float64)

    def _local(self, rays_o: np.ndarray, rays_d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World rays -> the shape's normalised frame: origins, unit directions (float32) and the world-to-local
        length factor."""
        o = rays_o @ self.to_shape[:3, :3].T + self.to_shape[:3, 3]
        d = rays_d @ self.to_shape[:3, :3].T
        length = np.linalg.norm(d, axis=1)
        return (np.ascontiguousarray(o, np.float32), np.ascontiguousarray(d / length[:, None], np.float32),
                length)


# ---------------------------------------------------------------------------------------------- cameras
def camera_rays(ndc_to_world: np.ndarray, width: int, height: int, offset: tuple[float, float] = (0.5, 0.5),
                rows: tuple[int, int] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Rays through the pixels of a width x height image (row 0 at the bottom), from the near plane toward the
    far plane of the camera whose inverse view-projection matrix is `ndc_to_world` (4, 4).

    offset: the sample's position inside each pixel (0.5, 0.5 = its centre); rows: (first, end) to make only
    those rows (a band of the image). Returns rays_o, rays_d: (R*W, 3) float64 (unit directions), row-major."""
    y0, y1 = rows if rows is not None else (0, height)
    xs = (np.arange(width) + offset[0]) / width * 2 - 1
    ys = (np.arange(y0, y1) + offset[1]) / height * 2 - 1
    px, py = np.meshgrid(xs, ys)
    ndc = np.stack([px.ravel(), py.ravel(), np.zeros(px.size), np.ones(px.size)], axis=1)
    m = np.asarray(ndc_to_world, np.float64)
    ends = []
    for z in (-1.0, 1.0):
        ndc[:, 2] = z
        h = ndc @ m.T
        ends.append(h[:, :3] / h[:, 3:4])
    d = ends[1] - ends[0]
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
    return ends[0], d


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """A (4, 4) view matrix in Blender's convention (world -> camera; the camera looks down its -Z, Z up in the
    world by default), for cameras made outside Blender (tests, benchmarks)."""
    eye, target, up = (np.asarray(v, np.float64) for v in (eye, target, up))
    f = (target - eye) / np.linalg.norm(target - eye)
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    view = np.eye(4)
    view[0, :3], view[1, :3], view[2, :3] = r, u, -f
    view[:3, 3] = -view[:3, :3] @ eye
    return view


def perspective(fov_y: float, aspect: float, near: float = 0.05, far: float = 100.0) -> np.ndarray:
    """A (4, 4) OpenGL-style perspective projection (fov_y in radians, aspect = width / height), as Blender's."""
    t = 1 / math.tan(fov_y / 2)
    p = np.zeros((4, 4))
    p[0, 0], p[1, 1] = t / aspect, t
    p[2, 2], p[2, 3], p[3, 2] = (far + near) / (near - far), 2 * far * near / (near - far), -1
    return p


def view_projection(view: np.ndarray, projection: np.ndarray) -> np.ndarray:
    """The `ndc_to_world` matrix of a camera: inverse(projection @ view), both (4, 4) as Blender gives them."""
    return np.linalg.inv(np.asarray(projection, np.float64) @ np.asarray(view, np.float64))


# ---------------------------------------------------------------------------------------------- renderer
@dataclass
class Hits:
    """Nearest hits over the scene for N rays: t (N,) world distance (inf: none); normal (N, 3); obj (N,) index
    into the placed objects (-1: none)."""

    t: np.ndarray
    normal: np.ndarray
    obj: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        return self.obj >= 0


class SceneRenderer:
    """Holds the scene's shapes between frames (each file loaded once per path, size and modification time) and
    renders images of it. Not thread-safe: one caller (the render worker's loop)."""

    def __init__(self):
        self._cache: dict[tuple, object] = {}
        self.spec: SceneSpec | None = None
        self.placed: list[Placed] = []

    def set_scene(self, spec: SceneSpec) -> list[str]:
        """Use `spec` from now on; returns one warning per object that cannot be drawn (and is left out)."""
        warnings, placed, used = [], [], set()
        for obj in spec.objects:
            if spec.geometry == "mesh" or not obj.model:
                path, kind = obj.mesh, "mesh"
            else:
                path, kind = obj.model, "model"
            if not path:
                warnings.append(f"{obj.name}: no {'mesh' if spec.geometry == 'mesh' else 'model or mesh'} to draw")
                continue
            try:
                key = (kind, *_file_key(path))
                if key not in self._cache:
                    self._cache[key] = load_shape(path, kind)
                used.add(key)
                placed.append(Placed(obj.name, self._cache[key], obj.matrix, obj.color))
            except (ValueError, OSError) as exc:
                warnings.append(f"{obj.name}: {exc}")
        for key in [k for k in self._cache if k not in used]:  # models no longer in the scene leave memory
            del self._cache[key]
        self.spec, self.placed = spec, placed
        return warnings

    def nearest(self, rays_o: np.ndarray, rays_d: np.ndarray, t_max: np.ndarray | None = None,
                should_stop: Callable[[], bool] | None = None) -> Hits:
        """Nearest hit over all objects of (N, 3) world rays (unit directions) within t_max (N,) (default inf)."""
        n = rays_o.shape[0]
        best = np.full(n, np.inf) if t_max is None else np.asarray(t_max, np.float64).copy()
        normal = np.zeros((n, 3))
        obj = np.full(n, -1, np.int64)
        for i, p in enumerate(self.placed):
            if should_stop is not None and should_stop():
                raise Cancelled("superseded")
            idx = p.candidates(rays_o, rays_d, best)
            if len(idx) == 0:
                continue
            hit, t, nrm = p.trace(rays_o[idx], rays_d[idx])
            closer = hit & (t < best[idx])
            j = idx[closer]
            best[j], normal[j], obj[j] = t[closer], nrm[closer], i
        return Hits(t=np.where(obj >= 0, best, np.inf), normal=normal, obj=obj)

    def render(self, ndc_to_world: np.ndarray, width: int, height: int, samples: int = 1,
               should_stop: Callable[[], bool] | None = None, rows: tuple[int, int] | None = None) -> np.ndarray:
        """(H, W, 4) float32 linear RGBA of the scene (row 0 at the bottom; only rows[0]:rows[1] when `rows` is
        given). samples: per pixel, on a stratified sqrt(samples) x sqrt(samples) grid (rounded down to a square;
        1 = the pixel centre). should_stop: polled between passes; True raises `process.Cancelled`."""
        if self.spec is None:
            raise ValueError("no scene set")
        y0, y1 = rows if rows is not None else (0, height)
        side = max(1, int(math.isqrt(max(1, int(samples)))))
        acc = np.zeros(((y1 - y0) * width, 4))
        for sy in range(side):
            for sx in range(side):
                o, d = camera_rays(ndc_to_world, width, height, ((sx + 0.5) / side, (sy + 0.5) / side), (y0, y1))
                acc += self._shade(o, d, should_stop)
        return (acc / side ** 2).reshape(y1 - y0, width, 4).astype(np.float32)

    def _shade(self, rays_o: np.ndarray, rays_d: np.ndarray, should_stop) -> np.ndarray:
        """(N, 4) RGBA of N primary rays."""
        spec = self.spec
        hits = self.nearest(rays_o, rays_d, should_stop=should_stop)
        out = np.zeros((len(rays_o), 4))
        if spec.shading == "lambert" and not spec.transparent:
            out[:, :3], out[:, 3] = spec.world, 1.0
        h = np.nonzero(hits.hit)[0]
        if len(h) == 0:
            return out
        p = rays_o[h] + hits.t[h, None] * rays_d[h]
        n = hits.normal[h]
        n = np.where((np.einsum("ij,ij->i", n, rays_d[h]) > 0)[:, None], -n, n)  # face the viewer
        if spec.shading == "cosine":
            out[h, :3] = self._cosine(p, n, rays_o[h])[:, None]
        else:
            albedo = self._albedo(rays_o[h], rays_d[h], hits.t[h], hits.obj[h])
            bias = np.array([pl.bias for pl in self.placed])[hits.obj[h]]
            out[h, :3] = albedo * (spec.world + self._direct(p, n, bias, should_stop) / math.pi)
        out[h, 3] = 1.0
        return out

    def _albedo(self, rays_o: np.ndarray, rays_d: np.ndarray, t: np.ndarray, obj: np.ndarray) -> np.ndarray:
        """(H, 3) linear albedo of H primary hits, each from the object it hit (its look, or its colour)."""
        out = np.zeros((len(t), 3))
        for i in np.unique(obj):
            rows = np.nonzero(obj == i)[0]
            out[rows] = self.placed[i].albedo(rays_o[rows], rays_d[rows], t[rows])
        return out

    def _cosine(self, p: np.ndarray, n: np.ndarray, eye: np.ndarray) -> np.ndarray:
        light = next(iter(self.spec.lights), None)
        if light is None:
            to_light = eye - p
        elif light.kind == "sun":
            to_light = np.broadcast_to(-light.direction, p.shape)
        else:
            to_light = light.position - p
        to_light = to_light / np.maximum(np.linalg.norm(to_light, axis=1, keepdims=True), 1e-300)
        return np.clip(np.einsum("ij,ij->i", n, to_light), 0.0, 1.0)

    def _direct(self, p: np.ndarray, n: np.ndarray, bias: np.ndarray, should_stop) -> np.ndarray:
        """(H, 3) irradiance from the lights at hit points p with viewer-facing normals n (W/m^2 per channel)."""
        total = np.zeros_like(p)
        for light in self.spec.lights:
            if light.kind == "sun":
                to_light = np.broadcast_to(-light.direction, p.shape)
                dist = np.full(len(p), np.inf)
                irradiance = np.full(len(p), light.power)
            else:
                delta = light.position - p
                dist = np.linalg.norm(delta, axis=1)
                to_light = delta / np.maximum(dist, 1e-300)[:, None]
                irradiance = light.power / (4 * math.pi * np.maximum(dist, 1e-6) ** 2)
                if light.kind == "spot":
                    irradiance = irradiance * _spot_falloff(light, -to_light)
            cos = np.clip(np.einsum("ij,ij->i", n, to_light), 0.0, None)
            lit = np.nonzero((cos > 0) & (irradiance > 0))[0]
            visible = np.ones(len(lit), bool)
            if self.spec.shadows and len(lit):
                start = p[lit] + n[lit] * bias[lit, None]
                blockers = self.nearest(start, np.ascontiguousarray(to_light[lit]), dist[lit], should_stop)
                visible = ~blockers.hit
            e = np.zeros(len(p))
            e[lit] = irradiance[lit] * cos[lit] * visible
            total += e[:, None] * light.color[None]
        return total


def _spot_falloff(light: Light, direction: np.ndarray) -> np.ndarray:
    """0..1 of a spot's cone for light travelling along `direction` (N, 3): 1 inside, a smooth edge of
    `spot_blend`, 0 outside (Blender's spot_size is the full angle)."""
    cos = np.einsum("ij,j->i", direction, light.direction)
    edge = math.cos(light.spot_size / 2)
    inner = edge + (1 - edge) * light.spot_blend
    if inner <= edge:
        return (cos >= edge).astype(np.float64)
    x = np.clip((cos - edge) / (inner - edge), 0.0, 1.0)
    return x * x * (3 - 2 * x)


def _file_key(path: str) -> tuple:
    st = os.stat(path)
    return (str(Path(path).resolve()), st.st_size, st.st_mtime_ns)
