"""A whole MLP over rows of inputs as one Triton kernel: each program takes BLOCK_M rows through every layer
(tl.dot per layer, K-blocked on the first; bias and ReLU fused; the activations stay on chip). The reference is
`neural.networks.run_layers` (torch's Linear + ReLU).

Layout the kernel reads (`pack_mlp`, once per model): the first layer's weight (W, K) with K padded to a multiple of
BLOCK_K, the hidden layers' weights stacked (H-1, W, W), the output layer's (OUT_PAD, W) with its rows padded to 16
(tl.dot's smallest tile), every bias float32. The network's own outputs are the first n_out columns.

    packed = pack_mlp(sequential)                  # from an nn.Sequential of Linear/ReLU, float32 weights
    out = mlp_forward(x, packed)                   # x (M, n_in) float32 -> (M, n_out) float32
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import triton
import triton.language as tl

BLOCK_M, BLOCK_K, MIN_TILE = 32, 32, 16


@dataclass(frozen=True)
class PackedMLP:
    """An MLP laid out for `_mlp_forward` (see the module docstring). hidden: the hidden layers after the first."""

    w_in: torch.Tensor
    b_in: torch.Tensor
    w_hidden: torch.Tensor
    b_hidden: torch.Tensor
    w_out: torch.Tensor
    b_out: torch.Tensor
    n_in: int
    n_out: int

    @property
    def width(self) -> int:
        return int(self.w_in.shape[0])

    @property
    def hidden(self) -> int:
        return int(self.w_hidden.shape[0])


def _round_up(n: int, to: int) -> int:
    return (n + to - 1) // to * to


def pack_mlp(net: torch.nn.Sequential, weight=None) -> PackedMLP:
    """`net` (Linear, ReLU, ..., Linear; at least one hidden layer) laid out for the kernel; weight(linear) -> its
    (out, in) float32 weight however it is held (default: `.weight` as float32; the caller passes the network's own
    dequantizing formula). Raises ValueError for a shape the kernel does not take (a width that is not a power of
    two >= 16): the caller falls back to torch and says so."""
    weight = weight or (lambda m: m.weight.detach().float())
    linears = [m for m in net if isinstance(m, torch.nn.Linear)]
    if len(linears) < 2:
        raise ValueError("the Triton MLP needs at least one hidden layer")
    width = linears[0].out_features
    if width < MIN_TILE or width & (width - 1) or any(m.out_features != width for m in linears[:-1]):
        raise ValueError(f"the Triton MLP takes hidden widths that are one power of two >= {MIN_TILE}, not {width}")
    dev = linears[0].weight.device
    first = weight(linears[0]).detach().float()
    w_in = torch.zeros(width, _round_up(first.shape[1], BLOCK_K), device=dev)
    w_in[:, :first.shape[1]] = first
    mids = linears[1:-1]
    w_hidden = (torch.stack([weight(m).detach().float() for m in mids]) if mids
                else torch.zeros(0, width, width, device=dev))
    b_hidden = (torch.stack([m.bias.detach().float() for m in mids]) if mids else torch.zeros(0, width, device=dev))
    last = linears[-1]
    out_pad = _round_up(max(last.out_features, MIN_TILE), MIN_TILE)
    w_out = torch.zeros(out_pad, width, device=dev)
    w_out[:last.out_features] = weight(last).detach().float()
    b_out = torch.zeros(out_pad, device=dev)
    b_out[:last.out_features] = last.bias.detach().float()
    return PackedMLP(w_in.contiguous(), linears[0].bias.detach().float().contiguous(), w_hidden.contiguous(),
                     b_hidden.contiguous(), w_out.contiguous(), b_out.contiguous(), first.shape[1],
                     last.out_features)


@triton.jit
def _mlp_forward(x_ptr, w_in_ptr, b_in_ptr, w_hid_ptr, b_hid_ptr, w_out_ptr, b_out_ptr, out_ptr, m, n_in,
                 K_PAD: tl.constexpr, W: tl.constexpr, HIDDEN: tl.constexpr, OUT_PAD: tl.constexpr, n_out,
                 BM: tl.constexpr, BK: tl.constexpr):
    rows = tl.program_id(0) * BM + tl.arange(0, BM)
    live = rows < m
    cols_w = tl.arange(0, W)
    acc = tl.zeros((BM, W), dtype=tl.float32)
    for k0 in tl.static_range(0, K_PAD, BK):  # first layer, K-blocked: x (BM, BK) @ W_in^T (BK, W)
        ks = k0 + tl.arange(0, BK)
        xk = tl.load(x_ptr + rows[:, None].to(tl.int64) * n_in + ks[None, :], mask=live[:, None] & (ks[None, :] < n_in),
                     other=0.0)
        wk = tl.load(w_in_ptr + cols_w[None, :] * K_PAD + ks[:, None])  # (BK, W): W_in transposed
        acc += tl.dot(xk, wk)
    h = tl.maximum(acc + tl.load(b_in_ptr + cols_w)[None, :], 0.0)
    for layer in tl.static_range(HIDDEN):
        w = tl.load(w_hid_ptr + layer * W * W + cols_w[None, :] * W + cols_w[:, None])  # (W_in, W_out)
        h = tl.maximum(tl.dot(h, w) + tl.load(b_hid_ptr + layer * W + cols_w)[None, :], 0.0)
    cols_o = tl.arange(0, OUT_PAD)
    w = tl.load(w_out_ptr + cols_o[None, :] * W + cols_w[:, None])  # (W, OUT_PAD)
    y = tl.dot(h, w) + tl.load(b_out_ptr + cols_o)[None, :]
    tl.store(out_ptr + rows[:, None].to(tl.int64) * n_out + cols_o[None, :], y,
             mask=live[:, None] & (cols_o[None, :] < n_out))


def mlp_forward(x: torch.Tensor, packed: PackedMLP) -> torch.Tensor:
    """x (M, n_in) float32 -> (M, n_out) float32: every layer of `packed` in one kernel (inference: no autograd;
    on a GPU tl.dot multiplies in TF32, ~1e-3 relative, as torch's own default for convolutions)."""
    x = x.contiguous().float()
    m = x.shape[0]
    out = torch.empty(m, packed.n_out, device=x.device)
    _mlp_forward[(triton.cdiv(m, BLOCK_M),)](
        x, packed.w_in, packed.b_in, packed.w_hidden, packed.b_hidden, packed.w_out, packed.b_out, out, m,
        packed.n_in, K_PAD=packed.w_in.shape[1], W=packed.width, HIDDEN=packed.hidden, OUT_PAD=packed.w_out.shape[0],
        n_out=packed.n_out, BM=BLOCK_M, BK=BLOCK_K)
    return out
