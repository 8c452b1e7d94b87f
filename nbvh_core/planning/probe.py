"""The machine's probes, once per machine and device, kept in the user's cache: the default preset's training on
the bundled blob for a few seconds (labels, encoding, network, Adam: the whole step, as a run trains), in leaf
samples per second. `machine_rate` reads it as the work a second buys; `card_batch` as the batch a card needs.
"""
from __future__ import annotations

import json
import os
import platform
import time
from pathlib import Path

PROBE_STEPS = 150


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


def probe_samples_per_s(device: str, rays_per_step: int, steps: int = PROBE_STEPS) -> float:
    """The default preset's training rate here: `steps` steps on the bundled blob (a few seconds), leaf samples per
    second of the training itself (the BVH and labels' setup not counted), at `rays_per_step` rays per step."""
    from ..geometry.bvh import build_bvh
    from ..geometry.bundled_samples import sample_path
    from ..geometry.exact import ExactTracer
    from ..geometry.mesh import load_mesh
    from ..neural.model import NeuralBVH
    from ..training.train import train
    from .settings import preset

    s = preset("default").with_overrides(log2_table=11, n_max=64, steps=steps, time_limit_s=None,
                                         device=device, seed=0, rays_per_step=rays_per_step)
    mesh = load_mesh(sample_path("blob"))
    bvh = build_bvh(mesh, s.nodes)
    model = NeuralBVH(bvh.nodes, s.model_config(), mesh.transform)
    cfg = s.train_config()
    result = train(model, bvh, ExactTracer(mesh), cfg)
    return float(result.samples_per_s)


def cached_probe(key: str, probe, valid) -> dict:
    """The user's cache's entry for `key` when `valid(entry)`, else `probe()`'s (a dict), measured now and kept."""
    path = _cache_path()
    try:
        cached = json.loads(path.read_text())
    except (OSError, ValueError):
        cached = {}
    cached = cached if isinstance(cached, dict) else {}
    entry = cached.get(key)
    if isinstance(entry, dict) and valid(entry):
        return entry
    entry = {**probe(), "measured": time.strftime("%Y-%m-%dT%H:%M:%S")}
    cached[key] = entry
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps(cached, indent=1))
        tmp.replace(path)
    except OSError:
        pass  # an unwritable cache costs a probe per process, nothing else
    return entry
