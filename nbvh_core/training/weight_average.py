"""The weights a training returns: a moving average of its last steps' weights (`TrainConfig.weight_average`).

At the end's learning rate each step moves the network around its optimum rather than toward it; the mean of the
last ~100 steps sits nearer (Polyak averaging). The average restarts whenever the model's form changes under it (a
grown table, a frozen index, the table snapped to its quantization grid), so the weights it hands back are always
ones this model, in its final form, can hold: after an 8-bit table's snap the table is constant and only the
network is averaged, and the averaged table stays exactly on its grid."""
from __future__ import annotations

import torch


class WeightAverage:
    """`update(fraction, form)` after each optimizer step; `apply()` at the end puts the average into the model.

    decay: per step (0 turns averaging off); start: the budget fraction from which steps are averaged. The first
    1 / (1 - decay) steps after a (re)start are averaged uniformly, later ones exponentially (no lag toward the
    weights at the start). form: anything that changes when the model's parameters change meaning (compared by ==).
    Not checkpointed: a run resumed inside the window averages from its resumption."""

    def __init__(self, model: torch.nn.Module, decay: float, start: float):
        self.model, self.decay, self.start = model, decay, start
        self._params: list[torch.nn.Parameter] = []
        self._mean: list[torch.Tensor] | None = None
        self._key = None
        self.steps = 0  # steps in the current average

    def update(self, fraction: float, form=None) -> None:
        """Add the model's present weights (after a step at budget `fraction`)."""
        if not self.decay or fraction < self.start:
            return
        params = [p for p in self.model.parameters() if p.requires_grad]
        key = (form, tuple((id(p), tuple(p.shape)) for p in params))
        with torch.no_grad():
            if key != self._key:  # first step in the window, or the model changed form: start over
                self._key, self._params = key, params
                self._mean = [p.detach().clone() for p in params]
                self.steps = 1
                return
            self.steps += 1
            rate = max(1.0 - self.decay, 1.0 / self.steps)
            torch._foreach_lerp_(self._mean, [p.detach() for p in params], rate)

    def restart(self) -> None:
        """Start the average over at the next step (the weights went back to an earlier state)."""
        self._key, self._mean, self.steps = None, None, 0

    def apply(self) -> bool:
        """Put the average into the model's parameters (in place); False when nothing was averaged."""
        if self._mean is None or self.steps < 2:
            return False
        now = [p for p in self.model.parameters() if p.requires_grad]
        if [(id(p), p.shape) for p in now] != [(id(p), p.shape) for p in self._params]:
            return False  # the model changed form after the last step: the average no longer fits it
        with torch.no_grad():
            for p, m in zip(self._params, self._mean):
                p.copy_(m)
        return True
