"""A training that diverges after it has learnt something goes back to its last healthy state and trains on at a 10x
lower learning rate, inside the same budget, rather than starting over.

Starting over from scratch (`app.trainings.train_with_restarts`, still the answer to a divergence before the first
healthy state is kept) costs a whole new budget, and the model trains at the lower rate from the start: the bunny
made to diverge at 120 s of 200 took 324.1 s for a held-out MSE of 0.00062 starting over, 205.7 s for 0.00031 going
back (bench/results/recovery.md). Here at most KEEP_EVERY of the budget is lost. Only a state of
the model's present form can be put back (`training.encoding_phases.state_form`: a grown table, a frozen index or a table put
on its grid since then makes the divergence end the training as before)."""
from __future__ import annotations

from typing import Callable

import torch

from ..protocol import events as wire
from ..protocol.events import EventSink
from ..protocol.process import TrainingDiverged
from .best_weights import KeptState

#: A healthy state is kept every this fraction of the budget (a divergence loses at most this much training).
KEEP_EVERY = 0.05
#: Each recovery multiplies the learning rate by this.
LR_FACTOR_AFTER = 0.1


class Recovery:
    """Watches each step's loss through `guard` (`training.train.DivergenceGuard`), keeps the model's state every
    KEEP_EVERY of the budget once the guard has settled, and on a divergence puts it back and lowers `schedule`'s
    learning rate (`Schedule.scale`), at most `recoveries` times. `recovered`: (step, seconds, learning rate scale
    after) of each."""

    def __init__(self, guard, schedule, recoveries: int, events: EventSink, form: Callable[[torch.nn.Module], tuple]):
        self.guard, self.schedule, self.left, self.events, self.form = guard, schedule, recoveries, events, form
        self.kept = KeptState()
        self.kept_at_s: float | None = None
        self.next_keep = KEEP_EVERY
        self.recovered: list[tuple[int, float, float]] = []

    def read_is_healthy(self, model, opt, average, losses: list[tuple[int, float]], fraction: float,
                        elapsed: float, vouched: bool = True) -> bool:
        """losses: (step, loss) of each step since the last read, in order (`loss_reads.PendingLosses`); vouched: the
        last is this step's, computed on the model as it is now (only then may the state be kept). True: apply this
        step. False: one diverged and the model went back (skip the step; its gradients are not applied). Raises
        TrainingDiverged when no state of the model's form is kept or no recovery is left. average: the weight
        average (`WeightAverage`), started over after going back."""
        for step, loss in losses:
            try:
                self.guard.observe(step, loss)
            except TrainingDiverged as exc:
                self._go_back(model, opt, average, step, elapsed, exc)
                return False
        step = losses[-1][0]
        if vouched:  # this step's gradients are set: a dead network is caught before its state could be kept
            try:
                self.guard.check_alive(model, step)
            except TrainingDiverged as exc:
                self._go_back(model, opt, average, step, elapsed, exc)
                return False
        if vouched and fraction >= self.next_keep and self.guard.settled(step):
            self.kept.keep(model, opt, self.form(model))  # the last loss vouches for the model as it is now
            self.kept_at_s, self.next_keep = elapsed, fraction + KEEP_EVERY
        return True

    def _go_back(self, model, opt, average, step: int, elapsed: float, exc: TrainingDiverged) -> None:
        if self.left <= 0 or not self.kept.restore(model, opt, self.form(model)):
            raise exc
        self.left -= 1
        self.schedule.scale *= LR_FACTOR_AFTER
        self.guard.went_back(step)
        average.restart()
        self.recovered.append((step, round(elapsed, 1), self.schedule.scale))
        self.events(wire.warning(message=f"training diverged at step {step} ({exc}): back to its state at "
                                         f"{self.kept_at_s:.0f} s, learning rate x{self.schedule.scale:g}"))
