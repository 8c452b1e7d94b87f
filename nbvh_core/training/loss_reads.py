"""The step's loss read back to the host every N steps, not every step.

Reading a card's loss (`float(loss)`) waits for the step's kernels to finish: the host cannot queue the next
step's work while the card runs this one, so every step pays the launch latency of all its kernels in series.
Held as device tensors and read N at a time (one `tolist` for all of them), the card runs ahead of the host by up
to N steps. The guard and the recovery still see every step's loss, in order, at the next read: a divergence is
caught up to N - 1 steps late, and the recovery puts back a state kept before it (`recovery.Recovery`; a state is
kept only at a read, where the latest loss vouches for it). On the CPU a loss is already on the host: N = 1, and
the loop behaves exactly as one that reads every step.
"""
from __future__ import annotations

import torch

#: Steps between reads on a card: 16 steps of ~1-3 ms each let the host run ~20-50 ms ahead.
CARD_READ_EVERY = 16


def read_every(requested: int | None, device: torch.device) -> int:
    """The steps between loss reads: `requested` (TrainConfig.loss_read_every) or, when None, CARD_READ_EVERY on a
    card and 1 on the CPU."""
    if requested is not None:
        if requested < 1:
            raise ValueError(f"loss_read_every must be >= 1, got {requested}")
        return int(requested)
    return CARD_READ_EVERY if device.type == "cuda" else 1


class PendingLosses:
    """Losses of the steps since the last read, as (step, loss) with loss a 0-d tensor or a float."""

    def __init__(self, every: int):
        self.every = every
        self.items: list[tuple[int, torch.Tensor | float]] = []

    def add(self, step: int, loss: torch.Tensor | float) -> None:
        self.items.append((step, loss.detach() if isinstance(loss, torch.Tensor) else loss))

    def due(self) -> bool:
        """Whether a read is due (N losses held)."""
        return len(self.items) >= self.every

    def peek(self) -> list[tuple[int, float]]:
        """The held losses as floats (one host read), kept held."""
        if not self.items:
            return []
        tensors = [v for _, v in self.items if isinstance(v, torch.Tensor)]
        values = iter(torch.stack([t.float().reshape(()) for t in tensors]).tolist() if tensors else [])
        return [(s, next(values) if isinstance(v, torch.Tensor) else float(v)) for s, v in self.items]

    def take(self) -> list[tuple[int, float]]:
        """The held losses as floats (one host read), no longer held."""
        read, self.items = self.peek(), []
        return read


class LossBook:
    """A training's loss history, (steps done, loss before that step's update), and the losses not yet read, judged
    at each read by `recovery` (`recovery.Recovery.read_is_healthy`) on the model, optimizer and weight average of
    `phases` (`encoding_phases.EncodingPhases`)."""

    def __init__(self, every: int, history: list, recovery, model, opt, phases):
        self.pending, self.history = PendingLosses(every), history
        self.recovery, self.model, self.opt, self.phases = recovery, model, opt, phases

    def add(self, step: int, loss: torch.Tensor | float) -> bool:
        """Hold the loss of step `step` (before its update); True when a read is due."""
        self.pending.add(step, loss)
        return self.pending.due()

    def read(self, fraction: float, elapsed: float, vouched: bool = False) -> bool:
        """Read and judge the held losses. vouched: the last one is this step's, on the model as it is now (a
        state may then be kept). False: one diverged and the model went back."""
        read = self.pending.take()
        if not read:
            return True
        if not self.recovery.read_is_healthy(self.model, self.opt, self.phases.average, read, fraction, elapsed,
                                             vouched):
            return False
        self.history.extend((s + 1, v) for s, v in read)
        return True

    def with_unread(self) -> list[tuple[int, float]]:
        """The history and the held losses (read, still held): what a checkpoint stores."""
        return self.history + [(s + 1, v) for s, v in self.pending.peek()]
