"""Training labels made on the card: `rays.label_samples`' samples (the same modes, fields and order) from Triton
kernels instead of the host's Embree and fused kernels, so a card's training is not held to the host's labelling pace
(bench/results/labels.md: 1.2M label samples/s on two host cores against the tens of millions a card trains on).

Per chunk of rays, drawn on the host as everywhere: the mesh's exact first hits (`CardTracer`), every leaf of the
model's tree each ray enters up to its first hit (`leaves_along_rays`, Triton's on a card), then the labels:
'ownership' reads the first hit's triangle's leaf; 'consistent' asks the mesh tracer for each segment's nearest hit in
[t_enter - SEGMENT_EPS, t_exit + SEGMENT_EPS], which is what the host's all-hits pass and search find (the host merges
hits closer than `exact.ALL_HITS_EPS`; one nearest query has nothing to merge). The samples stay on the card.
"""
from __future__ import annotations

import numpy as np
import torch

from .. import kernels
from ..geometry.bvh import BVH
from ..geometry.card_tracer import CardTracer
from ..geometry.exact import ExactTracer
from ..geometry.traversal import TorchBVH, leaves_along_rays
from .rays import LABEL_MODES, SEGMENT_EPS, TrainingSamples, finish_labels


class CardLabels:
    """Labels on `tracer`'s device for a BVH (its cut changes in training: each cut's nodes move to the card once)."""

    def __init__(self, tracer: CardTracer):
        self.tracer = tracer
        self._cut: tuple | None = None  # (bvh, its tree on the card, its tri_leaf on the card)

    def _on_card(self, bvh: BVH) -> tuple[TorchBVH, torch.Tensor]:
        if self._cut is None or self._cut[0] is not bvh:
            device = self.tracer.device
            tri_leaf = torch.from_numpy(np.asarray(bvh.tri_leaf, np.int64)).to(device)
            self._cut = (bvh, TorchBVH.from_bvh(bvh, device), tri_leaf)
        return self._cut[1], self._cut[2]

    def label(self, bvh: BVH, rays_o: np.ndarray, rays_d: np.ndarray, mode: str,
              normal_loss: str = "oriented") -> TrainingSamples:
        """`rays.label_samples` for these rays, its tensors on the card. rays_o, rays_d: (N, 3) float32 unit
        directions, normalised coordinates (host arrays or tensors)."""
        if mode not in LABEL_MODES:
            raise ValueError(f"label mode must be one of {LABEL_MODES}, got {mode!r}")
        tree, tri_leaf = self._on_card(bvh)
        o = torch.as_tensor(np.ascontiguousarray(rays_o, np.float32)).to(self.tracer.device)
        d = torch.as_tensor(np.ascontiguousarray(rays_d, np.float32)).to(self.tracer.device)
        n = o.shape[0]
        t_first, tri_first = self.tracer.nearest(o, d)
        lh = leaves_along_rays(tree, o, d, t_first + SEGMENT_EPS)
        ray, leaf = lh.ray, lh.leaf
        if mode == "ownership":
            tri = tri_first[ray]
            owner = torch.where(tri >= 0, tri_leaf[tri.clamp_min(0)], -1)
            hit = (tri >= 0) & (owner == leaf)
            t_hit = torch.where(hit, t_first[ray], lh.t_exit)
        else:
            t_seg, tri = self.tracer.nearest(o[ray], d[ray], lh.t_enter - SEGMENT_EPS, lh.t_exit + SEGMENT_EPS)
            hit = tri >= 0
            t_hit = torch.where(hit, t_seg, lh.t_exit)
        normal = torch.where(hit[:, None], self.tracer.normals_of(tri), 0.0)
        normal, t_hit = finish_labels(normal, t_hit, d, ray, lh.t_enter, lh.t_exit, normal_loss)
        rays_hit, samples_hit = torch.stack(((tri_first >= 0).sum(), hit.sum())).tolist()  # one read per chunk
        stats = {"rays": n, "rays_hit": rays_hit}
        if mode == "ownership":
            stats["first_hits_unlabelled"] = rays_hit - samples_hit
        else:
            stats["rays_hits_truncated"] = 0  # one nearest query per segment: no list to cut
        stats.update(samples=len(lh), samples_hit=samples_hit, labelled_on="card")
        return TrainingSamples(rays_o=o, rays_d=d, ray=ray, leaf=leaf, t_enter=lh.t_enter, t_exit=lh.t_exit, hit=hit,
                               t_hit=t_hit, normal=normal, rank=lh.rank(), mode=mode, stats=stats)


def card_labels_for(tracer: ExactTracer, bvh: BVH, device: torch.device | str) -> CardLabels | None:
    """A training's card labeller on `device` where labels are made there (`kernels.label_kernel`), else None: the
    host labels. The card's mesh tree comes from `bvh.full`, the run's shared tree over the same mesh."""
    if kernels.label_kernel(device) != "card":
        return None
    return CardLabels(tracer.on_card(device, getattr(bvh, "full", None)))
