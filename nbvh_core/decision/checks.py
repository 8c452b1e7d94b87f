"""The rule at each check of a training with a target (the need-driven default): stop when the level is met,
grow the table when growing pays better than the alternative would, stop and keep the mesh when the model will
not get under the alternative's curve. Every check is measured (the model at its stored precision on the check
views), weighed as it will ship (`bytes_at`), and recorded (`records.CheckDecision`)."""
from __future__ import annotations

import math
from typing import Callable, NamedTuple

from .alternative_curve import AlternativeCurve
from .records import CheckAction, CheckDecision, TrainingPoint

#: A check below this fraction of the target stops the training; the held-out evaluation after it confirms or not.
#: The margin is for the check views' error against the held-out views' and the training still moving: at the end of
#: six target runs (stored-precision checks) the held-out views read 0.93-1.05x the last check (bench/results/need.csv).
#: 0.8 was tried (bench_shipped's history in git): on eight assets nothing shipped differently from 0.9; the bunny, the
#: sheet and the 48k dragon took 107, 39 and 23 s longer (the checks' time off the clock in part).
EARLY_STOP_MARGIN = 0.9
#: A table grows only while at least this share of the budget is left: a table grown later trains too briefly to beat
#: the one it replaces. Measured on the bunny (target 0.0004, 200 s, 6x4 features): grown 2^11 -> 2^12 at 53 s and
#: -> 2^13 at 154 s, it ended at MSE 0.00043 in 237,116 B; a fixed 2^12 trained the whole 200 s read 0.00037 in
#: 137,916 B (bench/results/storage.md).
GROW_MIN_REMAINING = 0.4
#: A check reading more than this times the best check of the model's present form sends training back to that
#: check's state (`training.best_weights`): in 30 target runs of the bunny no check read more than 1.084x the best
#: before it; the runs that went on from 1.18x and 1.47x missed the level (bench/results/target_runs.csv, seed 9).
ROLLBACK_FACTOR = 1.15


class CheckScore(NamedTuple):
    """What a check's score may answer for an asset with a look: the geometry's image MSE and the colour MSE."""

    mse: float
    colour_mse: float | None


class CheckRule:
    """The target_reached callback of `training.train`: each call, rule(model, at) with `at` the training's
    `records.TrainingPoint`, answers a `records.CheckDecision` (its action one of `records.CheckAction`).

    score(model) -> check MSE of the model as stored, or a CheckScore (with its colour: a mesh then stands in for
    the model only when it also reaches the model's colour MSE as it reads now); target: the MSE level; max_log2: the
    largest table; budget_slope(log2) -> d ln MSE / d ln work at that size (the size predictor's, fitted as seconds
    of one machine's steady pace, so the same exponent in steps; None: the slope through the last two checks);
    grow_gain(log2) -> the predicted MSE ratio of a table twice as large (< 1; None: growth is judged on the
    target alone); bytes_at(log2) -> the file's bytes at that size as it ships (geometry, look, header); curve: the
    alternative on the check views (None: no alternative measured); force: train on even above the curve;
    shipped_form(model) -> whether the model already has the form it ships in (None: always): until then a met
    level trains on, since the phase still to come (a low-bit table's training through its grid) is what makes the
    score hold. A check far worse than the best of its form (ROLLBACK_FACTOR) answers "roll back"; state_form(model)
    -> the form of the model's parameters, as the training keys the states it can go back to
    (`training.encoding_phases.state_form`; None: table size and shipped form). After training, `decisions` holds every check
    and `keep_mesh` the decision that stopped it for the mesh."""

    def __init__(self, score: Callable, target: float, max_log2: int, bytes_at: Callable[[int], int],
                 curve: AlternativeCurve | None = None, budget_slope=None, grow_gain=None, force: bool = False,
                 shipped_form: Callable | None = None, state_form: Callable | None = None):
        self.score, self.target, self.max_log2 = score, target, max_log2
        self.bytes_at, self.curve, self.budget_slope, self.grow_gain = bytes_at, curve, budget_slope, grow_gain
        self.force, self.shipped_form, self.state_form = force, shipped_form, state_form
        self.decisions: list[CheckDecision] = []
        self.start_over()

    def start_over(self) -> None:
        """For a training started again from scratch (after a divergence): the best checks start over; the decisions
        so far stay on record."""
        self._best: dict[tuple, float] = {}  # the best check's MSE of each form (`state_form`)
        self.keep_mesh: CheckDecision | None = None
        self._first = len(self.decisions)  # this training's first decision (projections read its checks only)

    def projected(self, log2: int, steps_at_end: float) -> float | None:
        """The MSE at the budget's end (`steps_at_end`) from this size's checks; None: not enough checks yet. The
        projection is in work: MSE x (steps at the end / steps now)^slope, the predictor's exponent at this size (the
        learning rate decays over the budget, so the slope between two checks mid-way underestimates the end:
        bench/results/need.csv), else two checks'. In seconds it read a card's kernel compilation as its pace."""
        points = [(d.step, d.mse) for d in self.decisions[self._first:]
                  if d.log2_table == log2 and d.action != CheckAction.ROLL_BACK]
        s, m = max(points[-1][0], 1), points[-1][1]
        if self.budget_slope is not None:
            slope = self.budget_slope(log2)
        elif len(points) < 2:
            return None
        else:
            s1, m1 = points[-2]
            if m >= m1:  # no progress at this size
                return math.inf
            if s <= s1:
                return None  # no steps between the two checks: no law
            slope = math.log(m / m1) / math.log(s / max(s1, 1))
        return m * (max(steps_at_end, s) / s) ** slope

    def __call__(self, model, at: TrainingPoint) -> CheckDecision:
        """Measure `model` now, at the training's point `at`, and decide: the check's record (its action a
        CheckAction), also kept in `decisions`."""
        d, shipped, form, best = self._measure(model, at)
        d.projected_mse = self.projected(d.log2_table, at.steps_at_end)
        d.action, d.reason = self._decide(d, at)
        if d.action == CheckAction.STOP_LEVEL_MET and not shipped:
            d.action, d.reason = CheckAction.TRAIN_ON, f"{d.reason}; its final low-bit phase is still to run"
        elif d.action != CheckAction.STOP_LEVEL_MET and self._rolls_back(d, best):
            d.projected_mse = d.alternative_bytes = None  # a projection from a state training leaves is moot
        self._note_best(d, form, best)
        if d.action == CheckAction.STOP_KEEP_MESH:
            self.keep_mesh = d
        return d

    def at_end(self, model, at: TrainingPoint) -> CheckDecision:
        """The finished model (its budget spent) measured once more: "roll back" when it reads far worse than the
        best check of its form (ROLLBACK_FACTOR), else "finish". Nothing else is decided here: the final verdict
        weighs the finished model on the held-out views."""
        d, _, form, best = self._measure(model, at)
        d.action, d.reason = CheckAction.FINISH, "the budget is spent"
        self._rolls_back(d, best)
        self._note_best(d, form, best)
        return d

    def _measure(self, model, at: TrainingPoint) -> tuple[CheckDecision, bool, tuple, float | None]:
        """A new record of `model`'s check MSE at `at`; whether the model is in its shipped form; its form
        (`state_form`) and that form's best check."""
        score = self.score(model)
        mse, colour = (score.mse, score.colour_mse) if isinstance(score, CheckScore) else (score, None)
        log2 = model.cfg.encoding.log2_table
        self.decisions.append(CheckDecision(round(at.seconds, 2), log2, mse, None, self.bytes_at(log2), None,
                                            CheckAction.TRAIN_ON, "", colour, step=at.step,
                                            steps_at_end=round(at.steps_at_end, 1)))
        shipped = self.shipped_form is None or self.shipped_form(model)
        form = tuple(self.state_form(model)) if self.state_form is not None else (log2, shipped)
        return self.decisions[-1], shipped, form, self._best.get(form)

    def _rolls_back(self, d: CheckDecision, best: float | None) -> bool:
        """Whether `d` reads more than ROLLBACK_FACTOR x its form's best check (then its action says so)."""
        if best is None or d.mse <= ROLLBACK_FACTOR * best:
            return False
        d.action = CheckAction.ROLL_BACK
        d.reason = f"MSE {d.mse:.4g} > {ROLLBACK_FACTOR} x the best check's {best:.4g}: back to that check's weights"
        return True

    def _note_best(self, d: CheckDecision, form: tuple, best: float | None) -> None:
        if d.action != CheckAction.ROLL_BACK:
            self._best[form] = min(d.mse, best if best is not None else math.inf)

    def _decide(self, d: CheckDecision, at: TrainingPoint) -> tuple[str, str]:
        if d.mse <= EARLY_STOP_MARGIN * self.target:
            return CheckAction.STOP_LEVEL_MET, f"MSE {d.mse:.4g} <= {EARLY_STOP_MARGIN} x the level {self.target:g}"
        end = d.projected_mse if d.projected_mse is not None else d.mse
        alt = self.curve.bytes_at(end) if self.curve is not None else None
        d.alternative_bytes = None if alt is None else (alt if math.isfinite(alt) else None)
        grow = self._growth(d, end, at.fraction)
        if grow is not None:
            return grow
        beaten_by = self.curve.cheapest_meeting(end, d.colour_mse) if self.curve is not None else None
        if (beaten_by is not None and beaten_by.bytes < d.model_bytes and not self.force
                and d.projected_mse is not None):  # a measured decimation, not the interpolated curve, decides
            return (CheckAction.STOP_KEEP_MESH, f"the model ({d.model_bytes:,} B) stays above the alternative: "
                    f"{beaten_by.triangles:,} triangles reach MSE {beaten_by.mse:.4g}{_colour(beaten_by, d)} in "
                    f"{beaten_by.bytes:,} B, "
                    f"the model is projected to {end:.4g}; growing would not get it under")
        return CheckAction.TRAIN_ON, ("projected to meet the level" if end <= self.target
                            else f"projected MSE {end:.4g} misses the level; no larger size pays")

    def _growth(self, d: CheckDecision, end: float, fraction: float) -> tuple[str, str] | None:
        """("grow", why) when the projection misses the level at this size and a table twice as large is projected
        under the alternative's curve (its MSE gain per added byte beats the curve's); else None. fraction: of the
        budget spent."""
        if d.projected_mse is None or end <= self.target or d.log2_table >= self.max_log2:
            return None
        if fraction > 1.0 - GROW_MIN_REMAINING:
            return None  # too late to pay (GROW_MIN_REMAINING)
        grown_bytes = self.bytes_at(d.log2_table + 1)
        if self.grow_gain is None or self.curve is None:
            return CheckAction.GROW, f"projected MSE {end:.4g} misses the level {self.target:g}"
        grown_mse = end * self.grow_gain(d.log2_table)
        alt = self.curve.bytes_at(grown_mse)
        if grown_bytes < alt or self.force:
            return CheckAction.GROW, (f"projected MSE {end:.4g} misses the level; 2^{d.log2_table + 1} projected "
                            f"{grown_mse:.4g} in {grown_bytes:,} B, under the alternative's {alt:,.0f} B")
        return None


def _colour(point, d: CheckDecision) -> str:
    """The colour side of a keep, for the decision's line ('' for a bare shape)."""
    return "" if d.colour_mse is None else f" (colour {point.colour_mse:.4g}, the model's {d.colour_mse:.4g})"
