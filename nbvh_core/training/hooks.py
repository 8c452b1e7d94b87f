"""What a training calls back and where it keeps its state, declared once.

`TrainingHooks`: the callables the loop runs, each with where it runs and how often (`HOOK_SCHEDULE`);
`CheckpointFiles`: where its checkpoints go, what they carry besides the training's own state, and the one it
resumes. `train(model, bvh, tracer, cfg, hooks, files)` takes them whole, as the run's trainings pass them on.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Callable

from ..decision.records import TrainingPoint
from ..protocol.events import EventSink, null_sink


def never() -> bool:
    """The default cancel hook: a training nobody can cancel."""
    return False


#: Where in the loop each hook runs, and how often.
HOOK_SCHEDULE = {
    "events": "at each phase change, at most every cfg.progress_every_s with progress, and on a warning",
    "should_cancel": "before every step: True saves a checkpoint and raises Cancelled",
    "target_reached": "every cfg.target_check_every_s once 10% of the budget has passed and the encoding is in its "
                      "final form (`early_stop.EarlyStop`), and once at the end",
    "before_freeze": "once, just before HashVQAD's index is frozen",
}


@dataclass(frozen=True)
class TrainingHooks:
    """events: the training's event sink; should_cancel() -> bool; target_reached(model, at) -> bool, a check's action
    (`records.CheckAction`) or record (`CheckDecision`, as `CheckRule` answers): True or a stop ends training early,
    "grow" doubles the table, "roll back" returns to the best check's state (`at`: the training's
    `records.TrainingPoint`, its step, seconds, budget fraction and the step its budget ends at); before_freeze(model):
    e.g. to score the soft model. When each runs: HOOK_SCHEDULE."""

    events: EventSink = null_sink
    should_cancel: Callable[[], bool] = never
    target_reached: Callable[[object, TrainingPoint], object] | None = None
    before_freeze: Callable[[object], None] | None = None


@dataclass(frozen=True)
class CheckpointFiles:
    """path: where checkpoints are written (None: none are); extra: stored in every checkpoint under 'extra' (the
    caller's settings and mesh identity); resume_from: a checkpoint the training continues (None: a fresh one)."""

    path: str | os.PathLike | None = None
    extra: dict | None = None
    resume_from: str | os.PathLike | None = None
