"""Speed of the paper's method steps on the fast path: training leaf samples/s and 512x512 render time per
encoding x network (medians of interleaved rounds; ratios within the run), bunny, 2047 nodes, the default preset's
other settings.

    .venv/bin/python -m bench.speed.bench_method_speed [--steps 150] [--repeats 3] [--renders 5]
                                                  # -> bench/results/method_speed.{csv,md}

HashVQAD trains in its soft phase (the softmax over t candidates of every index entry each step: the expensive
one), then as many steps again on its frozen codes (the fine-tune phase's speed: a row of its own); its render is
after the freeze (hard codes looked up in the kernel).
"""
from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

from nbvh_core import kernels
from nbvh_core.geometry.bvh import build_bvh
from nbvh_core.geometry.exact import ExactTracer
from nbvh_core.geometry.mesh import load_mesh
from nbvh_core.neural.model import NeuralBVH
from nbvh_core.app.pipeline import preset
from nbvh_core.rendering.render import orbit_cameras, render_neural
from nbvh_core.geometry.bundled_samples import sample_path
from nbvh_core.training.train import train

from bench.harness import RESULTS, write_markdown, write_rows

# The paper's sizes (16 features, Table 5's T), written out: the default preset's own sizes are not the paper's.
PAPER = {"features": 16, "n_max": 64}
METHODS = [("HashGrid T=2^11 + MLP (base)", {"log2_table": 11}),
           ("HashGrid T=2^11 + KMLP (I/II)", {"log2_table": 11, "network": "kmlp"}),
           ("HashVQAD T=2^9 + MLP", {"encoding": "hashvqad", "log2_table": 9}),
           ("HashVQAD T=2^9 + KMLP (III)", {"encoding": "hashvqad", "network": "kmlp", "log2_table": 9})]


def measure(name: str, over: dict, steps: int, renders: int, bvh, mesh, tracer) -> list[dict]:
    """One training (and for HashVQAD one more on its frozen codes) and the median of `renders` 512x512 renders of
    one method: its row(s)."""
    s = preset("default").with_overrides(steps=steps, **PAPER, **over)
    s.time_limit_s = None
    model = NeuralBVH(bvh.nodes, s.model_config(), mesh.transform)
    cfg = s.train_config()
    cfg.anneal_fraction, cfg.freeze, cfg.table_bits = 0.0, False, None  # the soft phase throughout
    tr = train(model, bvh, tracer, cfg)
    out = [{"method": name, "train_samples_per_s": tr.samples_per_s, "compute_path": tr.compute_path}]
    if model.encoding.learned_index:
        model.encoding.freeze()
        frozen = train(model, bvh, tracer, cfg)
        out.append({"method": name + ", frozen codes", "train_samples_per_s": frozen.samples_per_s,
                    "compute_path": frozen.compute_path})
    model.eval()
    cam = orbit_cameras(1)[0]
    render_neural(model, cam, 64, 64)  # warm-up
    times = []
    for _ in range(renders):
        t = time.perf_counter()
        render_neural(model, cam, 512, 512)
        times.append(time.perf_counter() - t)
    for row in out:  # a HashVQAD model renders after its freeze: one render figure for both rows
        row["render_512_s"] = statistics.median(times)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=150)
    ap.add_argument("--repeats", type=int, default=3, help="rounds over all methods (medians reported)")
    ap.add_argument("--renders", type=int, default=5, help="512x512 renders per method and round")
    args = ap.parse_args()
    kernels.keep_freed_memory()
    mesh = load_mesh(sample_path("bunny"))
    bvh = build_bvh(mesh, 2047)
    tracer = ExactTracer(mesh)
    runs: dict[str, list[dict]] = {}
    for rep in range(args.repeats):  # methods interleaved: the machine's slow spells spread over all of them
        for name, over in METHODS:
            for row in measure(name, over, args.steps, args.renders, bvh, mesh, tracer):
                runs.setdefault(row["method"], []).append(row)
                print(rep, {k: round(v, 4) if isinstance(v, float) else v for k, v in row.items()}, flush=True)
    rows = []
    for method, got in runs.items():
        sps = [r["train_samples_per_s"] for r in got]
        ren = [r["render_512_s"] for r in got]
        rows.append({"method": method, "train_samples_per_s": round(statistics.median(sps)),
                     "train_samples_per_s_min": round(min(sps)), "train_samples_per_s_max": round(max(sps)),
                     "render_512_s": round(statistics.median(ren), 4), "rays_per_s": round(512 * 512 / statistics.median(ren)),
                     "compute_path": got[0]["compute_path"]})
    base = rows[0]
    for r in rows:
        r["train_slowdown_vs_base"] = round(base["train_samples_per_s"] / r["train_samples_per_s"], 2)
        r["render_slowdown_vs_base"] = round(r["render_512_s"] / base["render_512_s"], 2)
    write_rows(RESULTS / "method_speed.csv", rows)
    lines = ["# Method steps on the fast path (bench/speed/bench_method_speed.py)", "",
             f"Bunny, 2047 nodes, the paper's 16 features, N_max 64, {args.steps} training steps each; medians of "
             f"{args.repeats} rounds over all methods ({args.renders} renders each per round) on this 2-core CPU; "
             f"`{base['compute_path']}`.", "",
             "| method | training samples/s (median; min-max) | x slower than base | 512x512 render s | x slower than base |",
             "|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['method']} | {r['train_samples_per_s']:,} ({r['train_samples_per_s_min']:,}-"
                     f"{r['train_samples_per_s_max']:,}) | {r['train_slowdown_vs_base']} | "
                     f"{r['render_512_s']} | {r['render_slowdown_vs_base']} |")
    write_markdown(RESULTS / "method_speed.md", lines)


if __name__ == "__main__":
    main()
