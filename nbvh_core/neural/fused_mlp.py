"""Fused MLP and KMLP models on the fast path: one kernel call per wave of segments (inference) or per training step.

KMLP (the same `nbvh_net_segments` / `nbvh_net_train` with kmlp = 1): the shared pair network runs on the same tiles, pair j reading the
window [j D, (j + 2) D) of the segment's feature row (a first-layer GEMM on an offset pointer); queries combine the
pairs into the first hit in the kernel (`segments_first_hits`: `networks.KMLP.decode`, a decided segment's later pairs
skipped); training adds `networks.KMLP.loss` (the first-hit combination in log space) and its backward in the kernel,
and the overlapping windows' input gradients add up per point before the encoding backward.

`nbvh_net_segments` and `nbvh_net_train` (kernels/native/networks.cpp) compute, per tile of 48 segments kept in the cache,
the segment points, the grid lookup and every Linear layer (bias and ReLU fused; AVX2 register-blocked
micro-kernels); training adds `networks.MLP.loss` and its backward (the Linear layers' gradients, then the table's
through the encoding backward kernel). The reference is the layer-by-layer torch model; tests/test_fastpath.py
checks raw outputs, loss and every gradient against it.
"""
from __future__ import annotations

import torch
from torch import nn

from ..kernels import bindings
from ..kernels.plan import network_kernel, train_step_kernel
from .encodings.fused import level_rows
from .networks import linear_weight


def applies(model) -> bool:
    """True when a model's queries run fused (`kernels.plan`: its network stage is 'fused mlp' / 'fused kmlp')."""
    return network_kernel(model).startswith("fused")


def _is_kmlp(model) -> bool:
    return model.network.fused_kind == "kmlp"


def trains(model) -> bool:
    """True when a training step runs fused (`kernels.plan`: its train_step stage is fused)."""
    return train_step_kernel(model).startswith("fused")


def _linears(model) -> list[nn.Linear]:
    return [m for m in model.network.modules() if isinstance(m, nn.Linear)]


def pack(model) -> tuple[torch.Tensor, torch.Tensor]:
    """dims (layers + 1,) int32 (dims[0] = k * L * F) and params: each Linear's weight transposed (in, out), then
    its bias, packed in the weights' own type (float32 for training; float16 for a finalized half-precision
    network, which the inference kernel reads without widening it, and for an int8 one, expanded here)."""
    linears = _linears(model)
    dims = torch.tensor([linears[0].in_features] + [m.out_features for m in linears], dtype=torch.int32)
    # int8 rows (network_bits 8) expand per query into float16: the kernel's working copy, as its padded layer
    # copies already are; the model holds the int8 rows.
    dtype = torch.float16 if linears[0].weight.dtype in (torch.float16, torch.int8) else torch.float32
    params = torch.cat([torch.cat((linear_weight(m, dtype).detach().t().reshape(-1), m.bias.detach().to(dtype)))
                        for m in linears])
    return dims, params.contiguous()


def _segments(samples) -> dict:
    """The segment arguments of a kernel call: rays (N, 3), and per segment its ray, t_enter, t_exit (B,)."""
    return dict(rays_o=samples.rays_o.contiguous(), rays_d=samples.rays_d.contiguous(), ray=samples.ray.contiguous(),
                te=samples.t_enter.contiguous(), tx=samples.t_exit.contiguous(), b=len(samples))


def segments_raw(model, packed: tuple[torch.Tensor, torch.Tensor], rays_o: torch.Tensor, rays_d: torch.Tensor,
                 ray: torch.Tensor, t_enter: torch.Tensor, t_exit: torch.Tensor) -> torch.Tensor:
    """Raw network outputs of B segments, (B, 5) for an MLP, (B, k - 1, 5) for a KMLP: what `model.forward(rays_o[ray],
    rays_d[ray], t_enter, t_exit)` returns, to float rounding (the sums run in another order). rays_o, rays_d: (N, 3);
    ray: (B,) int64."""
    k, n_out = model.cfg.network.k, int(packed[0][-1])
    shape = (ray.numel(), k - 1, n_out) if _is_kmlp(model) else (ray.numel(), n_out)
    return _net_segments(model, packed, rays_o, rays_d, ray, t_enter, t_exit, torch.empty(shape), decode=False)


def segments_first_hits(model, packed: tuple[torch.Tensor, torch.Tensor], rays_o: torch.Tensor, rays_d: torch.Tensor,
                        ray: torch.Tensor, t_enter: torch.Tensor, t_exit: torch.Tensor
                        ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """`model.network.decode` of B segments' raw outputs, (hit probability (B,), local t (B,) in [0, 1], unit normal
    (B, 3)), float32. A KMLP combines its pairs in the kernel and skips a segment's remaining pairs once it is decided
    (a hit whose most likely pair later pairs cannot beat): the same hit decisions, depths and normals, to float
    rounding, and for such a segment the probability is a lower bound (> 0.5) from the pairs it ran."""
    if not _is_kmlp(model):
        return model.network.decode(segments_raw(model, packed, rays_o, rays_d, ray, t_enter, t_exit))
    out = _net_segments(model, packed, rays_o, rays_d, ray, t_enter, t_exit, torch.empty((ray.numel(), 5)),
                        decode=True)
    return out[:, 0], out[:, 1], out[:, 2:5]


def _net_segments(model, packed, rays_o, rays_d, ray, t_enter, t_exit, out: torch.Tensor,
                  decode: bool) -> torch.Tensor:
    """One `nbvh_net_segments` call writing into `out` (float32, contiguous)."""
    dims, params = packed
    look = model.encoding.fused_lookup()
    k = model.cfg.network.k
    frac = torch.linspace(0.0, 1.0, k, dtype=torch.float32)
    bindings.net_segments(
        rays_o=rays_o.contiguous(), rays_d=rays_d.contiguous(), ray=ray.contiguous(), te=t_enter.contiguous(),
        tx=t_exit.contiguous(), b=ray.numel(), k=k, frac=frac, **look.kernel_args(),
        **look.spec.args(level_rows(look.rows), look.codes, look.code_rows), kmlp=int(_is_kmlp(model)),
        decode=int(decode), n_layers=len(dims) - 1, dims=dims, params=params,
        weight_kind=int(params.dtype == torch.float16), out=out)
    return out


def _scratch(model, b: int, k: int, width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Kernel scratch (points (b * k, 3), d features (b, width)), kept on the model between steps: the dx buffer of a
    4096-ray step is ~8 MB, and a fresh one each step costs its page faults."""
    have = getattr(model, "_fused_scratch", None)
    if have is None or have[0] < b or have[1] != (k, width):
        cap = int(b * 1.25) + 64
        have = (cap, (k, width), torch.empty((cap * k, 3), dtype=torch.float32),
                torch.empty((cap, width), dtype=torch.float32))
        model._fused_scratch = have
    return have[2][:b * k], have[3][:b]


def entries_read(model, samples, frac: torch.Tensor) -> torch.Tensor | None:
    """(R,) uint8: 1 for each entry of a soft HashVQAD row table that the k points (fractions `frac` (k,)) of the
    samples' segments read, None for an encoding whose kernels read a stored table. The step then computes only
    those soft rows (a quarter of them on the bunny at T=2^9)."""
    enc = model.encoding
    if enc._reads_table():  # a stored table (HashGrid, frozen HashVQAD): nothing computed per step
        return None
    needed = torch.zeros(sum(enc.reachable_entries()), dtype=torch.uint8)
    spec = enc.grid_spec()
    bindings.mark_entries(**_segments(samples), k=frac.numel(), frac=frac, **spec.args(0, None, 0), needed=needed)
    return needed


def train_step(model, samples, want_raw: bool = False) -> tuple[float, dict]:
    """Loss of `model` on labelled `samples` (as `train.samples_loss` + `MLP.loss`) and its gradients, in one
    kernel call; sets `.grad` of every parameter (call after `zero_grad(set_to_none=True)`). Returns the total
    loss and its parts (bce, depth_l1, normal_l1; with want_raw also 'raw': the (B, 5) network outputs)."""
    net_cfg = model.cfg.network
    dims, params = pack(model)
    assert params.dtype == torch.float32, "training runs on float32 weights"
    linears = _linears(model)
    assert int(dims[-1]) == 5, "the fused losses are networks.MLP's and KMLP's (hit, depth, normal)"
    kmlp = _is_kmlp(model)
    b, k = len(samples), net_cfg.k
    frac = torch.linspace(0.0, 1.0, k, dtype=torch.float32)
    rows, codes, code_rows = model.encoding._fused_rows(entries_read(model, samples, frac))
    spec = model.encoding.grid_spec()
    codes = None if codes is None else codes.contiguous()
    table = rows.detach().contiguous()
    hit = samples.hit.to(torch.uint8).contiguous()
    local_t = samples.local_t.to(torch.float32).contiguous()
    normal = samples.normal.to(torch.float32).contiguous()
    grad_params = torch.empty_like(params)
    grad_table = torch.zeros_like(table)
    feat_width = model.encoding.out_dim * k  # a segment's feature row (KMLP's pairs are windows of it)
    points, dx = _scratch(model, b, k, feat_width)
    raw = (torch.empty((b, k - 1, 5) if kmlp else (b, 5), dtype=torch.float32)) if want_raw else None
    loss_parts = torch.zeros(5 if kmlp else 4, dtype=torch.float64)
    bindings.net_train(
        **_segments(samples), k=k, frac=frac, table=table, **spec.args(level_rows(table), codes, code_rows),
        kmlp=int(kmlp), n_layers=len(dims) - 1, dims=dims, params=params, hit=hit, local_t=local_t, normal=normal,
        hit_count=int(hit.sum()), w_t=float(net_cfg.depth_weight), w_n=float(net_cfg.normal_weight),
        unoriented=int(net_cfg.normal_loss == "unoriented"), w_unit=float(net_cfg.normal_unit_weight),
        loss_out=loss_parts, grad_params=grad_params, grad_table=grad_table, points=points, dx=dx, out_raw=raw)
    # Unpack the Linear gradients (stored transposed, like the parameters).
    pos = 0
    for m in linears:
        n_in, n_out = m.in_features, m.out_features
        m.weight.grad = grad_params[pos:pos + n_in * n_out].view(n_in, n_out).t().contiguous()
        pos += n_in * n_out
        m.bias.grad = grad_params[pos:pos + n_out].clone()
        pos += n_out
    if rows is model.encoding.table:
        model.encoding.table.grad = grad_table
    else:  # a soft HashVQAD row table: on through its softmax to the table and the index logits
        torch.autograd.backward(rows, grad_table)
    # The kernel's loss parts come in the network's order: bce, then its hit terms (networks.Network.HIT_TERMS).
    net = model.network
    means = dict(zip(["bce", *net.HIT_TERMS], (float(v) for v in loss_parts)))
    total = net.weighted_total(means)
    parts = {name: torch.tensor(v) for name, v in net.report_parts(means).items()}
    if want_raw:
        parts["raw"] = raw
    return total, parts
