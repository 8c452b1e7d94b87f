"""The weights of the best check so far, to return to when a later check reads far worse (`decision.checks`:
the action "roll back").

A training can leave a good state for a worse one it does not climb out of within its budget: the bunny's seed 9
(target 0.0004, 200 s) read 0.00039 at its 120 s check and 0.00057 at the next, and shipped 0.00051 held out; in 30
other target runs no check read more than 1.084x the best before it (bench/results/target_runs.csv). Going back to
the best check's parameters and Adam's moments (not the learning rate: the schedule runs on) retraces that stretch
from a good state. Only states of the model's present form count: a grown table, a frozen index or a table put on
its low-bit grid starts the record over (an older state would not fit, or would not score the same)."""
from __future__ import annotations

import copy

import torch


class KeptState:
    """One kept training state: the trainable parameters and Adam's moments (not the learning rate: the schedule runs
    on), about 3x the parameters' bytes (the bunny's default model: ~1 MB), with the form the model had (anything that
    changes when the parameters change meaning, compared by ==). Held in memory, not in checkpoints."""

    def __init__(self):
        self.form = None
        self._params: list[torch.Tensor] | None = None
        self._opt: dict | None = None
        self.restored = 0  # how many times training went back

    def keep(self, model: torch.nn.Module, opt: torch.optim.Optimizer, form) -> None:
        """Keep the model's and optimizer's state now, in place of the one held."""
        self.form = form
        with torch.no_grad():
            self._params = [p.detach().clone() for p in _trainable(model)]
        self._opt = copy.deepcopy(opt.state_dict())

    def restore(self, model: torch.nn.Module, opt: torch.optim.Optimizer, form) -> bool:
        """Put the kept state back into `model` and `opt` (the learning rate is left as it is now); False when none
        is held for `form`."""
        params = _trainable(model)
        if (self._params is None or form != self.form
                or [p.shape for p in params] != [p.shape for p in self._params]):
            return False
        lrs = [g["lr"] for g in opt.param_groups]
        with torch.no_grad():
            for p, kept in zip(params, self._params):
                p.copy_(kept)
        opt.load_state_dict(copy.deepcopy(self._opt))
        for g, lr in zip(opt.param_groups, lrs):
            g["lr"] = lr
        self.restored += 1
        return True


class BestWeights(KeptState):
    """`offer(model, opt, mse, form)` at each check; `restore(model, opt, form)` puts the best offered state back.
    mse: the check's score (lower is better). A resumed training starts its record afresh."""

    def __init__(self):
        super().__init__()
        self.mse: float | None = None

    def offer(self, model: torch.nn.Module, opt: torch.optim.Optimizer, mse: float, form) -> bool:
        """Keep this state if it is the best of its form (True when kept)."""
        if form == self.form and self.mse is not None and mse >= self.mse:
            return False
        self.mse = mse
        self.keep(model, opt, form)
        return True


def _trainable(model: torch.nn.Module) -> list[torch.nn.Parameter]:
    return [p for p in model.parameters() if p.requires_grad]
