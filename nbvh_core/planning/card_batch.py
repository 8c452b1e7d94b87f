"""Rays per training step by device. On the CPU, 2,048: at one wall-clock budget smaller steps read lower error
(bench/results/frontier.md). A card's step costs about as much at 2,048 rays as at tens of thousands (the H200 ran
8.7 ms per 2,048-ray step on the torch path, bench/results/cuda_h200/speed.md: launches and host work, not
arithmetic), so small steps leave it idle. On a card the batch is the smallest of `LADDER` whose training rate is
at least `SHARE` of the best rate the probe measured there: once per machine and card, kept in the user's cache
beside the work rate (`probe`, `machine_rate`); $NBVH_CARD_RAYS_PER_STEP pins it.
"""
from __future__ import annotations

import os

from ..training.config import TrainConfig
from . import probe

CPU_RAYS_PER_STEP = TrainConfig.rays_per_step
LADDER = (2048, 8192, 32768, 131072)
#: The batch's share of the best rate a card must reach: more rays per step only where they buy throughput.
SHARE = 0.7


def pick_batch(rates: dict[int, float]) -> int:
    """The smallest batch (rays per step) whose rate (leaf samples/s) is at least SHARE of the best one."""
    usable = {n: r for n, r in rates.items() if r > 0}
    if not usable:
        return CPU_RAYS_PER_STEP
    best = max(usable.values())
    return min(n for n, r in usable.items() if r >= SHARE * best)


def probe_ladder(device: str) -> dict[int, float]:
    """The default preset's training rate at each batch of LADDER on `device` (about the same samples each)."""
    return {n: probe.probe_samples_per_s(device, n, steps=max(30, probe.PROBE_STEPS * LADDER[0] // n))
            for n in LADDER}


def rays_per_step(device: str = "auto") -> int:
    """Rays per training step for a run on `device` ('auto' | 'cpu' | 'cuda'): CPU_RAYS_PER_STEP on the CPU, a
    card's from its cached probe (see the module docstring)."""
    from ..training.train import pick_device

    resolved = str(pick_device(device))
    if not resolved.startswith("cuda"):
        return CPU_RAYS_PER_STEP
    pinned = os.environ.get("NBVH_CARD_RAYS_PER_STEP")
    if pinned:
        return int(pinned)
    entry = probe.cached_probe(probe.machine_key(resolved) + "|batch",
                               lambda: {"rays_per_step": pick_batch(rates := probe_ladder(resolved)),
                                        "rates": {str(n): r for n, r in rates.items()}},
                               lambda e: isinstance(e.get("rays_per_step"), int) and e["rays_per_step"] > 0)
    return int(entry["rays_per_step"])
