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

import math
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from . import kernels
from .bvh import BVH, refine_cut
from .events import EventSink, null_sink
from .exact import ExactTracer
from .model import NeuralBVH
from .samples import (RayConfig, TrainingSamples, label_samples, root_box, sample_rays, sample_rays_in_leaves,
                      split_samples)


class Cancelled(Exception):
    """The job was cancelled; nothing was saved as a result."""


class TrainingDiverged(RuntimeError):
    """Loss or parameters became NaN/inf or exploded; the model is not usable and is never saved."""


@dataclass
class TrainConfig:
    """labels: 'ownership' | 'consistent'. Budget: `steps`, or `time_limit_s` (whichever ends first; at least
    one must be set). rays_per_step: rays drawn per step (each yields ~1-5 leaf samples)."""

    labels: str = "consistent"
    lr: float = 1e-3
    lr_final_factor: float = 0.1
    rays_per_step: int = 4096
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
    checkpoint_every: int = 0
    #: Also write a checkpoint every this many seconds of training (0 = off); a kill loses at most one period.
    checkpoint_every_s: float = 0.0
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
    # (MSE 3.6x in geometric mean, bench/results/leaf_sampling.md): off by default.
    leaf_sampling: str = "uniform"
    leaf_ray_fraction: float = 0.5
    leaf_floor: float = 0.05
    # N-BVH's tree-cut splitting: start from an SAH cut with tree_cut_start x the final leaves and split the leaves
    # with the highest running error in tree_cut_rounds rounds spread evenly over the first tree_cut_until of the
    # budget (the reference splits every 40 of its first 3,000 of 10,000 iterations). Measured at 15 s on 6 meshes:
    # MSE 1.12x in geometric mean (better only on the open sheet; bench/results/tree_cut.md): off by default.
    tree_cut: bool = False
    tree_cut_start: float = 0.5
    tree_cut_rounds: int = 10
    tree_cut_until: float = 0.3
    # Quantization-aware end of training: for the last qat_fraction of the budget the feature table is snapped to its
    # qat_bits-bit grid (per level and feature, `quantize.table_affine`) and held there while the network adapts to
    # the quantized rows; the affine map is kept (`encoding.qat_affine`) so the file's codes reproduce them exactly.
    qat_bits: int | None = None
    qat_fraction: float = 0.05
    # With a `target_reached` callback (a requested quality), it is asked every this many seconds once 10% of the
    # budget has passed; True ends training there (no more than the asset needs). HashVQAD stops only after its freeze.
    target_check_every_s: float = 20.0
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
    compute_path: str = ""  # kernels.describe(): fast (fused kernels) or reference (pure torch)
    stopped_early: bool = False  # the target_reached callback ended training before the budget


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


def sample_errors(network, raw: torch.Tensor, s: TrainingSamples) -> torch.Tensor:
    """(S,) per-sample error of decoded predictions: BCE of the hit probability, plus for hits the weighted depth
    and normal L1s (the loss's terms, per sample; for loss-proportional leaf sampling)."""
    prob, local_t, normal = network.decode(raw.detach().cpu())
    hit = s.hit.to(prob.dtype)
    bce = torch.nn.functional.binary_cross_entropy(prob.clamp(1e-6, 1 - 1e-6), hit, reduction="none")
    cfg = network.cfg
    return bce + hit * (cfg.depth_weight * (local_t - s.local_t).abs()
                        + cfg.normal_weight * (normal - s.normal).abs().sum(-1))


class LeafErrors:
    """Running mean error per leaf (exponential, per batch) and the sampling weights drawn from it."""

    def __init__(self, n_leaves: int, floor: float, decay: float = 0.9):
        self.error = torch.ones(n_leaves, dtype=torch.float64)  # untrained: every leaf alike
        self.floor, self.decay = floor, decay

    def update(self, leaf: torch.Tensor, errors: torch.Tensor) -> None:
        """leaf (S,) leaf ordinals, errors (S,) per-sample errors of one batch."""
        n = self.error.shape[0]
        total = torch.zeros(n, dtype=torch.float64).index_add_(0, leaf, errors.to(torch.float64))
        count = torch.bincount(leaf, minlength=n).to(torch.float64)
        seen = count > 0
        self.error[seen] = self.decay * self.error[seen] + (1 - self.decay) * total[seen] / count[seen]

    def weights(self) -> np.ndarray:
        e = self.error.numpy()
        return np.maximum(e, self.floor * e.mean())


class _Batches:
    """Fresh labelled rays for every step, from one seeded generator.

    Rays for `cfg.label_steps` steps are drawn and labelled together (one chunk) and split by ray into per-step
    batches. With `prefetch`, a background thread makes the next chunks while the current step trains (Embree,
    numpy and the kernels release the GIL), in the same order from the same generator, so the batches are the ones
    a synchronous run would see. `rng_state()` says where the last batch handed out came from (the generator's
    state before its chunk and its index in the chunk): what a checkpoint stores to resume exactly.
    """

    def __init__(self, bvh: BVH, tracer: ExactTracer, cfg: TrainConfig, rng: np.random.Generator,
                 prefetch: bool = False, resume: dict | None = None, leaf_errors: "LeafErrors | None" = None):
        self.bvh, self.tracer, self.cfg, self.rng = bvh, tracer, cfg, rng
        self.lo, self.hi = root_box(bvh)
        from .traversal import TorchBVH

        self.tree = TorchBVH.from_bvh(bvh)
        self._pending: list = []  # batches of the current chunk not yet handed out
        self._pool = None  # ray-drawing threads, made on first use
        self.leaf_errors = leaf_errors  # loss-proportional leaf sampling: the running per-leaf errors
        self._leaf_boxes = bvh.leaf_boxes() if leaf_errors is not None else None
        self._state = {"chunk_state": rng.bit_generator.state, "index": -1}
        skip = 0
        self._weights_override = None  # the leaf weights the resumed chunk was drawn with
        if resume is not None:
            rng.bit_generator.state = resume["chunk_state"]
            skip = resume["index"] + 1
            self._weights_override = resume.get("leaf_weights")
        self._queue = None
        if prefetch:
            import queue
            import threading

            self._queue = queue.Queue(maxsize=2)
            self._stop = threading.Event()
            self._thread = threading.Thread(target=self._produce, daemon=True)
            self._thread.start()
        for _ in range(skip):  # the resumed chunk's batches already trained on
            self.next()

    def _make(self):
        """One chunk: [(batch, {'chunk_state', 'index'}), ...] for label_steps steps."""
        chunk_state = self.rng.bit_generator.state
        n_steps = max(1, self.cfg.label_steps)
        per = self.cfg.rays_per_step
        weights = None
        if self.leaf_errors is not None:
            weights = self._weights_override if self._weights_override is not None else self.leaf_errors.weights()
            self._weights_override = None
        o, d = self._draw(per * n_steps, weights)
        chunk = label_samples(self.bvh, self.tracer, o, d, self.cfg.labels, tree=self.tree)
        return [(part, {"chunk_state": chunk_state, "index": i, "leaf_weights": weights})
                for i, part in enumerate(split_samples(chunk, per))]

    def set_bvh(self, bvh: BVH) -> None:
        """Label with a refined cut from now on: the rest of the current labelling pass (labelled with the old cut)
        is dropped, and the next pass starts from the generator's current state (recorded for checkpoints)."""
        from .traversal import TorchBVH

        self.bvh, self.tree = bvh, TorchBVH.from_bvh(bvh)
        if self._leaf_boxes is not None:
            self._leaf_boxes = bvh.leaf_boxes()
        self._pending = []
        self._state = {"chunk_state": self.rng.bit_generator.state, "index": -1}

    def _draw(self, n: int, leaf_weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """n rays: all from `sample_rays`, or with leaf weights `leaf_ray_fraction` of them from
        `sample_rays_in_leaves` (mixed by a permutation)."""
        if leaf_weights is not None:  # loss-proportional: part of the rays start in the worst leaves
            n_leaf = int(round(n * self.cfg.leaf_ray_fraction))
            o_u, d_u = self._draw_uniform(n - n_leaf)
            o_l, d_l = sample_rays_in_leaves(*self._leaf_boxes, leaf_weights, n_leaf, self.rng)
            perm = self.rng.permutation(n)
            return np.concatenate((o_u, o_l))[perm], np.concatenate((d_u, d_l))[perm]
        return self._draw_uniform(n)

    def _draw_uniform(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """n rays of `sample_rays` in two halves drawn by two threads (numpy's generators and ufuncs release the
        GIL), each from a generator seeded by the main one: deterministic, and resumable from its state."""
        seeds = self.rng.integers(0, 2 ** 63, size=2)
        sizes = (n // 2, n - n // 2)
        if self._pool is None:
            from concurrent.futures import ThreadPoolExecutor

            self._pool = ThreadPoolExecutor(max_workers=2, thread_name_prefix="nbvh-rays")
        halves = list(self._pool.map(
            lambda i: sample_rays(self.lo, self.hi, sizes[i], np.random.default_rng(seeds[i]), self.cfg.ray_config),
            range(2)))
        return np.concatenate([h[0] for h in halves]), np.concatenate([h[1] for h in halves])

    def _produce(self) -> None:
        import queue

        while not self._stop.is_set():
            try:
                item = self._make()
            except Exception as exc:  # handed to the consumer, raised there
                item = (exc, None)
            while not self._stop.is_set():
                try:
                    self._queue.put(item, timeout=0.1)
                    break
                except queue.Full:
                    continue
            if isinstance(item[0], Exception):
                return

    def next(self) -> TrainingSamples:
        if not self._pending:
            chunk = self._queue.get() if self._queue is not None else self._make()
            if isinstance(chunk[0], Exception):
                raise chunk[0]
            self._pending = list(chunk)
        batch, self._state = self._pending.pop(0)
        return batch

    def rng_state(self) -> dict:
        return self._state

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=False)
        if self._queue is not None:
            self._stop.set()
            self._thread.join(timeout=5)


class _TreeCut:
    """N-BVH's tree-cut splitting during training (TrainConfig.tree_cut): `start` is the coarse cut training begins
    on (or the cut a checkpoint stopped at); `refine` splits the leaves with the highest running error in
    cfg.tree_cut_rounds rounds spread over the first cfg.tree_cut_until of the budget, up to bvh's node budget."""

    def __init__(self, bvh: BVH, cfg: TrainConfig, resumed_cut: list | None = None, rounds_done: int = 0):
        from .bvh import coarse_cut, layout_cut

        self.cfg = cfg
        self.final_leaves = bvh.n_leaves
        self.rounds_done = rounds_done
        self.start = (layout_cut(bvh.full, {int(n) for n in resumed_cut}, bvh.budget, final=False)
                      if resumed_cut is not None else
                      coarse_cut(bvh, max(2, int(self.final_leaves * cfg.tree_cut_start))))

    def refine(self, frac: float, current: BVH, leaf_errors: LeafErrors) -> BVH | None:
        """The refined cut when a round is due at training fraction `frac` (leaf_errors follow the split: children
        inherit their parent's error), else None."""
        cfg = self.cfg
        due = min(cfg.tree_cut_rounds, int(frac / cfg.tree_cut_until * cfg.tree_cut_rounds)) \
            if cfg.tree_cut_until > 0 else 0
        if current.n_leaves >= self.final_leaves or self.rounds_done >= due:
            return None
        self.rounds_done = due
        # Leaves still to add, shared over the rounds left (the last round reaches the budget).
        per_round = -(-(self.final_leaves - current.n_leaves) // max(1, cfg.tree_cut_rounds - due + 1))
        refined, parent = refine_cut(current, leaf_errors.error.numpy(), per_round)
        if refined.n_leaves == current.n_leaves:  # nothing left to split
            self.final_leaves = refined.n_leaves
            return None
        leaf_errors.error = leaf_errors.error[torch.from_numpy(parent)]
        return refined


@torch.no_grad()
def _snap_table(model: NeuralBVH, bits: int) -> bool:
    """Snap the feature table onto its `bits`-bit grid (see TrainConfig.qat_bits); records the affine map."""
    from .quantize import dequantize_table, quantize_table, table_affine

    table = model.encoding.table
    arr = table.detach().cpu().numpy()
    offset, scale = table_affine(arr, bits)
    snapped = dequantize_table(quantize_table(arr, offset, scale, bits), offset, scale)
    table.copy_(torch.from_numpy(snapped).to(table.device))
    model.encoding.qat_affine = (offset, scale)
    return True


def _atomic_save(obj, path: Path) -> None:
    """torch.save, written atomically (outputs.write_atomic): a kill mid-write keeps the previous checkpoint."""
    import io

    from .outputs import write_atomic

    buf = io.BytesIO()
    torch.save(obj, buf)
    write_atomic(path, buf.getvalue())


def train(model: NeuralBVH, bvh: BVH, tracer: ExactTracer, cfg: TrainConfig, events: EventSink = null_sink,
          should_cancel: Callable[[], bool] = lambda: False, checkpoint_path: str | os.PathLike | None = None,
          resume_from: str | os.PathLike | None = None,
          before_freeze: Callable[[NeuralBVH], None] | None = None,
          checkpoint_extra: dict | None = None,
          target_reached: Callable[[NeuralBVH], bool] | None = None) -> TrainResult:
    """Train `model` in place on rays around `bvh`, labelled by `tracer`; freezes HashVQAD near the end.

    before_freeze(model) is called once just before the HashVQAD freeze (e.g. to score the soft model).
    checkpoint_extra: stored in every checkpoint under 'extra' (the caller's settings and mesh identity).
    target_reached(model) -> bool: polled every cfg.target_check_every_s seconds; True stops training early.
    """
    if cfg.steps is None and cfg.time_limit_s is None:
        raise ValueError("set a step budget or a time limit")
    device = pick_device(cfg.device)
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    model.to(device)
    logits = [p for n, p in model.named_parameters() if n.endswith("logits")]
    others = [p for n, p in model.named_parameters() if not n.endswith("logits")]
    groups = [{"params": others, "lr_factor": 1.0}]
    if logits:
        groups.append({"params": logits, "lr_factor": cfg.logits_lr_factor})
    # The fast path uses torch's fused Adam (one kernel over all parameters: 8 vs 84 ms per step for HashVQAD's
    # 8.4M index logits on the 2-core CPU); the reference path keeps the default implementation.
    opt = torch.optim.Adam(groups, lr=cfg.lr, fused=kernels.current_path() == "fast" or None)
    start_step, elapsed_before = 0, 0.0
    history: list = []
    ck: dict = {}  # the checkpoint resumed from (empty for a fresh run)
    if resume_from is not None:
        ck = torch.load(resume_from, map_location=device, weights_only=False)
        codes = ck["model"].get("encoding.codes")
        if codes is not None and codes.numel() and hasattr(model.encoding, "freeze"):
            model.encoding.freeze()  # the checkpoint is past the freeze: same structure before loading
        model.load_state_dict(ck["model"])
        opt.load_state_dict(ck["optimizer"])
        start_step, elapsed_before, history = ck["step"], ck["elapsed"], ck["history"]
        torch.set_rng_state(ck["torch_rng"])
        events({"event": "phase", "phase": "train", "message": f"resumed at step {start_step}"})
    # Overlapping labels with training is part of the fast path; the reference path stays synchronous.
    prefetch = device.type == "cuda" if cfg.prefetch is None else cfg.prefetch
    if cfg.leaf_sampling not in ("uniform", "loss"):
        raise ValueError(f"leaf_sampling must be 'uniform' or 'loss', got {cfg.leaf_sampling!r}")
    tree_cut = _TreeCut(bvh, cfg, ck.get("cut"), ck.get("tree_cut_rounds_done", 0)) if cfg.tree_cut else None
    if tree_cut is not None:  # train on a coarser cut first and split where the error is high (see TrainConfig)
        bvh = tree_cut.start
        model.nodes, model._tree = bvh.nodes, None
        prefetch = False  # a refinement drops the labelled batches of the old cut: none may be in flight
    leaf_errors = (LeafErrors(bvh.n_leaves, cfg.leaf_floor)
                   if cfg.leaf_sampling == "loss" or tree_cut is not None else None)
    if leaf_errors is not None and ck.get("leaf_errors") is not None:
        leaf_errors.error = ck["leaf_errors"].clone()
    batches = _Batches(bvh, tracer, cfg, rng, prefetch=prefetch and kernels.current_path() == "fast",
                       resume=ck.get("numpy_rng"), leaf_errors=leaf_errors if cfg.leaf_sampling == "loss" else None)
    is_vqad = hasattr(model.encoding, "freeze")
    result_losses: dict = {}
    from .kernels import mlp as fused_mlp

    # Fast path, MLP network: one fused kernel per step (kernels/mlp.py); otherwise torch autograd.
    fused_step = fused_mlp.trains(model)

    def held_out_loss() -> float:
        held_out = label_samples(batches.bvh, tracer, *sample_rays(batches.lo, batches.hi, 8192,
                                                           np.random.default_rng(cfg.seed + 7919), cfg.ray_config),
                                 cfg.labels, tree=batches.tree)
        with torch.no_grad():
            return float(samples_loss(model, held_out, device)[0])

    def freeze_now() -> None:
        result_losses["soft"] = held_out_loss()
        if before_freeze is not None:
            before_freeze(model)
        model.encoding.freeze()
        result_losses["frozen"] = held_out_loss()
        events({"event": "phase", "phase": "freeze",
                "message": f"index codes frozen; held-out loss {result_losses['soft']:.4f} -> "
                           f"{result_losses['frozen']:.4f}; fine-tuning on the frozen codes"})

    def save_checkpoint(step: int, elapsed: float) -> None:
        if checkpoint_path is not None:
            _atomic_save({"model": model.state_dict(), "optimizer": opt.state_dict(), "step": step,
                          "elapsed": elapsed, "history": history, "numpy_rng": batches.rng_state(),
                          "torch_rng": torch.get_rng_state(), "train_config": cfg.to_dict(),
                          "leaf_errors": None if leaf_errors is None else leaf_errors.error.clone(),
                          "cut": None if tree_cut is None else batches.bvh.leaf_full.tolist(),
                          "tree_cut_rounds_done": 0 if tree_cut is None else tree_cut.rounds_done,
                          "qat_affine": model.encoding.qat_affine if qat_on else None,
                          "extra": checkpoint_extra or {}},
                         Path(checkpoint_path))

    events({"event": "phase", "phase": "train",
            "message": f"{model.cfg.encoding.kind}+{model.cfg.network.kind}, {cfg.labels} labels, on {device}, "
                       f"{kernels.describe(device)}"})
    t0 = time.perf_counter() - elapsed_before
    last_emit = 0.0
    last_checkpoint = elapsed_before
    last_target_check = elapsed_before
    stopped_early = False
    n_samples = 0
    ema = None
    first_losses: list[float] = []  # the first 5 batches; [0] is the untrained model's loss
    step = start_step
    loss_val = float("nan")
    phase = "train"
    qat_on = False
    if ck.get("qat_affine") is not None:  # resumed inside the quantization-aware phase
        model.encoding.qat_affine = ck["qat_affine"]
        qat_on = True
    try:
        while True:
            elapsed = time.perf_counter() - t0
            frac = max(step / cfg.steps if cfg.steps else 0.0,
                       elapsed / cfg.time_limit_s if cfg.time_limit_s else 0.0)
            if frac >= 1.0:
                break
            if (target_reached is not None and frac >= 0.1 and elapsed - last_target_check >= cfg.target_check_every_s
                    and not (is_vqad and not model.encoding.frozen)):
                last_target_check = elapsed
                if target_reached(model):
                    stopped_early = True
                    events({"event": "phase", "phase": phase, "message": f"target reached at step {step} "
                                                                         f"({elapsed:.0f} s): training stops"})
                    break
            if should_cancel():
                save_checkpoint(step, elapsed)
                raise Cancelled(f"cancelled at step {step}")
            if is_vqad and cfg.freeze and not model.encoding.frozen and frac >= 1.0 - cfg.finetune_fraction:
                freeze_now()
                phase = "finetune"
            if is_vqad and not model.encoding.frozen:
                anneal_end = 1.0 - (cfg.finetune_fraction if cfg.freeze else 0.0)
                anneal_start = anneal_end - cfg.anneal_fraction
                if frac >= anneal_start and cfg.anneal_fraction > 0:
                    a = min(1.0, (frac - anneal_start) / cfg.anneal_fraction)
                    model.encoding.temperature = float(cfg.tau_min ** a)
                    if phase != "anneal":
                        phase = "anneal"
                        events({"event": "phase", "phase": "anneal",
                                "message": f"softmax temperature 1 -> {cfg.tau_min}"})
            if cfg.qat_bits and not qat_on and frac >= 1.0 - cfg.qat_fraction:
                qat_on = _snap_table(model, cfg.qat_bits)
                events({"event": "phase", "phase": "quantize",
                        "message": f"feature table snapped to {cfg.qat_bits} bits; the network adapts to it"})
            for g in opt.param_groups:
                g["lr"] = cfg.lr * g["lr_factor"] * cfg.lr_final_factor ** frac
            batch = batches.next()
            want_raw = leaf_errors is not None
            if fused_step:  # forward, loss and backward in one kernel call: the gradients are set already
                opt.zero_grad(set_to_none=True)
                loss_val, parts = fused_mlp.train_step(model, batch, want_raw=want_raw)
            else:
                loss, parts = samples_loss(model, batch, device, want_raw=want_raw)
                loss_val = float(loss.detach())
            if want_raw:
                leaf_errors.update(batch.leaf, sample_errors(model.network, parts["raw"], batch))
            if not math.isfinite(loss_val):
                raise TrainingDiverged(f"loss became {loss_val} at step {step}")
            if ema is not None and step - start_step > 50 and loss_val > cfg.divergence_factor * ema:
                raise TrainingDiverged(f"loss jumped to {loss_val:.4g} (running mean {ema:.4g}) at step {step}")
            ema = loss_val if ema is None else 0.98 * ema + 0.02 * loss_val
            if len(first_losses) < 5:
                first_losses.append(loss_val)  # what "rose" and "did not fall" compare with
            elif step - start_step >= 50 and ema > cfg.rise_factor * first_losses[0]:
                raise TrainingDiverged(f"loss rose from {first_losses[0]:.4g} to {ema:.4g} (running mean) by step "
                                       f"{step}: the learning rate {cfg.lr:g} is too high for this model")
            if not fused_step:
                opt.zero_grad(set_to_none=True)
                loss.backward()
            if qat_on:  # the snapped table stays on its grid
                model.encoding.table.grad = None
            opt.step()
            step += 1
            refined = tree_cut.refine(frac, batches.bvh, leaf_errors) if tree_cut is not None else None
            if refined is not None:
                model.nodes, model._tree = refined.nodes, None
                batches.set_bvh(refined)
                if refined.n_leaves >= tree_cut.final_leaves:
                    events({"event": "phase", "phase": phase, "message": f"tree cut refined to {refined.n_nodes} "
                            "nodes by splitting the leaves with the highest error"})
            n_samples += len(batch)
            history.append((step, loss_val))
            now = time.perf_counter() - t0
            if ((cfg.checkpoint_every and step % cfg.checkpoint_every == 0)
                    or (cfg.checkpoint_every_s and now - last_checkpoint >= cfg.checkpoint_every_s)):
                save_checkpoint(step, now)
                last_checkpoint = now
            if now - last_emit >= cfg.progress_every_s:
                last_emit = now
                run_time = now - elapsed_before
                sps = n_samples / max(run_time, 1e-9)
                eta = (now / frac - now) if frac > 0.01 else None
                events({"event": "progress", "phase": phase, "step": step, "total": cfg.steps, "fraction": round(frac, 4),
                        "loss": round(loss_val, 6), "samples_per_s": round(sps, 1), "elapsed_s": round(now, 2),
                        "eta_s": None if eta is None else round(eta, 1)})
    finally:
        batches.close()
    for p in model.parameters():
        if not torch.isfinite(p).all():
            raise TrainingDiverged("parameters contain NaN/inf after training")
    # One small batch is noisy enough to fake or hide a 2% fall: compare with the mean of the first 5 (a rate so high
    # that the loss explodes within them is caught by the rise check above).
    start_loss = max(float(np.mean(first_losses)), first_losses[0]) if first_losses else None
    if start_loss is not None and step - start_step >= 50 and ema >= 0.98 * start_loss:
        # A too-high learning rate can kill the network in the first steps (dead ReLUs): it then predicts the
        # prior and the loss stays at its starting value. Such a model is useless; do not save it.
        raise TrainingDiverged(f"the loss did not fall in {step - start_step} steps ({start_loss:.4g} -> {ema:.4g}): "
                               f"the learning rate {cfg.lr:g} is too high for this model, or it cannot learn")
    seconds = time.perf_counter() - t0
    run_time = seconds - elapsed_before
    result = TrainResult(steps=step, seconds=seconds, samples=n_samples,
                         samples_per_s=n_samples / max(run_time, 1e-9), final_loss=ema if ema is not None else loss_val,
                         device=str(device), history=history, compute_path=kernels.describe(device),
                         stopped_early=stopped_early)
    events({"event": "progress", "phase": phase, "step": step, "total": cfg.steps, "fraction": 1.0,
            "loss": round(result.final_loss, 6), "samples_per_s": round(result.samples_per_s, 1),
            "elapsed_s": round(seconds, 2), "eta_s": 0.0})
    if is_vqad and cfg.freeze:
        if not model.encoding.frozen:  # a budget too short to reach the fine-tune phase
            freeze_now()
        result.soft_loss_before_freeze = result_losses.get("soft")
        result.frozen_loss = result_losses.get("frozen")
        result.finetuned_loss = held_out_loss()
    return result
