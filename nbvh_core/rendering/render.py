"""Cameras and the paper's shading; reference images of the mesh (Embree).

Shading (the paper's metric): pixel = max(0, cos(normal, direction to one fixed white point light)); background
and misses are 0. The normal is the geometric normal flipped to face the camera (a mesh's winding is not a
property the metric should punish). The light sits at `LIGHT_OFFSET` from the asset's centre, in units of the
camera orbit radius, fixed for all views.

Cameras: pinhole, looking at the centre of the unit box from a point on an orbit sphere; `orbit_cameras`
spreads views evenly over the sphere (Fibonacci lattice), deterministic.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Light position relative to the box centre, in orbit radii (above, to the right, in front).
LIGHT_OFFSET = np.array([0.6, 0.8, 1.0])


@dataclass(frozen=True)
class Camera:
    """Pinhole camera. position, target, up: (3,) normalised coordinates; fov_deg: vertical field of view."""

    position: np.ndarray
    target: np.ndarray
    up: np.ndarray
    fov_deg: float = 40.0

    def rays(self, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """Primary rays through pixel centres, row-major from the top-left pixel.

        Returns rays_o (H*W, 3) float32, rays_d (H*W, 3) float32 unit directions.
        """
        fwd = self.target - self.position
        fwd = fwd / np.linalg.norm(fwd)
        right = np.cross(fwd, self.up)
        if np.linalg.norm(right) < 1e-8:  # looking along `up`
            right = np.cross(fwd, np.array([1.0, 0.0, 0.0]))
        right /= np.linalg.norm(right)
        true_up = np.cross(right, fwd)
        tan = np.tan(np.radians(self.fov_deg) / 2)
        xs = ((np.arange(width) + 0.5) / width * 2 - 1) * tan * width / height
        ys = (1 - (np.arange(height) + 0.5) / height * 2) * tan
        px, py = np.meshgrid(xs, ys)
        d = fwd[None] + px.reshape(-1, 1) * right[None] + py.reshape(-1, 1) * true_up[None]
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        o = np.broadcast_to(self.position, d.shape)
        return np.ascontiguousarray(o, np.float32), d.astype(np.float32)


CENTRE = np.array([0.5, 0.5, 0.5])
ORBIT_RADIUS = 1.9


#: The held-out views' turn of the whole lattice (radians about the vertical, then about x): each held-out view is
#: 5.6 degrees or more from every check view at 16 views (2.6 at 64; tests/test_metrics.py), median 17.
HELD_OUT_TURN = (0.9, 0.5)


def orbit_cameras(n_views: int, radius: float = ORBIT_RADIUS, fov_deg: float = 40.0,
                  held_out: bool = False, turn: tuple[float, float] | None = None) -> list[Camera]:
    """`n_views` cameras evenly spread on a sphere of `radius` around the box centre, looking at it. held_out: the
    same lattice turned by HELD_OUT_TURN, views that no training check used (the final evaluation's); turn: (a, b)
    radians, the lattice turned by these instead (a run's randomly turned set: `random_turn`)."""
    turn = turn if turn is not None else HELD_OUT_TURN if held_out else None
    cams = []
    golden = np.pi * (3 - np.sqrt(5))
    for i in range(n_views):
        z = 1 - 2 * (i + 0.5) / n_views
        r = np.sqrt(max(0.0, 1 - z * z))
        phi = golden * i
        direction = np.array([r * np.cos(phi), z, r * np.sin(phi)])
        if turn is not None:
            a, b = turn
            x, y, zz = direction
            x, zz = x * np.cos(a) - zz * np.sin(a), x * np.sin(a) + zz * np.cos(a)
            y, zz = y * np.cos(b) - zz * np.sin(b), y * np.sin(b) + zz * np.cos(b)
            direction = np.array([x, y, zz])
        cams.append(Camera(position=CENTRE + radius * direction, target=CENTRE.copy(),
                           up=np.array([0.0, 1.0, 0.0]), fov_deg=fov_deg))
    return cams


def random_turn(seed: int) -> tuple[float, float]:
    """A turn of the view lattice drawn from `seed`: (a, b), each uniform in [0, 2 pi) radians."""
    rng = np.random.default_rng(seed)
    return float(rng.uniform(0.0, 2 * np.pi)), float(rng.uniform(0.0, 2 * np.pi))


def light_position(radius: float = ORBIT_RADIUS) -> np.ndarray:
    return CENTRE + LIGHT_OFFSET * radius


def shade(rays_o: np.ndarray, rays_d: np.ndarray, hit: np.ndarray, t: np.ndarray, normal: np.ndarray,
          light: np.ndarray | None = None) -> np.ndarray:
    """Paper shading per ray: max(0, cos(n, to_light)) with n flipped toward the viewer; 0 for misses.

    All arrays per ray: rays_o, rays_d, normal (N, 3); hit (N,) bool; t (N,). Returns (N,) float32 in [0, 1].
    """
    light = light_position() if light is None else light
    value = np.zeros(hit.shape[0], np.float32)
    if not hit.any():
        return value
    p = rays_o[hit] + t[hit, None] * rays_d[hit]
    n = normal[hit].astype(np.float64)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    n = np.where((np.einsum("ij,ij->i", n, rays_d[hit]) > 0)[:, None], -n, n)
    to_light = light[None] - p
    to_light /= np.linalg.norm(to_light, axis=1, keepdims=True)
    value[hit] = np.clip(np.einsum("ij,ij->i", n, to_light), 0.0, 1.0)
    return value


@dataclass
class RenderResult:
    """image: (H, W) float32 shading in [0, 1]; hit: (H, W) bool; depth: (H, W) float32 (inf where missed);
    colour: (H, W, 3) float32 sRGB-encoded shading x the asset's albedo, or None for a bare shape."""

    image: np.ndarray
    hit: np.ndarray
    depth: np.ndarray
    colour: np.ndarray | None = None

    @property
    def display(self) -> np.ndarray:
        """What a preview shows: the coloured image when the asset has a look, else the grey shading."""
        return self.colour if self.colour is not None else self.image


def coloured(shading: np.ndarray, hit: np.ndarray, albedo: np.ndarray | None, shape: tuple[int, int]
             ) -> np.ndarray | None:
    """(H, W, 3) sRGB image of per-ray shading (N,) times the albedo (hits, 3) linear; None without albedo."""
    if albedo is None:
        return None
    from ..geometry.look import linear_to_srgb

    lin = np.zeros((hit.shape[0], 3), np.float32)
    lin[hit] = albedo * shading[hit, None]
    return linear_to_srgb(lin).reshape(*shape, 3)


def render_reference(tracer, camera: Camera, width: int, height: int) -> RenderResult:
    """Exact image of the mesh (an `exact.ExactTracer`) from `camera`."""
    o, d = camera.rays(width, height)
    fh = tracer.first_hit(o, d)
    img = shade(o, d, fh.hit, fh.t, fh.normal)
    mesh = getattr(tracer, "mesh", None)
    albedo = None
    if mesh is not None and mesh.look is not None:  # the exact look: the hit triangle's slot and coordinates
        from ..geometry.look import hit_albedo

        h = fh.hit
        albedo = hit_albedo(mesh.look, mesh.vertices, mesh.faces, fh.tri[h], o[h] + fh.t[h, None] * d[h])
    return RenderResult(img.reshape(height, width), fh.hit.reshape(height, width), fh.t.reshape(height, width),
                        coloured(img, fh.hit, albedo, (height, width)))


def save_png(path, image: np.ndarray) -> None:
    """Save a (H, W) or (H, W, 3) float image in [0, 1] as 8-bit PNG (`path`: a file name or a binary stream)."""
    from PIL import Image

    arr = (np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8)
    Image.fromarray(arr).save(path, format="PNG")


def png_bytes(image: np.ndarray) -> bytes:
    """The PNG file `save_png` would write, as bytes (for staged or returned outputs)."""
    import io

    buf = io.BytesIO()
    save_png(buf, image)
    return buf.getvalue()


def render_neural(model, camera: Camera, width: int, height: int) -> RenderResult:
    """Image of a `model.NeuralBVH` from `camera` (its first predicted hits, the same shading)."""
    import torch

    o, d = camera.rays(width, height)
    q = model.query(torch.from_numpy(o), torch.from_numpy(d))
    hit, t, normal = q.hit.cpu().numpy(), q.t.cpu().numpy(), q.normal.cpu().numpy()
    img = shade(o, d, hit, t, normal)
    albedo = model.albedo_at(np.clip(o[hit] + t[hit, None] * d[hit], 0.0, 1.0)) if hit.any() else None
    return RenderResult(img.reshape(height, width), hit.reshape(height, width), t.reshape(height, width),
                        coloured(img, hit, albedo, (height, width)))
