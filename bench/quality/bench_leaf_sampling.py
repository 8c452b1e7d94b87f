"""N-BVH reference ideas against our default training, at equal training time: loss-proportional leaf sampling
(--variant loss, the default) or tree-cut splitting (--variant tree_cut).

    .venv/bin/python -m bench.quality.bench_leaf_sampling [--variant loss|tree_cut] [--train-s 15] [--seeds 2] [--quick]

tree_cut: training starts from an SAH cut with half the leaves and splits the leaves with the highest running error
in 10 rounds over the first 30% of the time, up to the same 2047 nodes. Writes bench/results/tree_cut.md/.csv.

The user preset (`default`: HashGrid + MLP + consistent labels, 2047 nodes, T = 2^11) on the benchmark meshes,
trained --train-s seconds with `leaf_sampling` 'uniform' and 'loss' (half of every batch starts inside leaf boxes
drawn by their running error, floor 0.05 x the mean), same seeds; scored with the quality benchmark's metric
(image MSE, silhouette IoU on 8 orbit views at 128 px) and its failure subsets (hit error of near-surface and
grazing rays). Writes bench/results/leaf_sampling.md and .csv.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]

from bench.quality import rd_runs as rd
from bench.harness import RESULTS, write_markdown, write_rows
from nbvh_core.app.pipeline import compress_mesh, preset

MESHES = ("bunny", "studs", "gyroid", "spiky", "knot", "sheet")
VARIANTS = {"loss": ("leaf_sampling", "loss"), "tree_cut": ("tree_cut", True)}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--variant", choices=list(VARIANTS), default="loss")
    ap.add_argument("--train-s", type=float, default=15.0)
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--quick", action="store_true", help="smoke run: 2 meshes, 3 s, 1 seed")
    args = ap.parse_args()
    from nbvh_core import kernels

    kernels.keep_freed_memory()
    plan = rd.Plan(args.quick)
    meshes = MESHES[:2] if args.quick else MESHES
    train_s = 3.0 if args.quick else args.train_s
    seeds = 1 if args.quick else args.seeds
    cache = rd.MeshCache(plan)
    key, value = VARIANTS[args.variant]
    modes = ("uniform", args.variant)
    name_out = "leaf_sampling" if args.variant == "loss" else args.variant
    rows = []
    for name in meshes:
        mesh, _, fr = cache.get(name)
        for seed in range(seeds):
            for mode in modes:
                s = preset("default").with_overrides(time_limit_s=train_s, seed=seed, eval_views=plan.views,
                                                     eval_resolution=plan.res, force=True, **({key: value} if mode != "uniform" else {}))
                t0 = time.perf_counter()
                res = compress_mesh(mesh, s)
                fail = rd.failure_errors(res.model, fr)
                row = {"mesh": name, "mode": mode, "nodes": int(res.model.nodes.shape[0]), "seed": seed, "train_s": train_s, "steps": res.training.steps,
                       "mse": res.quality.mse, "iou": res.quality.silhouette_iou, **fail,
                       "wall_s": round(time.perf_counter() - t0, 1)}
                rows.append(row)
                print({k: (round(v, 5) if isinstance(v, float) else v) for k, v in row.items()}, flush=True)
    out = RESULTS / f"{name_out}{plan.suffix}.csv"
    write_rows(out, rows)
    fail_keys = [k for k in rows[0] if k.endswith("_hit_err")]  # % of failure-subset rays with the wrong hit
    v = args.variant
    what = ("'loss': half of every batch starts inside leaf boxes drawn in proportion to the running per-leaf error "
            "(floor 0.05 x the mean), the other half as 'uniform'" if v == "loss" else
            "'tree_cut': training starts from the SAH cut with half the leaves (1023 nodes) and splits the leaves "
            "with the highest running error in 10 rounds over the first 30% of the time, up to the same 2047 nodes; "
            "'uniform' trains on the 2047-node SAH cut throughout")
    L = [f"# {'Loss-proportional leaf sampling' if v == 'loss' else 'Tree-cut splitting'} vs our default"
         f"{' (quick)' if plan.quick else ''}\n",
         f"User preset (HashGrid + MLP + consistent labels, 2047 nodes, T=2^11), {train_s:g} s of training per run on "
         f"the 2-core CPU (fast path), {seeds} seed(s) per mesh and mode, scored on {plan.views} views at {plan.res} px. "
         f"{what}. Command: `.venv/bin/python -m bench.quality.bench_leaf_sampling --variant {v}`.\n",
         f"| mesh | MSE uniform | MSE {v} | {v} / uniform | IoU uniform | IoU {v} | "
         + " | ".join(f"{k} uniform | {k} {v}" for k in fail_keys) + " |",
         "|---|---|---|---|---|---|" + "---|---|" * len(fail_keys)]
    ratios = []
    for name in meshes:
        by = {m: [r for r in rows if r["mesh"] == name and r["mode"] == m] for m in modes}
        mean = {m: {k: float(np.mean([r[k] for r in by[m]])) for k in ["mse", "iou", *fail_keys]} for m in modes}
        ratio = mean[v]["mse"] / mean["uniform"]["mse"]
        ratios.append(ratio)
        L.append(f"| {name} | {mean['uniform']['mse']:.5f} | {mean[v]['mse']:.5f} | {ratio:.2f} | "
                 f"{mean['uniform']['iou']:.4f} | {mean[v]['iou']:.4f} | "
                 + " | ".join(f"{mean['uniform'][k]:.4f} | {mean[v][k]:.4f}" for k in fail_keys) + " |")
    gm = float(np.exp(np.mean(np.log(ratios))))
    better = sum(1 for r in ratios if r < 1)
    L.append(f"\nGeometric mean MSE ratio ({v} / uniform): {gm:.2f}; '{v}' has the lower mean MSE on {better} of "
             f"{len(ratios)} meshes (means over the seeds; the seed-to-seed spread of one mode is ~10% on the bunny, "
             "see quality.md).")
    write_markdown(RESULTS / f"{name_out}{plan.suffix}.md", L)
    print("\n".join(L))


if __name__ == "__main__":
    main()
