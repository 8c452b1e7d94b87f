"""The grid's finest resolution N_max against the table's capacity: the same preset, table size and step count at
several N_max per mesh (equal steps: N_max does not change the cost of a step, and equal steps are robust to a
busy machine), scored with the one metric (16 views, 128 px). Float32 storage, so only the grid differs.

    .venv/bin/python -m bench.quality.bench_resolution [--meshes bunny gyroid] [--n-max 64 128 256] [--steps 1500]
    .venv/bin/python -m bench.quality.bench_resolution --levels 2 4 8 [--meshes bunny gyroid studs] [--time-limit 200]

Resumable: one CSV row per (mesh, preset, log2 T, N_max, steps) in bench/results/resolution.csv; resolution.md is
rewritten after every row with `mesh_measures.choose_resolution`'s pick beside the best measured.

`--levels`: the grid's levels traded against its rows at the preset's table bytes (levels x T x features constant:
L = 2, 4, 8 at T = 2^13, 2^12, 2^11 for the default preset), each grid's N_max chosen for its T as the presets do. A
step's cost grows with L (L lookups per point and an L x wider first layer): the training seconds are in every row.
One row per (mesh, preset, levels, steps) in bench/results/levels.csv, levels.md rewritten after every row.
`--time-limit S`: equal wall time instead (each grid trains S seconds with the preset's own storage, as a user's run
does: the question equal steps leaves open, since a step's cost grows with L); one row per (mesh, preset, levels, S).
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

from bench.meshes import bench_grid, bench_mesh
from bench.harness import RESULTS, append_row, read_rows, write_markdown
from nbvh_core import kernels
from nbvh_core.app.pipeline import compress_mesh, preset
from nbvh_core.planning.mesh_measures import TABLE_LOAD, choose_resolution

FIELDS = ["mesh", "preset", "log2_table", "n_max", "steps", "train_s", "mse", "iou", "surface_cells", "created"]


def write_md(rows: list[dict]) -> None:
    lines = ["# Grid resolution against table capacity (bench/quality/bench_resolution.py)", "",
             "Equal steps per row (the preset's settings, float32 storage, seed 0) on this 2-core CPU; image MSE over "
             "16 views at 128 px. 'cells / T' = the surface cells of the finest level over the table's rows; the "
             f"chooser takes the finest N_max within {TABLE_LOAD:g} x T and the detail's need. (The first 17 rows were "
             "measured, with exactly these settings, by the one-off script this one was written from.)", "",
             "| mesh | preset | T | steps | N_max | surface cells / T | MSE | IoU |", "|---|---|---|---|---|---|---|---|"]
    for r in sorted(rows, key=lambda r: (r["mesh"], int(r["log2_table"]), int(r["steps"]), int(r["n_max"]))):
        load = int(r["surface_cells"]) / (1 << int(r["log2_table"])) if r.get("surface_cells") else float("nan")
        lines.append(f"| {r['mesh']} | {r['preset']} | 2^{r['log2_table']} | {r['steps']} | {r['n_max']} | "
                     f"{load:.1f} | {float(r['mse']):.5f} | {float(r['iou']):.4f} |")
    lines += ["", "| mesh | T | steps | best measured N_max | chooser's N_max |", "|---|---|---|---|---|"]
    groups = dict.fromkeys((r["mesh"], r["log2_table"], r["steps"]) for r in rows)
    for mesh, log2, steps in groups:
        mine = [r for r in rows if (r["mesh"], r["log2_table"], r["steps"]) == (mesh, log2, steps)]
        best = min(mine, key=lambda r: float(r["mse"]))
        pick = choose_resolution(bench_grid(mesh), int(log2))[0]
        lines.append(f"| {mesh} | 2^{log2} | {steps} | {best['n_max']} (MSE {float(best['mse']):.5f}) | {pick} |")
    write_markdown(RESULTS / "resolution.md", lines)


LEVEL_FIELDS = ["mesh", "preset", "levels", "steps", "log2_table", "n_max", "train_s", "mse", "iou", "created",
                "time_limit_s", "file_bytes"]


def write_levels_md(rows: list[dict]) -> None:
    lines = ["# Grid levels against table rows at equal table bytes (bench/quality/bench_resolution.py --levels)", "",
             "Equal steps per row (the preset's settings, levels x T x features constant, float32 storage, seed 0) on "
             "this 2-core CPU; image MSE over 16 views at 128 px; N_max chosen for each T as the presets choose it.",
             "Rows with a time limit trained that many seconds each with the preset's own (quantized) storage; "
             "their steps are the ones reached.",
             "", "| mesh | preset | budget | levels | T | N_max | steps | MSE | IoU | train s |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    def budget(r: dict) -> str:
        return f"{float(r['time_limit_s']):.0f} s" if r.get("time_limit_s") else f"{r['steps']} steps"
    for r in sorted(rows, key=lambda r: (r["mesh"], budget(r), int(r["levels"]))):
        lines.append(f"| {r['mesh']} | {r['preset']} | {budget(r)} | {r['levels']} | 2^{r['log2_table']} | "
                     f"{r['n_max']} | {r['steps']} | {float(r['mse']):.5f} | {float(r['iou']):.4f} | "
                     f"{float(r['train_s']):.0f} |")
    write_markdown(RESULTS / "levels.md", lines)


def equal_steps(mesh, base, steps: int, **overrides):
    """compress_mesh with `base` (Settings) and `overrides` for exactly `steps` steps, float32 storage."""
    s = base.with_overrides(steps=steps, table_bits=32, network_bits=32, node_bits=32, force=True, **overrides)
    s.time_limit_s = None
    return compress_mesh(mesh, s, None)


def equal_time(mesh, base, seconds: float, **overrides):
    """compress_mesh with `base` (Settings) and `overrides` for `seconds` of training, the preset's own storage."""
    s = base.with_overrides(steps=None, force=True, **overrides)
    s.time_limit_s = seconds
    return compress_mesh(mesh, s, None)


def level_key(row: dict) -> tuple:
    """What a levels row measured: (mesh, preset, levels, budget); the budget is its time limit in seconds, or its
    step count for an equal-steps row (whose steps are the ones asked for)."""
    return row["mesh"], row["preset"], row["levels"], row.get("time_limit_s") or f"{row['steps']} steps"


def run_levels(args) -> None:
    path = RESULTS / "levels.csv"
    for mesh_name in args.meshes:
        mesh = None
        for levels in args.levels:
            base = preset(args.preset)
            if levels & (levels - 1) or base.levels & (base.levels - 1):
                raise SystemExit("levels must be powers of two to keep the table bytes equal")
            log2 = base.log2_table + (base.levels.bit_length() - levels.bit_length())  # levels x T constant
            budget = f"{args.time_limit:g}" if args.time_limit else ""
            if (mesh_name, args.preset, str(levels), budget or f"{args.steps} steps") in {
                    level_key(r) for r in read_rows(path)}:
                continue
            mesh = mesh or bench_mesh(mesh_name)
            if args.time_limit:
                res = equal_time(mesh, base, args.time_limit, levels=levels, log2_table=log2)
            else:
                res = equal_steps(mesh, base, args.steps, levels=levels, log2_table=log2)
            row = {"mesh": mesh_name, "preset": args.preset, "levels": levels, "steps": res.training.steps,
                   "log2_table": log2, "n_max": res.settings.n_max, "train_s": round(res.training.seconds, 1),
                   "mse": res.quality.mse, "iou": res.quality.silhouette_iou,
                   "created": time.strftime("%Y-%m-%dT%H:%M:%S"), "time_limit_s": budget,
                   "file_bytes": res.file_bytes}
            append_row(path, row)
            print(row, flush=True)
            write_levels_md(read_rows(path))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--meshes", nargs="+", default=["blob", "bunny", "studs", "gyroid", "knot", "lattice"])
    ap.add_argument("--n-max", type=int, nargs="+", default=[64, 128, 256])
    ap.add_argument("--preset", default="default")
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--levels", type=int, nargs="+", help="trade levels against rows instead (powers of two)")
    ap.add_argument("--time-limit", type=float, help="with --levels: equal wall time (s) instead of equal steps")
    args = ap.parse_args()
    kernels.keep_freed_memory()
    if args.levels:
        return run_levels(args)
    path = RESULTS / "resolution.csv"
    for mesh_name in args.meshes:
        mesh = None
        for n_max in args.n_max:
            base = preset(args.preset)
            key = (mesh_name, args.preset, str(base.log2_table), str(n_max), str(args.steps))
            if key in {tuple(r[k] for k in FIELDS[:5]) for r in read_rows(path)}:
                continue
            mesh = mesh or bench_mesh(mesh_name)
            res = equal_steps(mesh, base, args.steps, n_max=n_max)
            s = res.settings
            cells = bench_grid(mesh_name).cells.get(n_max, "")
            row = {"mesh": mesh_name, "preset": args.preset, "log2_table": s.log2_table, "n_max": n_max,
                   "steps": res.training.steps, "train_s": round(res.training.seconds, 1), "mse": res.quality.mse,
                   "iou": res.quality.silhouette_iou, "surface_cells": cells,
                   "created": time.strftime("%Y-%m-%dT%H:%M:%S")}
            append_row(path, row)
            print(row, flush=True)
            write_md(read_rows(path))


if __name__ == "__main__":
    main()
