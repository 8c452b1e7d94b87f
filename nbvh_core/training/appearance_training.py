"""Training the appearance head (`neural/appearance.py`): exact labelled surface points and the loop.

Labels are exact: rays drawn as for geometry training (`rays.sample_rays`), their first hits traced on the mesh,
the hit triangle's patch and its corners' coordinates interpolated at the hit's barycentrics (`look.hit_labels`),
or the textured colour there for the colour target. The head trains after the geometry, in its share of the budget.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from ..geometry.look import albedo, hit_labels, linear_to_srgb
from ..geometry.mesh import Mesh
from ..neural.appearance import AppearanceHead
from .rays import sample_rays


class SurfaceLabels:
    """Exact labelled surface points: first hits of training-distribution rays on the mesh, each with its patch
    (`face_patch` (F,), default: its slot) and interpolated coordinates. draw(n) -> points (n, 3) float32,
    patch (n,) int64, uv (n, 2) float32 | None; with colour=True the third is the textured sRGB colour (n, 3)."""

    def __init__(self, mesh: Mesh, tracer, rng: np.random.Generator, face_patch: np.ndarray | None = None,
                 colour: bool = False):
        self.mesh, self.tracer, self.rng, self.want_colour = mesh, tracer, rng, colour
        # a slot without an image has no coordinates to learn: its patch's map is zero
        self.flat_slot = np.array([m.image is None for m in mesh.look.materials])
        self.face_patch = face_patch if face_patch is not None else mesh.look.face_slots
        self.lo, self.hi = mesh.vertices.min(0), mesh.vertices.max(0)

    def draw(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        pts, slots, uvs, have = [], [], [], 0
        while have < n:
            o, d = sample_rays(self.lo, self.hi, max(1024, 2 * (n - have)), self.rng)
            fh = self.tracer.first_hit(o, d)
            h = np.nonzero(fh.hit)[0]
            p = o[h] + fh.t[h, None] * d[h]
            slot, uv = hit_labels(self.mesh.look, self.mesh.vertices, self.mesh.faces, fh.tri[h], p)
            if self.want_colour:
                uv = linear_to_srgb(albedo(self.mesh.look.materials, slot, uv))
            elif uv is not None:
                uv = np.where(self.flat_slot[slot][:, None], np.float32(0), uv)
            pts.append(p.astype(np.float32))
            slots.append(self.face_patch[fh.tri[h]])
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
               batch: int = 1 << 10, lr: float = 1e-2, decay: float = 0.01, pool_size: int = 1 << 19,
               should_stop=None, min_steps: int = 20) -> AppearanceResult:
    """Adam on batches of a pool of exact labels until `seconds` (wall, the pool's tracing included) or
    `max_steps`, the learning rate decayed by `decay` over the run (by the larger of the step and time fractions).
    should_stop: polled each step; True ends training early (the head as it is). At least `min_steps` run whatever
    the clock says (a budget the label pool used up still gets a head that has seen its labels). Batches of 1,024: on the
    Smart-UV Suzanne (77 patches, 9 s, 2 CPU cores) 16k labels a step gave 460 steps, 99.0% of slots right and 90%
    of coordinates within half a 512 px texel; 4k 1,519 steps, 99.8%, 93%; 1k 3,223 steps, 99.8%, 94%."""
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
        if (frac >= 1.0 and step >= min(min_steps, max_steps)) or (should_stop is not None and should_stop()):
            break
        for g in opt.param_groups:  # past the clock, the minimum steps decay over themselves
            g["lr"] = lr * decay ** (frac if frac < 1.0 else step / max(min_steps, 1))
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
