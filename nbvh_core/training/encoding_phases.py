"""The encoding's life cycle inside a training: HashVQAD's anneal and freeze, the quantization-aware end (the table
snapped to its grid, or trained through it below 8 bits), the network's rows on their grid, the weight average,
and the form a kept state must share with the model to be put back (`state_form`)."""
from __future__ import annotations

import torch

from ..neural.model import NeuralBVH
from ..protocol import events as wire
from ..protocol.events import EventSink
from .config import TrainConfig, TrainResult
from .network_quantization import NetworkQuantization
from .weight_average import WeightAverage



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


def state_form(model: NeuralBVH) -> tuple:
    """What a kept state must share with the model to be put back in it (`best_weights`, and the checks' record of
    the best of each form: `decision.checks.CheckRule`): table size, table on its grid, index frozen."""
    return (model.cfg.encoding.log2_table, getattr(model.encoding, "qat_affine", None) is not None,
            model.encoding.frozen)


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
