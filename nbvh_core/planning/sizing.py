"""Model no more than a mesh needs: what it replaces, what it will cost, and which size to train.

* **What it replaces** (`mesh_resident_bytes`): a ray tracer keeps float32 vertices, int32 indices, float32
  vertex normals and a BVH with <= 4 triangles per leaf (32-byte nodes) resident before it traces one ray; the
  .nbvh model is traced as stored. What a user could ship instead is measured in `app/alternatives.py`.
* **Cheap predictor** (`mesh_features`, `predict_mse`): image MSE after training as a linear function in log
  space of the table size log2 T, properties of the mesh (how much its normals vary locally, triangle count) and
  the training budget (ln budget, and its product with log2 T: a larger table gains more from a longer budget),
  fitted on 84 measurements at 15-600 s by bench/fitting/fit_budget.py, then shifted to the presets' present shape by its own
  rows (`SizeFit.shape_shift`; bench/results/sizing_budget.md: leave-one-mesh-out errors); coefficients in
  sizing_fit.json.
* **Choice** (`resolve`, `choose_table_and_nodes`): a byte budget or a quality target turned into sizes: the
  (T, node count) of fewest file bytes whose predicted MSE meets the target; `pipeline.compress_mesh` trains it,
  measures and corrects (`decision.size_search`: up to TARGET_TRAININGS trainings, calibrated by each measurement).
  `choose_size` is the same over T alone (scenes).
* **Scenes** (`plan_scene`; the rule: `decision.scene_budget`): one byte budget over several meshes, shared by need: every mesh gets the
  smallest T that meets a common quality level (scaled by its weight, e.g. its size on screen), with the level
  set as strict as the budget allows.
"""
from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..geometry.bvh import build_full_tree, resident_bvh_nodes
from ..geometry.mesh import Mesh
from .mesh_measures import FEATURE_NAMES, GridMeasures, MeshFeatures, choose_resolution, mesh_features
from ..protocol.quality_levels import QUALITY_LEVELS  # noqa: F401  (re-exported)
from ..decision.scene_budget import split_budget
from .machine_rate import reference_budget_s, work_ratio
from .settings import PAPER_N_MAX, PRESETS, Settings, estimate_file_bytes
from ..decision.growth import SMALLEST_START
from ..decision.records import RunNote

FIT_PATH = Path(__file__).with_name("sizing_fit.json")
#: Table sizes the chooser considers (log2 T): the range the predictor was fitted on (bench/fitting/fit_budget.py: the
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


def mesh_resident_bytes(mesh: Mesh, tree=None) -> dict:
    """Bytes a ray tracer holds for `mesh`: vertices, indices, normals (float32 / int32, 12 B per vertex or
    triangle each), bvh (32-byte nodes, <= 4 triangles per leaf), total. tree: the mesh's `bvh.build_full_tree`
    when the caller has one (else it is built)."""
    nodes = resident_bvh_nodes(tree if tree is not None else build_full_tree(mesh), 4)
    out = {"vertices": mesh.n_vertices * 12, "indices": mesh.n_triangles * 12, "normals": mesh.n_vertices * 12,
           "bvh": nodes * 32}
    out["total"] = sum(out.values())
    return out


# -------------------------------------------------------------------------------------------------- predictor
def predictor_inputs(features: MeshFeatures, names: tuple | list = FEATURE_NAMES) -> np.ndarray:
    """The size predictor's inputs besides log2 T, by name (FEATURE_NAMES), from a mesh's measures."""
    values = {"log_area": math.log(max(features.area, 1e-6)), "occupancy": features.occupancy,
              "roughness": features.roughness, "log10_triangles": math.log10(max(features.triangles, 1))}
    return np.array([values[n] for n in names])


@dataclass
class SizeFit:
    """log(MSE) = coef . [1, log2 T, *features] for one method at one training budget; `features` names the
    mesh measures used (a subset of FEATURE_NAMES, chosen by leave-one-mesh-out error in bench/fitting/fit_sizing.py).
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
    #: fixed T, see bench/fitting/fit_sizing.py); 0 = not fitted (the node count stays at nodes_ref).
    nodes_coef: float = 0.0
    nodes_ref: int = 2047
    #: The training budget's effect (bench/fitting/fit_budget.py): log MSE changes by a L + c (log2 T - 10) L with
    #: L = ln(budget / train_s), [a, c] = budget_coef (a larger table gains more from a longer budget); [] = not
    #: fitted (predictions are for train_s seconds).
    budget_coef: list = field(default_factory=list)
    #: ln of the presets' present shape's MSE over what the slopes predict (fitted on its own rows, bench/fitting/fit_budget.py:
    #: the slopes were measured on older shapes that need a larger table for the same MSE); added to every prediction.
    shape_shift: float = 0.0
    #: This machine's training seconds in the fit machine's (`machine_rate.work_ratio`; 1 as shipped): a budget is
    #: read as the work it buys here (`load_fit(device=...)` sets it).
    work_ratio: float = 1.0

    def predict_log_mse(self, log2_table: int, features: MeshFeatures, nodes: int | None = None,
                        budget_s: float | None = None) -> float:
        """ln of the image MSE a model of table 2^log2_table on a mesh with `features` reaches after `budget_s`
        seconds of training here (None: the fit's own train_s; read in the fit machine's seconds through
        `work_ratio`) at `nodes` BVH nodes (None: nodes_ref)."""
        x = np.concatenate([[1.0, float(log2_table)], predictor_inputs(features, self.features)])
        out = float(np.dot(self.coef, x)) + self.shape_shift
        if nodes is not None and self.nodes_coef:
            out += self.nodes_coef * (math.log2(nodes + 1) - math.log2(self.nodes_ref + 1))
        if budget_s and self.budget_coef:
            out += self.budget_slope(log2_table) * math.log(reference_budget_s(budget_s, self.work_ratio)
                                                           / self.train_s)
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
    x = np.array([np.concatenate([[1.0, float(l2)], predictor_inputs(f, features)]) for l2, f, _ in rows])
    y = np.log(np.array([m for _, _, m in rows]))
    a = x.T @ x + ridge * np.eye(x.shape[1])
    coef = np.linalg.solve(a, x.T @ y)
    resid = y - x @ coef
    return SizeFit(method=method, train_s=train_s, coef=coef.tolist(), residual_std=float(np.std(resid)),
                   features=list(features))


def load_fit(path: Path = FIT_PATH, device: str | None = None) -> SizeFit | None:
    """The shipped fit (bench/fitting/fit_sizing.py writes it); None when missing or unreadable. device: the training's
    ('auto', 'cpu', 'cuda'): the fit then reads budgets as the work they buy there (`machine_rate.work_ratio`, a
    probe of a few seconds once per machine); None: as fitted."""
    try:
        fit = SizeFit(**json.loads(Path(path).read_text()))
    except (OSError, ValueError, TypeError):
        return None
    if device is not None:
        fit.work_ratio = work_ratio(device)
    return fit


def predict_mse(fit: SizeFit, log2_table: int, features: MeshFeatures, nodes: int | None = None,
                budget_s: float | None = None) -> float:
    """exp(`SizeFit.predict_log_mse`)."""
    return math.exp(fit.predict_log_mse(log2_table, features, nodes, budget_s))


def predictions(fit: SizeFit | None, features: MeshFeatures | None, sizes, nodes: int | None = None,
                budget_s: float | None = None) -> dict:
    """{log2 T: ln image MSE} the predictor expects at each of `sizes` (nodes None: the fitted count; budget_s None:
    the fitted budget); empty without a fit."""
    if fit is None or features is None:
        return {}
    return {l2: fit.predict_log_mse(l2, features, nodes, budget_s) for l2 in sizes}


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




@dataclass(frozen=True)
class SizedRequest:
    """A request with its sizes chosen (`size_request`): settings (sizes and grid resolution concrete), notes (why:
    the choice, and how this machine's budget reads to the predictor), fit (the size predictor, read as this machine's work; None without a target or a shipped fit), features
    (the mesh's measures the predictor reads; None without a fit) and, with a target, expected_log2_table (the table
    the predictor expects to meet it, `expected_table`), and resolutions {log2 T: the grid's finest resolution for
    the mesh at that table} over every size such a run may train, when the grid follows the mesh (`grid`)."""

    settings: Settings
    notes: tuple[RunNote, ...]
    fit: SizeFit | None = None
    features: MeshFeatures | None = None
    expected_log2_table: int | None = None
    resolutions: dict = field(default_factory=dict, compare=False)


def size_request(s: Settings, mesh: Mesh, grid: GridMeasures | None = None, resumed: bool = False) -> SizedRequest:
    """The one sizing of a run (`run_config.plan_run`): the size predictor loaded once (with a target), the mesh
    measured once, the sizes chosen (`resolve`) and the table the predictor expects. resumed: the checkpoint's sizes
    stand (its target only decides: checks and the final verdict)."""
    fit = load_fit(device=s.device) if s.target_mse is not None and not resumed else None
    feats = None
    if fit is not None:  # taken with the grid's measures when the plan has them: one pass over the mesh
        feats = grid.features if grid is not None and grid.features is not None else mesh_features(mesh)
    chosen, why = resolve(dataclasses.replace(s, target_mse=None) if resumed else s, mesh, grid, feats, fit)
    notes = (RunNote("plan", why),)
    if resumed:
        return SizedRequest(dataclasses.replace(chosen, target_mse=s.target_mse), notes)
    if fit is not None and fit.work_ratio != 1.0 and chosen.time_limit_s:
        notes += (RunNote("plan", f"this machine trains {fit.work_ratio:.3g}x as fast as the one the size predictor "
                                  f"was fitted on: its {chosen.time_limit_s:g} s budget is read as "
                                  f"{reference_budget_s(chosen.time_limit_s, fit.work_ratio):.0f} s of that "
                                  f"machine's work"),)
    resolutions = ({l2: choose_resolution(grid, l2)[0] for l2 in range(SMALLEST_START, LOG2_RANGE[-1] + 1)}
                   if grid is not None and chosen.target_mse is not None else {})
    return SizedRequest(chosen, notes, fit, feats, expected_table(chosen, mesh, feats, fit), resolutions)


@dataclass(frozen=True)
class Forecast:
    """The size predictor's word on a planned run with a target (empty without a fit): log_mse {log2 T: ln MSE} at
    the fitted node count and the training's budget (the retrain search's guide); growth_log_mse {log2 T: ln MSE} at
    the run's node count on the growth's clock, and budget_slopes {log2 T: d ln MSE / d ln time} (None when the fit
    has no budget term): what a growing training's checks read."""

    log_mse: dict
    growth_log_mse: dict
    budget_slopes: dict | None


def forecast(sized: SizedRequest, searched, reach, nodes: int, budget_s: float | None, clock_s: float) -> Forecast:
    """`Forecast` of the run `sized` plans: `searched` and `reach` the table sizes of the search and the growth."""
    fit, feats = sized.fit, sized.features
    slopes = {l2: fit.budget_slope(l2) for l2 in reach} if fit is not None and fit.budget_coef else None
    return Forecast(predictions(fit, feats, searched, None, budget_s), predictions(fit, feats, reach, nodes, clock_s),
                    slopes)


def resolve(s: Settings, mesh: Mesh | None = None, grid: GridMeasures | None = None,
            features: MeshFeatures | None = None, fit: SizeFit | None = None) -> tuple[Settings, str]:
    """Turn a byte budget or a quality target into concrete sizes; returns (settings, why).

    Budget: the largest (T, nodes) of the grid T in 2^5..2^13, nodes in 255..8191 whose file fits the budget
    (largest file first, ties to more nodes). Target (with the mesh and the size predictor `fit`): the method the
    predictor was fitted for (sizing_fit.json: HashGrid + MLP + consistent labels) at the smallest T whose predicted
    MSE meets the target (`choose_table_and_nodes`); `compress_mesh` then measures and corrects
    (`decision.size_search`); without a fit, the preset sizes of the target's level. n_max None: the grid's finest
    resolution is chosen for the mesh and the chosen T (`choose_resolution`; `grid`: its measures when the caller
    has them). features: `mesh_features(mesh)` when the caller has them.
    """
    free_grid = s.n_max is None
    sized = dataclasses.replace(s, n_max=PAPER_N_MAX) if free_grid else s
    if sized.budget_kb is not None:
        chosen, why = _for_budget(sized)
    elif sized.target_mse is not None:
        chosen, why = _for_target(sized, mesh, features, fit)
    else:
        chosen, why = sized, "fixed settings"
    if not free_grid:
        return chosen, why
    if mesh is None:
        return chosen, f"{why}; grid N_max {PAPER_N_MAX} (no mesh to measure)"
    n_max, grid_why = choose_resolution(grid or mesh, chosen.log2_table)
    return dataclasses.replace(chosen, n_max=n_max), f"{why}; {grid_why}"


def _for_budget(s: Settings) -> tuple[Settings, str]:
    """The largest grid point (T, nodes) whose file fits `s.budget_kb`."""
    budget = s.budget_kb * 1024
    best = None
    for log2 in range(LOG2_RANGE[-1], 4, -1):
        for nodes in (8191, 4095, 2047, 1023, 511, 255):
            cand = dataclasses.replace(s, log2_table=log2, nodes=nodes, budget_kb=None)
            size = estimate_file_bytes(cand)
            if size <= budget and (best is None or size > best[0]):
                best = (size, cand)
    if best is None:
        smallest = estimate_file_bytes(dataclasses.replace(s, log2_table=5, nodes=255))
        raise ValueError(f"a budget of {s.budget_kb:g} KB is too small for any model (the smallest needs "
                         f"{smallest / 1024:.0f} KB)")
    size, chosen = best
    return chosen, (f"budget {s.budget_kb:g} KB: chose T=2^{chosen.log2_table}, {chosen.nodes} nodes "
                    f"(estimated {size / 1024:.1f} KB), the largest grid point that fits")


def _for_target(s: Settings, mesh: Mesh | None, features: MeshFeatures | None,
                fit: SizeFit | None) -> tuple[Settings, str]:
    """The smallest file the predictor expects to meet `s.target_mse` (with its safety factor), or the preset sizes
    of the target's level without a fit or a mesh."""
    if s.target_mse <= 0:
        raise ValueError(f"target MSE must be > 0, got {s.target_mse:g}")
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


def expected_table(s: Settings, mesh: Mesh, features: MeshFeatures | None, fit: SizeFit | None) -> int | None:
    """log2 T of the smallest file the predictor `fit` expects to meet `s.target_mse` on `mesh` (its median
    prediction: no safety factor; the node count as `resolve` chooses it; the largest size when none does): the model
    the verdict before training weighs against the decimation measured at the target, since both then stand at the
    level (the safety factor only says where a training starts). features: `mesh_features(mesh)` when the caller has
    them. None without a target, a mesh or a fit."""
    if s.target_mse is None or mesh is None or fit is None:
        return None
    size_of = lambda lt, n: estimate_file_bytes(dataclasses.replace(s, log2_table=lt, nodes=n))  # noqa: E731
    l2, _, _, _ = choose_table_and_nodes(fit, features or mesh_features(mesh), s.target_mse, size_of,
                                         s.time_limit_s, safety=1.0)
    return l2


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
    fit = fit or load_fit(device=settings.device)
    if fit is None:
        raise ValueError("a scene budget needs the size predictor (nbvh_core/planning/sizing_fit.json), which is missing; "
                         "run bench/fitting/fit_sizing.py")
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
