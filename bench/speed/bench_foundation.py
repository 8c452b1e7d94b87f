"""Foundation benchmark: BVH build time, traversal rays/s, training samples/s, beside Embree rays/s.

    .venv/bin/python -m bench.speed.bench_foundation [--rays 200000] [--quick]

Writes bench/results/foundation.csv and foundation.md. All numbers of one row come from the same run on the
same machine, so the ratios (ours / Embree) are what to compare across machines.
"""
from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]

from nbvh_core.geometry.bvh import build_full_tree, cut_tree
from nbvh_core.geometry.exact import ExactTracer
from nbvh_core.geometry.mesh import load_mesh
from nbvh_core.rendering.render import orbit_cameras
from nbvh_core.training.rays import RayConfig, label_samples, root_box, sample_rays
from nbvh_core.geometry.bundled_samples import SAMPLE_NAMES, sample_path
from nbvh_core.geometry.traversal import LeafStream, TorchBVH, leaves_along_rays
from bench.harness import RESULTS, write_markdown, write_rows


def best_of(fn, repeat: int = 3) -> float:
    """Fastest wall time of `repeat` calls (seconds): the least disturbed by other load."""
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def drain(stream: LeafStream) -> int:
    n = 0
    while True:
        ray, *_ = stream.next()
        if ray.numel() == 0:
            return n
        n += ray.numel()


def bench_asset(name: str, n_rays: int, budget: int, repeat: int) -> dict:
    mesh = load_mesh(sample_path(name))
    t_full = best_of(lambda: build_full_tree(mesh), 1)
    tree = build_full_tree(mesh)
    t_cut = best_of(lambda: cut_tree(tree, budget), repeat)
    bvh = cut_tree(tree, budget)
    tb = TorchBVH.from_bvh(bvh)
    tracer = ExactTracer(mesh)
    lo, hi = root_box(bvh)
    o, d = sample_rays(lo, hi, n_rays, np.random.default_rng(0), RayConfig())
    o_t, d_t = torch.from_numpy(o), torch.from_numpy(d)
    t_trav = best_of(lambda: leaves_along_rays(tb, o_t, d_t), repeat)
    pairs = len(leaves_along_rays(tb, o_t, d_t))
    t_stream = best_of(lambda: drain(LeafStream(tb, o_t, d_t)), 1)
    t_embree_random = best_of(lambda: tracer.first_hit(o, d), repeat)
    co, cd = orbit_cameras(1)[0].rays(512, 512)
    t_embree_primary = best_of(lambda: tracer.first_hit(co, cd), repeat)
    t_all_hits = best_of(lambda: tracer.all_hits(o, d), 1)
    row = {"asset": name, "triangles": mesh.n_triangles, "nodes": bvh.n_nodes, "leaves": bvh.n_leaves,
           "full_tree_nodes": tree.n_nodes, "full_build_s": round(t_full, 3), "cut_s": round(t_cut, 4),
           "leaf_pairs_per_ray": round(pairs / n_rays, 2),
           "traversal_rays_per_s": round(n_rays / t_trav), "stream_rays_per_s": round(n_rays / t_stream),
           "embree_random_rays_per_s": round(n_rays / t_embree_random),
           "embree_primary_rays_per_s": round(len(co) / t_embree_primary),
           "embree_all_hits_rays_per_s": round(n_rays / t_all_hits)}
    for mode in ("ownership", "consistent"):
        t = best_of(lambda: label_samples(bvh, tracer, o, d, mode, tree=tb), 1)
        n_samples = len(label_samples(bvh, tracer, o, d, mode, tree=tb))
        row[f"{mode}_samples_per_s"] = round(n_samples / t)
    row["traversal_vs_embree_random"] = round(row["traversal_rays_per_s"] / row["embree_random_rays_per_s"], 4)
    row["consistent_samples_vs_embree_random"] = round(row["consistent_samples_per_s"] /
                                                       row["embree_random_rays_per_s"], 4)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rays", type=int, default=200_000)
    ap.add_argument("--nodes", type=int, default=4096)
    ap.add_argument("--quick", action="store_true", help="20k rays, one repeat (smoke run)")
    ap.add_argument("--out", default=str(RESULTS))
    args = ap.parse_args()
    n_rays, repeat = (20_000, 1) if args.quick else (args.rays, 3)
    rows = []
    for name in SAMPLE_NAMES:
        row = bench_asset(name, n_rays, args.nodes, repeat)
        print(row, flush=True)
        rows.append(row)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_rows(out / "foundation.csv", rows)
    cols = ["asset", "triangles", "full_build_s", "cut_s", "leaf_pairs_per_ray", "traversal_rays_per_s",
            "stream_rays_per_s", "ownership_samples_per_s", "consistent_samples_per_s",
            "embree_random_rays_per_s", "embree_primary_rays_per_s", "traversal_vs_embree_random"]
    machine = (f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, torch {torch.__version__} "
               f"({torch.get_num_threads()} threads), {n_rays} random training rays, {args.nodes} BVH nodes")
    lines = ["# Foundation benchmark\n", f"Machine: {machine}.\n",
             "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        lines.append("| " + " | ".join(f"{r[c]:,}" if isinstance(r[c], int) else str(r[c]) for c in cols) + " |")
    write_markdown(out / "foundation.md", lines)
    print(f"wrote {out / 'foundation.csv'} and {out / 'foundation.md'}")


if __name__ == "__main__":
    main()
