"""A whole MLP over rows of inputs as one Triton kernel: each program takes BLOCK_M rows through every layer
(tl.dot per layer, K-blocked on the first; bias and ReLU fused; the activations stay on chip). The reference is
`neural.networks.run_layers` (torch's Linear + ReLU).

Layout the kernel reads (`pack_mlp`, once per model): the first layer's weight (W, K) with K padded to a multiple of
BLOCK_K, the hidden layers' weights stacked (H-1, W, W), the output layer's (OUT_PAD, W) with its rows padded to a
power of two >= 16 (tl.dot's smallest tile; tl.arange's spans), every bias float32. The network's own outputs are
the first n_out columns.

    packed = pack_mlp(sequential)                  # from an nn.Sequential of Linear/ReLU, float32 weights
    out = mlp_forward(x, packed)                   # x (M, n_in) float32 -> (M, n_out) float32
    out = mlp_train_forward(x, sequential)         # the same, differentiable (training)

Training (`mlp_train_forward`, tiny-cuda-nn's split): the forward kernel also stores each layer's activations; the
backward kernel takes the output's gradient back through every layer on chip (ReLU masks from the stored
activations), storing each layer's pre-activation gradient and the input's; the weights' gradients are then one
matmul per layer over all rows (cuBLAS on a card: a (W, M) x (M, W) product is what it does best), the biases' a sum.
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
    return pack_layers([weight(m) for m in linears], [m.bias for m in linears])


def pack_layers(weights: list[torch.Tensor], biases: list[torch.Tensor]) -> PackedMLP:
    """Layers' (out, in) weights and (out,) biases, first to last, laid out for the kernel (`pack_mlp`)."""
    if len(weights) < 2:
        raise ValueError("the Triton MLP needs at least one hidden layer")
    width = weights[0].shape[0]
    if width < MIN_TILE or width & (width - 1) or any(w.shape[0] != width for w in weights[:-1]):
        raise ValueError(f"the Triton MLP takes hidden widths that are one power of two >= {MIN_TILE}, not {width}")
    weights = [w.detach().float() for w in weights]
    biases = [b.detach().float() for b in biases]
    first, dev = weights[0], weights[0].device
    w_in = torch.zeros(width, _round_up(first.shape[1], BLOCK_K), device=dev)
    w_in[:, :first.shape[1]] = first
    mids = range(1, len(weights) - 1)
    w_hidden = torch.stack([weights[i] for i in mids]) if mids else torch.zeros(0, width, width, device=dev)
    b_hidden = torch.stack([biases[i] for i in mids]) if mids else torch.zeros(0, width, device=dev)
    n_out = weights[-1].shape[0]
    out_pad = max(MIN_TILE, 1 << (n_out - 1).bit_length())  # tl.arange spans powers of two (an appearance head's 40)
    w_out = torch.zeros(out_pad, width, device=dev)
    w_out[:n_out] = weights[-1]
    b_out = torch.zeros(out_pad, device=dev)
    b_out[:n_out] = biases[-1]
    return PackedMLP(w_in.contiguous(), biases[0].contiguous(), w_hidden.contiguous(), b_hidden.contiguous(),
                     w_out.contiguous(), b_out.contiguous(), first.shape[1], n_out)


@triton.jit
def _mlp_forward(x_ptr, w_in_ptr, b_in_ptr, w_hid_ptr, b_hid_ptr, w_out_ptr, b_out_ptr, out_ptr, acts_ptr, m, n_in,
                 K_PAD: tl.constexpr, W: tl.constexpr, HIDDEN: tl.constexpr, OUT_PAD: tl.constexpr, n_out,
                 BM: tl.constexpr, BK: tl.constexpr, SAVE: tl.constexpr):
    # SAVE: every layer's activations to acts (HIDDEN + 1, m, W) for the backward
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
    at = rows[:, None].to(tl.int64) * W + cols_w[None, :]
    if SAVE:
        tl.store(acts_ptr + at, h, mask=live[:, None])
    for layer in tl.static_range(HIDDEN):
        w = tl.load(w_hid_ptr + layer * W * W + cols_w[None, :] * W + cols_w[:, None])  # (W_in, W_out)
        h = tl.maximum(tl.dot(h, w) + tl.load(b_hid_ptr + layer * W + cols_w)[None, :], 0.0)
        if SAVE:
            tl.store(acts_ptr + (layer + 1) * m * W + at, h, mask=live[:, None])
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
    _launch_forward(x, packed, out, None)
    return out


def _launch_forward(x: torch.Tensor, packed: PackedMLP, out: torch.Tensor, acts: torch.Tensor | None) -> None:
    m = x.shape[0]
    _mlp_forward[(triton.cdiv(m, BLOCK_M),)](
        x, packed.w_in, packed.b_in, packed.w_hidden, packed.b_hidden, packed.w_out, packed.b_out, out,
        out if acts is None else acts, m, packed.n_in, K_PAD=packed.w_in.shape[1], W=packed.width,
        HIDDEN=packed.hidden, OUT_PAD=packed.w_out.shape[0], n_out=packed.n_out, BM=BLOCK_M, BK=BLOCK_K,
        SAVE=acts is not None)


@triton.jit
def _mlp_backward(dy_ptr, acts_ptr, w_in_ptr, w_hid_ptr, w_out_ptr, dz_ptr, dx_ptr, m, n_in, n_out,
                  K_PAD: tl.constexpr, W: tl.constexpr, HIDDEN: tl.constexpr, OUT_PAD: tl.constexpr,
                  BM: tl.constexpr, BK: tl.constexpr):
    # dy (m, n_out) -> dz (HIDDEN + 1, m, W): each layer's pre-activation gradient; dx (m, n_in): the input's
    rows = tl.program_id(0) * BM + tl.arange(0, BM)
    live = rows < m
    cols_w = tl.arange(0, W)
    cols_o = tl.arange(0, OUT_PAD)
    dy = tl.load(dy_ptr + rows[:, None].to(tl.int64) * n_out + cols_o[None, :],
                 mask=live[:, None] & (cols_o[None, :] < n_out), other=0.0)
    g = tl.dot(dy, tl.load(w_out_ptr + cols_o[:, None] * W + cols_w[None, :]))  # (BM, OUT_PAD) @ (OUT_PAD, W)
    at = rows[:, None].to(tl.int64) * W + cols_w[None, :]
    for i in tl.static_range(HIDDEN):
        layer = HIDDEN - i  # the activations after hidden layer `layer` (0: after the first)
        h = tl.load(acts_ptr + layer * m * W + at, mask=live[:, None], other=0.0)
        dz = tl.where(h > 0.0, g, 0.0)
        tl.store(dz_ptr + layer * m * W + at, dz, mask=live[:, None])
        w = tl.load(w_hid_ptr + (layer - 1) * W * W + cols_w[:, None] * W + cols_w[None, :])  # (W_out, W_in)
        g = tl.dot(dz, w)
    h = tl.load(acts_ptr + at, mask=live[:, None], other=0.0)
    dz = tl.where(h > 0.0, g, 0.0)
    tl.store(dz_ptr + at, dz, mask=live[:, None])
    for k0 in tl.static_range(0, K_PAD, BK):  # the input's gradient, K-blocked: dz (BM, W) @ W_in (W, BK)
        ks = k0 + tl.arange(0, BK)
        dx = tl.dot(dz, tl.load(w_in_ptr + cols_w[:, None] * K_PAD + ks[None, :]))
        tl.store(dx_ptr + rows[:, None].to(tl.int64) * n_in + ks[None, :], dx,
                 mask=live[:, None] & (ks[None, :] < n_in))


class _TrainMLP(torch.autograd.Function):
    """x and every Linear's (weight, bias), float32 -> the network's output; gradients for all of them."""

    @staticmethod
    def forward(ctx, x, *params):
        packed = pack_layers(params[0::2], params[1::2])
        m, width = x.shape[0], packed.width
        out = torch.empty(m, packed.n_out, device=x.device)
        acts = torch.empty(packed.hidden + 1, m, width, device=x.device)
        _launch_forward(x, packed, out, acts)
        ctx.save_for_backward(x, acts)
        ctx.packed = packed
        return out

    @staticmethod
    def backward(ctx, dy):
        x, acts = ctx.saved_tensors
        p = ctx.packed
        dy = dy.contiguous().float()
        m = x.shape[0]
        dz, dx = torch.empty_like(acts), torch.empty(m, p.n_in, device=x.device)
        _mlp_backward[(triton.cdiv(m, BLOCK_M),)](
            dy, acts, p.w_in, p.w_hidden, p.w_out, dz, dx, m, p.n_in, p.n_out, K_PAD=p.w_in.shape[1], W=p.width,
            HIDDEN=p.hidden, OUT_PAD=p.w_out.shape[0], BM=BLOCK_M, BK=BLOCK_K)
        grads = [dz[0].T @ x, dz[0].sum(0)]  # the first layer
        if p.hidden:
            hidden_w = torch.bmm(dz[1:].transpose(1, 2), acts[:-1])  # (H, W_out, W_in), one batched matmul
            for layer in range(p.hidden):
                grads += [hidden_w[layer], dz[layer + 1].sum(0)]
        grads += [dy.T @ acts[-1], dy.sum(0)]
        return (dx, *grads)


def mlp_train_forward(x: torch.Tensor, net: torch.nn.Sequential) -> torch.Tensor:
    """x (M, n_in) float32 -> (M, n_out) float32 through `net` (Linear/ReLU, float32 weights; a shape `pack_mlp`
    takes), differentiable in x and every parameter: the forward and the activations' backward one kernel each, the
    weights' gradients one matmul per layer (module docstring). On a card tl.dot multiplies in TF32."""
    params = [t for lin in net if isinstance(lin, torch.nn.Linear) for t in (lin.weight, lin.bias)]
    return _TrainMLP.apply(x.contiguous().float(), *params)
