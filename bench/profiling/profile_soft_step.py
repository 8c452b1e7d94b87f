"""Where a training step's time goes, base (HashGrid + MLP) against III in its soft phase (HashVQAD + KMLP): the soft
row table's forward and backward, the fused train step (which includes both), Adam; bunny, 2047 nodes, F16, N_max 64.

    .venv/bin/python -m bench.profiling.profile_soft_step [STEPS]    # prints ms per step by part, and the share of index
                                                           # entries a step's batch reads
"""
import sys
import time

import torch

from collections import defaultdict
from nbvh_core import kernels
from nbvh_core.geometry.bvh import build_bvh
from nbvh_core.geometry.exact import ExactTracer
from nbvh_core.geometry.mesh import load_mesh
from nbvh_core.neural.model import NeuralBVH
from nbvh_core.app.pipeline import preset
from nbvh_core.geometry.bundled_samples import sample_path
from nbvh_core.training.train import train
from nbvh_core.neural.encodings import hashvqad as HV
from nbvh_core.neural import fused_mlp as KM
acc = defaultdict(float)
def wrap(obj, name, key):
    f = getattr(obj, name)
    def g(*a, **k):
        t = time.perf_counter(); r = f(*a, **k); acc[key] += time.perf_counter() - t; return r
    setattr(obj, name, g)
of, ob = HV._SoftTable.forward, HV._SoftTable.backward
def sf(ctx, *a):
    t = time.perf_counter(); r = of(ctx, *a); acc["soft_fwd"] += time.perf_counter() - t; return r
def sb(ctx, *a):
    acc["touched_rows_frac"] += float((a[0] != 0).any(dim=1).float().mean())
    t = time.perf_counter(); r = ob(ctx, *a); acc["soft_bwd"] += time.perf_counter() - t; return r
HV._SoftTable.forward, HV._SoftTable.backward = staticmethod(sf), staticmethod(sb)
wrap(KM, "train_step", "train_step(incl soft_bwd)")
wrap(torch.optim.Adam, "step", "adam")
kernels.keep_freed_memory()
mesh = load_mesh(sample_path("bunny")); bvh = build_bvh(mesh, 2047); tracer = ExactTracer(mesh)
steps = int(sys.argv[1]) if len(sys.argv) > 1 else 150
for name, over in [("base", {"log2_table": 11}), ("III", {"encoding": "hashvqad", "network": "kmlp", "log2_table": 9})]:
    s = preset("default").with_overrides(steps=steps, features=16, n_max=64, **over); s.time_limit_s = None
    model = NeuralBVH(bvh.nodes, s.model_config(), mesh.transform)
    cfg = s.train_config(); cfg.anneal_fraction, cfg.freeze, cfg.table_bits = 0.0, False, None
    acc.clear(); t = time.perf_counter(); tr = train(model, bvh, tracer, cfg); dt = time.perf_counter() - t
    read = acc.pop("touched_rows_frac", 0.0) / steps
    print(name, f"{dt / steps * 1e3:.1f} ms/step", {k: f"{v / steps * 1e3:.1f}" for k, v in acc.items()},
          f"entries read per step {read:.1%}" if read else "",
          "samples/s", round(tr.samples_per_s), flush=True)
