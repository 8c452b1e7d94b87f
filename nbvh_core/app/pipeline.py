"""mesh -> BVH -> training -> quality check -> .nbvh file: the one function the CLI, the add-on's job and the
benchmarks call (`compress_mesh`). What a run is asked to do (Settings, presets) lives in `settings.py`, how big a
model to train in `sizing.py`; both are re-exported here for callers that only need this module.
"""
from __future__ import annotations

import copy
import dataclasses
import json
import math
import platform
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, NamedTuple

import numpy as np
import torch

from ..neural.appearance import AppearanceConfig, finalize_head, make_head
from ..training.appearance_training import SurfaceLabels, train_head
from ..geometry.bvh import NODE_DTYPE, build_bvh
from ..protocol.events import EventSink, null_sink
from ..geometry.exact import ExactTracer
from ..storage.fileformat import component_bytes, encode_nbvh, write_atomic
from ..geometry.mesh import Mesh
from ..rendering.metrics import Quality, evaluate, reference_views
from ..neural.model import NeuralBVH
from ..protocol.process import Cancelled, NotWorthCompressing, TrainingDiverged
from ..neural.quantize import snap_nodes
from ..planning.settings import PRESETS, Settings, estimate_file_bytes, preset  # noqa: F401  (re-exported)
from ..planning import sizing
from ..planning.sizing import (LOG2_RANGE, assess, choose_resolution, grid_measures, load_fit, mesh_features, resolve,
                               search_size)
from ..training.train import TrainResult, train

#: A diverged training restarts from scratch at a 10x lower learning rate, at most this many times.
DIVERGENCE_RETRIES = 2
#: Training with a target stops early once a check's MSE (`_QualityCheck`: the evaluation's views, the model at its
#: stored precision) is below this fraction of the target: the margin is for the training still moving between the
#: check and the end, and the evaluation after it confirms or not.
EARLY_STOP_MARGIN = 0.9
#: size_search "grow": the training starts this many table sizes below the predicted one; at each check (every
#: budget / GROW_CHECKS seconds, at most target_check_every_s) the MSE is projected to the end of the budget with
#: the size predictor's own budget exponent at this T (`SizeFit.budget_slope`), and the table grows when the
#: projection misses the target. The exponent, not the slope between the last two checks: the learning rate decays
#: over the budget, so a run's MSE falls faster at its end than mid-way (the spiky sphere at 2^12: 0.00062 and
#: 0.00060 at 72 s and 89 s of 200 s, projected 0.00053 by those two, a miss; a fixed 2^12 run ends at 0.00042),
#: and the two-point rule grew it to 2^13 (bench/results/need.csv). Measured on four meshes at the preview
#: budget with a 4-view check (bench/results/grow.md): growing on a
#: plateau (MSE falling < 15% between checks) grew too late on the spiky sphere (2^9 reached at 36 s of 60, MSE
#: 0.011 against 0.01); starting one size below the prediction, the gyroid never grew and kept 2^12 where 2^11
#: met the level (the predictor is pessimistic), so the start is two sizes below.
GROW_START_BELOW = 2
GROW_CHECKS = 12


@dataclass
class CompressResult:
    """What one run produced. `path` is None when nothing was written (no output path given)."""

    path: str | None
    file_bytes: int
    components: dict
    quality: Quality | None
    training: TrainResult
    settings: Settings
    seconds: dict = field(default_factory=dict)
    model: NeuralBVH | None = None
    tracer: ExactTracer | None = None  # the mesh's exact tracer, for callers that render the reference too
    why: str = ""
    target_met: bool | None = None
    assessment: dict = field(default_factory=dict)  # sizing.Assessment: is the model smaller than the mesh?
    data: bytes = b""  # the complete .nbvh file contents (written to `path` when one was given)

    def summary(self) -> dict:
        return {"path": self.path, "file_bytes": self.file_bytes, "components": self.components,
                "quality": self.quality.to_dict() if self.quality else None,
                "training": {k: v for k, v in dataclasses.asdict(self.training).items() if k != "history"},
                "settings": self.settings.to_dict(), "seconds": self.seconds, "why": self.why,
                "target_met": self.target_met, "assessment": self.assessment}


class _Trained(NamedTuple):
    """One training of compress_mesh's size search."""

    model: NeuralBVH
    result: TrainResult
    settings: Settings  # as used (a divergence restart lowers lr)
    restart_notes: str  # what the restarts add to `why`
    quality: Quality | None


def mesh_identity(mesh: Mesh) -> dict:
    """What a checkpoint records of its mesh, to refuse resuming on another one: counts and a content hash."""
    import hashlib

    h = hashlib.sha256(mesh.vertices.tobytes())
    h.update(mesh.faces.tobytes())
    return {"triangles": mesh.n_triangles, "vertices": mesh.n_vertices, "sha256": h.hexdigest()}


def resume_settings(checkpoint_path: str | Path, mesh: Mesh) -> Settings:
    """The settings a checkpoint was training with (a fixed size: the resumed run trains that one model), after
    checking it belongs to `mesh`. The file is read as data (`checkpoint.read_checkpoint`: never unpickled).
    Raises ValueError (one line) for a foreign, damaged, crafted or mismatched checkpoint."""
    from ..storage.checkpoint import read_checkpoint
    from ..planning.settings import settings_from_dict

    ck = read_checkpoint(checkpoint_path)
    extra = ck.header["extra"]
    if not isinstance(extra.get("settings"), dict) or not isinstance(extra.get("mesh"), dict):
        raise ValueError(f"{checkpoint_path}: the checkpoint names no settings or mesh (not a compress run's)")
    settings = settings_from_dict(extra["settings"], f"{checkpoint_path}: checkpoint settings")
    # The model the settings describe must be the one whose tensors the file holds: sized on the meta device
    # (nothing allocated), so settings crafted to ask for a huge model are refused before it is built.
    with torch.device("meta"):
        meta_model = NeuralBVH(np.zeros(settings.nodes, NODE_DTYPE), settings.model_config())
    # HashVQAD's index logits go at the freeze: the table and the network are in every checkpoint
    wanted = sum(p.numel() * p.element_size() for n, p in meta_model.named_parameters() if not n.endswith("logits"))
    held = sum(t.numel() * t.element_size() for k, t in ck.tensors.items() if k.startswith("model."))
    if wanted > held:
        raise ValueError(f"{checkpoint_path}: the checkpoint's settings describe a {wanted} B model but it holds "
                         f"{held} B of model tensors")
    if extra.get("mesh") != mesh_identity(mesh):
        triangles = extra["mesh"].get("triangles")
        raise ValueError(f"{checkpoint_path}: the checkpoint was made for another mesh "
                         f"({str(triangles)[:20]} triangles; this one has {mesh.n_triangles})")
    return dataclasses.replace(settings, target_mse=None, budget_kb=None)


class _QualityCheck:
    """The checks during a training with a target: the evaluation's own metric, views and resolution, on a copy of
    the model at the precision its file will store (so a check reads what the final evaluation will: a 4-view 64 px
    check read 1.06-1.23x the full MSE and grew tables too early; the float32 model read 4.7% (spiky sphere) to 18%
    (bunny, its table grown late) below the stored one), with the exact images rendered once per run
    (`metrics.reference_views`)."""

    def __init__(self, tracer, views: int, resolution: int, storage):
        self.tracer, self.views, self.resolution, self.storage = tracer, views, resolution, storage
        self._reference = None

    def mse(self, model) -> float:
        """The image MSE of `model` as its file would hold it now (the training's own model is left as it is)."""
        if self._reference is None:
            self._reference = reference_views(self.tracer, self.views, self.resolution)
        stored = copy.deepcopy(model)
        stored.eval()
        stored.finalize_storage(self.storage)
        with torch.no_grad():
            return evaluate(stored, self.tracer, self.views, self.resolution, reference=self._reference)[0].mse


def _target_check(check: _QualityCheck, target: float):
    """The early-stop callback for a target MSE (see EARLY_STOP_MARGIN)."""
    def reached(model) -> bool:
        return check.mse(model) <= EARLY_STOP_MARGIN * target
    return reached


def _grow_check(check: _QualityCheck, target: float, max_log2: int, budget_s: float, budget_slope=None):
    """The callback of a growing training (size_search "grow"): True once the check's MSE is below EARLY_STOP_MARGIN
    x the target; "grow" when, at a size below 2^max_log2, the MSE projected to the end of the budget `budget_s`
    (seconds since the callback was made, ~ since training started) misses the target. The projection is
    MSE x (budget / now)^budget_slope(log2 T) (the size predictor's exponent, see GROW_START_BELOW); without one,
    the power law through the last two checks at this size."""
    start = time.perf_counter()

    def projected(points: list[tuple[float, float]], log2: int) -> float | None:
        """The MSE at the end of the budget from this size's checks [(seconds, MSE)]; None: not enough checks."""
        t, m = max(points[-1][0], 1e-6), points[-1][1]
        if budget_slope is not None:
            slope = budget_slope(log2)
        elif len(points) < 2:
            return None
        else:
            t1, m1 = points[-2]
            if m >= m1:  # no progress at this size
                return math.inf
            slope = math.log(m / m1) / math.log(t / max(t1, 1e-6))  # t is already >= 1e-6
        return m * (max(budget_s, t) / t) ** slope

    def decide(model) -> bool | str:
        mse = check.mse(model)
        log2 = model.cfg.encoding.log2_table
        decide.history.append((time.perf_counter() - start, log2, mse))
        if mse <= EARLY_STOP_MARGIN * target:
            return True
        if log2 >= max_log2:
            return False
        at_end = projected([(sec, m) for sec, l2, m in decide.history if l2 == log2], log2)
        # Grow only for a projected miss of the level itself: the margin is for stopping on a noisy check (aiming
        # growth at it grew the gyroid and the studs past the size that met the level).
        return "grow" if at_end is not None and at_end > target else False
    decide.history = []  # (seconds, log2 T, MSE) of every check: TrainResult.checks (seconds rounded there)
    return decide


def _train_with_restarts(mesh, bvh, tracer, settings, why, events, should_cancel, checkpoint_path, resume_from=None,
                         target_reached=None):
    """Train a fresh model (or resume `resume_from`); on divergence restart from scratch at a 10x lower learning rate
    (at most DIVERGENCE_RETRIES times). Returns (model, TrainResult, settings actually used, why)."""
    for attempt in range(DIVERGENCE_RETRIES + 1):
        model = NeuralBVH(bvh.nodes, settings.model_config(), mesh.transform)
        try:
            extra = {"settings": settings.to_dict(), "mesh": mesh_identity(mesh)}
            tr = train(model, bvh, tracer, settings.train_config(), events=events, should_cancel=should_cancel,
                       checkpoint_path=checkpoint_path, resume_from=resume_from if attempt == 0 else None,
                       checkpoint_extra=extra, target_reached=target_reached)
            return model, tr, settings, why
        except TrainingDiverged as exc:
            if attempt == DIVERGENCE_RETRIES:
                raise TrainingDiverged(f"{exc} (after {attempt} restarts at lower learning rates)") from None
            lower = settings.lr * 0.1
            why += f"; training diverged at lr {settings.lr:g} ({exc}), restarted at lr {lower:g}"
            events({"event": "warning", "message": f"training diverged ({exc}); restarting from scratch with the "
                                                   f"learning rate {settings.lr:g} -> {lower:g}"})
            settings = dataclasses.replace(settings, lr=lower)
    raise AssertionError("unreachable")


def _verdict(mesh: Mesh, settings: Settings, why: str, tracer: ExactTracer, events: EventSink,
             seconds: dict) -> "sizing.Assessment":
    """Is the model worth training (`sizing.assess`)? Raises NotWorthCompressing unless forced; in seconds."""
    t = time.perf_counter()
    events({"event": "phase", "phase": "plan", "message": why})
    assessment = assess(mesh, settings, measure_alternatives=settings.target_mse is not None, tracer=tracer)
    seconds["plan"] = time.perf_counter() - t
    if not assessment.worth_compressing:
        if not settings.force:
            events({"event": "verdict", "worth_compressing": False, "message": assessment.message,
                    "assessment": assessment.to_dict()})
            raise NotWorthCompressing(assessment)
        events({"event": "warning", "message": assessment.message + " (training anyway: forced)"})
    return assessment


def _training_bvh(mesh: Mesh, settings: Settings, events: EventSink, seconds: dict):
    """The BVH the model is trained on: `settings.nodes` nodes, snapped to 8-bit boxes when the file stores them
    so (each contains its exact box). A size search retrains with another T only, never another node count."""
    t = time.perf_counter()
    events({"event": "phase", "phase": "bvh", "message": f"{mesh.n_triangles} triangles -> {settings.nodes} nodes"})
    bvh = build_bvh(mesh, settings.nodes)
    if settings.node_bits == 8:
        bvh = dataclasses.replace(bvh, nodes=snap_nodes(bvh.nodes))
    seconds["bvh"] = time.perf_counter() - t
    return bvh


class _SizeSearch:
    """The trainings of one compress_mesh call: one at the resolved size, or with a target MSE the
    predict-train-measure-correct search over T (`sizing.search_size`, at most TARGET_TRAININGS). Each training is
    finalized to the stored precision and scored; `trained[log2 T]` keeps them all."""

    def __init__(self, mesh, bvh, tracer, settings: Settings, why: str, events, should_cancel, checkpoint_path,
                 resume_from, evaluate_quality: bool, compare_float32: bool, seconds: dict, grid=None):
        self.mesh, self.bvh, self.tracer, self.settings, self.why = mesh, bvh, tracer, settings, why
        self.grid = grid  # sizing.GridMeasures when N_max follows the mesh (re-chosen for every table size tried)
        self.events, self.should_cancel = events, should_cancel
        self.checkpoint_path, self.resume_from = checkpoint_path, resume_from
        self.evaluate_quality, self.compare_float32, self.seconds = evaluate_quality, compare_float32, seconds
        self.trained: dict[int, _Trained] = {}
        self.check = _QualityCheck(tracer, settings.eval_views, settings.eval_resolution, settings.storage())
        seconds.update(train=0.0, eval=0.0)

    def run(self) -> tuple[int, str]:
        """Train (and search); returns (the chosen log2 T, `why` with the search's trail)."""
        target = self.settings.target_mse
        if target is None or not self.evaluate_quality:
            self.train_and_measure(self.settings.log2_table)
            return self.settings.log2_table, self.why
        if self.settings.size_search == "grow":
            return self.grow()
        if self.settings.size_search != "retrain":
            raise ValueError(f"size_search must be 'retrain' or 'grow', got {self.settings.size_search!r}")
        fit = load_fit()
        feats = mesh_features(self.mesh) if fit is not None else None
        chosen, measured = search_size(fit, feats, target, self.settings.log2_table, self._measure_next,
                                       budget_s=self.settings.time_limit_s)
        why = self.why
        if len(measured) > 1:
            trail = ", ".join(f"T=2^{l2}: {mse:.4g}" for l2, mse in measured.items())
            why += f"; measured {trail} (target {target:g}): kept T=2^{chosen}"
        return chosen, why

    def grow(self) -> tuple[int, str]:
        """One training that starts GROW_START_BELOW sizes under the resolved T and grows its table while the quick
        checks say the target is out of reach at its size (up to one size above the resolved T); returns (the final
        log2 T, `why`)."""
        t = time.perf_counter()
        s = self.settings
        top = min(s.log2_table + 1, LOG2_RANGE[-1])  # never past the sizes the predictor knows
        start = max(6, s.log2_table - GROW_START_BELOW)
        budget = s.time_limit_s or 200.0
        s_start = dataclasses.replace(s, log2_table=start,
                                      target_check_every_s=min(s.target_check_every_s, budget / GROW_CHECKS))
        fit = load_fit()
        slope = fit.budget_slope if fit is not None and fit.budget_coef else None
        decide = _grow_check(self.check, s.target_mse, top, budget, slope)
        model, tr, s_used, why_used = _train_with_restarts(
            self.mesh, self.bvh, self.tracer, s_start, self.why, self.events, self.should_cancel,
            self.checkpoint_path, self.resume_from, decide)
        tr.checks = [(round(sec, 2), log2, mse) for sec, log2, mse in decide.history]
        final = model.cfg.encoding.log2_table
        s_used = dataclasses.replace(s_used, log2_table=final, target_check_every_s=s.target_check_every_s)
        trail = ", ".join(f"T=2^{log2} at {sec:g} s" for _, sec, log2 in tr.grew) or "no growth"
        why_used += (f"; one training from T=2^{start} growing its table to meet {s.target_mse:g}: {trail}"
                     + (f"; stopped after {tr.seconds:.0f} s, the target met" if tr.stopped_early else ""))
        self.seconds["train"] += time.perf_counter() - t
        self._keep(final, model, tr, s_used, why_used)
        return final, self.why

    def _keep(self, log2_table: int, model, tr, s_used: Settings, why_used: str) -> Quality | None:
        """Finalize a trained model to its stored precision, score it, keep it as `trained[log2_table]` (with the
        notes `why_used` adds to `why`); returns its quality (None without an evaluation)."""
        model.eval()
        if self.compare_float32 and self.evaluate_quality:  # the same training before its storage is quantized
            self.seconds["mse_float32"] = evaluate(model, self.tracer, s_used.eval_views, s_used.eval_resolution)[0].mse
        model.finalize_storage(s_used.storage())  # measure the model the file stores, not its float32 original
        quality = self._score(model, s_used) if self.evaluate_quality else None
        self.trained[log2_table] = _Trained(model, tr, s_used, why_used[len(self.why):], quality)
        return quality

    def _measure_next(self, log2_table: int) -> float:
        """A search step: says why this size comes next (after the first), then trains it."""
        if self.trained:
            target = self.settings.target_mse
            prev = list(self.trained)[-1]
            mse_prev = self.trained[prev].quality.mse
            verdict = "missed" if mse_prev > target else "met"
            step = "larger" if log2_table > prev else "smaller"
            self.events({"event": "warning" if verdict == "missed" else "phase", "phase": "search",
                         "message": f"measured MSE {mse_prev:.4g} {verdict} the target {target:g} at T=2^{prev}: "
                                    f"trying T=2^{log2_table} ({step})"})
        return self.train_and_measure(log2_table)

    def train_and_measure(self, log2_table: int) -> float:
        """One training at table size 2^log2_table, finalized and scored; its MSE (inf without an evaluation)."""
        t = time.perf_counter()
        s_try = dataclasses.replace(self.settings, log2_table=log2_table)
        if self.grid is not None and log2_table != self.settings.log2_table:
            s_try.n_max = choose_resolution(self.grid, log2_table)[0]
        target = s_try.target_mse
        stop = _target_check(self.check, target) if target is not None and self.evaluate_quality else None
        model, tr, s_used, why_used = _train_with_restarts(self.mesh, self.bvh, self.tracer, s_try, self.why,
                                                           self.events, self.should_cancel, self.checkpoint_path,
                                                           self.resume_from, stop)
        if tr.stopped_early:
            why_used += (f"; T=2^{log2_table}: training stopped after {tr.seconds:.0f} s of the "
                         f"{s_try.time_limit_s or 0:.0f} s budget, the target being met")
        self.seconds["train"] += time.perf_counter() - t
        quality = self._keep(log2_table, model, tr, s_used, why_used)
        return quality.mse if quality is not None else math.inf

    def _score(self, model: NeuralBVH, s: Settings) -> Quality:
        if self.should_cancel():
            raise Cancelled("cancelled before evaluation")
        self.events({"event": "phase", "phase": "eval", "message": f"{s.eval_views} views at {s.eval_resolution}px"})
        t = time.perf_counter()
        quality, _ = evaluate(model, self.tracer, s.eval_views, s.eval_resolution)
        self.seconds["eval"] += time.perf_counter() - t
        return quality


def _metadata(mesh: Mesh, settings: Settings, why: str, assessment, tr: TrainResult,
              quality: Quality | None) -> dict:
    """What the file's header records of the run: source, settings, why, verdict, training, quality, provenance."""
    training = {"steps": tr.steps, "seconds": round(tr.seconds, 2), "samples": tr.samples,
                "stopped_early": tr.stopped_early, "samples_per_s": round(tr.samples_per_s),
                "final_loss": tr.final_loss, "device": tr.device, "compute_path": tr.compute_path,  # the kernel plan, exactly
                "soft_loss_before_freeze": tr.soft_loss_before_freeze,
                "frozen_loss": tr.frozen_loss, "finetuned_loss": tr.finetuned_loss}
    q = quality.to_dict() if quality else None
    if q:
        q.pop("per_view_mse", None)
    return {"source": {"name": mesh.name, "triangles": mesh.n_triangles, "vertices": mesh.n_vertices},
            "settings": settings.to_dict(), "why": why, "assessment": assessment.to_dict(),
            "target_met": None if settings.target_mse is None or quality is None else quality.mse <= settings.target_mse,
            "training": training, "quality": q, "created": time.strftime("%Y-%m-%dT%H:%M:%S"),
            "torch": torch.__version__, "machine": platform.machine()}


def _appearance(model: NeuralBVH, mesh: Mesh, tracer: ExactTracer, settings: Settings, made, tr: TrainResult,
                events: EventSink, should_cancel, seconds: dict) -> dict:
    """Give the model the mesh's materials and, when its look needs one, train the appearance head (in
    `appearance_share` of the time budget, or that share of the geometry's training time when there is no budget)
    and hold it as the file stores it. Returns what the file's metadata records of it ({} for a bare shape)."""
    if mesh.look is None:
        return {}
    model.materials = list(mesh.look.materials)
    if made is not None and made[0].cfg.target == "colour":  # the colour is learnt: the images are not kept
        model.materials = [dataclasses.replace(m, image=None, _linear=None) for m in model.materials]
    if made is None:
        return {"slots": mesh.look.n_slots, "head": None}
    head, face_patch = made
    cfg = head.cfg
    share = settings.appearance_share
    budget = (settings.time_limit_s * share if settings.time_limit_s
              else max(1.0, tr.seconds * share / max(1 - share, 1e-6)))
    events({"event": "phase", "phase": "appearance",
            "message": f"{cfg.slots} material slot(s), {cfg.patches} patch(es)"
                       f"{', texture coordinates' if cfg.uv else ''}: {budget:.0f} s"})
    t = time.perf_counter()
    head = head.to(model.device)
    torch.manual_seed(settings.seed)
    labels = SurfaceLabels(mesh, tracer, np.random.default_rng(settings.seed + 1), face_patch,
                           colour=cfg.target == "colour")
    result = train_head(head, labels, budget, should_stop=should_cancel,
                        pool_size=1 << 19 if settings.time_limit_s else 1 << 15)
    if should_cancel():
        raise Cancelled("cancelled while training the appearance head")
    finalize_head(head, settings.table_bits, settings.network_bits)
    model.appearance = head
    seconds["appearance"] = time.perf_counter() - t
    return {"slots": cfg.slots, "patches": cfg.patches, "head": {"steps": result.steps, "seconds": round(result.seconds, 2),
                                         "final_loss": result.final_loss}}


def compress_mesh(mesh: Mesh, settings: Settings, out_path: str | Path | None = None,
                  events: EventSink = null_sink, should_cancel: Callable[[], bool] = lambda: False,
                  evaluate_quality: bool = True, checkpoint_path: str | Path | None = None,
                  compare_float32: bool = False, resume_from: str | Path | None = None) -> CompressResult:
    """Compress `mesh` with `settings`; write `out_path` (atomically) when given. Raises `process.Cancelled`,
    `process.TrainingDiverged` (nothing written in either case). compare_float32: also score each training before
    its storage is quantized (`seconds['mse_float32']`, for benchmarks). resume_from: a checkpoint of this mesh
    (`resume_settings` gives the settings it was made with; pass those). Raises NotWorthCompressing (in seconds,
    before any training) when the verdict says so and `settings.force` is off."""
    grid = grid_measures(mesh) if settings.n_max is None and resume_from is None else None
    settings, why = resolve(settings, mesh, grid)
    if resume_from is not None:
        why += f"; resumed from the checkpoint {resume_from}"
    seconds: dict = {}
    tracer = ExactTracer(mesh)  # one Embree scene for the alternatives, the labels and the evaluation
    assessment = _verdict(mesh, settings, why, tracer, events, seconds)
    head = make_head(mesh, AppearanceConfig(target=settings.appearance_target,
                                            log2_table=settings.appearance_log2_table))
    asked = settings
    if head is not None and settings.time_limit_s and resume_from is None:  # the head's share of the budget
        settings = dataclasses.replace(settings, time_limit_s=settings.time_limit_s * (1 - settings.appearance_share))
    bvh = _training_bvh(mesh, settings, events, seconds)
    search = _SizeSearch(mesh, bvh, tracer, settings, why, events, should_cancel, checkpoint_path, resume_from,
                         evaluate_quality, compare_float32, seconds, grid)
    chosen_log2, why = search.run()
    model, tr, settings, restart_notes, quality = search.trained[chosen_log2]
    why += restart_notes  # a restart at a lower learning rate, in the training kept
    if head is not None and asked is not settings:
        settings = dataclasses.replace(settings, time_limit_s=asked.time_limit_s)
    look_info = _appearance(model, mesh, tracer, settings, head, tr, events, should_cancel, seconds)
    metadata = _metadata(mesh, settings, why, assessment, tr, quality)
    if look_info:
        metadata["appearance"] = look_info
    data = encode_nbvh(model, metadata, settings.storage())
    size = len(data)
    if out_path is not None:
        if should_cancel():
            raise Cancelled("cancelled before saving")
        events({"event": "phase", "phase": "save", "message": str(out_path)})
        size = write_atomic(out_path, data)
    result = CompressResult(path=str(out_path) if out_path else None, file_bytes=size,
                            components=component_bytes(data), quality=quality, training=tr, settings=settings,
                            seconds={k: (v if k.startswith("mse") else round(v, 2)) for k, v in seconds.items()},
                            model=model, tracer=tracer, why=why,
                            target_met=metadata["target_met"], assessment=assessment.to_dict(), data=data)
    events({"event": "result", "path": result.path, "bytes": size,
            "quality": json.loads(json.dumps(metadata["quality"])), "train_seconds": round(tr.seconds, 2)})
    return result
