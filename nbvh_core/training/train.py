"""Training loop: fresh labelled rays every step, Adam, a step or wall-clock budget, events, cancel, checkpoints.

Phases: `train` (main phase), then for HashVQAD `anneal` (`anneal_fraction` of the budget: the softmax
temperature falls geometrically from 1 to `tau_min`), `freeze` (argmax codes) and `finetune` (the last
`finetune_fraction` of the budget: feature rows and network train on the frozen integer codes, so they adapt to
the hard lookups the file stores). The learning rate decays
exponentially to `lr_final_factor` x lr over the budget.

Failure handling: a non-finite loss or parameter, a loss whose running mean rises above `rise_factor` x the
untrained model's loss, a loss that never fell below its starting value in 50+ steps (a learning rate so high it
killed the network early: the running-mean test alone misses both), or a loss above `divergence_factor` x its running mean after
warm-up, raises `TrainingDiverged` (the caller saves nothing). `should_cancel()` is checked every step and
raises `Cancelled`. Checkpoints (model, optimizer, step, elapsed time, RNG states) are written atomically every
`checkpoint_every` steps and at cancel, and `resume_from` continues one.
"""
from __future__ import annotations

import dataclasses
import gc
import math
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from ..decision.records import CHECK_ACTIONS
from .. import kernels
from .ray_batches import Batches, LeafErrors, TreeCut  # noqa: F401  (LeafErrors: re-exported)
from ..geometry.bvh import BVH
from ..storage.checkpoint import CheckpointError, read_checkpoint, write_checkpoint
from ..protocol.events import EventSink, null_sink
from ..protocol import events as wire
from ..geometry.exact import ExactTracer
from ..neural.model import NeuralBVH
from ..protocol.process import Cancelled, TrainingDiverged
from .best_weights import BestWeights
from .recovery import Recovery
from .network_quantization import NetworkQuantization
from .weight_average import WeightAverage
from .rays import RayConfig, TrainingSamples, label_samples, sample_rays


#: Below 8 bits the table trains through its grid (straight through: each step's forward sees the rows on the grid,
#: the gradient updates the float rows under them) for at least this fraction of the budget, on the clipped grid
#: `quantize.table_affine` gives at those bits (at 8 bits the last 5% held on the grid suffice: 1.03x the float MSE).
LOW_BITS_QAT_FRACTION = 0.25


def trains_through_grid(table_bits: int | None) -> bool:
    """Whether a table stored at `table_bits` trains through its grid in its last phase (below 8 bits: see
    LOW_BITS_QAT_FRACTION); at 8 bits and above it is put on its grid and held there."""
    return bool(table_bits) and table_bits < 8


def grid_phase_pending(model: NeuralBVH, table_bits: int | None) -> bool:
    """Whether `model`'s table is to train through its `table_bits` grid and has not reached that phase yet: until
    then it is not in the form it ships in (a check scores it at 8 bits and does not stop it: `decision.checks`)."""
    return trains_through_grid(table_bits) and getattr(model.encoding, "qat_affine", None) is None


@dataclass
class TrainConfig:
    """labels: 'ownership' | 'consistent'. Budget: `steps`, or `time_limit_s` (whichever ends first; at least
    one must be set). rays_per_step: rays drawn per step (each yields ~1-5 leaf samples)."""

    labels: str = "consistent"
    #: The normal loss (Settings.normal_loss, resolved): 'facing' labels normal targets facing the ray
    #: (rays.label_samples) rather than as the mesh winds them; the network's loss reads the rest.
    normal_loss: str = "oriented"
    #: Adam's learning rate at the start of the schedule, decaying exponentially to lr_final_factor x lr at the end.
    #: 1e-2 -> 1e-4 read lower MSE than this at 60 s on six meshes (one run each: 6-23%) but not at the default
    #: preset's 200 s (bunny, five runs: 0.00039-0.00044, mean 0.000419; here six runs: 0.000383-0.00043, mean
    #: 0.000397; bench/results/frontier.md), so 5e-3 -> 5e-4 stays.
    lr: float = 5e-3
    lr_final_factor: float = 0.1
    #: At one wall-clock budget, more and smaller steps read lower error (bunny, default preset, 200 s, seeds 0 / 1,
    #: held-out image MSE: 4096 rays 0.000389 / 0.000399 in ~22k steps, 2048 0.000373 / 0.000381 in ~37k, 1024
    #: 0.000381 / 0.000398 in ~64k; bench/results/frontier.md).
    rays_per_step: int = 2048
    steps: int | None = 2000
    time_limit_s: float | None = None
    anneal_fraction: float = 0.3
    tau_min: float = 0.01
    logits_lr_factor: float = 10.0  # HashVQAD index logits learn this much faster (they must become decisive)
    finetune_fraction: float = 0.1
    freeze: bool = True  # HashVQAD: argmax-freeze (False keeps the soft model to the end, e.g. to compare)
    seed: int = 0
    device: str = "auto"
    divergence_factor: float = 50.0
    rise_factor: float = 3.0
    #: A divergence after the first healthy state was kept goes back to the last one at a 10x lower learning rate,
    #: at most this many times in one training (`recovery.Recovery`); before it, or after these, training ends with
    #: TrainingDiverged (the run then starts over at a lower rate).
    divergence_recoveries: int = 2
    checkpoint_every: int = 0
    #: With a checkpoint path: also write one every this many seconds of training (0 = off); a kill loses at most one
    #: period.
    checkpoint_every_s: float = 60.0
    progress_every_s: float = 0.5
    # Label the next batches in a background thread while this step trains. None = only on CUDA (the CPU is idle
    # while the GPU trains); on a 2-core CPU it was slower (bunny, default preset, 150 steps: 130k vs 149-154k
    # samples/s without), since labelling and training compete for the same two cores.
    prefetch: bool | None = None
    # Rays for this many steps are drawn and labelled in one pass, then handed out one step at a time (the same
    # distribution; per-call work is amortised: bunny, 4096 rays/step, 5.3 / 4.1 / 3.4 ms per step at 8 / 16 / 32,
    # 11.0 ms one step at a time before this and the label kernels' other changes).
    label_steps: int = 32
    # 'uniform': every ray from `sample_rays`. 'loss': `leaf_ray_fraction` of each batch starts inside leaf boxes
    # drawn in proportion to the running per-leaf error (N-BVH's loss-proportional node resampling; the floor keeps
    # every leaf at >= leaf_floor x the mean weight). Measured worse than 'uniform' on all 6 benchmark meshes at 15 s
    # (MSE 3.6x in geometric mean, bench/bench_leaf_sampling.py): off by default.
    leaf_sampling: str = "uniform"
    leaf_ray_fraction: float = 0.5
    leaf_floor: float = 0.05
    # N-BVH's tree-cut splitting: start from an SAH cut with tree_cut_start x the final leaves and split the leaves
    # with the highest running error in tree_cut_rounds rounds spread evenly over the first tree_cut_until of the
    # budget (the reference splits every 40 of its first 3,000 of 10,000 iterations). Measured at 15 s on 6 meshes:
    # MSE 1.12x in geometric mean (better only on the open sheet; bench/bench_leaf_sampling.py): off by default.
    tree_cut: bool = False
    tree_cut_start: float = 0.5
    tree_cut_rounds: int = 10
    tree_cut_until: float = 0.3
    # Quantization-aware end of training: for the last qat_fraction of the budget the feature table is snapped to its
    # table_bits-bit grid (per level and feature, `quantize.table_affine`) and held there while the network adapts to
    # the quantized rows; the affine map is kept (`encoding.qat_affine`) so the file's codes reproduce them exactly.
    table_bits: int | None = None
    qat_fraction: float = 0.05
    #: Below 8 bits the network's weights train through their rows on the grid for the same share of the budget as a
    #: low-bit table (`network_quantization.NetworkQuantization`); None or 8 and above: rounded once, at the end.
    network_bits: int | None = None
    # With a `target_reached` callback (a requested quality), it is asked every this many seconds once 10% of the
    # budget has passed; True ends training there (no more than the asset needs). HashVQAD stops only after its freeze.
    # The check's own time is not training time: the budget's clock (and the learning rate's schedule) stops for it,
    # so a checked training takes as many steps as an unchecked one (the bunny's 11 checks had cost it 10%).
    target_check_every_s: float = 20.0
    #: The weights training returns: from `average_from` of the budget on, a moving average of each step's
    #: weights with this decay per step (a uniform mean over its first 1 / (1 - decay) steps; 0 = the last step's).
    #: At the end's learning rate the network's last steps scatter around its optimum: on the bunny (default preset
    #: and three variants of it, 200 s, the two read from one training each) the average over ~100 steps read -8.0%,
    #: -3.7%, -0.5% and +1.0% image MSE against the last step's weights (mean -2.8%; over ~2,000 steps: -14% to +4%).
    weight_average: float = 0.99
    average_from: float = 0.9
    ray_config: RayConfig = field(default_factory=RayConfig)

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class TrainResult:
    steps: int
    seconds: float
    samples: int
    samples_per_s: float
    final_loss: float
    device: str
    history: list = field(default_factory=list)  # (step, loss)
    soft_loss_before_freeze: float | None = None
    frozen_loss: float | None = None  # right after the freeze
    finetuned_loss: float | None = None  # at the end, after the hard fine-tune
    compute_path: str = ""  # kernels.plan(...).describe(): which kernel ran each stage
    kernel_plan: dict = field(default_factory=dict)  # the same, as fields (kernels.KernelPlan)
    stopped_early: bool = False  # the target_reached callback ended training before the budget
    #: (step, seconds, new log2 T) of each time the table grew (the target_reached callback asked for it)
    grew: list = field(default_factory=list)
    #: (seconds since the start, log2 T, image MSE) of each quality check of a training with a target (the trajectory
    #: of a growing training through its sizes; filled by the caller's check)
    checks: list = field(default_factory=list)
    #: (step, seconds, learning rate scale after) of each divergence the training recovered from (`recovery`)
    recovered: list = field(default_factory=list)


def pick_device(name: str = "auto") -> torch.device:
    """'auto' -> CUDA when available, else CPU; 'cuda' without a GPU raises a clear error."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise RuntimeError("device 'cuda' requested but no CUDA GPU is available to PyTorch")
    return torch.device(name)


def samples_loss(model: NeuralBVH, s: TrainingSamples, device: torch.device, want_raw: bool = False):
    """Loss of the model on labelled samples (moved to `device`): (loss, parts); with want_raw, parts['raw'] holds
    the network's raw outputs (detached)."""
    r = s.ray.to(device)
    o, d = s.rays_o.to(device)[r], s.rays_d.to(device)[r]
    raw = model(o, d, s.t_enter.to(device), s.t_exit.to(device))
    loss, parts = model.network.loss(raw, s.hit.to(device), s.local_t.to(device), s.normal.to(device))
    if want_raw:
        parts["raw"] = raw.detach()
    return loss, parts


# ------------------------------------------------------------------------------------------- the loop's parts
def make_optimizer(model: NeuralBVH, cfg: TrainConfig, plan: kernels.KernelPlan) -> torch.optim.Adam:
    """Adam over the model's parameters, HashVQAD's index logits in their own group at `logits_lr_factor` x lr;
    the fused implementation where the plan says so (`kernels.optimizer_kernel`)."""
    logits = [p for n, p in model.named_parameters() if n.endswith("logits")]
    others = [p for n, p in model.named_parameters() if not n.endswith("logits")]
    groups = [{"params": others, "lr_factor": 1.0}]
    if logits:
        groups.append({"params": logits, "lr_factor": cfg.logits_lr_factor})
    return torch.optim.Adam(groups, lr=cfg.lr, fused=plan.optimizer == "fused Adam" or None)


class Schedule:
    """The training fraction in [0, 1] (steps or seconds, whichever budget runs out first) and the learning rate
    at a fraction: lr x lr_factor(group) x lr_final_factor ** fraction (exponential decay over the budget)."""

    def __init__(self, cfg: TrainConfig):
        self.cfg = cfg
        self.scale = 1.0  # lowered after a divergence (`recovery.Recovery`)

    def fraction(self, step: int, elapsed_s: float) -> float:
        cfg = self.cfg
        return max(step / cfg.steps if cfg.steps else 0.0, elapsed_s / cfg.time_limit_s if cfg.time_limit_s else 0.0)

    def set_lr(self, opt: torch.optim.Optimizer, fraction: float) -> None:
        for g in opt.param_groups:
            g["lr"] = self.cfg.lr * self.scale * g["lr_factor"] * self.cfg.lr_final_factor ** fraction


#: Steps from which a loss that never fell 2% below its start ends the training as diverged, live or not.
FLAT_JUDGED_STEPS = 500


class DivergenceGuard:
    """Raises TrainingDiverged for a non-finite loss, a loss above divergence_factor x its running mean after 50
    steps, a running mean risen above rise_factor x the untrained model's loss, and (at the end, `finish`) a loss
    that never fell 2% below its start in FLAT_JUDGED_STEPS steps, or in 50+ in a network whose gradients stop at
    its output bias (a learning rate so high it killed the network early)."""

    def __init__(self, cfg: TrainConfig, start_step: int):
        self.cfg, self.start_step = cfg, start_step
        self.ema: float | None = None
        self.first: list[float] = []  # the first 5 losses; [0] is the untrained model's
        self.warm_from = start_step  # the running mean counts from here (the start, or the last going back)

    def settled(self, step: int) -> bool:
        """Whether the running mean has 50+ steps behind it (a state now is one to go back to)."""
        return self.ema is not None and step - self.warm_from > 50

    def went_back(self, step: int) -> None:
        """The model went back to an earlier state (`recovery.Recovery`): the running mean starts again; the
        untrained loss stays the reference for the rise and the end's checks."""
        self.ema, self.warm_from = None, step

    def observe(self, step: int, loss: float) -> None:
        cfg, ran = self.cfg, step - self.start_step
        if not math.isfinite(loss):
            raise TrainingDiverged(f"loss became {loss} at step {step}")
        if self.settled(step) and loss > cfg.divergence_factor * self.ema:
            raise TrainingDiverged(f"loss jumped to {loss:.4g} (running mean {self.ema:.4g}) at step {step}")
        self.ema = loss if self.ema is None else 0.98 * self.ema + 0.02 * loss
        if len(self.first) < 5:
            self.first.append(loss)
        elif ran >= 50 and self.ema > cfg.rise_factor * self.first[0]:
            raise TrainingDiverged(f"loss rose from {self.first[0]:.4g} to {self.ema:.4g} (running mean) by step "
                                   f"{step}: the learning rate {cfg.lr:g} is too high for this model")

    def finish(self, model: NeuralBVH, step: int) -> None:
        for p in model.parameters():
            if not torch.isfinite(p).all():
                raise TrainingDiverged("parameters contain NaN/inf after training")
        # One small batch is noisy enough to fake or hide a 2% fall: compare with the mean of the first 5.
        start = max(float(np.mean(self.first)), self.first[0]) if self.first else None
        ran = step - self.start_step
        # A live network at a lowered learning rate on a slow machine can stay within 2% for a few hundred steps
        # (CI: blob, lr 5e-4, 188 steps): below FLAT_JUDGED_STEPS only a network that no longer learns (no gradient
        # past its output bias) is thrown away; from there a flat loss is judged as it always was.
        flat = start is not None and ran >= 50 and self.ema >= 0.98 * start
        if flat and (ran >= FLAT_JUDGED_STEPS or not gradients_pass_output_bias(model)):
            # Dead ReLUs predict the prior and the loss stays at its start: such a model is useless; never saved.
            raise TrainingDiverged(f"the loss did not fall in {ran} steps ({start:.4g} -> {self.ema:.4g}): "
                                   f"the learning rate {self.cfg.lr:g} is too high for this model, or it cannot learn")


def gradients_pass_output_bias(model: torch.nn.Module) -> bool:
    """Whether the last step's gradients reach a weight matrix or table (any parameter of 2+ dimensions): a network
    whose ReLUs all died passes gradient to its output bias alone; a model without gradients counts as not learning."""
    return any(p.grad is not None and p.dim() >= 2 and bool(p.grad.detach().abs().amax() > 0)
               for p in model.parameters())


def make_step(model: NeuralBVH, device: torch.device, plan: kernels.KernelPlan):
    """The training step the plan chose, hiding fused vs autograd: step(batch, want_raw) -> (loss, parts) with every
    parameter's .grad set (parts['raw']: the network's raw outputs when want_raw)."""
    if plan.train_step != "autograd":  # forward, loss and backward in one kernel call (neural/fused_mlp.py)
        from ..neural import fused_mlp

        return lambda batch, want_raw: fused_mlp.train_step(model, batch, want_raw=want_raw)

    def autograd_step(batch: TrainingSamples, want_raw: bool) -> tuple[float, dict]:
        loss, parts = samples_loss(model, batch, device, want_raw=want_raw)
        loss.backward()
        return float(loss.detach()), parts

    return autograd_step


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


class EncodingPhases:
    """The encoding's life cycle inside training: its own schedule (HashVQAD's anneal: `Encoding.schedule`), the
    freeze (scored before and after on held-out rays; `before_freeze(model)` is called first), and the
    quantization-aware end (cfg.table_bits: the table snapped to its grid and held there, see TrainConfig).
    `before_step(fraction)` returns the phase the step trains in."""

    def __init__(self, model: NeuralBVH, cfg: TrainConfig, events: EventSink, held_out_loss, before_freeze,
                 qat_affine=None):
        self.model, self.cfg, self.events = model, cfg, events
        self.held_out_loss, self.before_freeze = held_out_loss, before_freeze
        self.phase = "train"
        self.losses: dict = {}  # 'soft' / 'frozen': held-out losses around the freeze
        self.qat_on = qat_affine is not None
        self._float_rows = None  # below 8 bits, during a step: the float rows the grid's rows stand in for
        if self.qat_on:  # resumed inside the quantization-aware phase
            model.encoding.qat_affine = qat_affine
        #: Below 8 bits the network's weights train through their rows too (from the low-bit table's start).
        self.network_grid = NetworkQuantization(model.network, cfg.network_bits,
                                                1.0 - max(cfg.qat_fraction, LOW_BITS_QAT_FRACTION))
        #: What training returns: the last steps' mean, restarted by every change of form below (`weight_average`).
        self.average = WeightAverage(model, cfg.weight_average, cfg.average_from)

    def before_step(self, fraction: float) -> str:
        enc, cfg = self.model.encoding, self.cfg
        low_bits = trains_through_grid(cfg.table_bits)
        if enc.freeze_due(fraction, cfg):
            self.freeze()
            self.phase = "finetune"
        own = enc.schedule(fraction, cfg)
        if own is not None and own != self.phase:
            self.phase = own
            self.events(wire.phase(phase=own, message=f"softmax temperature 1 -> {cfg.tau_min}"))
        qat_fraction = max(cfg.qat_fraction, LOW_BITS_QAT_FRACTION) if low_bits else cfg.qat_fraction
        if cfg.table_bits and not self.qat_on and fraction >= 1.0 - qat_fraction:
            self.qat_on = _snap_table(self.model, cfg.table_bits, hold=not low_bits)
            self.events(wire.phase(phase="quantize",
                                   message=f"feature table on its {cfg.table_bits}-bit grid; the network adapts to it"
                                   + ("" if not low_bits else ", the rows train through it")))
        self.network_grid.before_step(fraction)
        if self.qat_on and low_bits:  # straight through: this step sees the rows on the grid
            table = enc.table
            self._float_rows = table.detach().clone()
            table.data.copy_(_on_grid(self._float_rows, enc.qat_affine, cfg.table_bits))
        return self.phase

    def after_backward(self) -> None:
        self.network_grid.after_backward()
        if not self.qat_on:
            return
        if self._float_rows is not None:  # the gradient at the grid's rows updates the float rows under them
            self.model.encoding.table.data.copy_(self._float_rows)
            self._float_rows = None
        else:  # 8 bits: the snapped table stays on its grid
            self.model.encoding.table.grad = None

    def after_step(self, fraction: float) -> None:
        """After the optimizer's step: the weights into the average (a snap or a freeze starts it over)."""
        self.average.update(fraction, state_form(self.model))

    def freeze(self) -> None:
        self.losses["soft"] = self.held_out_loss()
        if self.before_freeze is not None:
            self.before_freeze(self.model)
        self.model.encoding.freeze()
        self.losses["frozen"] = self.held_out_loss()
        self.events(wire.phase(phase="freeze",
                               message=f"index codes frozen; held-out loss {self.losses['soft']:.4f} -> "
                                       f"{self.losses['frozen']:.4f}; fine-tuning on the frozen codes"))

    @property
    def ready_to_stop(self) -> bool:
        """An early stop waits for the encoding's final form (HashVQAD: frozen)."""
        return self.model.encoding.frozen

    def finish(self, result: "TrainResult") -> None:
        """After the loop: the averaged weights go into the model; a learned index is frozen now if the budget ended
        before its fine-tune."""
        self.average.apply()
        if self.model.encoding.learned_index and self.cfg.freeze:
            if not self.model.encoding.frozen:
                self.freeze()
            result.soft_loss_before_freeze = self.losses.get("soft")
            result.frozen_loss = self.losses.get("frozen")
            result.finetuned_loss = self.held_out_loss()


@torch.no_grad()
def _snap_table(model: NeuralBVH, bits: int, hold: bool = True) -> bool:
    """Fix the feature table's `bits`-bit grid (see TrainConfig.table_bits) and record its affine map; hold: snap the
    rows onto it now (8 bits: they stay there)."""
    from ..neural.quantize import dequantize_table, quantize_table, table_affine

    table = model.encoding.table
    arr = table.detach().cpu().numpy()
    offset, scale = table_affine(arr, bits)
    if hold:
        snapped = dequantize_table(quantize_table(arr, offset, scale, bits), offset, scale)
        table.copy_(torch.from_numpy(snapped).to(table.device))
    model.encoding.qat_affine = (offset, scale)
    return True


def _on_grid(rows: torch.Tensor, affine: tuple, bits: int) -> torch.Tensor:
    """(L, T, F) float rows rounded onto the (L, F) affine grid of `bits` bits (clipped to its range)."""
    offset = torch.as_tensor(affine[0], device=rows.device)[:, None, :]
    scale = torch.as_tensor(affine[1], device=rows.device)[:, None, :]
    return offset + torch.clamp(torch.round((rows - offset) / scale), 0, (1 << bits) - 1) * scale


class Progress:
    """`progress` events at most every cfg.progress_every_s (fraction, loss, samples/s, ETA) and the final one."""

    def __init__(self, events: EventSink, cfg: TrainConfig, elapsed_before: float):
        self.events, self.cfg, self.elapsed_before = events, cfg, elapsed_before
        self.last = 0.0
        self.samples = 0

    def maybe_emit(self, phase: str, step: int, fraction: float, loss: float, now: float) -> None:
        if now - self.last < self.cfg.progress_every_s:
            return
        self.last = now
        eta = (now / fraction - now) if fraction > 0.01 else None
        self.emit(phase, step, fraction, loss, now, eta)

    def samples_per_s(self, now: float) -> float:
        return self.samples / max(now - self.elapsed_before, 1e-9)

    def emit(self, phase: str, step: int, fraction: float, loss: float, now: float, eta: float | None) -> None:
        self.events(wire.progress(phase=phase, step=step, total=self.cfg.steps, fraction=round(fraction, 4),
                                  loss=round(loss, 6), samples_per_s=round(self.samples_per_s(now), 1),
                                  elapsed_s=round(now, 2), eta_s=None if eta is None else round(eta, 1)))


class EarlyStop:
    """Asks target_reached(model) every cfg.target_check_every_s once 10% of the budget has passed (and the
    encoding is in its final form): True ends training (see TrainConfig.target_check_every_s); "grow" asks for a
    table twice as large (`grow_table`), honoured while the model can still be trained at its new size (before
    GROW_UNTIL of the budget, a HashGrid not yet quantized); "roll back" returns to the best check's state
    (`best_weights`). An answer that is a check record (`records.CheckDecision`) also offers its MSE, so the best
    check's state is kept."""

    #: No growth after this fraction of the budget: the larger table would get too little training to pay.
    GROW_UNTIL = 0.8

    def __init__(self, target_reached, cfg: TrainConfig, last_s: float):
        self.target_reached, self.cfg, self.last_s = target_reached, cfg, last_s
        self.grew: list[tuple[int, float, int]] = []  # (step, seconds, new log2 T) of each growth
        self.spent_s = 0.0  # the last act()'s own seconds
        self.best = BestWeights()
        self.last_mse: float | None = None  # the last check's MSE, when its answer carried one

    def act(self, model: NeuralBVH, opt, checkpoints: "Checkpoints", events: EventSink, phases, step: int,
            fraction: float, elapsed: float) -> bool:
        """Ask (when due) and do what the answer says: grow the table, or return True to end training. `spent_s`:
        the seconds this call took (the caller's budget clock stops for them)."""
        began = time.perf_counter()
        try:
            return self._act(model, opt, checkpoints, events, phases, step, fraction, elapsed)
        finally:
            self.spent_s = time.perf_counter() - began

    def _act(self, model, opt, checkpoints, events, phases, step: int, fraction: float, elapsed: float) -> bool:
        decision = self.reached(model, fraction, elapsed, phases.ready_to_stop)
        if decision == "roll back":
            self._roll_back(model, opt, phases, events, f"check at step {step}")
            return False
        if self.last_mse is not None:
            self.best.offer(model, opt, self.last_mse, state_form(model))
        if decision == "grow":
            grown = grow_table(model, opt, checkpoints)
            self.grew.append((step, round(elapsed, 1), grown))
            events(wire.phase(phase=phases.phase,
                              message=f"target not in reach at this size: the table grows to T=2^{grown}"))
            return False
        if decision:
            events(wire.phase(phase=phases.phase,
                              message=f"target reached at step {step} ({elapsed:.0f} s): training stops"))
        return bool(decision)

    def at_end(self, model: NeuralBVH, opt, phases: EncodingPhases, events: EventSink, stopped_early: bool) -> None:
        """When the budget is spent (not after an early stop): a callback with an `at_end(model)` method
        (`CheckRule.at_end`) measures the finished model once more, and its "roll back" puts the best check's state
        in its place (after the weight average; the result's loss and seconds are the finished model's). The
        finished state can read far worse than the last check: the bunny's seed 9 (target 0.0004) ended at 1.31x and
        1.32x its last check's MSE in two sessions, where 26 other runs ended at 0.84-1.01x
        (bench/results/target_runs.csv)."""
        ask = getattr(self.target_reached, "at_end", None)
        if ask is None or self.best.mse is None or stopped_early:
            return
        answer = ask(model)
        self.last_mse = getattr(answer, "mse", None)
        if getattr(answer, "action", answer) == "roll back":
            self._roll_back(model, opt, phases, events, "the finished model")

    def _roll_back(self, model, opt, phases, events: EventSink, what: str) -> None:
        if not self.best.restore(model, opt, state_form(model)):
            return
        phases.average.restart()  # the steps since the best check are not the weights' neighbourhood any more
        events(wire.phase(phase=phases.phase, message=f"{what} read {self.last_mse:.4g}, far above the best check "
                                                      f"({self.best.mse:.4g}): back to that check's weights"))

    def reached(self, model: NeuralBVH, fraction: float, elapsed: float, ready: bool) -> bool | str:
        """False (no check due, or train on), "grow" (honoured only while growth can pay), "roll back", or True
        (stop)."""
        self.last_mse = None
        if (self.target_reached is None or fraction < 0.1 or not ready
                or elapsed - self.last_s < self.cfg.target_check_every_s):
            return False
        self.last_s = elapsed
        answer = self.target_reached(model)
        self.last_mse = getattr(answer, "mse", None)
        answer = getattr(answer, "action", answer)
        if answer == "roll back":
            return answer
        if answer == "grow":
            return "grow" if fraction < self.GROW_UNTIL and model.encoding.can_grow() else False
        if isinstance(answer, str):  # a check's action (decision.records.CHECK_ACTIONS)
            if answer not in CHECK_ACTIONS:
                raise ValueError(f"unknown check action {answer!r}; one of {', '.join(CHECK_ACTIONS)}")
            return answer.startswith("stop")
        return bool(answer)


def state_form(model: NeuralBVH) -> tuple:
    """What a kept state must share with the model to be put back in it (`best_weights`, and the checks' record of
    the best of each form: `decision.checks.CheckRule`): table size, table on its grid, index frozen."""
    return (model.cfg.encoding.log2_table, getattr(model.encoding, "qat_affine", None) is not None,
            model.encoding.frozen)


def grow_table(model: NeuralBVH, opt: torch.optim.Optimizer, checkpoints: "Checkpoints") -> int:
    """Double the model's table in place, the encoded function unchanged (`HashGrid.grow`), with Adam's moments
    grown the same way so training goes on where it was; later checkpoints record the new size. Returns the new
    log2 T."""
    enc = model.encoding
    old = enc.table
    state = opt.state.pop(old, None) or {}
    moments = {k: enc.grown_like(v) if torch.is_tensor(v) and v.shape == old.shape else v for k, v in state.items()}
    new = enc.grow()
    for group in opt.param_groups:
        group["params"] = [new if p is old else p for p in group["params"]]
    if moments:
        opt.state[new] = moments
    model.cfg = dataclasses.replace(model.cfg, encoding=enc.cfg)
    settings = checkpoints.extra.get("settings")
    if isinstance(settings, dict):
        checkpoints.extra["settings"] = {**settings, "log2_table": enc.cfg.log2_table}
    return enc.cfg.log2_table


class _TreeCutHook:
    """N-BVH's tree cut inside training: the model and the batches start on the coarse cut, and follow each
    refinement (`TreeCut.refine`)."""

    def __init__(self, tree_cut: TreeCut, model: NeuralBVH, events: EventSink):
        self.tree_cut, self.model, self.events = tree_cut, model, events

    def after_step(self, fraction: float, batches: Batches, leaf_errors: LeafErrors, phase: str) -> None:
        refined = self.tree_cut.refine(fraction, batches.bvh, leaf_errors)
        if refined is None:
            return
        self.model.set_nodes(refined.nodes)
        batches.set_bvh(refined)
        if refined.n_leaves >= self.tree_cut.final_leaves:
            self.events(wire.phase(phase=phase, message=f"tree cut refined to {refined.n_nodes} nodes by splitting the "
                                                        "leaves with the highest error"))


def _held_out_loss(model: NeuralBVH, batches: Batches, tracer: ExactTracer, cfg: TrainConfig,
                   device: torch.device):
    """A fixed set of 8192 held-out rays (seeded apart from training) and the model's loss on them, as a callable."""
    def loss() -> float:
        rays = sample_rays(batches.lo, batches.hi, 8192, np.random.default_rng(cfg.seed + 7919), cfg.ray_config)
        held_out = label_samples(batches.bvh, tracer, *rays, cfg.labels, tree=batches.tree,
                                 normal_loss=cfg.normal_loss)
        with torch.no_grad():
            return float(samples_loss(model, held_out, device)[0])
    return loss


def _training_data(model, bvh, tracer, cfg, ck, device, plan, rng, events):
    """The batches, the leaf errors (loss sampling or tree cut) and the tree-cut hook of one run (resumed from ck)."""
    if cfg.leaf_sampling not in ("uniform", "loss"):
        raise ValueError(f"leaf_sampling must be 'uniform' or 'loss', got {cfg.leaf_sampling!r}")
    # Overlapping labels with training is part of the fast path; the reference path stays synchronous.
    prefetch = (device.type == "cuda" if cfg.prefetch is None else cfg.prefetch) and plan.path == "fast"
    cut = None
    if cfg.tree_cut:  # train on a coarser cut first and split where the error is high (see TrainConfig)
        tree_cut = TreeCut(bvh, cfg, ck.get("cut"), ck.get("tree_cut_rounds_done", 0))
        bvh = tree_cut.start
        model.set_nodes(bvh.nodes)
        prefetch = False  # a refinement drops the labelled batches of the old cut: none may be in flight
        cut = _TreeCutHook(tree_cut, model, events)
    leaf_errors = LeafErrors(bvh.n_leaves, cfg.leaf_floor) if cfg.leaf_sampling == "loss" or cut else None
    if leaf_errors is not None and ck.get("leaf_errors") is not None:
        if ck["leaf_errors"].shape != leaf_errors.error.shape or ck["leaf_errors"].dtype != leaf_errors.error.dtype:
            raise CheckpointError(f"the checkpoint's leaf errors do not fit this BVH ({bvh.n_leaves} leaves)")
        leaf_errors.error = ck["leaf_errors"].clone()
    batches = Batches(bvh, tracer, cfg, rng, prefetch=prefetch, resume=ck.get("numpy_rng"),
                      leaf_errors=leaf_errors if cfg.leaf_sampling == "loss" else None)
    return batches, leaf_errors, cut


def _resumed_at(ck: dict, events: EventSink) -> tuple[int, float, list]:
    """(step, elapsed seconds, loss history) a training starts from: a checkpoint's (said), or the beginning."""
    if ck:
        events(wire.phase(phase="train", message=f"resumed at step {ck['step']}"))
    return ck.get("step", 0), ck.get("elapsed", 0.0), ck.get("history", [])


def _checkpoint_state(model, opt, step, elapsed, history, batches, leaf_errors, cut, phases) -> dict:
    """What a checkpoint holds (see load_checkpoint): model, optimizer, step, elapsed seconds, loss history, the
    generators' states, the per-leaf errors, the tree cut, the quantization-aware phase's affine map (the caller adds
    the learning rate's scale, `Schedule.scale`)."""
    return {"model": model.state_dict(), "optimizer": opt.state_dict(), "step": step, "elapsed": elapsed,
            "history": history, "numpy_rng": batches.rng_state(), "torch_rng": torch.get_rng_state(),
            "leaf_errors": None if leaf_errors is None else leaf_errors.error.clone(),
            "cut": None if cut is None else batches.bvh.leaf_full.tolist(),
            "tree_cut_rounds_done": 0 if cut is None else cut.tree_cut.rounds_done,
            "qat_affine": model.encoding.qat_affine if phases.qat_on else None}


def check_config(cfg: TrainConfig) -> None:
    """Raise ValueError for a budget or phase fractions no training can follow."""
    if cfg.steps is None and cfg.time_limit_s is None:
        raise ValueError("set a step budget or a time limit")
    if not (0.0 <= cfg.finetune_fraction < 1.0 and 0.0 <= cfg.anneal_fraction <= 1.0 - cfg.finetune_fraction):
        raise ValueError(f"need 0 <= finetune_fraction < 1 and 0 <= anneal_fraction <= 1 - finetune_fraction, got "
                         f"{cfg.finetune_fraction} and {cfg.anneal_fraction}")


def _note_leaf_errors(leaf_errors: LeafErrors | None, model: NeuralBVH, batch: TrainingSamples, parts: dict) -> None:
    """Loss-proportional leaf sampling: the step's per-sample errors into the running per-leaf error."""
    if leaf_errors is not None:
        leaf_errors.update(batch.leaf, model.network.sample_errors(parts["raw"].cpu(), batch.hit, batch.local_t,
                                                                   batch.normal))


def train(model: NeuralBVH, bvh: BVH, tracer: ExactTracer, cfg: TrainConfig, events: EventSink = null_sink,
          should_cancel: Callable[[], bool] = lambda: False, checkpoint_path: str | os.PathLike | None = None,
          resume_from: str | os.PathLike | None = None, before_freeze: Callable[[NeuralBVH], None] | None = None,
          checkpoint_extra: dict | None = None,
          target_reached: Callable[[NeuralBVH], object] | None = None) -> TrainResult:
    """Train `model` in place on rays around `bvh`, labelled by `tracer`; freezes HashVQAD near the end.

    before_freeze(model) is called once just before the HashVQAD freeze (e.g. to score the soft model).
    checkpoint_extra: stored in every checkpoint under 'extra' (the caller's settings and mesh identity).
    target_reached(model) -> bool, a check's action (`records.CHECK_ACTIONS`) or record (`CheckDecision`, as
    `CheckRule` answers), asked every cfg.target_check_every_s seconds: True or "stop: ..." stops training early;
    "grow" doubles the table, "roll back" returns to the best check's state; see `EarlyStop` (and its `at_end`)."""
    check_config(cfg)
    device = pick_device(cfg.device)
    torch.manual_seed(cfg.seed)
    plan = kernels.plan(model.to(device), device)
    opt = make_optimizer(model, cfg, plan)
    ck = load_checkpoint(resume_from, model, opt, device) if resume_from is not None else {}
    step, elapsed_before, history = _resumed_at(ck, events)
    batches, leaf_errors, cut = _training_data(model, bvh, tracer, cfg, ck, device, plan,
                                               np.random.default_rng(cfg.seed), events)
    schedule, guard, progress = Schedule(cfg), DivergenceGuard(cfg, step), Progress(events, cfg, elapsed_before)
    schedule.scale = ck.get("lr_scale", 1.0)  # lowered by a recovery before the checkpoint
    recovery = Recovery(guard, schedule, cfg.divergence_recoveries, events, state_form)
    phases = EncodingPhases(model, cfg, events, _held_out_loss(model, batches, tracer, cfg, device), before_freeze,
                            ck.get("qat_affine"))
    checkpoints, early = Checkpoints(checkpoint_path, cfg, checkpoint_extra, elapsed_before), EarlyStop(target_reached, cfg, elapsed_before)
    train_step = make_step(model, device, plan)
    events(wire.phase(phase="train", message=f"{model.cfg.encoding.kind}+{model.cfg.network.kind}, "
                                                           f"{cfg.labels} labels, {plan.describe()}"))

    def state() -> dict:  # what a checkpoint holds now
        return dict(_checkpoint_state(model, opt, step, time.perf_counter() - t0, history, batches, leaf_errors, cut,
                                      phases), lr_scale=schedule.scale)

    t0 = time.perf_counter() - elapsed_before
    stopped_early, loss = False, float("nan")
    gc.freeze()  # what exists now (torch, the model, the data) lives on: full collections skip it (were ~8% of a step)
    try:
        while (frac := schedule.fraction(step, elapsed := time.perf_counter() - t0)) < 1.0:
            stopped_early = early.act(model, opt, checkpoints, events, phases, step, frac, elapsed)
            t0 += early.spent_s  # a check measures: its time is not the budget's (nor the schedule's)
            if stopped_early:
                break
            if should_cancel():
                checkpoints.save(state())
                raise Cancelled(f"cancelled at step {step}")
            phase = phases.before_step(frac)
            schedule.set_lr(opt, frac)
            batch = batches.next()
            opt.zero_grad(set_to_none=True)
            loss, parts = train_step(batch, leaf_errors is not None)
            if not recovery.step_is_healthy(model, opt, phases.average, step, loss, frac, elapsed):
                continue  # diverged: back to the last healthy state, this step's gradients dropped
            _note_leaf_errors(leaf_errors, model, batch, parts)
            phases.after_backward()
            opt.step()
            phases.after_step(frac)
            step += 1
            if cut is not None:
                cut.after_step(frac, batches, leaf_errors, phase)
            progress.samples += len(batch)
            history.append((step, loss))
            now = time.perf_counter() - t0
            checkpoints.maybe_save(step, now, state)
            progress.maybe_emit(phase, step, frac, loss, now)
    finally:
        batches.close()
        gc.unfreeze()
    guard.finish(model, step)
    seconds = time.perf_counter() - t0
    result = TrainResult(steps=step, seconds=seconds, samples=progress.samples,
                         samples_per_s=progress.samples_per_s(seconds),
                         final_loss=guard.ema if guard.ema is not None else loss, device=str(device),
                         history=history, compute_path=plan.describe(), kernel_plan=plan.to_dict(),
                         stopped_early=stopped_early, grew=early.grew, recovered=recovery.recovered)
    progress.emit(phases.phase, step, 1.0, result.final_loss, seconds, 0.0)
    phases.finish(result)
    early.at_end(model, opt, phases, events, stopped_early)
    return result
