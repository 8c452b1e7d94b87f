"""Model no more than a mesh needs: what it replaces, what it will cost, and which size to train.

* **What it replaces** (`mesh_resident_bytes`): a ray tracer keeps float32 vertices, int32 indices, float32
  vertex normals and a BVH with <= 4 triangles per leaf (32-byte nodes) resident before it traces one ray; the
  .nbvh model is traced as stored. `alternatives` also measures the smallest quadric decimation that meets a
  quality target (rendered with Embree, scored with the same metric) and the Draco size of the mesh (storage).
* **Cheap predictor** (`mesh_features`, `predict_mse`): image MSE after training as a linear function in log
  space of the table size log2 T, properties of the mesh (how much its normals vary locally, triangle count) and
  the training budget (ln budget, and its product with log2 T: a larger table gains more from a longer budget),
  fitted on 84 measurements at 15-600 s by bench/fit_budget.py, then shifted to the presets' present shape by its own
  rows (`SizeFit.shape_shift`; bench/results/sizing_budget.md: leave-one-mesh-out errors); coefficients in
  sizing_fit.json.
* **Choice** (`resolve`, `choose_table_and_nodes`): a byte budget or a quality target turned into sizes: the
  (T, node count) of fewest file bytes whose predicted MSE meets the target; `pipeline.compress_mesh` trains it,
  measures and corrects (`decision.size_search`: up to TARGET_TRAININGS trainings, calibrated by each measurement).
  `choose_size` is the same over T alone (scenes).
* **Verdict** (`assess`): when the mesh as it is, or the smallest decimation of it that meets the target, is no
  larger than the model held as a compact ray-traceable mesh (or, with mesh_layout "plain", as a plain ray tracer
  holds it), compressing is not worth it; the result says so with all sizes (a user can still force the model).
* **Scenes** (`plan_scene`; the rule: `decision.scene_budget`): one byte budget over several meshes, shared by need: every mesh gets the
  smallest T that meets a common quality level (scaled by its weight, e.g. its size on screen), with the level
  set as strict as the budget allows.
"""
from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..geometry.bvh import build_full_tree, resident_bvh_nodes
from ..geometry.mesh import Mesh, face_cross
from ..geometry.decimation import Decimator, decimate, simplifier_missing  # noqa: F401  (decimate: for benches)
from ..protocol.quality_levels import QUALITY_LEVELS  # noqa: F401  (re-exported)
from ..decision.config import DecisionConfig
from ..decision.records import Assessment
from ..decision.scene_budget import split_budget
from ..decision.verdict import verdict_before_training
from .settings import PAPER_N_MAX, PRESETS, Settings, estimate_file_bytes

FIT_PATH = Path(__file__).with_name("sizing_fit.json")
#: Table sizes the chooser considers (log2 T): the range the predictor was fitted on (bench/fit_budget.py: the
#: default preset's method at 2^8..2^13).
LOG2_RANGE = range(8, 14)
#: BVH node counts the chooser considers (the node effect is fitted at these counts).
NODE_CHOICES = (1023, 2047, 4095)
#: A BVH leaf of the model should cover at least this many triangles: a 3k-triangle part at 2,047 nodes had ~3 per
#: leaf, and its node bytes (8 bit: 10 B each) outweighed its table at small T.
MIN_TRIANGLES_PER_LEAF = 8


def max_nodes_for(triangles: int) -> int:
    """The most BVH nodes a model of a `triangles`-triangle mesh needs: 2^k - 1 with 2^(k-1) leaves of at least
    MIN_TRIANGLES_PER_LEAF triangles each, between 255 and 4,095."""
    nodes = 255
    while nodes < 4095 and (nodes + 1) * MIN_TRIANGLES_PER_LEAF <= triangles:
        nodes = 2 * nodes + 1
    return nodes
FEATURE_NAMES = ("log_area", "occupancy", "roughness", "log10_triangles")


def mesh_resident_bytes(mesh: Mesh, tree=None) -> dict:
    """Bytes a ray tracer holds for `mesh`: vertices, indices, normals (float32 / int32, 12 B per vertex or
    triangle each), bvh (32-byte nodes, <= 4 triangles per leaf), total. tree: the mesh's `bvh.build_full_tree`
    when the caller has one (else it is built)."""
    nodes = resident_bvh_nodes(tree if tree is not None else build_full_tree(mesh), 4)
    out = {"vertices": mesh.n_vertices * 12, "indices": mesh.n_triangles * 12, "normals": mesh.n_vertices * 12,
           "bvh": nodes * 32}
    out["total"] = sum(out.values())
    return out


# ------------------------------------------------------------------------------------------------ mesh features
@dataclass
class MeshFeatures:
    """Cheap shape measures (normalised unit box). area: surface area; occupancy: fraction of the 32^3 cells of the
    box the surface passes through; roughness: area-weighted mean over occupied cells of 1 - |mean normal| (0 for
    a flat patch per cell, near 1 for detail that turns within a cell); triangles: count."""

    triangles: int
    area: float
    occupancy: float
    roughness: float

    def vector(self, names: tuple | list = FEATURE_NAMES) -> np.ndarray:
        """The predictor's inputs besides log2 T, by name (FEATURE_NAMES)."""
        values = {"log_area": math.log(max(self.area, 1e-6)), "occupancy": self.occupancy,
                  "roughness": self.roughness, "log10_triangles": math.log10(max(self.triangles, 1))}
        return np.array([values[n] for n in names])

    def to_dict(self) -> dict:
        return asdict(self)


def mesh_features(mesh: Mesh, cells: int = 32) -> MeshFeatures:
    """Measure `mesh` (see MeshFeatures). Linear in the triangle count; ~0.1 s for 100k triangles."""
    centre, area, normal = _triangle_areas_normals(mesh)
    roughness, occupied = _cell_roughness(centre, area, normal, cells)
    return MeshFeatures(triangles=mesh.n_triangles, area=float(area.sum()), occupancy=occupied / cells ** 3,
                        roughness=roughness)


def _triangle_areas_normals(mesh: Mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The mesh's triangle centres (T, 3) float64 in its normalised frame, their areas (T,) and unit normals
    (T, 3), computed in chunks (`mesh.CROSS_CHUNK`: no (T, 3, 3) float64 copy of a heavy mesh)."""
    from ..geometry.mesh import CROSS_CHUNK

    cross = face_cross(mesh.vertices, mesh.faces)
    centre = np.empty((mesh.n_triangles, 3), np.float64)
    for a in range(0, mesh.n_triangles, CROSS_CHUNK):
        centre[a:a + CROSS_CHUNK] = mesh.vertices[mesh.faces[a:a + CROSS_CHUNK]].astype(np.float64).mean(axis=1)
    area = 0.5 * np.linalg.norm(cross, axis=1)
    cross /= np.maximum(2 * area, 1e-30)[:, None]
    return centre, area, cross


def _cell_roughness(centre: np.ndarray, area: np.ndarray, normal: np.ndarray, r: int) -> tuple[float, int]:
    """Triangles binned by centre into r^3 cells of the unit box: (area-weighted mean over occupied cells of
    1 - |mean normal|, occupied cells)."""
    cell = np.clip((centre * r).astype(np.int64), 0, r - 1)
    key = (cell[:, 0] * r + cell[:, 1]) * r + cell[:, 2]
    # up to 2^24 cells: the key is the bin (no sort; np.unique sorted 10M keys per resolution, ~1 s each)
    cid = key if r ** 3 <= 1 << 24 else np.unique(key, return_inverse=True)[1]
    cell_area = np.bincount(cid, weights=area)
    summed = np.stack([np.bincount(cid, weights=area * normal[:, a]) for a in range(3)], 1)
    occupied = cell_area > 0
    coherence = np.linalg.norm(summed[occupied], axis=1) / cell_area[occupied]
    return float(np.sum((1 - coherence) * cell_area[occupied]) / max(cell_area.sum(), 1e-30)), int(occupied.sum())


# ------------------------------------------------------------------------------------------ grid resolution
#: Resolutions (cells across the unit box) at which the surface is measured, and the range N_max is chosen in.
DETAIL_RESOLUTIONS = (16, 32, 64, 128, 256, 512, 1024)
N_MAX_RANGE = (64, 1024)
#: A surface is "resolved" at the first resolution whose cells are this close to flat (area-weighted mean of
#: 1 - |mean normal| per cell; 0.01 ~ normals within ~8 degrees of their cell's mean); no level needs to be finer
#: than DETAIL_FACTOR x that.
RESOLVED_ROUGHNESS = 0.01
DETAIL_FACTOR = 2
#: The finest level may touch at most TABLE_LOAD x T surface cells: beyond that its vertices collide in the T rows
#: faster than they add detail. Measured (bench/bench_resolution.py; default preset, T=2^12, 1,500 steps, image
#: MSE at N_max 32 / 64 / 128 / 256): bunny 0.00123 / 0.00120 / 0.00138 / 0.00171 (surface cells at 64: 3.1 T, at
#: 128: 11 T), knot - / 0.00074 / 0.00079 / - (1.4 T, 5.2 T), gyroid 0.0095 / 0.0096 / 0.0114 / -, blob - / 0.00040 /
#: 0.00059 / -, studs - / 0.0168 / 0.0172 / 0.0225, lattice - / 0.0545 / 0.0595 / 0.0596: every mesh measured, the
#: 3.3M-triangle lattice of fine detail included, is best at 64 at this table size, and 128 loses from 5.2 T on.
TABLE_LOAD = 4.0
#: Surface samples (area-weighted) for counting the cells the surface passes through.
SURFACE_SAMPLES = 200_000


def surface_cells(mesh: Mesh, resolutions: tuple[int, ...] = DETAIL_RESOLUTIONS,
                  samples: int = SURFACE_SAMPLES) -> dict[int, int]:
    """{cells across the unit box: cells of the normalised frame the surface passes through}, counted from
    `samples` area-weighted points on the triangles (fixed seed: the same mesh always gives the same counts; the
    count saturates near `samples` at fine resolutions, where every choice is already far over any table)."""
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
    normalised frame (triangles binned by centroid). It falls as cells shrink toward the scale below which the
    surface is flat; it is 0 once a cell holds one triangle. Linear in triangles (~4 s for 3.3M)."""
    centre, area, normal = _triangle_areas_normals(mesh)
    return {r: max(0.0, _cell_roughness(centre, area, normal, r)[0]) for r in resolutions}


@dataclass
class GridMeasures:
    """What the grid choice reads: roughness and surface cells by resolution (see the functions above)."""

    roughness: dict
    cells: dict


def grid_measures(mesh: Mesh) -> GridMeasures:
    return GridMeasures(roughness_at(mesh), surface_cells(mesh))


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


# -------------------------------------------------------------------------------------------------- predictor
@dataclass
class SizeFit:
    """log(MSE) = coef . [1, log2 T, *features] for one method at one training budget; `features` names the
    mesh measures used (a subset of FEATURE_NAMES, chosen by leave-one-mesh-out error in bench/fit_sizing.py).
    residual_std: spread of the fit in log space (leave-one-mesh-out); margin: how many residual_stds below the
    target the chooser aims (a safety factor exp(margin * std))."""

    method: str
    train_s: float
    coef: list
    residual_std: float
    features: list = field(default_factory=lambda: list(FEATURE_NAMES))
    margin: float = 0.5
    meshes: list = field(default_factory=list)
    #: Node count: log MSE changes by nodes_coef per doubling of the node count relative to nodes_ref (fitted at a
    #: fixed T, see bench/fit_sizing.py); 0 = not fitted (the node count stays at nodes_ref).
    nodes_coef: float = 0.0
    nodes_ref: int = 2047
    #: The training budget's effect (bench/fit_budget.py): log MSE changes by a L + c (log2 T - 10) L with
    #: L = ln(budget / train_s), [a, c] = budget_coef (a larger table gains more from a longer budget); [] = not
    #: fitted (predictions are for train_s seconds).
    budget_coef: list = field(default_factory=list)
    #: ln of the presets' present shape's MSE over what the slopes predict (fitted on its own rows, bench/fit_budget.py:
    #: the slopes were measured on older shapes that need a larger table for the same MSE); added to every prediction.
    shape_shift: float = 0.0

    def predict_log_mse(self, log2_table: int, features: MeshFeatures, nodes: int | None = None,
                        budget_s: float | None = None) -> float:
        """ln of the image MSE a model of table 2^log2_table on a mesh with `features` reaches after `budget_s`
        seconds of training (None: the fit's own train_s) at `nodes` BVH nodes (None: nodes_ref)."""
        x = np.concatenate([[1.0, float(log2_table)], features.vector(self.features)])
        out = float(np.dot(self.coef, x)) + self.shape_shift
        if nodes is not None and self.nodes_coef:
            out += self.nodes_coef * (math.log2(nodes + 1) - math.log2(self.nodes_ref + 1))
        if budget_s and self.budget_coef:
            out += self.budget_slope(log2_table) * math.log(budget_s / self.train_s)
        return out

    def budget_slope(self, log2_table: int) -> float:
        """d ln MSE / d ln budget at table 2^log2_table (0 without a budget fit): how much a longer training lowers
        the final MSE (-0.44 at 2^11, -0.51 at 2^12 in the shipped fit)."""
        if not self.budget_coef:
            return 0.0
        return self.budget_coef[0] + self.budget_coef[1] * (log2_table - 10)


def fit_size_model(rows: list[tuple[int, MeshFeatures, float]], method: str, train_s: float,
                   ridge: float = 1e-3, features: tuple | list = FEATURE_NAMES) -> SizeFit:
    """Least squares (slightly ridged) of log MSE on [1, log2 T, features] over (log2 T, features, mse) rows."""
    x = np.array([np.concatenate([[1.0, float(l2)], f.vector(features)]) for l2, f, _ in rows])
    y = np.log(np.array([m for _, _, m in rows]))
    a = x.T @ x + ridge * np.eye(x.shape[1])
    coef = np.linalg.solve(a, x.T @ y)
    resid = y - x @ coef
    return SizeFit(method=method, train_s=train_s, coef=coef.tolist(), residual_std=float(np.std(resid)),
                   features=list(features))


def load_fit(path: Path = FIT_PATH) -> SizeFit | None:
    """The shipped fit (bench/fit_sizing.py writes it); None when missing or unreadable."""
    try:
        return SizeFit(**json.loads(Path(path).read_text()))
    except (OSError, ValueError, TypeError):
        return None


def predict_mse(fit: SizeFit, log2_table: int, features: MeshFeatures, nodes: int | None = None,
                budget_s: float | None = None) -> float:
    """exp(`SizeFit.predict_log_mse`)."""
    return math.exp(fit.predict_log_mse(log2_table, features, nodes, budget_s))


def predictor(fit: SizeFit | None, features: MeshFeatures | None, nodes: int | None = None,
              budget_s: float | None = None):
    """predict(log2 T) -> ln image MSE of this mesh's model at that table size (the size search's input,
    `decision.size_search`), or None without a fit."""
    if fit is None or features is None:
        return None
    return lambda log2_table: fit.predict_log_mse(log2_table, features, nodes, budget_s)


def choose_size(fit: SizeFit, features: MeshFeatures, target_mse: float,
                budget_s: float | None = None) -> tuple[int, float, bool]:
    """`choose_table_and_nodes` over T alone (the fitted node count): the smallest log2 T in LOG2_RANGE whose
    predicted MSE x exp(margin x residual_std) <= target. Returns (log2 T, predicted MSE, reachable)."""
    l2, _, pred, reachable = choose_table_and_nodes(dataclasses.replace(fit, nodes_coef=0.0), features, target_mse,
                                                    lambda log2, nodes: log2, budget_s)  # file bytes grow with T
    return l2, pred, reachable


def choose_table_and_nodes(fit: SizeFit, features: MeshFeatures, target_mse: float,
                           size_of, budget_s: float | None = None,
                           safety: float | None = None) -> tuple[int, int, float, bool]:
    """The (log2 T, node count) of smallest file bytes `size_of(log2, nodes)` whose predicted MSE (times `safety`,
    default the fit's exp(margin x residual_std)) meets the target, over LOG2_RANGE x NODE_CHOICES (only the fitted
    node count without a node fit), no node count above `max_nodes_for(features.triangles)`. Returns (log2 T,
    nodes, predicted MSE, reachable); unreachable: the largest T and node count."""
    if safety is None:
        safety = math.exp(fit.margin * fit.residual_std)
    cap = max_nodes_for(features.triangles)
    node_choices = tuple(min(n, cap) for n in (NODE_CHOICES if fit.nodes_coef else (fit.nodes_ref,)))
    ok = [(size_of(l2, n), l2, n) for l2 in LOG2_RANGE for n in node_choices
          if predict_mse(fit, l2, features, n, budget_s) * safety <= target_mse]
    if ok:
        _, l2, n = min(ok)
        return l2, n, predict_mse(fit, l2, features, n, budget_s), True
    l2, n = LOG2_RANGE[-1], max(node_choices)
    return l2, n, predict_mse(fit, l2, features, n, budget_s), False




def resolve(s: Settings, mesh: Mesh | None = None, grid: GridMeasures | None = None,
            features: MeshFeatures | None = None) -> tuple[Settings, str]:
    """Turn a byte budget or a quality target into concrete sizes; returns (settings, why).

    Budget: the largest (T, nodes) of the grid T in 2^5..2^13, nodes in 255..8191 whose file fits the budget
    (largest file first, ties to more nodes). Target (with the mesh): the method the size predictor was fitted
    for (sizing_fit.json: HashGrid + MLP + consistent labels) at the smallest T whose predicted MSE meets the
    target (`sizing.choose_table_and_nodes`); `compress_mesh` then measures and corrects (`decision.size_search`).
    n_max None: the grid's finest resolution is chosen for the mesh and the chosen T (`choose_resolution`; `grid`:
    its measures when the caller has them). features: `mesh_features(mesh)` when the caller has them.
    """
    if s.n_max is None:
        if mesh is None:
            s, grid_why = dataclasses.replace(s, n_max=PAPER_N_MAX), f"grid N_max {PAPER_N_MAX} (no mesh to measure)"
        else:
            chosen, why = resolve(dataclasses.replace(s, n_max=PAPER_N_MAX), mesh, None, features)  # sizes, then grid
            n_max, grid_why = choose_resolution(grid or mesh, chosen.log2_table)
            return dataclasses.replace(chosen, n_max=n_max), f"{why}; {grid_why}"
        chosen, why = resolve(s, mesh, None, features)
        return chosen, f"{why}; {grid_why}"
    if s.budget_kb is not None:
        budget = s.budget_kb * 1024
        best = None
        for log2 in range(LOG2_RANGE[-1], 4, -1):
            for nodes in (8191, 4095, 2047, 1023, 511, 255):
                cand = dataclasses.replace(s, log2_table=log2, nodes=nodes, budget_kb=None)
                size = estimate_file_bytes(cand)
                if size <= budget and (best is None or size > best[0]):
                    best = (size, cand)
        if best is None:
            raise ValueError(f"a budget of {s.budget_kb:g} KB is too small for any model "
                             f"(the smallest needs {estimate_file_bytes(dataclasses.replace(s, log2_table=5, nodes=255)) / 1024:.0f} KB)")
        size, chosen = best
        return chosen, (f"budget {s.budget_kb:g} KB: chose T=2^{chosen.log2_table}, {chosen.nodes} nodes "
                        f"(estimated {size / 1024:.1f} KB), the largest grid point that fits")
    if s.target_mse is not None:
        if s.target_mse <= 0:
            raise ValueError(f"target MSE must be > 0, got {s.target_mse:g}")
        fit = load_fit()
        if fit is None or mesh is None:
            base = PRESETS["high" if s.target_mse < QUALITY_LEVELS["standard"]
                           else "default" if s.target_mse < QUALITY_LEVELS["preview"] else "preview"]
            chosen = dataclasses.replace(s, nodes=base.nodes, log2_table=base.log2_table)
            return chosen, (f"target MSE {s.target_mse:g}: no size predictor available, used preset sizes "
                            f"(T=2^{base.log2_table}, {base.nodes} nodes)")
        feats = features or mesh_features(mesh)
        fitted = PRESETS[fit.method]
        base = dataclasses.replace(s, encoding=fitted.encoding, network=fitted.network, labels=fitted.labels)
        l2, nodes, pred, reachable = choose_table_and_nodes(
            fit, feats, s.target_mse,
            lambda lt, n: estimate_file_bytes(dataclasses.replace(base, log2_table=lt, nodes=n)), s.time_limit_s)
        chosen = dataclasses.replace(base, nodes=nodes, log2_table=l2)
        why = (f"target MSE {s.target_mse:g}: predicted MSE {pred:.4g} at T=2^{l2}, {nodes} nodes, "
               f"{s.time_limit_s or fit.train_s:g} s "
               f"({fitted.encoding}+{fitted.network}; mesh area {feats.area:.2f}, occupancy {feats.occupancy:.3f}, "
               f"roughness {feats.roughness:.3f}, {feats.triangles:,} triangles), the smallest file predicted to "
               f"meet it with a {math.exp(fit.margin * fit.residual_std):.2f}x safety factor")
        if not reachable:
            why += "; the target is beyond every size the predictor knows: using the largest"
        return chosen, why
    return s, "fixed settings"


def expected_table(s: Settings, mesh: Mesh, features: MeshFeatures | None = None) -> int | None:
    """log2 T of the smallest file the predictor expects to meet `s.target_mse` on `mesh` (its median prediction: no
    safety factor; the node count as `resolve` chooses it; the largest size when none does): the model the verdict
    before training weighs against the decimation measured at the target, since both then stand at the level (the
    safety factor only says where a training starts). features: `mesh_features(mesh)` when the caller has them.
    None without a target, a mesh or a fit."""
    fit = load_fit()
    if s.target_mse is None or mesh is None or fit is None:
        return None
    size_of = lambda lt, n: estimate_file_bytes(dataclasses.replace(s, log2_table=lt, nodes=n))  # noqa: E731
    l2, _, _, _ = choose_table_and_nodes(fit, features or mesh_features(mesh), s.target_mse, size_of,
                                         s.time_limit_s, safety=1.0)
    return l2


# ----------------------------------------------------------------------------------------------- alternatives
def mesh_like(mesh: Mesh, vertices: np.ndarray, faces: np.ndarray) -> Mesh:
    """Another triangulation of `mesh` (a decimation, a Draco-decoded copy) in the same normalised coordinates:
    no re-normalisation, triangles with a repeated index dropped."""
    f = np.asarray(faces, np.int32).reshape(-1, 3)
    keep = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    return Mesh(vertices=np.asarray(vertices, np.float32), faces=f[keep], transform=mesh.transform, name=mesh.name)


#: Decimation sizes tried first (triangles, x4 apart; those >= DECIMATE_MAX_SHARE of the mesh are not tried), then
#: DECIMATE_REFINE bisections (in log space) between the last that missed and the first that met: the decimation
#: reported is within 2^(2 / 2^DECIMATE_REFINE) = 1.19x of the smallest that meets the target. One size x4 above the
#: first that met is measured too, so the alternative's curve (`decision.alternative_curve`) reaches models that
#: beat the target by measurement, not by extrapolation.
DECIMATE_COUNTS = (250, 1000, 4000, 16000, 64000, 256000, 1024000)
DECIMATE_MAX_SHARE = 0.7
DECIMATE_REFINE = 3


def look_carried_bytes(mesh: Mesh, n_vertices: int, n_triangles: int) -> int:
    """The bytes a mesh of `n_vertices` / `n_triangles` (the asset or a decimation of it) needs to carry the asset's
    look, as a compact mesh would hold it: the same slot images the model stores (`Material.stored_image`),
    16-bit texture coordinates per vertex when images are sampled, and a slot id per triangle (ceil(log2 slots)
    bits) when there are several slots. Counted, not written: the compact mesh this product writes is geometry only
    (Blender's Decimate modifier, which the add-on offers, keeps the object's UVs and slots). 0 for a bare shape."""
    look = mesh.look
    if look is None:
        return 0
    from ..neural.quantize import StorageConfig
    from ..storage.fileformat import look_stored_bytes

    textures = look_stored_bytes(None, look.materials, StorageConfig())["textures"]  # each image encoded once
    uv = 4 * n_vertices if look.textured else 0
    slots = math.ceil(n_triangles * math.ceil(math.log2(look.n_slots)) / 8) if look.n_slots > 1 else 0
    return int(textures + uv + slots)


def decimation_entry(mesh: Mesh, count: int, checks, held_out, draco, decimator: Decimator | None = None) -> dict:
    """One point of the alternative: the decimation to ~`count` triangles (`decimator`, the mesh's
    `geometry.decimation.Decimator`: one chain for every point; else one is made), plainly and as a compact mesh
    (exact bytes; the decoded compact mesh scored on the check views and, when given, the held-out views)."""
    from ..geometry.compact_mesh import compact_mesh

    dec = (decimator or Decimator(mesh))(count)
    if dec.n_triangles == 0:
        return {"triangles": 0, "requested_triangles": count, "mse": math.inf, "compact_mse": math.inf}
    tree = build_full_tree(dec)  # one tree for the resident count and the compact layout's clusters
    entry = {"triangles": dec.n_triangles, "requested_triangles": count, "mse": checks.score_mesh(dec).mse,
             "resident_bytes": mesh_resident_bytes(dec, tree)["total"]}
    nbytes, decoded = compact_mesh(dec, tree)
    entry["compact_bytes"] = nbytes
    entry["look_bytes"] = look_carried_bytes(mesh, dec.n_vertices, dec.n_triangles)
    entry["compact_mse"] = checks.score_mesh(decoded).mse
    if held_out is not None:
        entry["compact_mse_held_out"] = held_out.score_mesh(decoded).mse
    if draco is not None:
        entry["draco11_bytes"] = len(draco.encode(dec.vertices, dec.faces, quantization_bits=11, compression_level=7))
    return entry


def alternatives(mesh: Mesh, target_mse: float | None, checks=None, held_out=None, tree=None,
                 decimator: Decimator | None = None, tick=None) -> dict:
    """What a user could ship instead, measured: Draco (11-bit, storage bytes) of the mesh, and decimations
    (`geometry.decimation.decimate`: meshoptimizer, the look kept) up to the smallest whose image MSE meets `target_mse` (see DECIMATE_COUNTS), each with its
    resident and compact-mesh bytes and the compact mesh's MSE, scored by the run's own metric: `checks` (a
    rendering.metrics.ViewScorer: the training checks' views) and `held_out` (the final evaluation's). The whole
    mesh as a compact mesh is scored too ('mesh_compact'; `tree`: its `bvh.build_full_tree` when the caller has one).
    Missing optional packages give a note instead of numbers. With a target, `checks` is required. decimator:
    the mesh's `Decimator` (its chain serves later points too), else one is made. tick(message, planned): called
    before each measurement (`planned`: the most it may take in all; progress, and a Cancel point: it may raise)."""
    out: dict = {}
    try:
        import DracoPy
    except ImportError:
        DracoPy = None
        out["note"] = "DracoPy not installed: no Draco sizes"
    if DracoPy is not None:
        out["draco11_bytes"] = len(DracoPy.encode(mesh.vertices, mesh.faces, quantization_bits=11, compression_level=7))
    if target_mse is None:
        return out
    missing = simplifier_missing()
    if missing:  # said, not silent: the verdict then weighs no decimation, and the report says why
        out["note"] = (out.get("note", "") + "; " if "note" in out else "") + missing
        out["no_alternative"] = missing
        return out
    out["metric"] = checks.name
    tried: dict[int, dict] = {}
    decimator = decimator or Decimator(mesh)

    counts = [c for c in DECIMATE_COUNTS if c < mesh.n_triangles * DECIMATE_MAX_SHARE]
    planned = len(counts) + DECIMATE_REFINE + 3  # the ladder, the top, the refinements, one above, the whole mesh

    def measure(count: int) -> dict:
        if tick is not None:
            tick(f"decimation to {count:,} triangles", planned)
        tried[count] = decimation_entry(mesh, count, checks, held_out, DracoPy, decimator)
        return tried[count]

    def meets(entry: dict) -> bool:  # on the check views and, when measured, the held-out views alike
        return max(entry["compact_mse"], entry.get("compact_mse_held_out", 0.0)) <= target_mse

    # Past the plan's time budget (`tick.over_budget`) the optional points go first: the one above the level, the
    # refinements, then the rest of the ladder; the run says what it skipped and decides on what it measured (the
    # final verdict measures the decimation at the model's quality either way).
    over = getattr(tick, "over_budget", lambda: False)
    skipped: list[str] = []
    missed, met = None, None
    for i, count in enumerate(counts):
        if over():
            skipped.append(f"the decimations from {count:,} triangles up")
            break
        if meets(measure(count)):
            met = count
            if i + 1 < len(counts):
                if over():
                    skipped.append(f"the decimation to {counts[i + 1]:,} (one above the level)")
                else:
                    measure(counts[i + 1])
            break
        missed = count
    top = int(mesh.n_triangles * DECIMATE_MAX_SHARE)
    if met is None and not skipped and counts and counts[-1] < top:  # the gap up to the whole mesh
        if over():
            skipped.append(f"the decimation to {top:,} triangles")
        elif meets(measure(top)):
            missed, met = counts[-1], top
    if met is not None:
        lo = missed if missed is not None else max(met // 4, 4)
        for _ in range(DECIMATE_REFINE):
            mid = int(round(math.sqrt(lo * met)))
            if mid in (lo, met):
                break
            if over():
                skipped.append(f"the refinement between {lo:,} and {met:,} triangles")
                break
            if meets(measure(mid)):
                met = mid
            else:
                lo = mid
        out["decimation"] = tried[met]
    out["decimations_tried"] = [tried[c] for c in sorted(tried)]
    if tick is not None:
        tick(f"the whole mesh ({mesh.n_triangles:,} triangles) as a compact mesh", planned)
    scored = not over()
    if not scored:
        skipped.append("the whole mesh's image error (its bytes are exact)")
    out["mesh_compact"] = _whole_mesh_entry(mesh, checks if scored else None, held_out if scored else None, tree)
    if skipped:
        out["skipped"] = "past the plan's time budget, not measured: " + "; ".join(skipped)
    return out


def _whole_mesh_entry(mesh: Mesh, checks, held_out, tree=None) -> dict:
    """The whole mesh as a compact mesh: its exact bytes and the grid's own error on both view sets (without
    `checks`: the bytes alone)."""
    from ..geometry.compact_mesh import compact_mesh

    nbytes, decoded = compact_mesh(mesh, tree)
    entry = {"triangles": mesh.n_triangles, "compact_bytes": nbytes,
             "look_bytes": look_carried_bytes(mesh, mesh.n_vertices, mesh.n_triangles)}
    if checks is None:
        return entry
    entry["compact_mse"] = checks.score_mesh(decoded).mse
    if held_out is not None:
        entry["compact_mse_held_out"] = held_out.score_mesh(decoded).mse
    return entry


def winning_decimation(mesh: Mesh, assessment: "Assessment") -> Mesh | None:
    """The decimation the verdict recommends instead of a model (rebuilt exactly: the simplifier is deterministic
    and moves no vertex), or None when the verdict is not 'decimate'."""
    dec = assessment.alternatives.get("decimation")
    if assessment.recommendation != "decimate" or not dec:
        return None
    return decimate(mesh, int(dec["requested_triangles"]))


def mesh_file_bytes(mesh: Mesh) -> bytes:
    """`mesh` in its original coordinates as a binary PLY (what a user imports back into Blender)."""
    import trimesh

    original = mesh.transform.to_original(mesh.vertices)
    return trimesh.Trimesh(original, mesh.faces, process=False).export(file_type="ply", encoding="binary")


# ---------------------------------------------------------------------------------------------------- verdict
def assess(mesh: Mesh, model_bytes: int, decision: DecisionConfig, checks=None, held_out=None,
           look_bytes: int = 0, decimator: Decimator | None = None, tree=None, tick=None) -> Assessment:
    """Weigh a model of `model_bytes` (its file, `RunConfig.file_bytes`) against the mesh and, with a target MSE
    (`decision.target_mse`) and the run's view sets (`checks`, `held_out`: `rendering.metrics.view_sets`), against
    the smallest decimation that meets it, each held in `decision.mesh_layout` (see MESH_LAYOUTS; both layouts are
    reported): 'mesh' when the whole mesh is no larger than the model, 'decimate' when the decimation is not, else
    'neural'. Draco's size (storage only) is reported beside. look_bytes: what the model's file adds for the
    asset's look (appearance head and textures, `fileformat.look_stored_bytes`), so the model is weighed as it will
    ship. decimator: the mesh's `Decimator` (the caller's, to measure more points later); tree: the mesh's
    `bvh.build_full_tree` when the caller has one; tick: `alternatives`'."""
    from ..geometry.compact_mesh import compact_bytes

    layout = decision.mesh_layout
    model = model_bytes + look_bytes
    tree = tree if tree is not None else build_full_tree(mesh)
    resident_bytes = mesh_resident_bytes(mesh, tree)
    resident = resident_bytes["total"]
    # The Draco size always (cheap: shows which tool wins for storage alone); decimations only with a target.
    alt = alternatives(mesh, decision.target_mse if checks is not None else None, checks, held_out, tree,
                       decimator, tick)
    compact = alt["mesh_compact"]["compact_bytes"] if "mesh_compact" in alt else compact_bytes(mesh, tree)
    dec = alt.get("decimation")
    # A mesh weighed against the model carries the asset's look too (the model's head and images are in `model`).
    whole_look = look_carried_bytes(mesh, mesh.n_vertices, mesh.n_triangles)
    resident, compact = resident + whole_look, compact + whole_look
    if dec is not None and dec.get("look_bytes"):
        dec = {**dec, "resident_bytes": dec["resident_bytes"] + dec["look_bytes"],
               "compact_bytes": dec["compact_bytes"] + dec["look_bytes"]}
    rec, msg = verdict_before_training(model, mesh.n_triangles, resident, compact, dec, alt.get("draco11_bytes"),
                                       layout)
    return Assessment(model_bytes=model, resident=resident_bytes, worth_compressing=rec == "neural", message=msg,
                      alternatives=alt, recommendation=rec, compact_bytes=compact, layout=layout)


# ------------------------------------------------------------------------------------------------------ scenes
def mesh_bytes(mesh: Mesh, layout: str) -> int:
    """`mesh` held in `layout` (MESH_LAYOUTS): the compact ray-traceable mesh's exact bytes, or plain resident."""
    if layout == "compact":
        from ..geometry.compact_mesh import compact_bytes

        return compact_bytes(mesh)
    return mesh_resident_bytes(mesh)["total"]


def split_scene(meshes: list[Mesh], budget_bytes: float, fit: SizeFit, bytes_for_log2,
                weights: list[float] | None = None, layout: str = "compact") -> dict:
    """The one scene-budget split (CLI `plan`, the add-on's jobs): an object whose mesh held in `layout`
    (MESH_LAYOUTS) is no larger than the model its share would buy is not worth compressing: it gets nothing (log2
    None, 0 bytes) and the budget is shared by need among the others (`split_budget`), again until no share buys a
    model larger than its mesh (a share grows as others drop out). Returns split_budget's dict over all meshes, in
    order, plus 'excluded': [indices], 'declined_log2': per mesh, the table size of the share an excluded object
    turned down (5, the smallest, when its mesh is below every model; None for the others) and 'features'."""
    feats = [mesh_features(m) for m in meshes]
    weights = [1.0] * len(meshes) if weights is None else list(weights)
    held = [mesh_bytes(m, layout) for m in meshes]
    smallest = bytes_for_log2(0, 5)
    keep = [i for i in range(len(meshes)) if held[i] > smallest]
    declined = [None if i in keep else 5 for i in range(len(meshes))]
    out = {"level": None, "log2": [None] * len(meshes), "bytes": [0] * len(meshes),
           "predicted_mse": [None] * len(meshes), "total": 0, "weights": weights, "budget": budget_bytes}
    plan = None
    while keep:
        def choose(j: int, level: float, keep=keep) -> tuple[int, float]:
            return choose_size(fit, feats[keep[j]], level)[:2]

        plan = split_budget(len(keep), budget_bytes, choose, lambda j, l2, keep=keep: bytes_for_log2(keep[j], l2),
                            [weights[i] for i in keep])
        # The exact mesh at no more bytes than its model always wins: the comparison is on the share actually given.
        worth = [i for j, i in enumerate(keep) if held[i] > plan["bytes"][j]]
        for j, i in enumerate(keep):
            if i not in worth:
                declined[i] = plan["log2"][j]
        if len(worth) == len(keep):
            break
        keep, plan = worth, None
    if plan is not None:
        for j, i in enumerate(keep):
            out["log2"][i], out["bytes"][i], out["predicted_mse"][i] = (plan["log2"][j], plan["bytes"][j],
                                                                        plan["predicted_mse"][j])
        out["level"], out["total"] = plan["level"], plan["total"]
    out["excluded"] = [i for i in range(len(meshes)) if i not in keep]
    out["declined_log2"] = declined
    out["features"] = feats
    return out


def scene_base(settings: Settings, fit: SizeFit) -> Settings:
    """The settings every object of a scene budget is sized with: `settings` with the method and node count the
    size predictor was fitted for (only its predictions are comparable across objects) and no size request."""
    fitted = PRESETS[fit.method]
    return dataclasses.replace(settings, encoding=fitted.encoding, network=fitted.network, labels=fitted.labels,
                               nodes=fitted.nodes, budget_kb=None, target_mse=None)


def plan_scene(meshes: list[Mesh], budget_bytes: float, settings: Settings, weights: list[float] | None = None,
               names: list[str] | None = None, fit: SizeFit | None = None) -> dict:
    """The one scene-budget plan (CLI `plan`, the add-on's jobs): `split_scene` over `meshes` with every model's
    bytes from `scene_base(settings)`. Returns split_scene's dict plus 'objects': one row per mesh (name, weight,
    triangles, log2_table, bytes, predicted_mse, excluded) and 'base': the settings each share applies to
    (`dataclasses.replace(plan['base'], log2_table=row['log2_table'])`). Raises ValueError without a size
    predictor or when the budget is too small."""
    fit = fit or load_fit()
    if fit is None:
        raise ValueError("a scene budget needs the size predictor (nbvh_core/planning/sizing_fit.json), which is missing; "
                         "run bench/fit_sizing.py")
    weights = [1.0] * len(meshes) if weights is None else list(weights)
    if len(weights) != len(meshes):
        raise ValueError(f"{len(weights)} weights for {len(meshes)} meshes")
    base = scene_base(settings, fit)
    plan = split_scene(meshes, budget_bytes, fit,
                       lambda i, l2: estimate_file_bytes(dataclasses.replace(base, log2_table=l2)), weights,
                       settings.mesh_layout)
    names = names or [m.name or str(i) for i, m in enumerate(meshes)]
    plan["objects"] = [{"name": n, "weight": w, "triangles": f.triangles, "log2_table": l2, "bytes": b,
                        "predicted_mse": p, "excluded": i in plan["excluded"]}
                       for i, (n, w, l2, b, p, f) in enumerate(zip(names, plan["weights"], plan["log2"], plan["bytes"],
                                                                   plan["predicted_mse"], plan["features"]))]
    plan["base"] = base
    return plan
