"""The trainings of one run: a fresh model trained (restarted at a lower learning rate when it diverges), and with a
target the growing training or the retrain search over table sizes (`SizeSearch`), each finalized to its stored
precision and scored on the held-out views. The decisions themselves live in `decision` (checks, size search);
this module runs the trainings they ask for."""
from __future__ import annotations

import copy
import dataclasses
import hashlib
import math
import time
from dataclasses import dataclass
from typing import NamedTuple

import torch

from ..decision.checks import CheckRule, CheckScore
from ..decision.growth import GrowthPlan
from ..decision.records import RunNote
from ..decision.size_search import search_size
from ..geometry.bvh import BVH
from ..geometry.exact import ExactTracer
from ..geometry.mesh import Mesh
from ..neural.model import NeuralBVH
from ..planning.run_config import RunConfig
from ..planning.sizing import LOG2_RANGE
from ..protocol import events as wire
from ..protocol.process import Cancelled, TrainingDiverged
from ..rendering.metrics import Quality, ViewScorer
from ..training.encoding_phases import grid_phase_pending, state_form
from ..training.hooks import CheckpointFiles, TrainingHooks
from ..training.train import TrainResult, train
from .weighing import Weighing

#: A training that diverged and could not go back (`training.recovery`) restarts from scratch at a 10x lower
#: learning rate, at most this many times.
DIVERGENCE_RETRIES = 2


@dataclass(frozen=True)
class RunContext:
    """What every training of one run shares: the mesh, its training BVH and exact tracer, the hooks the trainings
    call (events, cancel; `training.hooks`) and the checkpoint files (where they go, the one resumed); look: for an
    asset whose appearance head was trained before the geometry, (the head as stored, the materials the file ships):
    the checks score the model with it, its colour too."""

    mesh: Mesh
    bvh: BVH
    tracer: ExactTracer
    hooks: TrainingHooks
    files: CheckpointFiles
    look: tuple | None = None


class Trained(NamedTuple):
    """One training of compress_mesh's size search."""

    model: NeuralBVH
    result: TrainResult
    run: RunConfig  # as used (a divergence restart lowers lr; growth changes the table)
    notes: tuple  # what this training adds to the run's account (RunNote: restarts, growth, an early stop)
    quality: Quality | None

def mesh_identity(mesh: Mesh) -> dict:
    """What a checkpoint records of its mesh, to refuse resuming on another one: counts and a content hash."""
    h = hashlib.sha256(mesh.vertices.tobytes())
    h.update(mesh.faces.tobytes())
    return {"triangles": mesh.n_triangles, "vertices": mesh.n_vertices, "sha256": h.hexdigest()}

def stored_mse(scorer: ViewScorer, storage, look: tuple | None = None):
    """score(model) for the training's checks: the image MSE of `model` as its file would hold it (a copy at its
    stored precision; the training's own model is left as it is): the float32 model read 4.7% (spiky sphere) to 18%
    (bunny, its table grown late) below the stored one. A low-bit table is scored at 8 bits until it trains through
    its own grid (`training.encoding_phases.grid_phase_pending`): that last phase recovers the rounding (6 bits: +3.1% over
    the float model after it, 1.24x rounded without it; `tests/test_quantize.py`), and growth decided on the rounded
    score grew the bunny's table in both runs so scored (bench/results/target_runs.md). look: (the appearance head,
    the materials) to score the model with: the answer is then a `CheckScore`, its colour MSE beside."""
    def score(model) -> float | CheckScore:
        stored = copy.deepcopy(model)
        stored.eval()
        pending = grid_phase_pending(model, storage.table_bits)
        stored.finalize_storage(dataclasses.replace(storage, table_bits=8) if pending else storage)
        if look is not None:
            stored.appearance, stored.materials = look
        with torch.no_grad():
            quality = scorer.score_model(stored)[0]
        return quality.mse if look is None else CheckScore(quality.mse, quality.colour_mse)
    return score

def train_with_restarts(ctx: RunContext, run: RunConfig,
                        target_reached=None) -> tuple[NeuralBVH, TrainResult, RunConfig, tuple]:
    """Train a fresh model (or resume the context's checkpoint), its checks `target_reached` (a CheckRule or None). A divergence the training cannot recover from in place
    (`training.recovery`: before its first healthy state, or a third time) restarts it from scratch at a 10x lower
    learning rate (at most DIVERGENCE_RETRIES times; the checks start over with it). Returns (model, TrainResult, the
    run as used, the notes of its restarts and recoveries)."""
    notes: tuple = ()
    for attempt in range(DIVERGENCE_RETRIES + 1):
        if attempt and target_reached is not None:  # a CheckRule
            target_reached.start_over()
        torch.manual_seed(run.training.seed)  # the initial weights are the seed's, whatever this process ran before
        model = NeuralBVH(ctx.bvh.nodes, run.model, ctx.mesh.transform)
        try:
            files = dataclasses.replace(ctx.files, extra={"settings": run.request.to_dict(),
                                                          "mesh": mesh_identity(ctx.mesh)},
                                        resume_from=ctx.files.resume_from if attempt == 0 else None)
            tr = train(model, ctx.bvh, ctx.tracer, run.training,
                       dataclasses.replace(ctx.hooks, target_reached=target_reached), files)
            for step, seconds, scale in tr.recovered:
                notes += (RunNote("recovered", f"training diverged at {seconds:g} s (step {step}) and went back to "
                                               f"its last healthy state at learning rate x{scale:g}"),)
            return model, tr, run, notes
        except TrainingDiverged as exc:
            if attempt == DIVERGENCE_RETRIES:
                raise TrainingDiverged(f"{exc} (after {attempt} restarts at lower learning rates)") from None
            lr = run.training.lr
            notes += (RunNote("restart", f"training diverged at lr {lr:g} ({exc}), restarted at lr {lr * 0.1:g}"),)
            ctx.hooks.events(wire.warning(message=f"training diverged ({exc}); restarting from scratch with the "
                                        f"learning rate {lr:g} -> {lr * 0.1:g}"))
            run = run.with_training(lr=lr * 0.1)
    raise AssertionError("unreachable")

class SizeSearch:
    """The trainings of one compress_mesh call: one at the planned size, or with a target MSE one growing training
    (`grow`, the default: `decision.checks.CheckRule`) or the predict-train-measure-correct search over T
    (`decision.size_search`, at most TARGET_TRAININGS). Each training is finalized to the stored precision and scored
    on the held-out views; `trained[log2 T]` keeps them all, `notes` the search's own account."""

    def __init__(self, ctx: RunContext, run: RunConfig, evaluate_quality: bool, compare_float32: bool, seconds: dict,
                 weighing: Weighing):
        self.ctx, self.run = ctx, run
        self.mesh, self.bvh, self.tracer = ctx.mesh, ctx.bvh, ctx.tracer
        self.events, self.should_cancel = ctx.hooks.events, ctx.hooks.should_cancel
        self.resume_from = ctx.files.resume_from
        self.evaluate_quality, self.compare_float32, self.seconds = evaluate_quality, compare_float32, seconds
        self.weighing = weighing
        self.trained: dict[int, Trained] = {}
        self.notes: list[RunNote] = []
        self.rule: CheckRule | None = None  # the growing training's checks, once it ran
        self.check_views_mse: float | None = None  # the kept model on the check views (the report gives both)
        self.score_stored = stored_mse(weighing.checks, run.storage, ctx.look)
        seconds.update(train=0.0, eval=0.0)

    def search(self) -> int:
        """Train (and search); returns the chosen log2 T."""
        target, run = self.run.decision.target_mse, self.run
        if target is None or not self.evaluate_quality or self.resume_from is not None:  # resumed: its one size
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
        return CheckRule(self.score_stored, run.decision.target_mse, growth.max_log2, self.bytes_at,
                         self.weighing.curve, slope, gain, run.decision.force, self.shipped_form, state_form)

    def grow(self) -> int:
        """One training that starts below the planned T and grows its table while the checks say growing pays
        (`RunConfig.growth`); returns the final log2 T."""
        t = time.perf_counter()
        run, growth = self.run, self.run.growth
        run_start = run.at_table(growth.start_log2, regrid=False).with_training(
            target_check_every_s=growth.check_every_s)
        self.rule = rule = self._rule(growth)
        model, tr, run_used, notes = train_with_restarts(self.ctx, run_start, rule)
        tr.checks = [(d.seconds, d.log2_table, d.mse) for d in rule.decisions]
        final = model.cfg.encoding.log2_table
        run_used = run_used.at_table(final, regrid=False).with_training(target_check_every_s=run.decision.check_every_s)
        trail = ", ".join(f"T=2^{log2} at {sec:g} s" for _, sec, log2 in tr.grew) or "no growth"
        notes += (RunNote("growth", f"one training from T=2^{growth.start_log2} growing its table to meet "
                                    f"{run.decision.target_mse:g}: {trail}"),)
        if tr.stopped_early:
            notes += (RunNote("early stop", f"stopped after {tr.seconds:.0f} s: {rule.decisions[-1].action.value}"),)
        self.seconds["train"] += time.perf_counter() - t
        if rule.keep_mesh is not None:  # nothing worth finishing: the verdict is the mesh
            self.trained[final] = Trained(model, tr, run_used, notes, None)
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
        self.trained[log2_table] = Trained(model, tr, run_used, notes, quality)
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
        stop = (CheckRule(self.score_stored, target, log2_table, self.bytes_at, shipped_form=self.shipped_form,
                          state_form=state_form)
                if target is not None and self.evaluate_quality else None)
        model, tr, run_used, notes = train_with_restarts(self.ctx, run_try, stop)
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
