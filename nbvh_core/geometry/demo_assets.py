"""Textured, multi-material assets made in code (tests, benchmarks and the README's figure need assets whose
look is known exactly, with no download).

Each returns a `Mesh` whose `look` has material slots, texture coordinates of the kind real assets have (a seam
where a chart wraps, an atlas of islands, coordinates that tile past [0, 1]) and procedural images.
"""
from __future__ import annotations

import numpy as np

from .look import Look, Material
from .mesh import Mesh, mesh_from_arrays


def pattern(size: int = 512, seed: int = 0) -> np.ndarray:
    """(size, size, 3) uint8 sRGB test image: 8 x 8 checker of two tints over a colour gradient, with a thin
    grid, so that an error of a few texels shows and colour differs across the image."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:size, 0:size] / size
    tint = rng.uniform(0.2, 0.9, (2, 3))
    checker = ((np.floor(x * 8) + np.floor(y * 8)) % 2)[..., None]
    img = checker * tint[0] + (1 - checker) * tint[1]
    img = img * (0.6 + 0.4 * np.stack([x, y, 1 - x], -1))
    line = ((x * 32) % 1 < 0.06) | ((y * 32) % 1 < 0.06)
    img[line] *= 0.3
    return np.clip(img * 255 + 0.5, 0, 255).astype(np.uint8)


def globe(segments: int = 64, rings: int = 32, texture: int = 512) -> Mesh:
    """UV sphere; the upper half textured (equirectangular coordinates, a seam at u = 0 / 1), the lower half a
    plain blue second slot."""
    verts, uvs, faces, slots = [], [], [], []
    for j in range(rings + 1):
        for i in range(segments + 1):  # the seam column is duplicated: same position, u = 0 and u = 1
            u, v = i / segments, 1 - j / rings
            th, ph = 2 * np.pi * u, np.pi * j / rings
            verts.append([np.sin(ph) * np.cos(th), np.sin(ph) * np.sin(th), np.cos(ph)])
            uvs.append([u, v])
    w = segments + 1
    for j in range(rings):
        for i in range(segments):
            a, b, c, d = j * w + i, j * w + i + 1, (j + 1) * w + i, (j + 1) * w + i + 1
            for tri in ((a, c, b), (b, c, d))[(j == 0):2 - (j == rings - 1)]:  # one triangle at each pole
                faces.append(tri)
                slots.append(0 if j < rings // 2 else 1)
    return _asset("globe", verts, uvs, faces, slots,
                  [Material("painted", image=pattern(texture, 1)),
                   Material("blue", np.array([0.05, 0.15, 0.7, 1.0], np.float32))])


def crate(cells: int = 8, texture: int = 512) -> Mesh:
    """Cube whose six faces are islands of a 3 x 2 atlas (seams on every edge); the sides are one textured slot,
    top and bottom a plain red one."""
    verts, uvs, faces, slots = [], [], [], []
    g = np.linspace(0, 1, cells + 1)
    for f, (axis, sign) in enumerate([(0, 1), (0, -1), (1, 1), (1, -1), (2, 1), (2, -1)]):
        u_axis, v_axis = [a for a in range(3) if a != axis]
        ox, oy = (f % 3) / 3, (f // 3) / 2
        base = len(verts)
        for j in range(cells + 1):
            for i in range(cells + 1):
                p = np.zeros(3)
                p[axis], p[u_axis], p[v_axis] = (sign + 1) / 2, g[i], g[j]
                verts.append(p)
                uvs.append([ox + (0.02 + 0.96 * g[i]) / 3, oy + (0.02 + 0.96 * g[j]) / 2])
        for j in range(cells):
            for i in range(cells):
                a = base + j * (cells + 1) + i
                quad = ((a, a + 1, a + cells + 2), (a, a + cells + 2, a + cells + 1))
                for tri in quad:
                    faces.append(tri if sign > 0 else tri[::-1])
                    slots.append(1 if axis == 2 else 0)
    return _asset("crate", verts, uvs, faces, slots,
                  [Material("planks", image=pattern(texture, 2)),
                   Material("red", np.array([0.6, 0.05, 0.03, 1.0], np.float32))])


def ring(segments: int = 96, sides: int = 24, texture: int = 512) -> Mesh:
    """Torus with one textured slot whose coordinates tile 4 x 1 around it (u runs 0..4: repeat wrap)."""
    verts, uvs, faces = [], [], []
    for j in range(sides + 1):
        for i in range(segments + 1):
            th, ph = 2 * np.pi * i / segments, 2 * np.pi * j / sides
            r = 1 + 0.35 * np.cos(ph)
            verts.append([r * np.cos(th), r * np.sin(th), 0.35 * np.sin(ph)])
            uvs.append([4 * i / segments, j / sides])
    w = segments + 1
    for j in range(sides):
        for i in range(segments):
            a, b, c, d = j * w + i, j * w + i + 1, (j + 1) * w + i, (j + 1) * w + i + 1
            faces += [(a, b, d), (a, d, c)]
    return _asset("ring", verts, uvs, faces, [0] * len(faces), [Material("tiles", image=pattern(texture, 3))])


def patchwork(subdivisions: int = 4, slots: int = 4) -> Mesh:
    """Icosphere split into `slots` plain-coloured material slots by longitude, no texture coordinates (slots
    only: the head has no coordinates to learn)."""
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    c = v[f].mean(1)
    s = (((np.arctan2(c[:, 1], c[:, 0]) + np.pi) / (2 * np.pi) * slots).astype(int)) % slots
    rng = np.random.default_rng(4)
    mats = [Material(f"paint{i}", np.append(rng.uniform(0.05, 0.9, 3), 1.0).astype(np.float32))
            for i in range(slots)]
    return mesh_from_arrays(v, f, "patchwork", Look(s.astype(np.int32), None, mats))


ASSETS = {"globe": globe, "crate": crate, "ring": ring, "patchwork": patchwork}


def _asset(name, verts, uvs, faces, slots, materials) -> Mesh:
    v = np.asarray(verts, np.float64)
    f = np.asarray(faces, np.int64)
    corner_uvs = np.asarray(uvs, np.float32)[f]
    return mesh_from_arrays(v, f, name, Look(np.asarray(slots, np.int32), corner_uvs, materials))
