"""The run's wall: a run with a time budget ends its training within RUN_WALL_FACTOR x that budget of its start.

A user who gives 200 s expects the answer in about that time. The plan may take PLAN_SHARE of the budget
(`weighing`), the training its budget; loading, the BVH and the training's checks come on top. On light meshes they
fit in the margin (the bunny at level standard: a 6.5 s plan, 11.7 s of checks); on a 10M-triangle scan they did not
(~60 s before training and 31 s of checks: 307 s for a 200 s budget, bench/results/heavy.csv). So before training
the time left to the wall is split: the training keeps its budget while it fits, and the checks may run outside the
budget's clock only in what is left over; past that they are the budget's, and a training that no longer fits
whole is shortened to what does. The evaluation after training is not counted (it scores what was made).
"""
from __future__ import annotations

import dataclasses
import time

from ..decision.records import RunNote
from ..planning.run_config import RunConfig

#: The run's wall (from its start to the training's end) as a multiple of its time budget: the plan's 25% share on
#: top of the training's budget.
RUN_WALL_FACTOR = 1.25
#: The share of the budget held back for what follows the training before its evaluation (the finished model made
#: ready to store and score: ~1 s on the 10M lattice, which ended its training 1.0 s past its wall without this).
END_RESERVE = 0.01
#: A shortened training keeps at least this share of its budget (a run whose plan overran on a slow machine still
#: trains a model worth weighing; it then ends past its wall, and says so).
MIN_TRAINING_SHARE = 0.5


def run_budget_s(run: RunConfig) -> float | None:
    """The run's whole time budget (the geometry's training and the look's head), seconds; None for a run in steps."""
    if not run.training.time_limit_s:
        return None
    return run.training.time_limit_s + (run.look.budget_s or 0.0)


def within_wall(run: RunConfig, started_at: float, now: float | None = None) -> tuple[RunConfig, RunNote | None]:
    """The run with its training fitted to the wall, as `started_at` (time.perf_counter() at the run's start)
    leaves it at `now`: the training's `checks_outside_budget_s` set to the margin left, and, where its budget no
    longer fits, its `time_limit_s` shortened (at least MIN_TRAINING_SHARE of it), with a note that says so."""
    budget = run_budget_s(run)
    if budget is None:
        return run, None
    now = time.perf_counter() if now is None else now
    spent = now - started_at
    training_s = run.training.time_limit_s
    left = (RUN_WALL_FACTOR - END_RESERVE) * budget - spent - (run.look.budget_s or 0.0)  # the geometry's wall
    fitted = max(min(training_s, left), MIN_TRAINING_SHARE * training_s)
    training = dataclasses.replace(run.training, time_limit_s=fitted, checks_outside_budget_s=max(left - fitted, 0.0))
    note = None
    if fitted < training_s:
        note = RunNote("wall", f"the training gets {fitted:.0f} s of its {training_s:g} s, its checks included: "
                               f"loading, the plan and the BVH took {spent:.0f} s of the run's "
                               f"{RUN_WALL_FACTOR * budget:.0f} s ({RUN_WALL_FACTOR:g}x its budget)")
    return dataclasses.replace(run, training=training), note  # the checks project to its end (`BudgetEnd`)
