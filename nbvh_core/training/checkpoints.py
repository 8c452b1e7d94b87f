"""A training's checkpoints: its state written atomically every N steps or seconds and at cancel
(`Checkpoints`), gathered from the loop's parts (`checkpoint_state`), and read back as data, every tensor checked
against the model it goes into (`load_checkpoint`; the file format: `storage/checkpoint.py`)."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from ..neural.model import NeuralBVH
from ..protocol import events as wire
from ..protocol.events import EventSink
from ..storage.checkpoint import CheckpointError, read_checkpoint, write_checkpoint
from .config import TrainConfig



class Checkpoints:
    """Writes the training state (atomically) every cfg.checkpoint_every steps and every cfg.checkpoint_every_s
    seconds, and on demand (cancel); nothing without a path. `state()` gathers it (see `load_checkpoint`)."""

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


def load_checkpoint(path: str | os.PathLike, model: NeuralBVH, opt: torch.optim.Optimizer,
                    device: torch.device) -> dict:
    """Load a checkpoint's model, optimizer moments and torch RNG state into `model` and `opt`, after checking every
    tensor against what this model holds (names, shapes, dtypes); returns the rest for the other parts: step,
    elapsed, history [(step, loss)], numpy_rng {chunk_state, index, leaf_weights}, leaf_errors, cut,
    tree_cut_rounds_done, lr_scale, qat_affine. Raises CheckpointError (one line) for a file that does not fit."""
    ck = read_checkpoint(path)
    where = str(path)
    codes = ck.get("model.encoding.codes")
    if codes is not None and codes.numel() and model.encoding.learned_index:
        model.encoding.freeze()  # the checkpoint is past the freeze: same structure before loading
    model.load_state_dict(_matching(ck.tensors, "model.", model.state_dict(), where))
    opt.load_state_dict(_optimizer_state(ck.tensors, opt, where))
    torch.set_rng_state(ck.tensors["torch_rng"])
    h = ck.header
    rng = None if h["numpy_rng"] is None else dict(h["numpy_rng"], leaf_weights=_numpy(ck.get("leaf_weights")))
    qat = ck.get("qat_offset"), ck.get("qat_scale")
    return {"step": h["step"], "elapsed": float(h["elapsed"]),
            "history": [(int(s), float(v)) for s, v in ck.tensors["history"].tolist()], "numpy_rng": rng,
            "leaf_errors": ck.get("leaf_errors"), "cut": None if ck.get("cut") is None else ck.get("cut").tolist(),
            "tree_cut_rounds_done": h["tree_cut_rounds_done"], "lr_scale": h["lr_scale"],
            "qat_affine": None if qat[0] is None else (qat[0].numpy(), qat[1].numpy())}


def _numpy(t: torch.Tensor | None) -> np.ndarray | None:
    return None if t is None else t.numpy()


def _matching(tensors: dict, prefix: str, expected: dict, where: str) -> dict:
    """The checkpoint's tensors under `prefix`, refused unless they are exactly `expected`'s names, shapes, dtypes."""
    got = {k[len(prefix):]: v for k, v in tensors.items() if k.startswith(prefix)}
    if set(got) != set(expected):
        odd = sorted(set(got) ^ set(expected))[:3]
        raise CheckpointError(f"{where}: the checkpoint does not hold this model's tensors (differs in {odd})")
    for name, want in expected.items():
        if got[name].shape != want.shape or got[name].dtype != want.dtype:
            raise CheckpointError(f"{where}: tensor {name!r} is {tuple(got[name].shape)} {got[name].dtype}, this "
                                  f"model's is {tuple(want.shape)} {want.dtype}")
    return got


def _optimizer_state(tensors: dict, opt: torch.optim.Optimizer, where: str) -> dict:
    """Adam's state_dict: the structure and hyperparameters of `opt` (this run's own: nothing of the file's but
    numbers), the moments and step counts of the file, each checked against its parameter."""
    own = opt.state_dict()
    params = [p for g in opt.param_groups for p in g["params"]]
    state = {}
    for i, p in enumerate(params):
        entry = {k.split(".")[-1]: v for k, v in tensors.items() if k.startswith(f"optimizer.{i}.")}
        if not entry:
            continue
        want = {"step": torch.zeros((), dtype=torch.float32), "exp_avg": p.detach().cpu(),
                "exp_avg_sq": p.detach().cpu()}
        state[i] = _matching({f"{k}": v for k, v in entry.items()}, "", want, where)
    if any(int(k.split(".")[1]) >= len(params) for k in tensors if k.startswith("optimizer.")):
        raise CheckpointError(f"{where}: optimizer state for a parameter this model does not have")
    return {"state": state, "param_groups": own["param_groups"]}


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
