"""Quantization-aware end of training for the network's weights below 8 bits (the straight-through estimator).

A file at `network_bits` 4 stores each Linear's weight rows as codes in [-7, 7] with one float16 scale per row
(`neural.quantize.quantize_rows`). Rounded after training, those rows lose what 16 levels cannot hold; so for the
last part of the budget each step's forward and backward see the weights as the file will hold them
(float16(code * scale), recomputed every step from the float weights), and the gradient taken there updates the
float weights under them. The last step's rounding is then the file's. At 8 bits the rounding alone costs ~1% of
the image MSE (`quantize.py`), so nothing is done there.
"""
from __future__ import annotations

import torch
from torch import nn

from ..neural.quantize import code_limit


@torch.no_grad()
def rows_on_grid(weight: torch.Tensor, bits: int) -> torch.Tensor:
    """(out, in) float32 weights -> the same rows as a `bits`-bit file holds them, float32: per row
    scale = float16(max |w| / code_limit), code = round(w / scale) clipped, value = float16(code * scale) (the
    formulas of `quantize.quantize_rows` and `dequantize_rows`)."""
    limit = code_limit(bits)
    amax = weight.abs().amax(dim=1)
    scale = torch.where(amax > 0, amax / limit, torch.ones_like(amax)).half().float()
    scale = torch.where(scale > 0, scale, torch.ones_like(scale))
    codes = torch.clamp(torch.round(weight / scale[:, None]), -limit, limit)
    return (codes * scale[:, None]).half().float()


class NetworkQuantization:
    """The network's weights trained through their `bits`-bit rows (bits < 8) once `fraction` of the budget is
    past `start`: `before_step(fraction)` puts the rows on the grid (keeping the float weights), `after_backward()`
    puts the float weights back for the optimizer. Stateless between steps, so a resumed run needs nothing saved."""

    def __init__(self, network: nn.Module, bits: int | None, start: float):
        self.linears = [m for m in network.modules() if isinstance(m, nn.Linear)]
        self.bits, self.start = bits, start
        self.active = bits is not None and bits < 8
        self._float: list[torch.Tensor] | None = None

    def before_step(self, fraction: float) -> bool:
        """Put the weights on their grid for this step when due; True when they are."""
        if not self.active or fraction < self.start:
            return False
        self._float = [m.weight.detach().clone() for m in self.linears]
        for m, w in zip(self.linears, self._float):
            m.weight.data.copy_(rows_on_grid(w, self.bits))
        return True

    def after_backward(self) -> None:
        """The float weights back under the gradient the grid's rows produced."""
        if self._float is None:
            return
        for m, w in zip(self.linears, self._float):
            m.weight.data.copy_(w)
        self._float = None
