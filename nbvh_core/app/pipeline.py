"""mesh -> BVH -> training -> quality check -> .nbvh file: the one function the CLI, the add-on's job, library
batches and the benchmarks call (`compress_mesh`). What a run is asked (`Settings`, presets) is planned once into
its parts (`planning.run_config.plan_run` -> RunConfig); every stage below takes only its part. Settings and the
presets are re-exported here for callers that only need this module.
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

from ..neural.appearance import finalize_head, make_head
from ..training.appearance_training import SurfaceLabels, train_head
from ..geometry.bvh import NODE_DTYPE, build_bvh
from ..protocol.events import EventSink, null_sink
from ..protocol import events as wire
from ..geometry.exact import ExactTracer
from ..storage.fileformat import component_bytes, decode_nbvh, encode_nbvh, look_stored_bytes, write_atomic
from ..geometry.mesh import Mesh
from ..rendering.metrics import Quality, ViewScorer, view_sets
from ..neural.model import NeuralBVH
from ..protocol.process import Cancelled, NotWorthCompressing, TrainingDiverged
from ..neural.quantize import StorageConfig, snap_nodes
from ..planning.settings import PRESETS, Settings, estimate_file_bytes, preset  # noqa: F401  (re-exported)
from ..planning import sizing
from ..planning.run_config import LookConfig, RunConfig, plan_run
from ..planning.sizing import LOG2_RANGE, assess
from ..training.train import TrainResult, grid_phase_pending, state_form, train
from ..decision.alternative_curve import AlternativeCurve, CurvePoint
from ..decision.checks import CheckRule
from ..decision.growth import GrowthPlan
from ..decision.size_search import search_size
from ..decision.verdict import mesh_kept
from ..decision.records import Assessment, RunNote, why_of
from ..decision.final_verdict import final_verdict

#: A diverged training restarts from scratch at a 10x lower learning rate, at most this many times.
DIVERGENCE_RETRIES = 2


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
    assessment: dict = field(default_factory=dict)  # decision.records.Assessment: is the model smaller than the mesh?
    data: bytes = b""  # the complete .nbvh file contents (written to `path` when one was given)
    #: The decisions on measurements: every training check (decision.records.CheckDecision), the final verdict
    #: (FinalVerdict: the model as shipped against the alternative at the same held-out MSE) and that curve.
    decisions: dict = field(default_factory=dict)
    #: The file as shipped, decoded from its bytes with its look, on the held-out views: colour MSE and FLIP beside
    #: the geometry's MSE (for a bare shape the file is the model `quality` scored, at its stored precision).
    quality_as_shipped: Quality | None = None
    #: The run's account in order (decision.records.RunNote): the plan, a resume, restarts, growth, the search.
    notes: list = field(default_factory=list)

    def summary(self) -> dict:
        return {"path": self.path, "file_bytes": self.file_bytes, "components": self.components,
                "quality": self.quality.to_dict() if self.quality else None,
                "quality_as_shipped": self.quality_as_shipped.brief() if self.quality_as_shipped else None,
                "model_resident_bytes": self.model.resident_bytes() if self.model is not None else None,
                "training": {k: v for k, v in dataclasses.asdict(self.training).items() if k != "history"},
                "settings": self.settings.to_dict(), "seconds": self.seconds, "why": self.why,
                "notes": [n.to_dict() for n in self.notes],
                "target_met": self.target_met, "assessment": self.assessment, "decisions": self.decisions}


class _Trained(NamedTuple):
    """One training of compress_mesh's size search."""

    model: NeuralBVH
    result: TrainResult
    run: RunConfig  # as used (a divergence restart lowers lr; growth changes the table)
    notes: tuple  # what this training adds to the run's account (RunNote: restarts, growth, an early stop)
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


def _stored_mse(scorer: ViewScorer, storage):
    """score(model) for the training's checks: the image MSE of `model` as its file would hold it (a copy at its
    stored precision; the training's own model is left as it is): the float32 model read 4.7% (spiky sphere) to 18%
    (bunny, its table grown late) below the stored one. A low-bit table is scored at 8 bits until it trains through
    its own grid (`training.train.grid_phase_pending`): that last phase recovers the rounding (6 bits: +3.1% over
    the float model after it, 1.24x rounded without it; `tests/test_quantize.py`), and growth decided on the rounded
    score grew the bunny's table in both runs so scored (bench/results/target_runs.md, 5c9d155)."""
    def score(model) -> float:
        stored = copy.deepcopy(model)
        stored.eval()
        pending = grid_phase_pending(model, storage.table_bits)
        stored.finalize_storage(dataclasses.replace(storage, table_bits=8) if pending else storage)
        with torch.no_grad():
            return scorer.score_model(stored)[0].mse
    return score


def _train_with_restarts(mesh, bvh, tracer, run: RunConfig, events, should_cancel, checkpoint_path, resume_from=None,
                         target_reached=None) -> tuple[NeuralBVH, TrainResult, RunConfig, tuple]:
    """Train a fresh model (or resume `resume_from`); on divergence restart from scratch at a 10x lower learning rate
    (at most DIVERGENCE_RETRIES times; the checks start over with it). Returns (model, TrainResult, the run as used,
    the restarts' notes)."""
    notes: tuple = ()
    for attempt in range(DIVERGENCE_RETRIES + 1):
        if attempt and target_reached is not None:  # a CheckRule
            target_reached.start_over()
        model = NeuralBVH(bvh.nodes, run.model, mesh.transform)
        try:
            extra = {"settings": run.request.to_dict(), "mesh": mesh_identity(mesh)}
            tr = train(model, bvh, tracer, run.training, events=events, should_cancel=should_cancel,
                       checkpoint_path=checkpoint_path, resume_from=resume_from if attempt == 0 else None,
                       checkpoint_extra=extra, target_reached=target_reached)
            return model, tr, run, notes
        except TrainingDiverged as exc:
            if attempt == DIVERGENCE_RETRIES:
                raise TrainingDiverged(f"{exc} (after {attempt} restarts at lower learning rates)") from None
            lr = run.training.lr
            notes += (RunNote("restart", f"training diverged at lr {lr:g} ({exc}), restarted at lr {lr * 0.1:g}"),)
            events(wire.warning(message=f"training diverged ({exc}); restarting from scratch with the "
                                        f"learning rate {lr:g} -> {lr * 0.1:g}"))
            run = run.with_training(lr=lr * 0.1)
    raise AssertionError("unreachable")


def _shipped_materials(mesh: Mesh, made) -> list:
    """The slots' materials as the file keeps them: without their images when the head `made` learns the colour."""
    materials = list(mesh.look.materials)
    if made is not None and made[0].cfg.target == "colour":  # the colour is learnt: the images are not kept
        materials = [dataclasses.replace(m, image=None, _linear=None) for m in materials]
    return materials


@dataclass
class Weighing:
    """What a run's decisions are measured and weighed with: the check views and the held-out views (one metric for
    every contender), the alternative's curve on each (None without a target), and the bytes the asset's look adds
    to every model (appearance head and textures, as stored)."""

    checks: ViewScorer
    held_out: ViewScorer
    curve: AlternativeCurve | None = None
    curve_held_out: AlternativeCurve | None = None
    look_bytes: int = 0


def weigh(mesh: Mesh, run: RunConfig, tracer: ExactTracer, made=None) -> tuple[Assessment, Weighing]:
    """The verdict before training, the same for a run and a library batch's measurement: the model `run` plans,
    with what its file adds for the asset's look (the head `made`, `make_head`; the images it keeps), weighed
    against the mesh and, with a target, the measured decimations (`sizing.assess`, on the run's view sets). With a
    target the model is weighed at the size the predictor expects to meet it (`RunConfig.expected_log2_table`, no
    safety factor), as the decimation is weighed at the target: the safety factor says where training starts, and
    the checks weigh every size the training reaches against the measured alternative."""
    expected = run.expected_log2_table
    model_bytes = run.at_table(expected, regrid=False).file_bytes if expected is not None else run.file_bytes
    checks, held_out = view_sets(tracer, mesh.transform, run.metric)
    look_bytes = 0
    if mesh.look is not None:
        look_bytes = sum(look_stored_bytes(made[0].cfg if made else None, _shipped_materials(mesh, made),
                                           run.storage).values())
    measured = run.decision.target_mse is not None
    assessment = assess(mesh, model_bytes, run.decision, checks if measured else None, held_out, look_bytes)
    return assessment, Weighing(checks, held_out, AlternativeCurve.from_alternatives(assessment.alternatives),
                                AlternativeCurve.from_alternatives(assessment.alternatives, held_out=True), look_bytes)


def _verdict(mesh: Mesh, run: RunConfig, tracer: ExactTracer, made, events: EventSink, seconds: dict):
    """Is the model worth training (`weigh`)? Raises NotWorthCompressing unless forced; returns (Assessment,
    Weighing); in seconds['plan']."""
    t = time.perf_counter()
    events(wire.phase(phase="plan", message=why_of(run.notes)))
    assessment, weighing = weigh(mesh, run, tracer, made)
    seconds["plan"] = time.perf_counter() - t
    if not assessment.worth_compressing:
        if not run.decision.force:
            events(wire.verdict(worth_compressing=False, message=assessment.message, assessment=assessment.to_dict()))
            raise NotWorthCompressing(assessment)
        events(wire.warning(message=assessment.message + " (training anyway: forced)"))
    return assessment, weighing


def _measure_decimation(mesh: Mesh, weighing: Weighing, assessment):
    """measure(triangles) -> CurvePoint for the final verdict: one more decimation scored on the held-out views
    (and recorded with the others, so the one that ships can be written)."""
    def measure(count: int) -> CurvePoint:
        entry = sizing.decimation_entry(mesh, count, weighing.checks, weighing.held_out, None)
        if not entry["triangles"]:
            return CurvePoint(2 ** 62, math.inf, 0, count)
        assessment.alternatives.setdefault("decimations_tried", []).append(entry)
        return CurvePoint.from_entry(entry, held_out=True)
    return measure


def _keep_the_mesh(assessment, verdict, events: EventSink, checks: list):
    """NotWorthCompressing for a decision taken on measurements (a check's or the final verdict's): the assessment
    now recommends the measured decimation (or the whole mesh) that the CLI writes, with the training's `checks`
    (`decision.verdict.mesh_kept`)."""
    kept = mesh_kept(assessment, verdict, checks)
    events(wire.verdict(worth_compressing=False, message=kept.message, assessment=kept.to_dict()))
    return NotWorthCompressing(kept)


def _training_bvh(mesh: Mesh, nodes: int, node_bits: int, events: EventSink, seconds: dict):
    """The BVH the model is trained on: `nodes` nodes, snapped to 8-bit boxes when the file stores them so
    (node_bits 8: each contains its exact box). A size search retrains with another T only, never another node
    count."""
    t = time.perf_counter()
    events(wire.phase(phase="bvh", message=f"{mesh.n_triangles} triangles -> {nodes} nodes"))
    bvh = build_bvh(mesh, nodes)
    if node_bits == 8:
        bvh = dataclasses.replace(bvh, nodes=snap_nodes(bvh.nodes))
    seconds["bvh"] = time.perf_counter() - t
    return bvh


class _SizeSearch:
    """The trainings of one compress_mesh call: one at the planned size, or with a target MSE one growing training
    (`grow`, the default: `decision.checks.CheckRule`) or the predict-train-measure-correct search over T
    (`decision.size_search`, at most TARGET_TRAININGS). Each training is finalized to the stored precision and scored
    on the held-out views; `trained[log2 T]` keeps them all, `notes` the search's own account."""

    def __init__(self, mesh, bvh, tracer, run: RunConfig, events, should_cancel, checkpoint_path, resume_from,
                 evaluate_quality: bool, compare_float32: bool, seconds: dict, weighing: Weighing):
        self.mesh, self.bvh, self.tracer, self.run = mesh, bvh, tracer, run
        self.events, self.should_cancel = events, should_cancel
        self.checkpoint_path, self.resume_from = checkpoint_path, resume_from
        self.evaluate_quality, self.compare_float32, self.seconds = evaluate_quality, compare_float32, seconds
        self.weighing = weighing
        self.trained: dict[int, _Trained] = {}
        self.notes: list[RunNote] = []
        self.rule: CheckRule | None = None  # the growing training's checks, once it ran
        self.check_views_mse: float | None = None  # the kept model on the check views (the report gives both)
        self.score_stored = _stored_mse(weighing.checks, run.storage)
        seconds.update(train=0.0, eval=0.0)

    def search(self) -> int:
        """Train (and search); returns the chosen log2 T."""
        target, run = self.run.decision.target_mse, self.run
        if target is None or not self.evaluate_quality:
            self.train_and_measure(run.log2_table)
            return run.log2_table
        if run.decision.size_search == "grow":
            return self.grow()
        predict = run.predicted_log_mse.__getitem__ if run.predicted_log_mse else None
        chosen, measured = search_size(predict, target, run.log2_table, self._measure_next, LOG2_RANGE)
        if len(measured) > 1:
            trail = ", ".join(f"T=2^{l2}: {mse:.4g}" for l2, mse in measured.items())
            self.notes.append(RunNote("search", f"measured {trail} (target {target:g}): kept T=2^{chosen}"))
        return chosen

    def shipped_form(self, model: NeuralBVH) -> bool:
        """Whether a check may stop `model`'s training: its table is in the form the file stores (`CheckRule`)."""
        return not grid_phase_pending(model, self.run.storage.table_bits)

    def bytes_at(self, log2_table: int) -> int:
        """The file's bytes at table size 2^log2_table as it ships: geometry, look, header."""
        return self.run.at_table(log2_table, regrid=False).file_bytes + self.weighing.look_bytes

    def _rule(self, growth: GrowthPlan) -> CheckRule:
        """The growing training's checks: the plan's predicted time slopes and growth gains (none without a size
        fit), the file's bytes at each size, the alternative's curve on the check views."""
        run = self.run
        slope = growth.budget_slopes.__getitem__ if growth.budget_slopes else None
        gain = growth.grow_gains.__getitem__ if growth.grow_gains else None
        return CheckRule(self.score_stored, run.decision.target_mse, growth.max_log2, growth.budget_s, self.bytes_at,
                         self.weighing.curve, slope, gain, run.decision.force, self.shipped_form, state_form)

    def grow(self) -> int:
        """One training that starts below the planned T and grows its table while the checks say growing pays
        (`RunConfig.growth`); returns the final log2 T."""
        t = time.perf_counter()
        run, growth = self.run, self.run.growth
        run_start = run.at_table(growth.start_log2, regrid=False).with_training(
            target_check_every_s=growth.check_every_s)
        self.rule = rule = self._rule(growth)
        model, tr, run_used, notes = _train_with_restarts(self.mesh, self.bvh, self.tracer, run_start, self.events,
                                                          self.should_cancel, self.checkpoint_path, self.resume_from,
                                                          rule)
        tr.checks = [(d.seconds, d.log2_table, d.mse) for d in rule.decisions]
        final = model.cfg.encoding.log2_table
        run_used = run_used.at_table(final, regrid=False).with_training(target_check_every_s=run.decision.check_every_s)
        trail = ", ".join(f"T=2^{log2} at {sec:g} s" for _, sec, log2 in tr.grew) or "no growth"
        notes += (RunNote("growth", f"one training from T=2^{growth.start_log2} growing its table to meet "
                                    f"{run.decision.target_mse:g}: {trail}"),)
        if tr.stopped_early:
            notes += (RunNote("early stop", f"stopped after {tr.seconds:.0f} s: {rule.decisions[-1].action}"),)
        self.seconds["train"] += time.perf_counter() - t
        if rule.keep_mesh is not None:  # nothing worth finishing: the verdict is the mesh
            self.trained[final] = _Trained(model, tr, run_used, notes, None)
            return final
        self._keep(final, model, tr, run_used, notes)
        return final

    def _keep(self, log2_table: int, model, tr, run_used: RunConfig, notes: tuple) -> Quality | None:
        """Finalize a trained model to its stored precision, score it, keep it as `trained[log2_table]` (with its
        notes); returns its quality (None without an evaluation)."""
        model.eval()
        if self.compare_float32 and self.evaluate_quality:  # the same training before its storage is quantized
            self.seconds["mse_float32"] = self.weighing.held_out.score_model(model)[0].mse
        model.finalize_storage(run_used.storage)  # measure the model the file stores, not its float32 original
        quality = self._score(model) if self.evaluate_quality else None
        if quality is not None and run_used.decision.target_mse is not None:  # the same model on the check views
            self.check_views_mse = self.weighing.checks.score_model(model)[0].mse
        self.trained[log2_table] = _Trained(model, tr, run_used, notes, quality)
        return quality

    def _measure_next(self, log2_table: int) -> float:
        """A search step: says why this size comes next (after the first), then trains it."""
        if self.trained:
            target = self.run.decision.target_mse
            prev = list(self.trained)[-1]
            mse_prev = self.trained[prev].quality.mse
            verdict = "missed" if mse_prev > target else "met"
            step = "larger" if log2_table > prev else "smaller"
            said = wire.warning if verdict == "missed" else wire.phase
            self.events(said(phase="search", message=f"measured MSE {mse_prev:.4g} {verdict} the target {target:g} "
                                                     f"at T=2^{prev}: trying T=2^{log2_table} ({step})"))
        return self.train_and_measure(log2_table)

    def train_and_measure(self, log2_table: int) -> float:
        """One training at table size 2^log2_table, finalized and scored; its MSE (inf without an evaluation)."""
        t = time.perf_counter()
        run_try = self.run if log2_table == self.run.log2_table else self.run.at_table(log2_table)
        target, budget = run_try.decision.target_mse, run_try.training.time_limit_s or 0.0
        # a fixed size: the checks only stop the training once the level is met (no growth, no alternative)
        stop = (CheckRule(self.score_stored, target, log2_table, budget, self.bytes_at, shipped_form=self.shipped_form,
                          state_form=state_form) if target is not None and self.evaluate_quality else None)
        model, tr, run_used, notes = _train_with_restarts(self.mesh, self.bvh, self.tracer, run_try, self.events,
                                                          self.should_cancel, self.checkpoint_path, self.resume_from,
                                                          stop)
        if tr.stopped_early:
            notes += (RunNote("early stop", f"T=2^{log2_table}: training stopped after {tr.seconds:.0f} s of the "
                                            f"{budget:.0f} s budget, the target being met"),)
        self.seconds["train"] += time.perf_counter() - t
        quality = self._keep(log2_table, model, tr, run_used, notes)
        return quality.mse if quality is not None else math.inf

    def _score(self, model: NeuralBVH) -> Quality:
        """The final evaluation: the held-out views (no check used them)."""
        if self.should_cancel():
            raise Cancelled("cancelled before evaluation")
        self.events(wire.phase(phase="eval", message=self.weighing.held_out.name))
        t = time.perf_counter()
        quality, _ = self.weighing.held_out.score_model(model)
        self.seconds["eval"] += time.perf_counter() - t
        return quality


def _metadata(mesh: Mesh, run: RunConfig, notes: list, assessment, tr: TrainResult, quality: Quality | None) -> dict:
    """What the file's header records of the run: source, settings, why (the notes in one line; the report keeps
    them typed), verdict, training, quality, provenance."""
    training = {"steps": tr.steps, "seconds": round(tr.seconds, 2), "samples": tr.samples,
                "stopped_early": tr.stopped_early, "samples_per_s": round(tr.samples_per_s),
                "final_loss": tr.final_loss, "device": tr.device, "compute_path": tr.compute_path,  # the kernel plan, exactly
                "soft_loss_before_freeze": tr.soft_loss_before_freeze,
                "frozen_loss": tr.frozen_loss, "finetuned_loss": tr.finetuned_loss}
    q = quality.to_dict() if quality else None
    if q:
        q.pop("per_view_mse", None)
    target = run.decision.target_mse
    return {"source": {"name": mesh.name, "triangles": mesh.n_triangles, "vertices": mesh.n_vertices},
            "settings": run.request.to_dict(), "why": why_of(notes),
            "assessment": assessment.to_dict(),
            "target_met": None if target is None or quality is None else quality.mse <= target,
            "training": training, "quality": q, "created": time.strftime("%Y-%m-%dT%H:%M:%S"),
            "torch": torch.__version__, "machine": platform.machine()}


def _appearance(model: NeuralBVH, mesh: Mesh, tracer: ExactTracer, look: LookConfig, storage: StorageConfig,
                seed: int, made, tr: TrainResult, events: EventSink, should_cancel, seconds: dict) -> dict:
    """Give the model the mesh's materials and, when its look needs one, train the appearance head (`look.budget_s`,
    or without a time budget `look.share` of the geometry's training time added; `seed`: the run's) and hold it as
    the file stores it (`storage`). Returns what the file's metadata records of it ({} for a bare shape)."""
    if mesh.look is None:
        return {}
    model.materials = _shipped_materials(mesh, made)
    if made is None:
        return {"slots": mesh.look.n_slots, "head": None}
    head, face_patch = made
    cfg = head.cfg
    budget = look.budget_s or max(1.0, tr.seconds * look.share / max(1 - look.share, 1e-6))
    events(wire.phase(phase="appearance", message=f"{cfg.slots} material slot(s), {cfg.patches} patch(es)"
                                                  f"{', texture coordinates' if cfg.uv else ''}: {budget:.0f} s"))
    t = time.perf_counter()
    head = head.to(model.device)
    torch.manual_seed(seed)
    labels = SurfaceLabels(mesh, tracer, np.random.default_rng(seed + 1), face_patch, colour=cfg.target == "colour")
    result = train_head(head, labels, budget, should_stop=should_cancel,
                        pool_size=1 << 19 if look.budget_s else 1 << 15)
    if should_cancel():
        raise Cancelled("cancelled while training the appearance head")
    finalize_head(head, storage.table_bits, storage.network_bits)
    model.appearance = head
    seconds["appearance"] = time.perf_counter() - t
    return {"slots": cfg.slots, "patches": cfg.patches, "head": {"steps": result.steps, "seconds": round(result.seconds, 2),
                                         "final_loss": result.final_loss}}


def compress_mesh(mesh: Mesh, settings: Settings, out_path: str | Path | None = None,
                  events: EventSink = null_sink, should_cancel: Callable[[], bool] = lambda: False,
                  evaluate_quality: bool = True, checkpoint_path: str | Path | None = None,
                  compare_float32: bool = False, resume_from: str | Path | None = None) -> CompressResult:
    """Compress `mesh` as `settings` ask (planned once: `plan_run`); write `out_path` (atomically) when given.
    Raises `process.Cancelled`, `process.TrainingDiverged` (nothing written in either case). compare_float32: also
    score each training before its storage is quantized (`seconds['mse_float32']`, for benchmarks). resume_from: a
    checkpoint of this mesh (`resume_settings` gives the settings it was made with; pass those). Raises
    NotWorthCompressing, unless `settings.force`: before training when the verdict says so (seconds), at a training
    check that projects the model above the alternative's curve, or after the held-out evaluation when a measured
    decimation reaches the model's MSE in fewer bytes than its file (`decision.final_verdict`); the assessment then
    names what to ship."""
    run = plan_run(settings, mesh, resumed=resume_from is not None)
    return _compress(mesh, run, out_path, events, should_cancel, evaluate_quality, checkpoint_path, compare_float32,
                     resume_from)


def _compress(mesh: Mesh, run: RunConfig, out_path, events: EventSink, should_cancel, evaluate_quality: bool,
              checkpoint_path, compare_float32: bool, resume_from) -> CompressResult:
    """compress_mesh's stages on the planned run: verdict, BVH, size search, look, file, final verdict, ship."""
    notes = list(run.notes) + ([RunNote("resumed", f"resumed from the checkpoint {resume_from}")] if resume_from else [])
    seconds: dict = {}
    tracer = ExactTracer(mesh)  # one Embree scene for the alternatives, the labels and the evaluation
    head = make_head(mesh, run.look.head)
    assessment, weighing = _verdict(mesh, run, tracer, head, events, seconds)
    bvh = _training_bvh(mesh, run.nodes, run.storage.node_bits, events, seconds)
    search = _SizeSearch(mesh, bvh, tracer, run, events, should_cancel, checkpoint_path, resume_from,
                         evaluate_quality, compare_float32, seconds, weighing)
    chosen_log2 = search.search()
    model, tr, run_used, trained_notes, quality = search.trained[chosen_log2]
    target = run.decision.target_mse
    if search.rule is not None and search.rule.keep_mesh is not None:
        d = search.rule.keep_mesh
        raise _keep_the_mesh(assessment, final_verdict(d.model_bytes, d.projected_mse, target, weighing.curve), events,
                             search.rule.decisions)
    notes += search.notes + list(trained_notes)
    look_info = _appearance(model, mesh, tracer, run.look, run_used.storage, run_used.training.seed, head, tr, events,
                            should_cancel, seconds)
    metadata = _metadata(mesh, run_used, notes, assessment, tr, quality)
    if look_info:
        metadata["appearance"] = look_info
    data = encode_nbvh(model, metadata, run_used.storage)
    verdict = None
    if quality is not None and weighing.curve_held_out is not None:
        verdict = final_verdict(len(data), quality.mse, target, weighing.curve_held_out, run.decision.force,
                                _measure_decimation(mesh, weighing, assessment))
        if verdict.shipped != "model":
            raise _keep_the_mesh(assessment, verdict, events, search.rule.decisions if search.rule else [])
    as_shipped = quality
    if quality is not None and look_info:  # the file read back with its look: what a user sees
        events(wire.phase(phase="eval", message=f"the file as shipped: {weighing.held_out.name}"))
        as_shipped, _ = weighing.held_out.score_model(decode_nbvh(data, "<the file as shipped>"), flip=True)
    decisions = {"checks": [d.to_dict() for d in search.rule.decisions] if search.rule else [],
                 "mse_check_views": search.check_views_mse, "mse_held_out_views": quality.mse if quality else None,
                 "final": verdict.to_dict() if verdict else None,
                 "alternative": weighing.curve_held_out.to_dict() if weighing.curve_held_out else None}
    result = CompressResult(path=None, file_bytes=len(data), components=component_bytes(data), quality=quality,
                            training=tr, settings=run_used.request,
                            seconds={k: (v if k.startswith("mse") else round(v, 2)) for k, v in seconds.items()},
                            model=model, tracer=tracer, why=why_of(notes), target_met=metadata["target_met"],
                            assessment=assessment.to_dict(), data=data, decisions=decisions,
                            quality_as_shipped=as_shipped, notes=notes)
    return _ship(out_path, result, metadata["quality"], events, should_cancel)


def _ship(out_path, result: CompressResult, quality: dict | None, events: EventSink, should_cancel) -> CompressResult:
    """Write the file (atomically) when a path is given; the run's result, with its path and bytes on disk."""
    if out_path is not None:
        if should_cancel():
            raise Cancelled("cancelled before saving")
        events(wire.phase(phase="save", message=str(out_path)))
        result.file_bytes = write_atomic(out_path, result.data)
        result.path = str(out_path)
    events(wire.result(path=result.path, bytes=result.file_bytes, quality=json.loads(json.dumps(quality)),
                       train_seconds=round(result.training.seconds, 2)))
    return result
