"""Budgets in work, not seconds: how much training a second buys on this machine, against the machine the size
predictor was fitted on (`sizing_fit.json`, measured on a 2-core CPU). The predictor's budget term reads the
training budget in that machine's seconds: a machine that trains twice as fast gets the predictions of a budget
twice as long (`SizeFit.work_ratio`).

The rate is the default preset's training on the bundled blob for `probe.PROBE_STEPS` steps at the device's batch
(labels, encoding, network, Adam: the whole step, as a run trains), in leaf samples per second, measured once per
machine and device and kept in the user's cache (`work_ratio`); $NBVH_WORK_RATIO overrides it (a number; the tests
pin it to 1). The ratio reads 1 within (1/sqrt(2), sqrt(2)) and is rounded to a power of sqrt(2) outside: run-to-run
noise of the probe (4% in three probes here) never moves a prediction, a 16-core desktop or a card does.
"""
from __future__ import annotations

import math
import os

from . import probe
from .card_batch import rays_per_step as card_rays_per_step

#: The probe's leaf samples per second on the kind of machine the predictor was fitted on (the project's 2-core
#: x86_64 VM, fast path: 343k, 351k and 356k in three probes, 0.8 s each after the first's 2.9 s).
REFERENCE_SAMPLES_PER_S = 350_000.0
#: The predictor's budget term was fitted on 15-600 s trainings (bench/fitting/fit_budget.py): a faster machine's budget is
#: read as at most this many reference seconds, never extrapolated further.
MAX_REFERENCE_BUDGET_S = 600.0


def rounded_ratio(rate: float, reference: float = REFERENCE_SAMPLES_PER_S) -> float:
    """rate / reference: 1 within (1/sqrt(2), sqrt(2)), else rounded to the nearest power of sqrt(2)."""
    if not (rate > 0 and math.isfinite(rate)):
        return 1.0
    octaves = math.log2(rate / reference)
    return 1.0 if abs(octaves) < 0.5 else 2.0 ** (round(2.0 * octaves) / 2.0)


def work_ratio(device: str = "auto") -> float:
    """How many of the fit machine's training seconds one second here buys (see the module docstring): from
    $NBVH_WORK_RATIO, else the cache, else a probe (a few seconds, once per machine and device, then cached)."""
    pinned = os.environ.get("NBVH_WORK_RATIO")
    if pinned:
        return float(pinned)
    from ..training.train import pick_device

    device = str(pick_device(device))
    entry = probe.cached_probe(probe.machine_key(device),  # the batch (a card's own probe) only when measuring
                               lambda: {"samples_per_s": probe.probe_samples_per_s(device,
                                                                                   card_rays_per_step(device))},
                               lambda e: isinstance(e.get("samples_per_s"), (int, float)))
    return rounded_ratio(float(entry["samples_per_s"]))


def reference_budget_s(budget_s: float, ratio: float) -> float:
    """A training budget of `budget_s` seconds here, in the fit machine's seconds (capped at the fitted range)."""
    return min(budget_s * ratio, max(MAX_REFERENCE_BUDGET_S, budget_s))
