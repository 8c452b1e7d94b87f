"""mesh -> BVH -> training -> quality check -> .nbvh file: the one function the CLI, the add-on's job, library
batches and the benchmarks call (`compress_mesh`). What a run is asked (`Settings`, presets) is planned once into
its parts (`planning.run_config.plan_run` -> RunConfig); every stage below takes only its part. Settings and the
presets are re-exported here for callers that only need this module.
"""
from __future__ import annotations

import dataclasses
import json
import math
import platform
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from ..decision.final_verdict import final_verdict, missed_surface
from ..decision.records import Assessment, RunDecisions, RunNote, why_of
from ..decision.verdict import mesh_kept
from ..geometry.bvh import NODE_DTYPE, SharedTree, cut_tree, shared_tree
from ..geometry.exact import ExactTracer
from ..geometry.mesh import Mesh
from ..geometry.texture_hold import hold_textures
from ..neural.appearance import finalize_head, make_head
from ..neural.model import NeuralBVH
from ..neural.quantize import StorageConfig, snap_nodes
from ..planning.run_config import LookConfig, RunConfig, plan_run
from ..planning.settings import PRESETS, Settings, estimate_file_bytes, preset  # noqa: F401  (re-exported)
from ..protocol.memory import peak_resident_bytes  # noqa: F401 - the report's peak, read here
from ..protocol import events as wire
from ..protocol.events import EventSink, null_sink
from ..protocol.process import Cancelled, NotWorthCompressing
from ..rendering.metrics import Quality, ViewScorer
from ..storage.fileformat import component_bytes, decode_nbvh, encode_nbvh, write_atomic
from ..training.appearance_training import SurfaceLabels, train_head
from ..training.hooks import CheckpointFiles, TrainingHooks
from ..training.train import TrainResult, pick_device
from .run_wall import within_wall
from .trainings import RunContext, SizeSearch, mesh_identity
from .weighing import alternative_at_model, measure_decimation, shipped_materials, weigh
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
    assessment: Assessment | None = None  # is the model smaller than the mesh, and what was measured to say so
    data: bytes = b""  # the complete .nbvh file contents (written to `path` when one was given)
    #: The decisions on measurements: every training check, the final verdict (the model as shipped against the
    #: alternative at the same held-out MSE) and that curve.
    decisions: RunDecisions = field(default_factory=RunDecisions)
    #: The file as shipped, decoded from its bytes with its look, on the held-out views: colour MSE and FLIP beside
    #: the geometry's MSE (for a bare shape the file is the model `quality` scored, at its stored precision).
    quality_as_shipped: Quality | None = None
    #: The file on a second held-out view set, the lattice turned at random for this run (`Quality.turn_seed`): the
    #: held-out MSE is not an accident of one set of views (the verdict weighs the fixed set, as the alternative's).
    quality_turned: Quality | None = None
    #: The run's account in order (decision.records.RunNote): the plan, a resume, restarts, growth, the search.
    notes: list = field(default_factory=list)
    #: The process's peak resident memory so far (`peak_resident_bytes`) and per input triangle.
    memory: dict = field(default_factory=dict)

    def summary(self) -> dict:
        return {"path": self.path, "file_bytes": self.file_bytes, "components": self.components,
                "quality": self.quality.to_dict() if self.quality else None,
                "quality_as_shipped": self.quality_as_shipped.brief() if self.quality_as_shipped else None,
                "quality_turned_views": self.quality_turned.brief() if self.quality_turned else None,
                "model_resident_bytes": self.model.resident_bytes() if self.model is not None else None,
                "training": {k: v for k, v in dataclasses.asdict(self.training).items() if k != "history"},
                "settings": self.settings.to_dict(), "seconds": self.seconds, "why": self.why,
                "notes": [n.to_dict() for n in self.notes],
                "target_met": self.target_met,
                "assessment": self.assessment.to_dict() if self.assessment is not None else None,
                "decisions": self.decisions.to_dict(),
                "memory": self.memory}


def memory_record(mesh: Mesh) -> dict:
    """{'peak_resident_bytes', 'per_triangle'} for the run's report (empty where the platform does not say)."""
    peak = peak_resident_bytes()
    return {} if peak is None else {"peak_resident_bytes": peak,
                                    "per_triangle": round(peak / max(mesh.n_triangles, 1), 1)}


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
    # The size is the checkpoint's; a target stays: the resumed run measures the alternative and ends with the final
    # verdict, as the run it continues would have.
    return dataclasses.replace(settings, budget_kb=None)


def _verdict(mesh: Mesh, run: RunConfig, tracer: ExactTracer, made, events: EventSink, seconds: dict,
             resumed: bool = False, should_cancel: Callable[[], bool] = lambda: False):
    """Is the model worth training (`weigh`)? Raises NotWorthCompressing unless forced or `resumed` (the run it
    continues decided to train; its final verdict still weighs the model); returns (Assessment, Weighing); in
    seconds['plan']."""
    t = time.perf_counter()
    events(wire.phase(phase="plan", message=why_of(run.notes)))
    assessment, weighing = weigh(mesh, run, tracer, made, events, should_cancel)
    seconds["plan"] = time.perf_counter() - t
    if not assessment.worth_compressing:
        if resumed and not run.decision.force:
            events(wire.warning(message=assessment.message + " (resumed: training on; the final verdict decides)"))
        elif not run.decision.force:
            events(wire.verdict(worth_compressing=False, message=assessment.message, assessment=assessment.to_dict()))
            raise NotWorthCompressing(assessment, weighing.decimator)
        events(wire.warning(message=assessment.message + " (training anyway: forced)"))
    return assessment, weighing


def _keep_the_mesh(assessment, verdict, events: EventSink, checks: list, decimator=None):
    """NotWorthCompressing for a decision taken on measurements (a check's or the final verdict's): the assessment
    now recommends the measured decimation (or the whole mesh) that the CLI writes, with the training's `checks`
    (`decision.verdict.mesh_kept`); decimator: the run's chain, which the files are rebuilt from."""
    kept = mesh_kept(assessment, verdict, checks)
    events(wire.verdict(worth_compressing=False, message=kept.message, assessment=kept.to_dict()))
    return NotWorthCompressing(kept, decimator)


def _training_bvh(mesh: Mesh, nodes: int, node_bits: int, events: EventSink, seconds: dict,
                  tree: SharedTree | None = None):
    """The BVH the model is trained on: `nodes` nodes cut from the mesh's full tree (`tree`, the plan's, else
    built), snapped to 8-bit boxes when the file stores them so (node_bits 8: each contains its exact box). A size
    search retrains with another T only, never another node count."""
    t = time.perf_counter()
    events(wire.phase(phase="bvh", message=f"{mesh.n_triangles} triangles -> {nodes} nodes"))
    bvh = cut_tree(tree.get() if tree is not None else shared_tree(mesh), nodes)
    if node_bits == 8:
        bvh = dataclasses.replace(bvh, nodes=snap_nodes(bvh.nodes))
    seconds["bvh"] = time.perf_counter() - t
    return bvh


def _metadata(mesh: Mesh, run: RunConfig, notes: list, assessment, tr: TrainResult, quality: Quality | None) -> dict:
    """What the file's header records of the run: source, settings, why (the notes in one line; the report keeps
    them typed), verdict, training, quality, provenance."""
    training = {"steps": tr.steps, "seconds": round(tr.seconds, 2), "samples": tr.samples,
                "stopped_early": tr.stopped_early, "samples_per_s": round(tr.samples_per_s),
                "rays_per_step": tr.rays_per_step, "label_reuse": tr.label_reuse, "reused_batches": tr.reused_batches,
                # None when no step ran (a checkpoint resumed at its end): a file's header holds no NaN
                "final_loss": tr.final_loss if math.isfinite(tr.final_loss) else None, "device": tr.device,
                "compute_path": tr.compute_path,  # the kernel plan, exactly
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


#: The appearance head's steps in a run without a time budget, at least: the tiny globe's head (tests/test_look.py)
#: reads colour MSE 0.049 at 200 steps, 0.080 at 100; the 1 s it was given before read 0.060-0.082 on the 2-core VM.
HEAD_STEPS_IN_STEPS_RUN = 200


def _appearance(model: NeuralBVH, mesh: Mesh, tracer: ExactTracer, look: LookConfig, storage: StorageConfig,
                seed: int, made, tr: TrainResult | None, events: EventSink, should_cancel, seconds: dict,
                trained: tuple | None = None) -> dict:
    """Give the model the mesh's materials and, when its look needs one, the appearance head: `trained` (head,
    metadata) when it was trained before the geometry (`_head_first`), else trained now (`look.budget_s`, or in a
    run without a time budget steps in `look.share` of the geometry's steps `tr`, at least HEAD_STEPS_IN_STEPS_RUN;
    `seed`: the run's). Returns what the file's metadata records of it ({} for a bare shape)."""
    if mesh.look is None:
        return {}
    model.materials = shipped_materials(mesh, made)
    if made is None:
        return {"slots": mesh.look.n_slots, "head": None}
    if trained is None:
        # A run in steps is the same on every machine, its head too: steps, not the seconds they took (a 1 s floor
        # gave the tiny globe's head colour MSE 0.060 or 0.082 as the machine was busy).
        steps = None if look.budget_s else max(HEAD_STEPS_IN_STEPS_RUN,
                                               round(tr.steps * look.share / max(1 - look.share, 1e-6)))
        trained = _train_head(mesh, tracer, look, storage, seed, made, look.budget_s or math.inf, model.device,
                              events, should_cancel, seconds, max_steps=steps)
    model.appearance = trained[0]
    return trained[1]


def _train_head(mesh: Mesh, tracer: ExactTracer, look: LookConfig, storage: StorageConfig, seed: int, made,
                budget_s: float, device, events: EventSink, should_cancel, seconds: dict,
                max_steps: int | None = None) -> tuple:
    """The appearance head `made` trained on the mesh's exact surface labels for `budget_s` seconds (or `max_steps`
    steps) and held as the file stores it (`storage`): (the head, what the file's metadata records of it)."""
    head, face_patch = made
    cfg = head.cfg
    budget = f"{max_steps} steps" if max_steps else f"{budget_s:.0f} s"
    events(wire.phase(phase="appearance", message=f"{cfg.slots} material slot(s), {cfg.patches} patch(es)"
                                                  f"{', texture coordinates' if cfg.uv else ''}: {budget}"))
    t = time.perf_counter()
    head = head.to(device)
    torch.manual_seed(seed)
    labels = SurfaceLabels(mesh, tracer, np.random.default_rng(seed + 1), face_patch, colour=cfg.target == "colour")
    result = train_head(head, labels, budget_s, should_stop=should_cancel,
                        pool_size=1 << 19 if look.budget_s else 1 << 15,
                        **({"max_steps": max_steps} if max_steps else {}))
    if should_cancel():
        raise Cancelled("cancelled while training the appearance head")
    finalize_head(head, storage.table_bits, storage.network_bits)
    seconds["appearance"] = time.perf_counter() - t
    return head, {"slots": cfg.slots, "patches": cfg.patches,
                  "head": {"steps": result.steps, "seconds": round(result.seconds, 2), "final_loss": result.final_loss}}


def _head_first(mesh: Mesh, tracer: ExactTracer, run: RunConfig, made, events: EventSink, should_cancel,
                seconds: dict) -> tuple | None:
    """For a run whose checks weigh the model against the mesh (a target, a time budget) and an asset whose look
    needs a head: the head trained before the geometry - it learns from the mesh's surface, not the model's - so that
    every check scores the model's colour beside its geometry, as the mesh's is (`trainings.stored_mse`). Returns
    `_train_head`'s (head, metadata), or None: the head, if any, trains after the geometry."""
    if made is None or not run.look.budget_s or run.decision.target_mse is None:
        return None
    return _train_head(mesh, tracer, run.look, run.storage, run.training.seed, made, run.look.budget_s,
                       pick_device(run.training.device), events, should_cancel, seconds)


def compress_mesh(mesh: Mesh, settings: Settings, out_path: str | Path | None = None,
                  events: EventSink = null_sink, should_cancel: Callable[[], bool] = lambda: False,
                  evaluate_quality: bool = True, checkpoint_path: str | Path | None = None,
                  compare_float32: bool = False, resume_from: str | Path | None = None,
                  started_at: float | None = None) -> CompressResult:
    """Compress `mesh` as `settings` ask (planned once: `plan_run`); write `out_path` (atomically) when given.
    Raises `process.Cancelled`, `process.TrainingDiverged` (nothing written in either case). compare_float32: also
    score each training before its storage is quantized (`seconds['mse_float32']`, for benchmarks). resume_from: a
    checkpoint of this mesh (`resume_settings` gives the settings it was made with; pass those). Raises
    NotWorthCompressing, unless `settings.force`: before training when the verdict says so (seconds), at a training
    check that projects the model above the alternative's curve, or after the held-out evaluation when a measured
    decimation reaches the model's MSE in fewer bytes than its file (`decision.final_verdict`); the assessment then
    names what to ship. started_at: time.perf_counter() at the run's start, when it began before this call (the
    CLI's loading): the training ends within `run_wall.RUN_WALL_FACTOR` x the budget of it."""
    started_at = time.perf_counter() if started_at is None else started_at
    run = plan_run(settings, mesh, resumed=resume_from is not None)
    return _compress(mesh, run, out_path, events, should_cancel, evaluate_quality, checkpoint_path, compare_float32,
                     resume_from, started_at)


def _score_the_file(model, data: bytes, has_look: bool, quality: Quality | None, weighing, tracer, events,
                    seconds: dict) -> tuple[Quality | None, Quality | None]:
    """(the file as shipped on the held-out views: read back with its look, FLIP beside, what a user sees and what is
    weighed - for a bare shape the model `quality` scored; the same file on a second held-out set, the lattice
    turned at random for this run, its seed recorded: `turned_views_seed`). None without a quality."""
    if quality is None:
        return None, None
    start = time.perf_counter()
    shipped, as_shipped = model, quality
    if has_look:
        events(wire.phase(phase="eval", message=f"the file as shipped: {weighing.held_out.name}"))
        shipped = decode_nbvh(data, "<the file as shipped>")
        as_shipped, _ = weighing.held_out.score_model(shipped, flip=True)
    held = weighing.held_out
    turned_views = ViewScorer(tracer, tracer.mesh.transform, held.n_views, held.resolution,
                              turn_seed=turned_views_seed())
    events(wire.phase(phase="eval", message=f"the file on {turned_views.name}"))
    turned, _ = turned_views.score_model(shipped)
    seconds["eval_as_shipped"] = time.perf_counter() - start
    return as_shipped, turned


def turned_views_seed() -> int:
    """A fresh seed for a run's randomly turned held-out views (from the OS; recorded in the report)."""
    return int(np.random.SeedSequence().entropy % (1 << 31))


def _compress(mesh: Mesh, run: RunConfig, out_path, events: EventSink, should_cancel, evaluate_quality: bool,
              checkpoint_path, compare_float32: bool, resume_from, started_at: float) -> CompressResult:
    """compress_mesh's stages on the planned run: verdict, BVH, size search, look, file, final verdict, ship."""
    notes = list(run.notes) + ([RunNote("resumed", f"resumed from the checkpoint {resume_from}")] if resume_from else [])
    seconds: dict = {}
    tracer = ExactTracer(mesh)  # one Embree scene for the alternatives, the labels and the evaluation
    mesh, held = hold_textures(mesh, run.look.on_screen_px)  # what both sides store; the source stays the reference
    notes += [RunNote("look", held)] if held else []
    torch.manual_seed(run.training.seed)  # the head's initial weights too (a batch runs many assets in one process)
    head = make_head(mesh, run.look.head)
    assessment, weighing = _verdict(mesh, run, tracer, head, events, seconds, resume_from is not None, should_cancel)
    if should_cancel():
        raise Cancelled("cancelled before the BVH was built")
    bvh = _training_bvh(mesh, run.nodes, run.storage.node_bits, events, seconds, weighing.tree)
    weighing.tree = None  # the full tree (~100 B per triangle) is not needed past the cut
    run, wall = within_wall(run, started_at) if resume_from is None else (run, None)  # the look's time reserved
    if wall is not None:
        notes.append(wall)
        events(wire.phase(phase="train", message=wall.text))
    look = _head_first(mesh, tracer, run, head, events, should_cancel, seconds) if resume_from is None else None
    ctx = RunContext(mesh, bvh, tracer, TrainingHooks(events, should_cancel),
                     CheckpointFiles(checkpoint_path, resume_from=resume_from),
                     None if look is None else (look[0], shipped_materials(mesh, head)))
    search = SizeSearch(ctx, run, evaluate_quality, compare_float32, seconds, weighing)
    chosen_log2 = search.search()
    model, tr, run_used, trained_notes, quality = search.trained[chosen_log2]
    target = run.decision.target_mse
    if search.rule is not None and search.rule.keep_mesh is not None:
        d = search.rule.keep_mesh
        # The mesh kept is chosen on the held-out views, as every keep is (the check views only decided to stop).
        kept_on = weighing.curve_held_out or weighing.curve
        raise _keep_the_mesh(assessment, final_verdict(d.model_bytes, d.projected_mse, target, kept_on,
                                                       model_colour_mse=d.colour_mse),
                             events, search.rule.decisions, weighing.decimator)
    notes += search.notes + list(trained_notes)
    missed = quality and missed_surface(quality.silhouette_iou, quality.mse, target, tr.steps, tr.seconds)
    if missed:
        notes.append(RunNote("warning", missed))
        events(wire.warning(message=missed))
    look_info = _appearance(model, mesh, tracer, run.look, run_used.storage, run_used.training.seed, head, tr, events,
                            should_cancel, seconds, look)
    metadata = _metadata(mesh, run_used, notes, assessment, tr, quality)
    if look_info:
        metadata["appearance"] = look_info
    data = encode_nbvh(model, metadata, run_used.storage)
    as_shipped, turned = _score_the_file(model, data, bool(look_info), quality, weighing, tracer, events, seconds)
    verdict = None
    if quality is not None and weighing.curve_held_out is None and math.isfinite(quality.mse):
        # a fixed size measured nothing before training: weigh it now (forced, the verdict says what is given up)
        events(wire.phase(phase="eval", message="the alternative at the model's quality"))
        weighing.curve_held_out = alternative_at_model(mesh, weighing, assessment, len(data))
    if quality is not None and weighing.curve_held_out is not None:
        verdict = final_verdict(len(data), quality.mse, target, weighing.curve_held_out, run.decision.force,
                                measure_decimation(mesh, weighing, assessment),
                                as_shipped.colour_mse if look_info else None)
        if verdict.shipped != "model":
            raise _keep_the_mesh(assessment, verdict, events, search.rule.decisions if search.rule else [],
                                 weighing.decimator)
    decisions = RunDecisions(list(search.rule.decisions) if search.rule else [], search.check_views_mse,
                             quality.mse if quality else None, verdict,
                             weighing.curve_held_out.to_dict() if weighing.curve_held_out else None)
    result = CompressResult(path=None, file_bytes=len(data), components=component_bytes(data), quality=quality,
                            training=tr, settings=run_used.request,
                            seconds={k: (v if k.startswith("mse") else round(v, 2)) for k, v in seconds.items()},
                            model=model, tracer=tracer, why=why_of(notes), target_met=metadata["target_met"],
                            assessment=assessment, data=data, decisions=decisions,
                            quality_as_shipped=as_shipped, quality_turned=turned, notes=notes,
                            memory=memory_record(mesh))
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
