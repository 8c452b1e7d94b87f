"""The plan of a growing training (size_search "grow", the need-driven default): the table size it starts at, the
largest it may grow to, and the period of its checks (`checks.CheckRule` decides at each check whether to grow)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

#: The training starts this many table sizes below the planned one and grows while growing pays. The planned size
#: aims above the level by the size fit's safety factor (1.14x, about a third of a size), so the start is one size
#: below it. (Two sizes while the predictor over-predicted the presets' shape 2.4x: the gyroid then kept 2^12 where
#: 2^11 met the level, bench/results/grow.md; the fit's shape_shift now corrects that.)
GROW_START_BELOW = 1
#: A growing training is checked at least this many times in its budget (the growth has that many chances).
GROW_CHECKS = 12
#: The smallest table a growing training starts at (log2 T).
SMALLEST_START = 6
#: The clock a training in steps only (no time budget) is checked on: the default preset's budget.
STEPS_ONLY_BUDGET_S = 200.0


@dataclass(frozen=True)
class GrowthPlan:
    """start_log2: the table the training starts at; max_log2: the largest it may grow to (one size above the
    planned one, never past the sizes the predictor knows); check_every_s: seconds between its checks (the checks
    project to where the training's own budget ends, `records.TrainingPoint`); the size predictor's word on each
    size the training may reach (empty without a fit): budget_slopes {log2 T: d ln MSE / d ln training time}, grow_gains {log2 T: predicted MSE ratio of a
    table twice as large (< 1)}."""

    start_log2: int
    max_log2: int
    check_every_s: float
    budget_slopes: dict = field(default_factory=dict, compare=False)
    grow_gains: dict = field(default_factory=dict, compare=False)


def growth_sizes(planned_log2: int, largest_log2: int) -> range:
    """The table sizes (log2 T) a growing training planned at 2^planned_log2 may train at: from GROW_START_BELOW
    sizes below it (at least SMALLEST_START) to one above it, never past `largest_log2` (the predictor's largest)."""
    return range(max(SMALLEST_START, planned_log2 - GROW_START_BELOW), min(planned_log2 + 1, largest_log2) + 1)


def growth_clock(budget_s: float | None) -> float:
    """The clock a growing training's checks are spaced on: its budget in seconds, or STEPS_ONLY_BUDGET_S for one in
    steps."""
    return budget_s or STEPS_ONLY_BUDGET_S


def plan_growth(planned_log2: int, largest_log2: int, budget_s: float | None, check_every_s: float,
                budget_slopes: dict | None = None, log_mse: dict | None = None) -> GrowthPlan:
    """The growing training for a run planned at table 2^planned_log2 (`largest_log2`: the predictor's largest
    size), a time budget of `budget_s` seconds (None: a run in steps) and checks every `check_every_s` seconds at
    most (more often when the budget holds fewer than GROW_CHECKS of them). The size predictor's word, where there is
    one: budget_slopes {log2 T: d ln MSE / d ln time} over `growth_sizes`, log_mse {log2 T: ln MSE at the end of
    the clock (`growth_clock`)} over those sizes and one above the largest."""
    budget = growth_clock(budget_s)
    sizes = growth_sizes(planned_log2, largest_log2)
    return GrowthPlan(start_log2=sizes.start, max_log2=sizes.stop - 1,
                      check_every_s=min(check_every_s, budget / GROW_CHECKS),
                      budget_slopes={l2: budget_slopes[l2] for l2 in sizes} if budget_slopes else {},
                      grow_gains=({l2: math.exp(log_mse[l2 + 1] - log_mse[l2]) for l2 in sizes} if log_mse else {}))
