"""The fused train step on one fixed labelled batch (bunny, 4,096 rays, 2047 nodes, the paper's 16 features, N_max 64):
median ms per step over repeated steps, split into its kernel calls, for base (HashGrid T=2^11 + MLP) and III
(HashVQAD T=2^9 + KMLP) on frozen codes and in its soft phase. A fixed batch takes batch drawing, labelling and the
optimiser out of the comparison: what is left is the kernels, old code against new code back to back.

    .venv/bin/python -m bench.profiling.profile_fixed_batch [STEPS]    # prints one line per model
"""
import statistics
import sys
import time
from collections import defaultdict

import numpy as np

from nbvh_core import kernels
from nbvh_core.geometry.bvh import build_bvh
from nbvh_core.neural.encodings import hashvqad
from nbvh_core.geometry.exact import ExactTracer
from nbvh_core.kernels import bindings
from nbvh_core.neural import fused_mlp as mlp
from nbvh_core.geometry.mesh import load_mesh
from nbvh_core.neural.model import NeuralBVH
from nbvh_core.app.pipeline import preset
from nbvh_core.training.rays import label_samples, root_box, sample_rays
from nbvh_core.geometry.bundled_samples import sample_path

parts: dict[str, list[float]] = defaultdict(list)


def timed(owner, name: str, key: str, static: bool = False) -> None:
    """Wrap owner.name so that each call's seconds add to parts[key]."""
    fn = getattr(owner, name)

    def wrapper(*a, **kw):
        t = time.perf_counter()
        out = fn(*a, **kw)
        parts[key].append(time.perf_counter() - t)
        return out
    setattr(owner, name, staticmethod(wrapper) if static else wrapper)


def main() -> None:
    steps = int(sys.argv[1]) if len(sys.argv) > 1 else 30
    kernels.keep_freed_memory()
    timed(mlp, "entries_read", "mark entries")
    timed(hashvqad._SoftTable, "forward", "soft forward", static=True)
    timed(hashvqad._SoftTable, "backward", "soft backward", static=True)
    timed(bindings, "net_train", "train kernel")
    mesh = load_mesh(sample_path("bunny"))
    bvh = build_bvh(mesh, 2047)
    o, d = sample_rays(*root_box(bvh), 4096, np.random.default_rng(0))
    batch = label_samples(bvh, ExactTracer(mesh), o, d, "consistent")
    iii = {"encoding": "hashvqad", "network": "kmlp", "log2_table": 9}
    for name, over, freeze in [("base", {"log2_table": 11}, False), ("III frozen", iii, True), ("III soft", iii, False)]:
        s = preset("default").with_overrides(steps=10, features=16, n_max=64, **over)
        model = NeuralBVH(bvh.nodes, s.model_config(), mesh.transform)
        if freeze:
            model.encoding.freeze()
        times = []
        for i in range(steps + 3):  # 3 warm-up steps
            if i == 3:
                parts.clear()
            model.zero_grad(set_to_none=True)
            t = time.perf_counter()
            mlp.train_step(model, batch)
            times.append(time.perf_counter() - t)
        ms = {k: round(statistics.median(v) * 1e3, 2) for k, v in parts.items()}
        print(f"{name}: {len(batch)} segments, {statistics.median(times[3:]) * 1e3:.2f} ms per step (median of "
              f"{steps}); parts {ms}", flush=True)


if __name__ == "__main__":
    main()
