"""The paper's Table 5 at equal steps or equal wall time: the bytes each method step needs to reach base's MSE.

    .venv/bin/python -m bench.quality.bench_table5 [--steps 1200] [--meshes bunny knot spiky gyroid studs]
    .venv/bin/python -m bench.quality.bench_table5 --time-limit 200 --plan base:11 I:10 III:8 III:9   # equal wall time

Methods (pipeline presets): base = HashGrid + MLP + ownership labels, I = + KMLP, II = + consistent labels,
III = + HashVQAD. base trains at T=2^11 (its 775 KB file in the paper's float32 storage); I/II at T=2^9, 2^10 and
III at T=2^8, 2^9, each for the same number of steps, scored with the one metric (`metrics.evaluate`, 16 views,
128 px). Bytes are the float32 file (the paper stores floats) and, beside them, the same model in this product's
default storage (8-bit tables, boxes and weight rows; `estimate_file_bytes`). Resumable: one CSV row per
(mesh, method, log2 T) in bench/results/table5.csv; table5.md is rewritten after every row. Every method trains
with its network's own normal targets (`settings.NORMAL_LOSS_BY_NETWORK`: the MLP's as the mesh winds them, KMLP's
facing the ray); `--normal-loss facing|oriented|unoriented` gives every method one loss, in its own CSV
(table5_facing_loss.csv, table5_oriented_loss.csv, table5_unoriented_loss.csv); normal_loss.md compares the older
three.
`--n-max auto` (default) lets every method's grid be chosen from the mesh and its table (`mesh_measures.choose_resolution`,
as the user presets do; base and III alike), `--n-max 128` is the paper's fixed grid (stem suffix `_nmax128`).
Older runs (KMLP normal weight 0.5, N_max 128) are kept as table5_kmlp_weight05_{facing,oriented,unoriented}_loss.csv.
`--time-limit S` trains every model for S seconds instead of a step count (the default preset's 200 s is the users'
budget; a slower step buys fewer steps), stem suffix `_time{S}`; needs an otherwise idle CPU.
"""
from __future__ import annotations

import argparse
import itertools
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

from bench.meshes import bench_mesh
from bench.harness import RESULTS, append_row, read_rows, write_markdown
from nbvh_core import kernels
from nbvh_core.app.pipeline import compress_mesh, estimate_file_bytes, preset

PLAN = [("base", 11), ("I", 9), ("I", 10), ("II", 9), ("II", 10), ("III", 8), ("III", 9)]
FIELDS = ["mesh", "method", "log2_table", "seed", "n_max", "normal_weight", "steps", "train_s", "mse", "iou",
          "file_bytes_float32", "file_bytes_default_storage", "neural_rays_per_s", "created"]


def bytes_to_reach(points: list[tuple[int, float]], target: float) -> float | None:
    """Bytes at which a method's MSE reaches `target`: log-log interpolation between the measured sizes that
    bracket it (the paper's Table 5 reads memory at equal quality the same way); the smallest measured size when
    that already reaches it; None when no measured size does."""
    import math

    for i, (b, mse) in enumerate(points):
        if mse <= target:
            if i == 0:
                return float(b)
            b0, m0 = points[i - 1]
            f = (math.log(target) - math.log(m0)) / (math.log(mse) - math.log(m0))
            return math.exp(math.log(b0) + f * (math.log(b) - math.log(b0)))
    return None


def mean_mse(rows: list[dict], method: str) -> list[tuple[float, float]]:
    """[(float32 bytes, MSE), both averaged over the seeds run] of one method's table sizes, smallest first (a file's
    header differs by a few bytes between runs)."""
    by_size: dict[int, list[tuple[int, float]]] = {}
    for r in rows:
        if r["method"] == method:
            by_size.setdefault(int(r["log2_table"]), []).append((int(r["file_bytes_float32"]), float(r["mse"])))
    return sorted((sum(b for b, _ in v) / len(v), sum(m for _, m in v) / len(v)) for v in by_size.values())


def write_md(rows: list[dict], steps: int, stem: str = "table5", normal_loss: str | None = None,
             n_max: str = "auto", time_limit: float | None = None) -> None:
    grid = "the grid chosen per mesh" if n_max == "auto" else f"N_max {n_max}"
    if time_limit is None:
        title, budget = "equal steps", f"{steps} training steps per model"
    else:
        title, budget = f"equal wall time ({time_limit:g} s, --time-limit)", f"{time_limit:g} s of training per model"
    loss = f"{normal_loss} normal loss" if normal_loss else "each network's own normal targets (MLP wound, KMLP facing)"
    lines = [f"# Table 5 at {title} (bench/quality/bench_table5.py --n-max {n_max}), {loss}, {grid}", "",
             f"{budget} on this 2-core CPU; MSE over 16 views at 128 px. 'reaches at' = the "
             "bytes at which the method's MSE equals base's, interpolated (log-log) between its measured sizes, over "
             "base's bytes (float32 storage, as the paper stores; the default-storage column is the same model's size "
             "in this product's 8-bit format)."
             " 'render rays/s': the trained model's rays per second over the metric's 16 views (128 px), where recorded.",
             "", "| mesh | method | T | seed | N_max | normal weight | MSE | IoU | float32 file B | default-storage B | "
             "steps | train s | render rays/s |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['mesh']} | {r['method']} | 2^{r['log2_table']} | {r.get('seed') or 0} | "
                     f"{r.get('n_max') or 128} | {r.get('normal_weight') or '-'} | {float(r['mse']):.5f} | "
                     f"{float(r['iou']):.4f} | {int(r['file_bytes_float32']):,} | "
                     f"{int(r['file_bytes_default_storage']):,} | {r['steps']} | {float(r['train_s']):.0f} | "
                     f"{format(int(r['neural_rays_per_s']), ',') if r.get('neural_rays_per_s') else '-'} |")
    lines += ["", "Each size's MSE is the mean over the seeds run (the seeds column); with one seed per cell a single "
              "run decides, and 1,200-step runs differ by ~10% between seeds.", "",
              "| mesh | seeds | base MSE | I reaches at | II reaches at | III reaches at (bytes / base) |",
              "|---|---|---|---|---|---|"]
    for mesh in dict.fromkeys(r["mesh"] for r in rows):
        mine = [r for r in rows if r["mesh"] == mesh]
        base = mean_mse(mine, "base")
        if not base:
            continue
        (base_bytes, base_mse), = base
        cells = []
        for method in ("I", "II", "III"):
            pts = mean_mse(mine, method)
            b = bytes_to_reach(pts, base_mse)
            cells.append("- (not run)" if not pts else "not reached" if b is None else f"{b / base_bytes:.3f}x")
        seeds = sorted({r.get("seed") or "0" for r in mine})
        lines.append(f"| {mesh} | {', '.join(seeds)} | {base_mse:.5f} | " + " | ".join(cells) + " |")
    write_markdown(RESULTS / f"{stem}.md", lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=1200)
    ap.add_argument("--meshes", nargs="+", default=["bunny", "knot", "spiky", "gyroid", "studs"])
    ap.add_argument("--methods", nargs="+", default=["base", "I", "II", "III"],
                    help="method steps to run (base and III answer the Table 5 question alone)")
    ap.add_argument("--normal-loss", choices=["facing", "oriented", "unoriented"],
                    help="one normal loss for every method (default: each network's own)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0], help="one row per seed; the tables average them")
    ap.add_argument("--n-max", default="auto", help="'auto' (chosen per mesh and table) or a resolution (128: the "
                    "paper's)")
    ap.add_argument("--time-limit", type=float, help="seconds of training per model instead of --steps")
    ap.add_argument("--plan", nargs="+", metavar="METHOD:LOG2T",
                    help="the (method, table size) cells to run, e.g. base:11 III:8 (default: "
                         + " ".join(f"{m}:{t}" for m, t in PLAN) + ")")
    ap.add_argument("--tag", default="", help="appended to the CSV's name: a run of its own (an equal-time "
                    "comparison needs all its rows from one machine)")
    args = ap.parse_args()
    plan = [(m, int(t)) for m, t in (c.split(":") for c in args.plan)] if args.plan else PLAN
    kernels.keep_freed_memory()
    n_max = None if args.n_max == "auto" else int(args.n_max)
    stem = ("table5" if args.normal_loss is None else f"table5_{args.normal_loss}_loss") + (
        "" if n_max is None else f"_nmax{n_max}") + ("" if args.time_limit is None else f"_time{args.time_limit:g}") + (
        f"_{args.tag}" if args.tag else "")
    path = RESULTS / f"{stem}.csv"
    done = {(r["mesh"], r["method"], r["log2_table"], r.get("seed") or "0") for r in read_rows(path)}
    for mesh_name in args.meshes:
        mesh = None
        for (method, log2), seed in itertools.product(plan, args.seeds):
            if method not in args.methods or (mesh_name, method, str(log2), str(seed)) in done:
                continue
            mesh = mesh or bench_mesh(mesh_name)
            s = preset(method).with_overrides(steps=None if args.time_limit else args.steps, log2_table=log2, table_bits=32, network_bits=32,
                                              node_bits=32, force=True, normal_loss=args.normal_loss, seed=seed)
            s.time_limit_s, s.n_max = args.time_limit, n_max
            t = time.perf_counter()
            res = compress_mesh(mesh, s, None)
            row = {"mesh": mesh_name, "method": method, "log2_table": log2, "seed": seed, "n_max": res.settings.n_max,
                   "normal_weight": res.model.cfg.network.normal_weight, "steps": res.training.steps,
                   "train_s": round(res.training.seconds, 1), "mse": res.quality.mse,
                   "iou": res.quality.silhouette_iou, "file_bytes_float32": res.file_bytes,
                   "file_bytes_default_storage": estimate_file_bytes(s.with_overrides(table_bits=8, network_bits=8,
                                                                                      node_bits=8)),
                   "neural_rays_per_s": round(res.quality.neural_rays_per_s),  # the metric's 16 views
                   "created": time.strftime("%Y-%m-%dT%H:%M:%S")}
            append_row(path, {k: row[k] for k in FIELDS})
            print(row, f"({time.perf_counter() - t:.0f} s)", flush=True)
            write_md(read_rows(path), args.steps, stem, args.normal_loss, args.n_max, args.time_limit)


if __name__ == "__main__":
    main()
