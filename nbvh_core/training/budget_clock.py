"""The training's budget clock: the seconds its budget (`TrainConfig.time_limit_s`) is spent by; and where the budget
ends in steps (`BudgetEnd`), which the checks project to.

Steps are always the budget's time. The training's other time - its setup before the first step and its checks -
is left off the clock while the run's wall allows (`TrainConfig.checks_outside_budget_s`, set by `app.run_wall`;
None: always, as a run without a wall); past that margin it is the budget's time too, and the finished model's
check, which comes after the last step, is held back from the budget (as long as the last check took), so that the
training ends within the wall it was given. On the 10M lattice (2-core VM) the setup took 1.7 s, each check ~2.3 s
and the finished model's check ~2.3 s (bench/results/heavy.csv).
"""
from __future__ import annotations

import math
import time


class BudgetClock:
    """elapsed(): seconds of the budget spent; planned(): that plus the finished model's check still to come, where
    it is the budget's time (the training's end is judged on it). started_at: time.perf_counter() when the
    training was called (its setup runs until this clock is made); elapsed_before: a resumed training's seconds."""

    def __init__(self, outside_s: float | None, elapsed_before: float, started_at: float):
        now = time.perf_counter()
        self.left = math.inf if outside_s is None else outside_s  # overhead seconds still off the clock
        self.checks_s = 0.0  # every check's wall seconds
        self.tail_s = 0.0
        self.t0 = now - elapsed_before
        setup = now - started_at
        self.t0 -= setup - self._off(setup)

    def _off(self, seconds: float) -> float:
        """Of `seconds` of overhead, the part left off the clock."""
        off = min(seconds, max(self.left, 0.0))
        self.left -= off
        return off

    def elapsed(self) -> float:
        return time.perf_counter() - self.t0

    def planned(self) -> float:
        return self.elapsed() + self.tail_s

    def checked(self, seconds: float) -> float:
        """A check took `seconds` (0: none was asked): the part off the clock moves it back. Returns the part that was
        the budget's (the check period, counted in steps' time, skips it)."""
        if not seconds:
            return 0.0
        off = self._off(seconds)
        self.t0 += off
        self.checks_s += seconds
        if off < seconds:  # checks are the budget's now: so is the finished model's, about as long
            self.tail_s = seconds
        return seconds - off


#: Steps a training takes before its pace is read: its first steps compile a card's kernels and wait for the first
#: labels, seconds no later step repeats.
WARM_STEPS = 16


class BudgetEnd:
    """The step a training's budget ends at, as its checks project to (`records.TrainingPoint.steps_at_end`): a step
    budget's own; a time budget's is this step plus the steady step rate times the seconds left (the lesser when both
    are set). The steady rate is the steps' since the last check (before the first: since WARM_STEPS into the
    training), so it follows a grown table's slower steps and leaves out the first steps' warm-up. step0, elapsed0:
    where the training started (a resumed one's step and seconds)."""

    def __init__(self, steps: int | None, time_limit_s: float | None, step0: int = 0, elapsed0: float = 0.0):
        self.steps, self.time_limit_s = steps, time_limit_s
        self.start = (step0, elapsed0)
        self.window: tuple[int, float] | None = None  # where the steady rate is read from

    def note(self, step: int, elapsed: float) -> None:
        """Each step of the loop: the steady rate's window opens WARM_STEPS into the training."""
        if self.window is None and step >= self.start[0] + WARM_STEPS:
            self.window = (step, elapsed)

    def at_check(self, step: int, elapsed: float) -> float:
        """The step the budget ends at, read at a check at `step`, `elapsed` budget seconds; the window restarts."""
        end = math.inf if self.steps is None else float(self.steps)
        if self.time_limit_s is not None:
            end = min(end, step + self.rate(step, elapsed) * max(self.time_limit_s - elapsed, 0.0))
        self.window = (step, elapsed)
        return max(end, float(step))

    def rate(self, step: int, elapsed: float) -> float:
        """Steps per budget second: the window's, else since the training started; 0 before any step."""
        for s0, t0 in (self.window or self.start, self.start):
            if step > s0 and elapsed > t0:
                return (step - s0) / (elapsed - t0)
        return 0.0

