"""The training's budget clock: the seconds its budget (`TrainConfig.time_limit_s`) is spent by.

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
