"""Networks that turn the encodings of k points on a leaf segment into the leaf's answer: hit, distance, normal.

Both take `feats` (B, k, D): the encodings of the k points t_i = t_enter + i / (k - 1) * (t_exit - t_enter),
i = 0..k-1 (both segment ends included), and share one interface:

    raw = net(feats)                        # network-specific raw outputs
    loss, parts = net.loss(raw, targets)    # targets: hit (B,) bool, local_t (B,) in [0, 1], normal (B, 3)
    hit_prob, local_t, normal = net.decode(raw)   # (B,), (B,) in [0, 1] along the segment, (B, 3) unit

**MLP** (N-BVH baseline): one MLP over the concatenated k encodings (k * D inputs), 4 hidden layers of 64,
ReLU, 5 outputs: hit logit h, depth logit d, normal (3). hit_prob = sigmoid(h), local_t = sigmoid(d).
Loss = BCE(h, hit) + w_t * |sigmoid(d) - local_t| + w_n * |normalize(n) - normal|_1 + w_u * (|n| - 1)^2, the
last three only where the target is a hit (N-BVH's masked L1s, and a pull that keeps the raw normal near unit
length: NORMAL_UNIT_WEIGHTS).

**KMLP**: one shared MLP over each of the k - 1 adjacent pairs (2 * D inputs), 5 outputs per pair j: hit logit
h_j, depth logit d_j inside sub-segment j, normal n_j. Combination rule, front to back: with p_j = sigmoid(h_j),
the probability that the first hit lies in sub-segment j is q_j = p_j * prod_{i<j} (1 - p_i), and the leaf's
hit probability is P = sum_j q_j = 1 - prod_j (1 - p_i). The leaf reports a hit when P > 0.5, in the
sub-segment j^ = argmax_j q_j, at local_t = (j^ + sigmoid(d_j^)) / (k - 1) with normal n_j^.
Loss (log space, stable): BCE(P, hit) + for hits, the cross-entropy -log(q_j* / P) of the true sub-segment
j* = min(floor(local_t * (k - 1)), k - 2), plus the masked L1s of depth (on the sub-segment scale) and normal
of pair j* and the unit pull on its normal.
Parameter count does not depend on k.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import ClassVar

import torch
import torch.nn.functional as F
from torch import nn

from .. import kernels


NORMAL_LOSSES = ("oriented", "unoriented")
#: Weight of the normal L1 per network. The MLP's 0.5 is N-BVH's (its L1 on (n + 1) / 2). KMLP's loss adds the
#: sub-segment cross-entropy and measures depth on the 7x finer sub-segment scale, so at 0.5 its normals starved
#: (gyroid, 1,200 steps, image MSE; one run each): I at T=2^10 0.030-0.038 at 0.5, 0.0124-0.0128 at 2, 0.0143 at 4,
#: 0.020 at 8 (67% -> 29% of pixels with normals off by > 18 deg); III at T=2^9, N_max 64: 0.0088 at 2, 0.0076 at 3.
#: The MLP barely moves (0.0084 at 0.5, 0.0095 at 1, 0.0090 at 2); lowering KMLP's depth weight to the leaf scale
#: instead made it worse (0.048).
NORMAL_WEIGHTS = {"mlp": 0.5, "kmlp": 3.0}
#: Weight of the unit pull (|v| - 1)^2 on the raw normal v (hit rows; KMLP's true pair). The L1 of normalize(v) is blind
#: to |v| and its gradient shrinks as 1 / |v|; every Adam step on it is orthogonal to v and lengthens it. Measured on
#: the studs (III, T=2^8, 1,200 steps, image MSE): without the pull, 3 of 4 seeds stalled with |v| at 20-25 and the
#: normal L1 at ~1.83 (no better than not knowing the ray's side) from step ~300 on (MSE 0.0498 x3, the fourth
#: 0.0148); with 0.1 none stalled but all learnt slower (0.0153-0.0224); with 0.01 the two stalling seeds reach
#: 0.0130 and 0.0142 (k=4: 0.0127 vs 0.0121 without). The MLP never stalled: off.
NORMAL_UNIT_WEIGHTS = {"mlp": 0.0, "kmlp": 0.01}


@dataclass
class NetworkConfig:
    """kind: 'mlp' | 'kmlp'; k points per segment; `hidden` layers of `width`; loss weights w_t, w_n.

    normal_loss: 'oriented' (default) - the L1 to the target normal as given (the mesh's winding, or facing the ray
    when the trainer labels so: TrainConfig.normal_loss 'facing'); 'unoriented' - the L1 to the nearer of +-target (the
    surface's line only; measured worse than facing targets, bench/quality/bench_table5.py).
    """

    kind: str = "kmlp"
    k: int = 8
    hidden: int = 4
    width: int = 64
    depth_weight: float = 1.0
    #: None: the network's own (NORMAL_WEIGHTS); a file stores the resolved number.
    normal_weight: float | None = None
    #: Weight of the unit pull (|raw normal| - 1)^2; None: the network's own (NORMAL_UNIT_WEIGHTS).
    normal_unit_weight: float | None = None
    normal_loss: str = "oriented"

    def __post_init__(self) -> None:
        if self.normal_weight is None:
            self.normal_weight = NORMAL_WEIGHTS.get(self.kind, NORMAL_WEIGHTS["mlp"])
        if self.normal_unit_weight is None:
            self.normal_unit_weight = NORMAL_UNIT_WEIGHTS.get(self.kind, NORMAL_UNIT_WEIGHTS["mlp"])
        if self.normal_loss not in NORMAL_LOSSES:
            raise ValueError(f"unknown normal loss {self.normal_loss!r}; choose from {', '.join(NORMAL_LOSSES)}")

    def to_dict(self) -> dict:
        return asdict(self)


def _mlp(n_in: int, cfg: NetworkConfig, n_out: int = 5) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i in range(cfg.hidden):
        layers += [nn.Linear(n_in if i == 0 else cfg.width, cfg.width), nn.ReLU()]
    layers.append(nn.Linear(cfg.width if cfg.hidden else n_in, n_out))
    return nn.Sequential(*layers)


def linear_weight(m: nn.Linear, dtype: torch.dtype) -> torch.Tensor:
    """A Linear's (out, in) weight in `dtype`, however it is held: float32/float16 as they are, int8 rows
    (`network_bits=8`: `weight` int8 codes + `weight_scale` (out,) float16) as float16(code * scale) - the one
    formula every path uses (quantize.dequantize_rows)."""
    w = m.weight
    if w.dtype == torch.int8:
        w = (w.float() * m.weight_scale.float()[:, None]).half()
    return w.to(dtype)


def run_layers(net: nn.Sequential, x: torch.Tensor) -> torch.Tensor:
    """`net(x)` for weights held in any form (a finalized model keeps its network as stored: float16, or int8 rows
    with scales): each Linear runs in x's dtype (a transient cast of its weights on this reference path; the fused
    kernels read float16 weights as they are). At inference on a card the layers run as one Triton kernel
    (`kernels.triton.mlp`, the weights packed once per change of the network); in training, its forward and
    backward kernels (`kernels.training_layers_kernel`)."""
    if x.dim() >= 2 and not torch.is_grad_enabled() and kernels.mlp_kernel(net, x.device) == "triton":
        return _triton_layers(net, x)
    if x.dim() >= 2 and torch.is_grad_enabled() and kernels.training_layers_kernel(net, x.device) == "triton":
        from ..kernels.triton.mlp import mlp_train_forward

        return mlp_train_forward(x.reshape(-1, x.shape[-1]), net).reshape(*x.shape[:-1], -1).to(x.dtype)
    for m in net:
        if isinstance(m, nn.Linear):
            x = F.linear(x, linear_weight(m, x.dtype), m.bias.to(x.dtype))
        else:
            x = m(x)
    return x


def _triton_layers(net: nn.Sequential, x: torch.Tensor) -> torch.Tensor:
    """`run_layers` through the Triton MLP: x (..., n_in) -> (..., n_out) float32 (the packed weights are cached on
    `net`, keyed by every parameter's version, so training steps between queries repack)."""
    from ..kernels.triton.mlp import mlp_forward

    flat = x.reshape(-1, x.shape[-1]).float()
    return mlp_forward(flat, triton_packed(net)).reshape(*x.shape[:-1], -1).to(x.dtype)


def triton_packed(net: nn.Sequential):
    """`net`'s layers laid out for the Triton kernels (`mlp.pack_mlp`, weights dequantized to float32 by
    `linear_weight`), cached on `net` and keyed by every parameter's version: training steps between queries
    repack."""
    from ..kernels.triton.mlp import pack_mlp

    key = tuple((id(p), p._version) for p in net.parameters())
    cached = getattr(net, "_triton_pack", None)
    if cached is None or cached[0] != key:
        cached = (key, pack_mlp(net, lambda m: linear_weight(m, torch.float32)))
        net._triton_pack = cached
    return cached[1]


def _l1(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(B,) L1 distance per row (summed over the last dim when 2-D)."""
    diff = (pred - target).abs()
    return diff.sum(-1) if diff.dim() == 2 else diff


def _normal_l1(pred: torch.Tensor, target: torch.Tensor, unoriented: bool) -> torch.Tensor:
    """(B,) L1 of unit normals (B, 3); unoriented: to the nearer of +target and -target."""
    same = _l1(pred, target)
    return torch.minimum(same, _l1(pred, -target)) if unoriented else same


def _unit_pull(v: torch.Tensor) -> torch.Tensor:
    """(B,) (|v| - 1)^2 of raw normals v (B, 3): keeps them near unit length (see NORMAL_UNIT_WEIGHTS)."""
    return (v.norm(dim=-1) - 1.0) ** 2


def _masked_mean(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of (B,) values over the masked rows; 0 when nothing is masked."""
    m = mask.to(values.dtype)
    return (values * m).sum() / m.sum().clamp_min(1.0)


class Network(nn.Module):
    """The contract every network keeps (the model, the trainer and the kernels' planner use only this).

    * `forward(feats (B, k, D)) -> raw` (network-specific shape); `decode(raw) -> (hit_prob (B,), local_t (B,) in
      [0, 1] along the segment, normal (B, 3) unit)`.
    * `terms(raw, hit, local_t, normal) -> {name: (B,) per-sample term}` with 'bce' (every sample) and the hit-only
      terms; `loss` is their means (hit-only terms over the hits, weighted by the config) and `sample_errors` the
      same weighted sum per sample (loss-proportional leaf sampling): one definition of the loss.
    * Capability flag `fused_kind`: the fused kernel that computes this network ('mlp' | 'kmlp'), or None.
    """

    fused_kind: ClassVar[str | None] = None
    #: Hit-only terms and their weights' names in NetworkConfig (None: weight 1).
    HIT_TERMS: ClassVar[dict[str, str | None]] = {}

    def terms(self, raw: torch.Tensor, hit: torch.Tensor, local_t: torch.Tensor,
              normal: torch.Tensor) -> dict[str, torch.Tensor]:
        raise NotImplementedError

    @property
    def unoriented(self) -> bool:
        return self.cfg.normal_loss == "unoriented"

    def _weight(self, name: str) -> float:
        attr = self.HIT_TERMS[name]
        return 1.0 if attr is None else float(getattr(self.cfg, attr))

    def loss(self, raw: torch.Tensor, hit: torch.Tensor, local_t: torch.Tensor, normal: torch.Tensor):
        """(total loss, {term: detached mean}) over B labelled segments."""
        per = self.terms(raw, hit, local_t, normal)
        parts = {"bce": per["bce"].mean()}
        parts.update({name: _masked_mean(per[name], hit) for name in self.HIT_TERMS})
        total = self.weighted_total(parts)
        return total, self.report_parts({k: v.detach() for k, v in parts.items()})

    def weighted_total(self, parts: dict):
        """The loss from its parts' means (tensors or floats; 'bce' and every HIT_TERMS name), hit terms weighted."""
        return parts["bce"] + sum(self._weight(name) * parts[name] for name in self.HIT_TERMS)

    def report_parts(self, parts: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """The loss parts as reported (a network may rescale one to a common scale)."""
        return parts

    @torch.no_grad()
    def sample_errors(self, raw: torch.Tensor, hit: torch.Tensor, local_t: torch.Tensor,
                      normal: torch.Tensor) -> torch.Tensor:
        """(B,) the loss's weighted terms per sample (hit-only terms count where hit)."""
        per = self.terms(raw, hit, local_t, normal)
        hit_f = hit.to(per["bce"].dtype)
        return per["bce"] + hit_f * sum(self._weight(name) * per[name] for name in self.HIT_TERMS)


class MLP(Network):
    """Baseline network (see module docstring). feats (B, k, D) -> raw (B, 5)."""

    fused_kind = "mlp"
    HIT_TERMS = {"depth_l1": "depth_weight", "normal_l1": "normal_weight", "normal_unit": "normal_unit_weight"}

    def __init__(self, in_dim: int, cfg: NetworkConfig):
        super().__init__()
        self.cfg = cfg
        self.net = _mlp(in_dim * cfg.k, cfg)

    def forward(self, feats: torch.Tensor) -> torch.Tensor:
        return run_layers(self.net, feats.reshape(feats.shape[0], -1))

    def decode(self, raw: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        return torch.sigmoid(raw[:, 0]), torch.sigmoid(raw[:, 1]), F.normalize(raw[:, 2:5], dim=-1)

    def terms(self, raw: torch.Tensor, hit: torch.Tensor, local_t: torch.Tensor,
              normal: torch.Tensor) -> dict[str, torch.Tensor]:
        return {"bce": F.binary_cross_entropy_with_logits(raw[:, 0], hit.to(raw.dtype), reduction="none"),
                "depth_l1": _l1(torch.sigmoid(raw[:, 1]), local_t),
                "normal_l1": _normal_l1(F.normalize(raw[:, 2:5], dim=-1), normal, self.unoriented),
                "normal_unit": _unit_pull(raw[:, 2:5])}


class KMLP(Network):
    """Shared pair network (see module docstring). feats (B, k, D) -> raw (B, k - 1, 5)."""

    fused_kind = "kmlp"
    HIT_TERMS = {"segment_ce": None, "depth_l1": "depth_weight", "normal_l1": "normal_weight",
                 "normal_unit": "normal_unit_weight"}

    def __init__(self, in_dim: int, cfg: NetworkConfig):
        super().__init__()
        if cfg.k < 2:
            raise ValueError("KMLP needs k >= 2 points per segment")
        self.cfg = cfg
        self.net = _mlp(2 * in_dim, cfg)

    def forward(self, feats: torch.Tensor) -> torch.Tensor:
        pairs = torch.cat((feats[:, :-1], feats[:, 1:]), dim=-1)  # (B, k-1, 2D)
        return run_layers(self.net, pairs)

    @staticmethod
    def _first_hit_log_probs(logit: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """logit (B, k-1) -> log q (B, k-1) and log(1 - P) (B,) (see module docstring)."""
        log_miss = -F.softplus(logit)  # log(1 - p_j)
        log_p = -F.softplus(-logit)  # log p_j
        before = torch.cumsum(log_miss, dim=1) - log_miss  # sum_{i<j} log(1 - p_i)
        return log_p + before, log_miss.sum(dim=1)

    def decode(self, raw: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        log_q, log_none = self._first_hit_log_probs(raw[..., 0])
        hit_prob = -torch.expm1(log_none)
        n_sub = raw.shape[1]
        j = log_q.argmax(dim=1)
        rows = torch.arange(raw.shape[0], device=raw.device)
        local_t = (j.to(raw.dtype) + torch.sigmoid(raw[rows, j, 1])) / n_sub
        normal = F.normalize(raw[rows, j, 2:5], dim=-1)
        return hit_prob, local_t, normal

    def terms(self, raw: torch.Tensor, hit: torch.Tensor, local_t: torch.Tensor,
              normal: torch.Tensor) -> dict[str, torch.Tensor]:
        n_sub = raw.shape[1]
        log_q, log_none = self._first_hit_log_probs(raw[..., 0])
        log_hit = torch.log((-torch.expm1(log_none)).clamp_min(1e-12))  # log P, stable as P -> 0
        hit_f = hit.to(raw.dtype)
        pos = local_t * n_sub
        j_star = pos.floor().clamp(0, n_sub - 1).long()
        rows = torch.arange(raw.shape[0], device=raw.device)
        sub_t = (pos - j_star.to(raw.dtype)).clamp(0, 1)
        return {"bce": -(hit_f * log_hit + (1 - hit_f) * log_none),
                "segment_ce": -(log_q[rows, j_star] - log_hit),  # -log(q_j* / P)
                "depth_l1": _l1(torch.sigmoid(raw[rows, j_star, 1]), sub_t),
                "normal_l1": _normal_l1(F.normalize(raw[rows, j_star, 2:5], dim=-1), normal, self.unoriented),
                "normal_unit": _unit_pull(raw[rows, j_star, 2:5])}

    def report_parts(self, parts: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        # Depth reported on the leaf scale (a sub-segment is 1/(k-1) of the leaf), comparable with the MLP's.
        return {**parts, "depth_l1": parts["depth_l1"] / (self.cfg.k - 1)}


NETWORKS = {"mlp": MLP, "kmlp": KMLP}


def make_network(in_dim: int, cfg: NetworkConfig) -> Network:
    if cfg.kind not in NETWORKS:
        raise ValueError(f"unknown network {cfg.kind!r}; choose from {', '.join(NETWORKS)}")
    return NETWORKS[cfg.kind](in_dim, cfg)
