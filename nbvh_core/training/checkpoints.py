"""A training's checkpoints: its state written atomically every N steps or seconds and at cancel
(`Checkpoints`) and gathered from the loop's parts (`checkpoint_state`); the file, and loading it back into a model
and its optimizer with every tensor checked, are `storage/checkpoint.py`'s."""
from __future__ import annotations

import os
from pathlib import Path

import torch

from ..protocol import events as wire
from ..protocol.events import EventSink
from ..storage.checkpoint import write_checkpoint
from .config import TrainConfig


class Checkpoints:
    """Writes the training state (atomically) every cfg.checkpoint_every steps and every cfg.checkpoint_every_s
    seconds, and on demand (cancel); nothing without a path. `state()` gathers it (see `storage.checkpoint.load_checkpoint`)."""

    def __init__(self, path: str | os.PathLike | None, cfg: TrainConfig, extra: dict | None, last_s: float):
        self.path = None if path is None else Path(path)
        self.cfg, self.extra, self.last_s = cfg, extra or {}, last_s

    def maybe_save(self, step: int, now_s: float, state) -> None:
        cfg = self.cfg
        if ((cfg.checkpoint_every and step % cfg.checkpoint_every == 0)
                or (cfg.checkpoint_every_s and now_s - self.last_s >= cfg.checkpoint_every_s)):
            self.save(state())
            self.last_s = now_s

    def save(self, state: dict) -> None:
        if self.path is not None:
            write_checkpoint(self.path, {**state, "train_config": self.cfg.to_dict(), "extra": self.extra})


def resumed_at(ck: dict, events: EventSink) -> tuple[int, float, list]:
    """(step, elapsed seconds, loss history) a training starts from: a checkpoint's (said), or the beginning."""
    if ck:
        events(wire.phase(phase="train", message=f"resumed at step {ck['step']}"))
    return ck.get("step", 0), ck.get("elapsed", 0.0), ck.get("history", [])


def checkpoint_state(model, opt, step, elapsed, history, batches, leaf_errors, cut, phases) -> dict:
    """What a checkpoint holds (see load_checkpoint): model, optimizer, step, elapsed seconds, loss history, the
    generators' states, the per-leaf errors, the tree cut, the quantization-aware phase's affine map (the caller adds
    the learning rate's scale, `Schedule.scale`)."""
    return {"model": model.state_dict(), "optimizer": opt.state_dict(), "step": step, "elapsed": elapsed,
            "history": history, "numpy_rng": batches.rng_state(), "torch_rng": torch.get_rng_state(),
            "leaf_errors": None if leaf_errors is None else leaf_errors.error.clone(),
            "cut": None if cut is None else batches.bvh.leaf_full.tolist(),
            "tree_cut_rounds_done": 0 if cut is None else cut.tree_cut.rounds_done,
            "qat_affine": model.encoding.qat_affine if phases.qat_on else None}
