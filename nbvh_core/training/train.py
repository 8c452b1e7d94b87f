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

The loop's parts, one concern per file beside it: config.py (TrainConfig, TrainResult), checkpoints.py (write,
gather, read back), encoding_phases.py (the encoding's anneal, freeze and grid phases; `state_form`),
early_stop.py (the checks inside the loop: stop, grow, roll back), recovery.py (a late divergence put back),
ray_batches.py (labelled batches, leaf errors, the tree cut).
"""
from __future__ import annotations

import gc
import math
import time

import numpy as np
import torch

from .. import kernels
from .card_labels import card_labels_for
from .ray_batches import Batches, LeafErrors, TreeCut, label_workers  # noqa: F401  (LeafErrors: re-exported)
from ..geometry.bvh import BVH
from ..storage.checkpoint import CheckpointError, load_checkpoint
from ..protocol.events import EventSink
from ..protocol import events as wire
from ..geometry.exact import ExactTracer
from ..neural.model import NeuralBVH
from ..protocol.process import Cancelled, TrainingDiverged
from .budget_clock import BudgetClock
from .checkpoints import Checkpoints, checkpoint_state, resumed_at
from .config import LEAF_SAMPLINGS, TrainConfig, TrainResult
from .early_stop import EarlyStop
from .hooks import CheckpointFiles, TrainingHooks
from .encoding_phases import EncodingPhases, state_form
from .loss_reads import LossBook, read_every
from .recovery import Recovery
from .rays import TrainingSamples, label_samples, sample_rays


def pick_device(name: str = "auto") -> torch.device:
    """'auto' -> CUDA when available, else CPU; 'cuda' without a GPU raises ValueError (one line: the CLI's exit 2)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError("device 'cuda' requested but no CUDA GPU is available to PyTorch (--device auto uses the "
                         "card when there is one)")
    return torch.device(name)


def samples_loss(model: NeuralBVH, s: TrainingSamples, device: torch.device, want_raw: bool = False):
    """Loss of the model on labelled samples (moved to `device`): (loss, parts); with want_raw, parts['raw'] holds
    the network's raw outputs (detached)."""
    def on(t: torch.Tensor) -> torch.Tensor:  # pinned batches (`Batches.pin`) copy while the host goes on
        return t.to(device, non_blocking=True)

    r = on(s.ray)
    o, d = on(s.rays_o)[r], on(s.rays_d)[r]
    t_enter, t_exit = on(s.t_enter), on(s.t_exit)
    raw = model(o, d, t_enter, t_exit)
    local_t = ((on(s.t_hit) - t_enter) / (t_exit - t_enter).clamp_min(1e-12)).clamp(0.0, 1.0)  # as s.local_t
    loss, parts = model.network.loss(raw, on(s.hit), local_t, on(s.normal))
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

    def __init__(self, cfg: TrainConfig, scale: float = 1.0):
        self.cfg = cfg
        self.scale = scale  # lowered after a divergence (`recovery.Recovery`)

    def fraction(self, step: int, elapsed_s: float) -> float:
        cfg = self.cfg
        return max(step / cfg.steps if cfg.steps else 0.0, elapsed_s / cfg.time_limit_s if cfg.time_limit_s else 0.0)

    def set_lr(self, opt: torch.optim.Optimizer, fraction: float) -> None:
        for g in opt.param_groups:
            g["lr"] = self.cfg.lr * self.scale * g["lr_factor"] * self.cfg.lr_final_factor ** fraction


#: Steps from which a loss that never fell 2% below its start ends the training as diverged, live or not.
FLAT_JUDGED_STEPS = 500
#: Steps between the checks that the network still learns (`live_unit_fraction`; one device read each).
ALIVE_EVERY = 50
#: Below this share of live units in the last hidden layer, with a loss that has not fallen below DEAD_LOSS_FALL x
#: the untrained one, the network has stopped learning (`check_alive`; healthy runs of every preset: 0.31-1.0).
MIN_LIVE_UNITS = 0.125
DEAD_LOSS_FALL = 0.9


class DivergenceGuard:
    """Raises TrainingDiverged for a non-finite loss, a loss above divergence_factor x its running mean after 50
    steps, a running mean risen above rise_factor x the untrained model's loss, a network whose units have died
    while its loss barely fell (`check_alive`, every ALIVE_EVERY steps), and (at the end, `finish`) a loss
    that never fell 2% below its start in FLAT_JUDGED_STEPS steps, or in 50+ in a network whose gradients stop at
    its output bias (a learning rate so high it killed the network early)."""

    def __init__(self, cfg: TrainConfig, start_step: int):
        self.cfg, self.start_step = cfg, start_step
        self.ema: float | None = None
        self.first: list[float] = []  # the first 5 losses; [0] is the untrained model's
        self.warm_from = start_step  # the running mean counts from here (the start, or the last going back)
        self.next_alive_check = start_step + ALIVE_EVERY

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

    def check_alive(self, model: NeuralBVH, step: int) -> None:
        """Every ALIVE_EVERY steps, with this step's gradients set: raises TrainingDiverged when under MIN_LIVE_UNITS
        of the last hidden layer's units pass gradient and the loss has not fallen 10% below the untrained model's
        (a healthy one has fallen ~60% by step 50 on the blob). An early spike can kill the ReLUs; the all but dead
        network then predicts about a constant at a loss a little below the untrained one, which neither the rise nor
        the flat check sees (the blob at lr 0.5: losses 1.89, 39.5, 239, then 1.84 for the whole budget, shipped at
        MSE 0.075; 2 of 32 units live at step 50, none at 100, where a healthy run has 30-32; failures.md)."""
        if step < self.next_alive_check:
            return
        self.next_alive_check = step + ALIVE_EVERY
        fell = self.ema is not None and bool(self.first) and self.ema < DEAD_LOSS_FALL * self.first[0]
        live = live_unit_fraction(model)
        if live < MIN_LIVE_UNITS and not fell:
            raise TrainingDiverged(f"the network stopped learning by step {step} ({live:.0%} of its last layer's "
                                   f"units pass gradient): the learning rate {self.cfg.lr:g} is too high for "
                                   f"this model")

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


def live_unit_fraction(model: torch.nn.Module) -> float:
    """The share of the last hidden layer's units through which this step's gradient passed: columns of the network's
    last linear weight with any non-zero gradient (0.0 with no gradient; 1.0 for a model without such a layer, whose
    death `gradients_pass_output_bias` judges)."""
    linears = [m for m in getattr(model, "network", model).modules() if isinstance(m, torch.nn.Linear)]
    if not linears:
        return 1.0 if gradients_pass_output_bias(model) else 0.0
    grad = linears[-1].weight.grad
    if grad is None:
        return 0.0
    return float((grad.detach() != 0).any(dim=0).float().mean())


def gradients_pass_output_bias(model: torch.nn.Module) -> bool:
    """Whether the last step's gradients reach a weight matrix or table (any parameter of 2+ dimensions): a network
    whose ReLUs all died passes gradient to its output bias alone; a model without gradients counts as not learning."""
    return any(p.grad is not None and p.dim() >= 2 and bool(p.grad.detach().abs().amax() > 0)
               for p in model.parameters())


def make_step(model: NeuralBVH, device: torch.device, plan: kernels.KernelPlan):
    """The training step the plan chose, hiding fused vs autograd: step(batch, want_raw) -> (loss, parts) with every
    parameter's .grad set (parts['raw']: the network's raw outputs when want_raw); loss: a float (the fused CPU
    step) or a 0-d tensor on the training device, read to the host later (`loss_reads`)."""
    if plan.train_step.startswith("fused"):  # forward, loss and backward in one kernel call (neural/fused_mlp.py)
        from ..neural import fused_mlp

        return lambda batch, want_raw: fused_mlp.train_step(model, batch, want_raw=want_raw)

    def autograd_step(batch: TrainingSamples, want_raw: bool) -> tuple[torch.Tensor, dict]:
        loss, parts = samples_loss(model, batch, device, want_raw=want_raw)
        loss.backward()
        return loss.detach(), parts  # read to the host with the next steps' (`loss_reads`)

    return autograd_step


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
    if cfg.leaf_sampling not in LEAF_SAMPLINGS:
        raise ValueError(f"leaf_sampling must be one of {', '.join(LEAF_SAMPLINGS)}, got {cfg.leaf_sampling!r}")
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
    card_labels = card_labels_for(tracer, bvh, device)
    # the host's labels take several threads on a many-core card host; the card's, one thread that draws and launches
    workers = label_workers(kernels.threads()) if device.type == "cuda" and card_labels is None else 1
    batches = Batches(bvh, tracer, cfg, rng, prefetch=prefetch, resume=ck.get("numpy_rng"),
                      leaf_errors=leaf_errors if cfg.leaf_sampling == "loss" else None, pin=device.type == "cuda",
                      reuse=cfg.label_reuse, spare_passes=cfg.spare_label_passes,
                      draw_parts=max(2, kernels.threads()) if device.type == "cuda" else 2,
                      label_workers=workers, card_labels=card_labels)
    return batches, leaf_errors, cut


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
        leaf_errors.update(batch.leaf.cpu(), model.network.sample_errors(  # held on the CPU (labels may be on the card)
            parts["raw"].cpu(), batch.hit.cpu(), batch.local_t.cpu(), batch.normal.cpu()))


def _what_trains(model: NeuralBVH, cfg: TrainConfig, plan: kernels.KernelPlan) -> str:
    """The training's opening line: encoding + network, labels, the kernel plan."""
    return f"{model.cfg.encoding.kind}+{model.cfg.network.kind}, {cfg.labels} labels, {plan.describe()}"


def train(model: NeuralBVH, bvh: BVH, tracer: ExactTracer, cfg: TrainConfig,
          hooks: TrainingHooks = TrainingHooks(), files: CheckpointFiles = CheckpointFiles()) -> TrainResult:
    """Train `model` in place on rays around `bvh`, labelled by `tracer`; freezes HashVQAD near the end. hooks: what
    the loop calls back, and when (`hooks.HOOK_SCHEDULE`: events, cancel, the target's checks, before the freeze);
    files: where checkpoints go and the one it resumes (`hooks.CheckpointFiles`)."""
    events, called_at = hooks.events, time.perf_counter()
    check_config(cfg)
    device = pick_device(cfg.device)
    torch.manual_seed(cfg.seed)
    plan = kernels.plan(model.to(device), device)
    opt = make_optimizer(model, cfg, plan)
    ck = load_checkpoint(files.resume_from, model, opt, device) if files.resume_from is not None else {}
    step, elapsed_before, history = resumed_at(ck, events)
    batches, leaf_errors, cut = _training_data(model, bvh, tracer, cfg, ck, device, plan,
                                               np.random.default_rng(cfg.seed), events)
    schedule = Schedule(cfg, scale=ck.get("lr_scale", 1.0))  # a recovery before the checkpoint lowered the scale
    guard, progress = DivergenceGuard(cfg, step), Progress(events, cfg, elapsed_before)
    recovery = Recovery(guard, schedule, cfg.divergence_recoveries, events, state_form)
    phases = EncodingPhases(model, cfg, events, _held_out_loss(model, batches, tracer, cfg, device),
                            hooks.before_freeze, ck.get("qat_affine"))
    checkpoints = Checkpoints(files.path, cfg, files.extra, elapsed_before)
    early = EarlyStop(hooks.target_reached, cfg, elapsed_before, step)
    train_step = make_step(model, device, plan)
    events(wire.phase(phase="train", message=_what_trains(model, cfg, plan)))
    losses = LossBook(read_every(cfg.loss_read_every, device), history, recovery, model, opt, phases)

    def state() -> dict:  # what a checkpoint holds now
        return dict(checkpoint_state(model, opt, step, clock.elapsed(), losses.with_unread(), batches,
                                     leaf_errors, cut, phases), lr_scale=schedule.scale)

    clock, stopped_early = BudgetClock(cfg.checks_outside_budget_s, elapsed_before, called_at), False
    gc.freeze()  # what exists now (torch, the model, the data) lives on: full collections skip it (were ~8% of a step)
    try:
        while (frac := schedule.fraction(step, (elapsed := clock.elapsed()) + clock.tail_s)) < 1.0:
            if early.due(frac, elapsed, phases.ready_to_stop):
                losses.read(frac, elapsed)  # a check may roll back or grow the model: judge the steps before it
            stopped_early = early.act(model, opt, checkpoints, events, phases, step, frac, elapsed)
            early.last_s += clock.checked(early.spent_s)  # a check measures: budget time only past the wall margin
            if stopped_early:
                break
            if hooks.should_cancel():
                checkpoints.save(state())
                raise Cancelled(f"cancelled at step {step}")
            phase = phases.before_step(frac)
            schedule.set_lr(opt, frac)
            batch = batches.next()
            opt.zero_grad(set_to_none=True)
            loss, parts = train_step(batch, leaf_errors is not None)
            if losses.add(step, loss) and not losses.read(frac, elapsed, vouched=True):
                continue  # diverged: back to the last healthy state, this step's gradients dropped
            _note_leaf_errors(leaf_errors, model, batch, parts)
            phases.after_backward()
            opt.step()
            phases.after_step(frac)
            step += 1
            if cut is not None:
                cut.after_step(frac, batches, leaf_errors, phase)
            progress.samples += len(batch)
            now = clock.elapsed()
            checkpoints.maybe_save(step, now, state)
            progress.maybe_emit(phase, step, frac, history[-1][1] if history else float("nan"), now)
        losses.read(frac, clock.elapsed())  # the last steps' losses, judged as every other
    finally:
        batches.close()
        gc.unfreeze()
    guard.finish(model, step)
    seconds = clock.elapsed()
    result = TrainResult(steps=step, seconds=seconds, samples=progress.samples,
                         samples_per_s=progress.samples_per_s(seconds),
                         final_loss=guard.ema if guard.ema is not None else float("nan"), device=str(device),
                         history=history, compute_path=plan.describe(), kernel_plan=plan.to_dict(),
                         stopped_early=stopped_early, grew=early.grew, recovered=recovery.recovered,
                         checks_s=round(clock.checks_s, 2), label_reuse=batches.reuse,
                         reused_batches=batches.reused, rays_per_step=cfg.rays_per_step)
    progress.emit(phases.phase, step, 1.0, result.final_loss, seconds, 0.0)
    phases.finish(result)
    early.at_end(model, opt, phases, events, stopped_early, step, seconds)
    return result
