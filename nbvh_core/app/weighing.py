"""What a run's decisions are weighed with, before and after training: the check and held-out view sets (one metric
for every contender), the alternative's measured curve on each, and the bytes the asset's look adds to every model.
The same verdict serves a run (`pipeline.compress_mesh`) and a library batch's measurement before any training."""
from __future__ import annotations

import dataclasses
import math
import time
from typing import Callable
from dataclasses import dataclass

from ..decision.alternative_curve import AlternativeCurve, CurvePoint
from ..decision.records import Assessment
from ..geometry.bvh import SharedTree, TreeWatch
from ..geometry.decimation import Decimator
from ..geometry.exact import ExactTracer
from ..geometry.mesh import Mesh
from ..planning.run_config import RunConfig
from . import alternatives
from .alternatives import assess
from ..rendering.metrics import ViewScorer, view_sets
from ..protocol import events as wire
from ..protocol.events import EventSink, null_sink
from ..protocol.process import Cancelled
from ..storage.layout import look_stored_bytes


def shipped_materials(mesh: Mesh, made) -> list:
    """The slots' materials as the file keeps them: without their images when the head `made` learns the colour."""
    materials = list(mesh.look.materials)
    if made is not None and made[0].cfg.target == "colour":  # the colour is learnt: the images are not kept
        materials = [dataclasses.replace(m, image=None) for m in materials]
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
    #: the mesh's decimation chain: the final verdict's extra points come from it, never from a fresh pass
    decimator: Decimator | None = None
    #: the mesh's full tree (`bvh.SharedTree`), built once in the plan (after its decimations); the training's BVH is
    #: cut from it
    tree: SharedTree | None = None


#: The share of the training's time budget the plan's measurements may take: past it the optional ones are skipped
#: (`alternatives.alternatives`). A 10M-triangle lattice's plan took 809 s against a 200 s training before this.
PLAN_SHARE = 0.25
#: ...but never less than this (seconds): a short budget (a preview, a test) still weighs a light mesh fully (the
#: 1M-triangle lattice's whole plan took 18 s on 2 cores, bench/results/heavy.md; a slower machine has margin).
PLAN_MIN_S = 30.0


class PlanProgress:
    """tick(message, planned) for the plan's measurements (`alternatives.alternatives`): a progress event per step
    (fraction of the most steps it may take, elapsed and an ETA from the mean step so far) and a Cancel point.
    over_budget(seconds): the plan has spent its `budget_s`, or would with `seconds` more (None: no limit, a budget in
    steps)."""

    def __init__(self, events: EventSink, should_cancel: Callable[[], bool], budget_s: float | None = None):
        self.events, self.should_cancel, self.budget_s = events, should_cancel, budget_s
        self.t0, self.done = time.perf_counter(), 0

    def over_budget(self, seconds: float = 0.0) -> bool:
        return self.budget_s is not None and time.perf_counter() - self.t0 + seconds > self.budget_s

    def __call__(self, message: str, planned: int) -> None:
        if self.should_cancel():
            raise Cancelled(f"cancelled while measuring the alternative (before the {message})")
        elapsed = time.perf_counter() - self.t0
        eta = elapsed / self.done * max(planned - self.done, 0) if self.done else None
        self.events(wire.progress(min(self.done / max(planned, 1), 0.99), phase="plan", message=message,
                                  step=self.done, total=planned, elapsed_s=round(elapsed, 1),
                                  eta_s=None if eta is None else round(eta, 1)))
        self.done += 1


def tree_watch(events: EventSink, should_cancel: Callable[[], bool], n_triangles: int) -> TreeWatch:
    """The shared tree's build as the user sees it (`bvh.TreeWatch`): a progress event of phase "bvh" with an ETA
    about every `tree_build.WATCH_EVERY_S` seconds (a 10M-triangle tree takes ~11 s on 2 cores), and a Cancel point."""
    t0 = time.perf_counter()

    def watch(fraction: float) -> None:
        if should_cancel():
            raise Cancelled(f"cancelled while building the BVH ({fraction:.0%} of its full tree)")
        elapsed = time.perf_counter() - t0
        eta = elapsed * (1 - fraction) / fraction if fraction > 0 else None
        events(wire.progress(fraction, phase="bvh", message=f"the full tree of {n_triangles:,} triangles",
                             elapsed_s=round(elapsed, 1), eta_s=None if eta is None else round(eta, 1)))
    return watch


def weigh(mesh: Mesh, run: RunConfig, tracer: ExactTracer, made=None, events: EventSink = null_sink,
          should_cancel: Callable[[], bool] = lambda: False) -> tuple[Assessment, Weighing]:
    """The verdict before training, the same for a run and a library batch's measurement: the model `run` plans,
    with what its file adds for the asset's look (the head `made`, `make_head`; the images it keeps), weighed
    against the mesh and, with a target, the measured decimations (`alternatives.assess`, on the run's view sets). With a
    target the model is weighed at the size the predictor expects to meet it (`RunConfig.expected_log2_table`, no
    safety factor), as the decimation is weighed at the target: the safety factor says where training starts, and
    the checks weigh every size the training reaches against the measured alternative. events, should_cancel:
    the plan's progress and Cancel between its measurements (`PlanProgress`)."""
    expected = run.expected_log2_table
    model_bytes = run.at_table(expected, regrid=False).file_bytes if expected is not None else run.file_bytes
    checks, held_out = view_sets(tracer, mesh.transform, run.metric)
    look_bytes = 0
    if mesh.look is not None:
        look_bytes = sum(look_stored_bytes(made[0].cfg if made else None, shipped_materials(mesh, made),
                                           run.storage).values())
    measured = run.decision.target_mse is not None
    limit = run.training.time_limit_s
    ticker = PlanProgress(events, should_cancel, max(PLAN_SHARE * limit, PLAN_MIN_S) if limit else None)
    decimator, tree = Decimator(mesh), SharedTree(mesh, tree_watch(events, should_cancel, mesh.n_triangles))
    assessment = assess(mesh, model_bytes, run.decision, checks if measured else None, held_out, look_bytes,
                        decimator, tree, ticker)
    if assessment.alternatives.skipped:
        events(wire.warning(message=f"{assessment.alternatives.skipped} (the plan may take {ticker.budget_s:g} s: "
                                    f"{PLAN_SHARE:.0%} of the {limit:g} s training budget, at least {PLAN_MIN_S:g} s)"))
    return assessment, Weighing(checks, held_out, AlternativeCurve.from_alternatives(assessment.alternatives),
                                AlternativeCurve.from_alternatives(assessment.alternatives, held_out=True), look_bytes,
                                decimator, tree)


#: Decimations aimed at a fixed-size model's bytes after its evaluation, at most (`alternative_at_model`).
AIM_TRIES = 3


def alternative_at_model(mesh: Mesh, weighing: Weighing, assessment, model_bytes: int) -> AlternativeCurve | None:
    """For a run without a target (a preset, a byte budget, a scene's share), which measured nothing before
    training: the alternative at the model's own quality, measured after its evaluation and held on the held-out
    views, so that it ships by the same rule as the need-driven default. Decimations are aimed at the model's bytes
    (from the whole mesh's bytes per triangle, 3% under) until one fits within them (a small decimation carries
    more bytes per triangle: at most AIM_TRIES); the final verdict measures on from there (`final_verdict._settle`).
    A model about as large as the whole mesh meets the whole mesh itself. Bytes are compact, as in every final
    verdict (a run weighed plainly before training meets the compact mesh after it: the file kept is one). None (said
    in the assessment's `no_alternative`) without the simplifier."""
    missing = alternatives.simplifier_missing()
    if missing:
        assessment.alternatives.no_alternative = missing
        return None
    count = int(mesh.n_triangles * model_bytes / max(assessment.compact_bytes, 1) * 0.97)
    if count >= mesh.n_triangles * alternatives.DECIMATE_MAX_SHARE:
        whole = alternatives.whole_mesh_entry(mesh, weighing.checks, weighing.held_out, weighing.tree)
        assessment.alternatives.mesh_compact = whole
        return AlternativeCurve([CurvePoint.from_entry(whole, held_out=True)])
    measure, points = measure_decimation(mesh, weighing, assessment), []
    for _ in range(AIM_TRIES):
        points.append(measure(max(count, 4)))
        last = points[-1]
        if not math.isfinite(last.mse) or last.bytes < model_bytes or count <= 4:
            break
        count = int(last.triangles * model_bytes / last.bytes * 0.97)
    curve = AlternativeCurve(points)
    return curve if curve.points else None


def measure_decimation(mesh: Mesh, weighing: Weighing, assessment):
    """measure(triangles) -> CurvePoint for the final verdict: one more decimation scored on the held-out views
    (and recorded with the others, so the one that ships can be written)."""
    def measure(count: int) -> CurvePoint:
        if count >= mesh.n_triangles * alternatives.DECIMATE_MAX_SHARE:  # no decimation: the whole mesh is the point
            return CurvePoint(2 ** 62, math.inf, 0, count)
        entry = alternatives.decimation_entry(mesh, count, weighing.checks, weighing.held_out, None, weighing.decimator)
        if not entry.triangles:
            return CurvePoint(2 ** 62, math.inf, 0, count)
        assessment.alternatives.decimations_tried.append(entry)
        return CurvePoint.from_entry(entry, held_out=True)
    return measure
