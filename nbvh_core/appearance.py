"""The appearance head: what a hit looks like - its material slot and texture coordinates - from its position.

The geometry network answers hit, distance and normal per (ray, leaf) segment; the look of a hit depends only on
where on the surface it is, so it is a field over points, queried once per hit pixel after the geometry query:

    point (N, 3) in [0, 1]^3 -> HashGrid features (L * F) ++ point -> MLP -> slot logits (S), uv (2)

The point itself is an input beside the grid's features: a chart's coordinates are an affine function of
position, which the MLP then carries without the grid spending rows on it. Slots are a classification over the
asset's material slots (cross-entropy); coordinates a regression (L1: at a UV seam, where two charts meet, the
L1's minimiser picks one side's coordinates, where an L2 would average them into texels of neither).
Labels are exact: rays drawn as for geometry training, their first hits traced on the mesh, the hit triangle's
slot and its corners' coordinates interpolated at the hit's barycentrics (`look.hit_labels`).

A look with one slot and no texture needs no head (`Look.plain`); the model then carries the material only.
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from .encodings import EncodingConfig, make_encoding
from .look import Look, hit_labels
from .mesh import Mesh


@dataclass
class AppearanceConfig:
    """The head's architecture. slots: the asset's material slots; uv: whether it regresses coordinates;
    levels x 2^log2_table rows of `features` floats at resolutions n_min..n_max; `hidden` layers of `width`."""

    slots: int = 1
    uv: bool = True
    levels: int = 8
    n_min: int = 16
    n_max: int = 1024
    features: int = 2
    log2_table: int = 12
    hidden: int = 2
    width: int = 32
    uv_weight: float = 10.0

    def encoding(self) -> EncodingConfig:
        return EncodingConfig(kind="hashgrid", levels=self.levels, n_min=self.n_min, n_max=self.n_max,
                              features=self.features, log2_table=self.log2_table)

    @property
    def outputs(self) -> int:
        return (self.slots if self.slots > 1 else 0) + (2 if self.uv else 0)

    def to_dict(self) -> dict:
        return asdict(self)


class AppearanceHead(nn.Module):
    """points (N, 3) normalised -> slot logits (N, S) and uv (N, 2) (see the module docstring)."""

    def __init__(self, cfg: AppearanceConfig, inference: bool = False):
        super().__init__()
        if cfg.outputs == 0:
            raise ValueError("an appearance head needs more than one slot or texture coordinates")
        self.cfg = cfg
        self.encoding = make_encoding(cfg.encoding(), inference)
        layers: list[nn.Module] = []
        d = self.encoding.out_dim + 3
        for _ in range(cfg.hidden):
            layers += [nn.Linear(d, cfg.width), nn.ReLU()]
            d = cfg.width
        layers.append(nn.Linear(d, cfg.outputs))
        self.network = nn.Sequential(*layers)

    def forward(self, points: torch.Tensor) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        """points (N, 3) float32 -> slot logits (N, S) or None (one slot), uv (N, 2) or None."""
        feats = self.encoding(points)
        x = torch.cat([feats, points * 2 - 1], dim=1)
        w = self.network[0].weight
        out = self.network(x.to(w.dtype) if w.dtype != torch.int8 else x).float()
        s = self.cfg.slots if self.cfg.slots > 1 else 0
        return (out[:, :s] if s else None), (out[:, s:s + 2] if self.cfg.uv else None)

    @torch.no_grad()
    def predict(self, points: torch.Tensor, batch: int = 1 << 16) -> tuple[np.ndarray, np.ndarray | None]:
        """points (N, 3) normalised -> slot (N,) int32 (0 with one slot), uv (N, 2) float32 or None."""
        dev = self.encoding.table.device if self.encoding.table.numel() else self.encoding.qcodes.device
        n = points.shape[0]
        slot = np.zeros(n, np.int32)
        uv = np.zeros((n, 2), np.float32) if self.cfg.uv else None
        for a in range(0, n, batch):
            logits, coords = self(points[a:a + batch].to(dev, torch.float32))
            if logits is not None:
                slot[a:a + batch] = logits.argmax(1).cpu().numpy()
            if coords is not None:
                uv[a:a + batch] = coords.cpu().numpy()
        return slot, uv

    def loss(self, points: torch.Tensor, slot: torch.Tensor, uv: torch.Tensor | None) -> torch.Tensor:
        """Cross-entropy of the slot + uv_weight x L1 of the coordinates, averaged over the points."""
        logits, coords = self(points)
        total = points.new_zeros(())
        if logits is not None:
            total = total + F.cross_entropy(logits, slot)
        if coords is not None and uv is not None:
            total = total + self.cfg.uv_weight * (coords - uv).abs().sum(1).mean()
        return total


def head_config(look: Look, base: AppearanceConfig | None = None) -> AppearanceConfig | None:
    """The head a look needs (None: a plain look needs none): `base`'s sizes with the look's slots and uv."""
    if look is None or look.plain:
        return None
    cfg = AppearanceConfig(**(base.to_dict() if base is not None else {}))
    cfg.slots, cfg.uv = look.n_slots, look.textured
    return cfg


class SurfaceLabels:
    """Exact labelled surface points: first hits of training-distribution rays on the mesh, each with its slot
    and interpolated coordinates. draw(n) -> points (n, 3) float32, slot (n,) int64, uv (n, 2) float32 | None."""

    def __init__(self, mesh: Mesh, tracer, rng: np.random.Generator):
        self.mesh, self.tracer, self.rng = mesh, tracer, rng
        self.lo, self.hi = mesh.vertices.min(0), mesh.vertices.max(0)

    def draw(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        from .samples import sample_rays

        pts, slots, uvs, have = [], [], [], 0
        while have < n:
            o, d = sample_rays(self.lo, self.hi, max(1024, 2 * (n - have)), self.rng)
            fh = self.tracer.first_hit(o, d)
            h = np.nonzero(fh.hit)[0]
            p = o[h] + fh.t[h, None] * d[h]
            s, uv = hit_labels(self.mesh.look, self.mesh.vertices, self.mesh.faces, fh.tri[h], p)
            pts.append(p.astype(np.float32))
            slots.append(s)
            uvs.append(uv)
            have += len(h)
        uv = None if uvs[0] is None else np.concatenate(uvs)[:n]
        return np.concatenate(pts)[:n], np.concatenate(slots)[:n].astype(np.int64), uv


@dataclass
class AppearanceResult:
    steps: int
    seconds: float
    final_loss: float


def train_head(head: AppearanceHead, labels: SurfaceLabels, seconds: float, max_steps: int = 100000,
               batch: int = 1 << 14, lr: float = 1e-2, decay: float = 0.01, pool_size: int = 1 << 19, should_stop=None) -> AppearanceResult:
    """Adam on fresh exact labels each step until `seconds` (wall) or `max_steps`, learning rate decayed
    by `decay` over the run (by the larger of the step and time fractions). should_stop: polled each step; True ends
    training early (the head as it is)."""
    opt = torch.optim.Adam(head.parameters(), lr=lr, eps=1e-12)
    start = time.perf_counter()
    # Tracing fresh labels costs 2.6x a step (16k points, 2 cores); a pool of exact labels drawn once covers the
    # surface densely and lets the steps run back to back.
    pool = labels.draw(pool_size)
    rng = np.random.default_rng(0)
    step, loss_value = 0, float("nan")
    dev = head.encoding.table.device
    while step < max_steps:
        elapsed = time.perf_counter() - start
        frac = max(step / max_steps, elapsed / max(seconds, 1e-9))
        if frac >= 1.0 or (should_stop is not None and should_stop()):
            break
        for g in opt.param_groups:
            g["lr"] = lr * decay ** frac
        pick = rng.integers(0, len(pool[0]), batch)
        p, s, uv = pool[0][pick], pool[1][pick], None if pool[2] is None else pool[2][pick]
        loss = head.loss(torch.from_numpy(p).to(dev), torch.from_numpy(s).to(dev),
                         None if uv is None else torch.from_numpy(uv).to(dev))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        loss_value = float(loss.detach())
        step += 1
    return AppearanceResult(steps=step, seconds=time.perf_counter() - start, final_loss=loss_value)


@torch.no_grad()
def finalize_head(head: AppearanceHead, table_bits: int, network_bits: int) -> None:
    """Hold the head as a file at these widths stores it: table as uint8 codes (8) or float16-rounded (16);
    network weights rounded to float16 (16 or 8: the head is small, so it is never stored below 16 bits)."""
    if table_bits == 8:
        head.encoding.quantize_(8)
    elif table_bits == 16:
        head.encoding.table.copy_(head.encoding.table.half().float())
    if network_bits < 32:
        for p in head.network.parameters():
            p.copy_(p.half().float())
    head.eval()


def head_stored_bytes(cfg: AppearanceConfig, table_bits: int, network_bits: int) -> dict[str, int]:
    """Bytes the file holds for a head: appearance.features (+ 8 bytes per level and feature of affine at 8 bits)
    and appearance.network (float16 unless network_bits is 32)."""
    rows = cfg.levels * (1 << cfg.log2_table) * cfg.features
    feats = rows * table_bits // 8 + (8 * cfg.levels * cfg.features if table_bits == 8 else 0)
    d, params = cfg.levels * cfg.features + 3, 0
    for _ in range(cfg.hidden):
        params += d * cfg.width + cfg.width
        d = cfg.width
    params += d * cfg.outputs + cfg.outputs
    return {"appearance.features": feats, "appearance.network": params * (4 if network_bits == 32 else 2)}
