"""What the planner reads of a mesh: cheap shape measures for the size predictor (`mesh_features`: area,
occupancy, roughness, triangle count) and the surface's detail by resolution for the grid's finest level
(`grid_measures`, `choose_resolution`). Linear in the triangle count; float64 work in chunks
(`geometry.mesh.CROSS_CHUNK`)."""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ..geometry.mesh import Mesh, face_cross, face_cross_chunks

FEATURE_NAMES = ("log_area", "occupancy", "roughness", "log10_triangles")


@dataclass
class MeshFeatures:
    """Cheap shape measures (normalised unit box). area: surface area; occupancy: fraction of the 32^3 cells of the
    box the surface passes through; roughness: area-weighted mean over occupied cells of 1 - |mean normal| (0 for
    a flat patch per cell, near 1 for detail that turns within a cell); triangles: count."""

    triangles: int
    area: float
    occupancy: float
    roughness: float

    def to_dict(self) -> dict:
        return asdict(self)


def mesh_features(mesh: Mesh, cells: int = 32) -> MeshFeatures:
    """Measure `mesh` (see MeshFeatures; `cells` a power of two). Linear in the triangle count; ~0.1 s for 100k
    triangles."""
    area, (roughness, occupied) = cell_measures(mesh, (cells,))
    return MeshFeatures(triangles=mesh.n_triangles, area=area, occupancy=occupied[0] / cells ** 3,
                        roughness=roughness[0])


def _morton(cells: np.ndarray) -> np.ndarray:
    """(T, 3) int64 cell coordinates below 2^21 -> (T,) uint64 Z-order codes: a cell at resolution r / 2^k is the
    code shifted right by 3k, so one sort orders the triangles for every coarser resolution."""
    code = np.zeros(len(cells), np.uint64)
    for axis in range(3):
        x = cells[:, axis].astype(np.uint64)
        x = (x | (x << np.uint64(32))) & np.uint64(0x1F00000000FFFF)
        x = (x | (x << np.uint64(16))) & np.uint64(0x1F0000FF0000FF)
        x = (x | (x << np.uint64(8))) & np.uint64(0x100F00F00F00F00F)
        x = (x | (x << np.uint64(4))) & np.uint64(0x10C30C30C30C30C3)
        x = (x | (x << np.uint64(2))) & np.uint64(0x1249249249249249)
        code |= x << np.uint64(2 - axis)
    return code


def cell_measures(mesh: Mesh, resolutions: tuple[int, ...]) -> tuple[float, tuple[list[float], list[int]]]:
    """(surface area, ([roughness per resolution], [occupied cells per resolution])): triangles binned by centre
    into r^3 cells of the normalised unit box (r a power of two up to 2^21); roughness: area-weighted mean over
    occupied cells of 1 - |mean normal|. One pass in chunks (`face_cross_chunks`) and one sort of the cells'
    Z-order codes at the finest resolution serve every resolution: ~44 B per triangle at the peak, where a bin per
    cell held ~0.9 GB at 256^3 cells whatever the mesh (10M triangles: a 6.4 GB peak, bench/results/heavy.md)."""
    finest = _finest(resolutions)
    return _cell_stats(*_triangle_cells(mesh, finest), finest, resolutions)


def _finest(resolutions: tuple[int, ...]) -> int:
    finest = max(resolutions)
    if any(r & (r - 1) or finest % r for r in resolutions) or finest > 1 << 21:
        raise ValueError(f"resolutions {resolutions}: powers of two up to 2^21 expected")
    return finest


def _triangle_cells(mesh: Mesh, finest: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per triangle, in the mesh's order: its centre's cell as a Z-order code at `finest` cells across (T,) uint64,
    its area (T,) float64 and its unit normal (T, 3) float32."""
    n = mesh.n_triangles
    code, area, normal = np.empty(n, np.uint64), np.empty(n, np.float64), np.empty((n, 3), np.float32)
    for a, b, cross in face_cross_chunks(mesh.vertices, mesh.faces):
        twice = np.linalg.norm(cross, axis=1)
        area[a:b] = 0.5 * twice
        normal[a:b] = cross / np.maximum(twice, 1e-30)[:, None]
        centre = mesh.vertices[mesh.faces[a:b]].astype(np.float64).mean(axis=1)
        code[a:b] = _morton(np.clip((centre * finest).astype(np.int64), 0, finest - 1))
    return code, area, normal


def _cell_stats(code: np.ndarray, area: np.ndarray, normal: np.ndarray, finest: int,
                resolutions: tuple[int, ...]) -> tuple[float, tuple[list[float], list[int]]]:
    """cell_measures' result from `_triangle_cells`' arrays (left as they are)."""
    total = float(area.sum())
    order = np.argsort(code, kind="stable")
    key, cell_area = code[order], area[order]
    summed = normal[order] * cell_area[:, None]  # float64 (T, 3): each cell's summed normal, area-weighted
    del order
    found: dict[int, tuple[float, int]] = {}
    level = finest
    # Finest first; each coarser resolution sums the cells of the one before (fewer every time), where a pass over
    # the triangles per resolution took 5.5 s on the 10M-triangle lattice.
    for r in sorted(resolutions, reverse=True):
        key = key >> np.uint64(3 * (level // r).bit_length() - 3)
        level = r
        if len(key):
            starts = np.flatnonzero(np.concatenate(([True], key[1:] != key[:-1])))
            key, cell_area = key[starts], np.add.reduceat(cell_area, starts)
            summed = np.add.reduceat(summed, starts, axis=0)
        held = cell_area > 0
        coherence = np.linalg.norm(summed[held], axis=1) / cell_area[held]
        found[r] = (float(np.sum((1 - coherence) * cell_area[held]) / max(total, 1e-30)), int(held.sum()))
    roughness = [found[r][0] for r in resolutions]
    occupied = [found[r][1] for r in resolutions]
    return total, (roughness, occupied)


#: Resolutions (cells across the unit box) at which the surface is measured, and the range N_max is chosen in.
DETAIL_RESOLUTIONS = (16, 32, 64, 128, 256, 512, 1024)
N_MAX_RANGE = (64, 1024)
#: A surface is "resolved" at the first resolution whose cells are this close to flat (area-weighted mean of
#: 1 - |mean normal| per cell; 0.01 ~ normals within ~8 degrees of their cell's mean); no level needs to be finer
#: than DETAIL_FACTOR x that.
RESOLVED_ROUGHNESS = 0.01
DETAIL_FACTOR = 2
#: The finest level may touch at most TABLE_LOAD x T surface cells: beyond that its vertices collide in the T rows
#: faster than they add detail. Measured (bench/quality/bench_resolution.py; default preset, T=2^12, 1,500 steps, image
#: MSE at N_max 32 / 64 / 128 / 256): bunny 0.00123 / 0.00120 / 0.00138 / 0.00171 (surface cells at 64: 3.1 T, at
#: 128: 11 T), knot - / 0.00074 / 0.00079 / - (1.4 T, 5.2 T), gyroid 0.0095 / 0.0096 / 0.0114 / -, blob - / 0.00040 /
#: 0.00059 / -, studs - / 0.0168 / 0.0172 / 0.0225, lattice - / 0.0545 / 0.0595 / 0.0596: every mesh measured, the
#: 3.3M-triangle lattice of fine detail included, is best at 64 at this table size, and 128 loses from 5.2 T on.
TABLE_LOAD = 4.0
#: Surface samples (area-weighted) for counting the cells the surface passes through.
SURFACE_SAMPLES = 200_000


def surface_cells(mesh: Mesh, resolutions: tuple[int, ...] = DETAIL_RESOLUTIONS,
                  samples: int = SURFACE_SAMPLES, area: np.ndarray | None = None) -> dict[int, int]:
    """{cells across the unit box: cells of the normalised frame the surface passes through}, counted from
    `samples` area-weighted points on the triangles (fixed seed: the same mesh always gives the same counts; the
    count saturates near `samples` at fine resolutions, where every choice is already far over any table). area:
    the triangles' areas (T,) float64 when the caller has them."""
    if area is None:
        area = 0.5 * np.linalg.norm(face_cross(mesh.vertices, mesh.faces), axis=1)
    if not area.sum() > 0:
        return {r: 0 for r in resolutions}
    rng = np.random.default_rng(0)
    pick = rng.choice(len(area), samples, p=area / area.sum())
    uv = rng.random((samples, 2))
    uv = np.where(uv.sum(1, keepdims=True) > 1, 1 - uv, uv)
    t = mesh.vertices[mesh.faces[pick]].astype(np.float64)
    points = t[:, 0] + uv[:, :1] * (t[:, 1] - t[:, 0]) + uv[:, 1:] * (t[:, 2] - t[:, 0])
    out = {}
    for r in resolutions:
        cell = np.clip((points * r).astype(np.int64), 0, r - 1)
        out[r] = int(len(np.unique((cell[:, 0] * r + cell[:, 1]) * r + cell[:, 2])))
    return out


def roughness_at(mesh: Mesh, resolutions: tuple[int, ...] = DETAIL_RESOLUTIONS) -> dict[int, float]:
    """{cells across the unit box: area-weighted mean over occupied cells of 1 - |mean normal|} of the mesh in its
    normalised frame (triangles binned by centroid; `cell_measures`). It falls as cells shrink toward the scale below
    which the surface is flat; it is 0 once a cell holds one triangle. Linear in triangles, one sort."""
    _, (roughness, _) = cell_measures(mesh, resolutions)
    return {r: max(0.0, v) for r, v in zip(resolutions, roughness)}


@dataclass
class GridMeasures:
    """What the grid choice reads: roughness and surface cells by resolution (see the functions above); features:
    the size predictor's `mesh_features`, taken in the same pass."""

    roughness: dict
    cells: dict
    features: MeshFeatures | None = None


#: mesh_features' resolution (cells across the unit box), one of DETAIL_RESOLUTIONS.
FEATURE_CELLS = 32


def grid_measures(mesh: Mesh) -> GridMeasures:
    """Everything the planner reads of `mesh` in one pass over its triangles and one sort: the grid's roughness and
    surface cells by resolution, and the predictor's features (the same values `roughness_at`, `surface_cells` and
    `mesh_features` give apart; three passes took 15.5 s on the 10M-triangle lattice, 2 cores)."""
    finest = _finest(DETAIL_RESOLUTIONS)
    code, area, normal = _triangle_cells(mesh, finest)
    cells = surface_cells(mesh, area=area)
    total, (roughness, occupied) = _cell_stats(code, area, normal, finest, DETAIL_RESOLUTIONS)
    del code, area, normal
    at = DETAIL_RESOLUTIONS.index(FEATURE_CELLS)
    features = MeshFeatures(triangles=mesh.n_triangles, area=total, occupancy=occupied[at] / FEATURE_CELLS ** 3,
                            roughness=roughness[at])
    return GridMeasures({r: max(0.0, v) for r, v in zip(DETAIL_RESOLUTIONS, roughness)}, cells, features)


def choose_resolution(mesh: Mesh | GridMeasures, log2_table: int) -> tuple[int, str]:
    """The grid's finest resolution N_max for this mesh and table size T = 2^log2_table, and why: the finest
    resolution whose surface cells fit TABLE_LOAD x T (the table's capacity), no finer than DETAIL_FACTOR x the
    resolution at which the surface is flat within cells (the detail's need), in N_MAX_RANGE. The paper fixes 128
    for every model; here the default preset's T=2^12 gives 64 on every benchmark mesh (measured better there), a
    larger table finer grids where the surface is small (the knot at T=2^13: 128)."""
    m = mesh if isinstance(mesh, GridMeasures) else grid_measures(mesh)
    table = 1 << log2_table
    resolved = next((r for r, v in m.roughness.items() if v <= RESOLVED_ROUGHNESS), max(m.roughness))
    detail_cap = DETAIL_FACTOR * resolved
    fits = [r for r, c in m.cells.items() if c <= TABLE_LOAD * table]
    table_cap = max(fits) if fits else min(m.cells)
    n_max = int(min(max(min(detail_cap, table_cap), N_MAX_RANGE[0]), N_MAX_RANGE[1]))
    return n_max, (f"grid N_max {n_max}: the surface is flat within cells from {resolved} across (need <= "
                   f"{detail_cap}); at {table_cap} it touches {m.cells.get(table_cap, 0):,} cells, within "
                   f"{TABLE_LOAD:g} x T={table:,} rows (table capacity)")
