"""A scene to render, as the add-on describes it (`SceneSpec.from_dict`): objects (a model or a mesh at a matrix),
lights, world colour and how to shade, each field checked on the way in (no torch).

A scene is plain JSON (`SceneSpec.from_dict`), written by the add-on without torch:
  {"objects": [{"name": str, "matrix": 4x4 rows, "model": PATH.nbvh | null, "mesh": PATH.npz | null
                (arrays vertices (V, 3) object-local, faces (F, 3)), "color": [r, g, b]}],
   "lights": [{"kind": "point" | "sun" | "spot", "color": [3], "power": W or W/m^2, "position": [3],
               "direction": [3] (the way the light travels), "spot_size": rad, "spot_blend": 0..1}],
   "world": [r, g, b], "transparent": bool, "shading": "lambert" | "cosine", "shadows": bool,
   "geometry": "neural" | "mesh"}   ("mesh": every object from its mesh, the exact reference)
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

SHADINGS = ("lambert", "cosine")
GEOMETRIES = ("neural", "mesh")
LIGHT_KINDS = ("point", "sun", "spot")


def _vec(value, n: int, what: str) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64).reshape(-1)
    if arr.shape != (n,) or not np.isfinite(arr).all():
        raise ValueError(f"{what}: expected {n} finite numbers, got {value!r}")
    return arr


@dataclass
class Light:
    """One light. color: (3,) linear RGB; power: W (point, spot) or W/m^2 (sun); position: (3,) world;
    direction: (3,) unit, the way the light travels (sun, spot); spot_size: full cone angle in radians;
    spot_blend: 0..1 soft edge of the cone."""

    kind: str
    color: np.ndarray
    power: float
    position: np.ndarray = field(default_factory=lambda: np.zeros(3))
    direction: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, -1.0]))
    spot_size: float = math.pi
    spot_blend: float = 0.0

    @staticmethod
    def from_dict(d: dict) -> "Light":
        kind = d.get("kind")
        if kind not in LIGHT_KINDS:
            raise ValueError(f"light kind must be one of {LIGHT_KINDS}, got {kind!r}")
        direction = _vec(d.get("direction", [0, 0, -1]), 3, "light direction")
        norm = np.linalg.norm(direction)
        return Light(kind=kind, color=_vec(d.get("color", [1, 1, 1]), 3, "light color"),
                     power=float(_vec([d.get("power", 0.0)], 1, "light power")[0]),
                     position=_vec(d.get("position", [0, 0, 0]), 3, "light position"),
                     direction=direction / norm if norm > 0 else np.array([0.0, 0.0, -1.0]),
                     spot_size=float(d.get("spot_size", math.pi)), spot_blend=float(d.get("spot_blend", 0.0)))


@dataclass
class ObjectSpec:
    """One object. matrix: (4, 4) object-local -> world; model: an .nbvh path; mesh: an .npz path (object-local
    `vertices`, `faces`); color: (3,) linear albedo."""

    name: str
    matrix: np.ndarray
    model: str | None = None
    mesh: str | None = None
    color: np.ndarray = field(default_factory=lambda: np.full(3, 0.8))

    @staticmethod
    def from_dict(d: dict) -> "ObjectSpec":
        name = str(d.get("name", "object"))
        matrix = _vec(d.get("matrix", np.eye(4)), 16, f"{name}: matrix").reshape(4, 4)
        return ObjectSpec(name=name, matrix=matrix, model=d.get("model") or None, mesh=d.get("mesh") or None,
                          color=np.clip(_vec(d.get("color", [0.8, 0.8, 0.8]), 3, f"{name}: color"), 0, 1))


@dataclass
class SceneSpec:
    """What to draw and how (see the module docstring for the JSON form)."""

    objects: list[ObjectSpec]
    lights: list[Light]
    world: np.ndarray = field(default_factory=lambda: np.full(3, 0.05))
    transparent: bool = False
    shading: str = "lambert"
    shadows: bool = True
    geometry: str = "neural"

    @staticmethod
    def from_dict(d: dict) -> "SceneSpec":
        if not isinstance(d, dict):
            raise ValueError("a scene must be a JSON object")
        shading, geometry = d.get("shading", "lambert"), d.get("geometry", "neural")
        if shading not in SHADINGS:
            raise ValueError(f"shading must be one of {SHADINGS}, got {shading!r}")
        if geometry not in GEOMETRIES:
            raise ValueError(f"geometry must be one of {GEOMETRIES}, got {geometry!r}")
        return SceneSpec(objects=[ObjectSpec.from_dict(o) for o in d.get("objects", [])],
                         lights=[Light.from_dict(x) for x in d.get("lights", [])],
                         world=np.clip(_vec(d.get("world", [0.05] * 3), 3, "world color"), 0, None),
                         transparent=bool(d.get("transparent", False)), shading=shading,
                         shadows=bool(d.get("shadows", True)), geometry=geometry)
