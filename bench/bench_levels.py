"""Grid levels traded against the table: the same preset and table bytes (levels x T x features constant) at L = 2,
4 and 8 levels (T = 2^13, 2^12, 2^11 at the default preset's 8 features), each grid's N_max chosen for its T as the
presets do (`sizing.choose_resolution`), equal steps, scored with the one metric (16 views, 128 px). Float32 storage,
so only the grid differs. A step's cost grows with L (L lookups per point and an L x wider first layer): the
training seconds are in every row, so the equal-steps ranking can be read against time too.

    .venv/bin/python bench/bench_levels.py [--meshes bunny gyroid studs knot] [--levels 2 4 8] [--steps 1500]

Resumable: one CSV row per (mesh, preset, levels, steps) in bench/results/levels.csv; levels.md is rewritten after
every row.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "bench")]

from bench_meshes import bench_mesh  # noqa: E402
from bench_quality import append_row, read_rows  # noqa: E402
from nbvh_core import kernels  # noqa: E402
from nbvh_core.pipeline import compress_mesh, preset  # noqa: E402

RESULTS = ROOT / "bench" / "results"
FIELDS = ["mesh", "preset", "levels", "steps", "log2_table", "n_max", "train_s", "mse", "iou", "created"]


def write_md(rows: list[dict]) -> None:
    lines = ["# Grid levels against table rows at equal table bytes (bench/bench_levels.py)", "",
             "Equal steps per row (the preset's settings, levels x T x features constant, float32 storage, seed 0) on "
             "this 2-core CPU; image MSE over 16 views at 128 px; N_max chosen for each T as the presets choose it.",
             "", "| mesh | preset | steps | levels | T | N_max | MSE | IoU | train s |", "|---|---|---|---|---|---|---|---|---|"]
    for r in sorted(rows, key=lambda r: (r["mesh"], int(r["steps"]), int(r["levels"]))):
        lines.append(f"| {r['mesh']} | {r['preset']} | {r['steps']} | {r['levels']} | 2^{r['log2_table']} | "
                     f"{r['n_max']} | {float(r['mse']):.5f} | {float(r['iou']):.4f} | {float(r['train_s']):.0f} |")
    (RESULTS / "levels.md").write_text("\n".join(lines) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--meshes", nargs="+", default=["bunny", "gyroid", "studs", "knot"])
    ap.add_argument("--levels", type=int, nargs="+", default=[2, 4, 8])
    ap.add_argument("--preset", default="default")
    ap.add_argument("--steps", type=int, default=1500)
    args = ap.parse_args()
    kernels.keep_freed_memory()
    path = RESULTS / "levels.csv"
    for mesh_name in args.meshes:
        mesh = None
        for levels in args.levels:
            base = preset(args.preset)
            # the preset's table bytes: levels x T constant (powers of two only)
            log2 = base.log2_table + (base.levels.bit_length() - levels.bit_length())
            if levels & (levels - 1) or base.levels & (base.levels - 1):
                raise SystemExit("levels must be powers of two to keep the table bytes equal")
            key = (mesh_name, args.preset, str(levels), str(args.steps))
            if key in {tuple(r[k] for k in FIELDS[:4]) for r in read_rows(path)}:
                continue
            mesh = mesh or bench_mesh(mesh_name)
            s = base.with_overrides(steps=args.steps, levels=levels, log2_table=log2, table_bits=32, network_bits=32,
                                    node_bits=32, force=True)
            s.time_limit_s = None
            res = compress_mesh(mesh, s, None)
            row = {"mesh": mesh_name, "preset": args.preset, "levels": levels, "steps": res.training.steps,
                   "log2_table": log2, "n_max": res.settings.n_max, "train_s": round(res.training.seconds, 1),
                   "mse": res.quality.mse, "iou": res.quality.silhouette_iou,
                   "created": time.strftime("%Y-%m-%dT%H:%M:%S")}
            append_row(path, row)
            print(row, flush=True)
            write_md(read_rows(path))


if __name__ == "__main__":
    main()
