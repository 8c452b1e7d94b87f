"""Budgets in work, not seconds: how much training a second buys on this machine, against the machine the size
predictor was fitted on (`sizing_fit.json`, measured on a 2-core CPU). The predictor's budget term reads the
training budget in that machine's seconds: a machine that trains twice as fast gets the predictions of a budget
twice as long (`SizeFit.work_ratio`).

The rate is the default preset's training on the bundled blob for `PROBE_STEPS` steps (labels, encoding, network,
Adam: the whole step, as a run trains), in leaf samples per second, measured once per machine and device and kept
in the user's cache (`work_ratio`); $NBVH_WORK_RATIO overrides it (a number; the tests pin it to 1). The ratio reads
1 within (1/sqrt(2), sqrt(2)) and is rounded to a power of sqrt(2) outside: run-to-run noise of the probe (4% in
three probes here) never moves a prediction, a 16-core desktop or a card does.
"""
from __future__ import annotations

import json
import math
import os
import platform
import time
from pathlib import Path

#: The probe's leaf samples per second on the kind of machine the predictor was fitted on (the project's 2-core
#: x86_64 VM, fast path: 343k, 351k and 356k in three probes, 0.8 s each after the first's 2.9 s).
REFERENCE_SAMPLES_PER_S = 350_000.0
PROBE_STEPS = 150
#: The predictor's budget term was fitted on 15-600 s trainings (bench/fitting/fit_budget.py): a faster machine's budget is
#: read as at most this many reference seconds, never extrapolated further.
MAX_REFERENCE_BUDGET_S = 600.0


def _cache_path() -> Path:
    root = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(root) / "nbvh" / "work_rate.json"


def machine_key(device: str) -> str:
    """What the rate belongs to: host, CPUs, the device (and the card's name), torch, the kernel path."""
    import torch

    from .. import kernels

    card = torch.cuda.get_device_name(0) if device.startswith("cuda") and torch.cuda.is_available() else ""
    return "|".join([platform.node(), platform.machine(), str(os.cpu_count()), device, card, torch.__version__,
                     kernels.current_path(), str(kernels.threads())])


def probe_samples_per_s(device: str) -> float:
    """The default preset's training rate here: PROBE_STEPS steps on the bundled blob (a few seconds), leaf
    samples per second of the training itself (the BVH and labels' setup not counted)."""
    from ..geometry.bvh import build_bvh
    from ..geometry.bundled_samples import sample_path
    from ..geometry.exact import ExactTracer
    from ..geometry.mesh import load_mesh
    from ..neural.model import NeuralBVH
    from ..training.train import train
    from .settings import preset

    s = preset("default").with_overrides(log2_table=11, n_max=64, steps=PROBE_STEPS, time_limit_s=None,
                                         device=device, seed=0)
    mesh = load_mesh(sample_path("blob"))
    bvh = build_bvh(mesh, s.nodes)
    model = NeuralBVH(bvh.nodes, s.model_config(), mesh.transform)
    cfg = s.train_config()
    result = train(model, bvh, ExactTracer(mesh), cfg)
    return float(result.samples_per_s)


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
    key = machine_key(device)
    path = _cache_path()
    try:
        cached = json.loads(path.read_text())
    except (OSError, ValueError):
        cached = {}
    entry = cached.get(key) if isinstance(cached, dict) else None
    if isinstance(entry, dict) and isinstance(entry.get("samples_per_s"), (int, float)):
        return rounded_ratio(float(entry["samples_per_s"]))
    rate = probe_samples_per_s(device)
    cached = cached if isinstance(cached, dict) else {}
    cached[key] = {"samples_per_s": rate, "measured": time.strftime("%Y-%m-%dT%H:%M:%S")}
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps(cached, indent=1))
        tmp.replace(path)
    except OSError:
        pass  # an unwritable cache costs a probe per process, nothing else
    return rounded_ratio(rate)


def reference_budget_s(budget_s: float, ratio: float) -> float:
    """A training budget of `budget_s` seconds here, in the fit machine's seconds (capped at the fitted range)."""
    return min(budget_s * ratio, max(MAX_REFERENCE_BUDGET_S, budget_s))
