"""The paper's Table 5 at equal steps: the bytes each method step needs to reach base's image MSE.

    .venv/bin/python bench/bench_table5.py [--steps 1200] [--meshes bunny knot spiky gyroid studs]

Methods (pipeline presets): base = HashGrid + MLP + ownership labels, I = + KMLP, II = + consistent labels,
III = + HashVQAD. base trains at T=2^11 (its 775 KB file in the paper's float32 storage); I/II at T=2^9, 2^10 and
III at T=2^8, 2^9, each for the same number of steps, scored with the one metric (`metrics.evaluate`, 16 views,
128 px). Bytes are the float32 file (the paper stores floats) and, beside them, the same model in this product's
default storage (8-bit tables, boxes and weight rows; `estimate_file_bytes`). Resumable: one CSV row per
(mesh, method, log2 T) in bench/results/table5.csv; table5.md is rewritten after every row. Every method trains
with this product's normal targets facing the ray (`Settings.normal_loss`, default 'facing'); `--normal-loss
oriented` is the paper's (as the mesh winds them), `unoriented` either sign; each loss has its own CSV
(table5.csv, table5_oriented_loss.csv, table5_unoriented_loss.csv) and normal_loss.md compares them.
`--n-max auto` (default) lets every method's grid be chosen from the mesh and its table (`sizing.choose_resolution`,
as the user presets do; base and III alike), `--n-max 128` is the paper's fixed grid (stem suffix `_nmax128`).
Stop 14's runs (KMLP normal weight 0.5, N_max 128) are kept as table5_stop14_{facing,oriented,unoriented}_loss.csv.
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
from nbvh_core.pipeline import compress_mesh, estimate_file_bytes, preset  # noqa: E402

RESULTS = ROOT / "bench" / "results"
PLAN = [("base", 11), ("I", 9), ("I", 10), ("II", 9), ("II", 10), ("III", 8), ("III", 9)]
FIELDS = ["mesh", "method", "log2_table", "n_max", "normal_weight", "steps", "train_s", "mse", "iou",
          "file_bytes_float32", "file_bytes_default_storage", "created"]


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


def write_normal_loss_md() -> None:
    """normal_loss.md: base's and III's MSE per mesh under each normal loss (stop 14's three Table 5 CSVs)."""
    runs = {loss: read_rows(RESULTS / f"table5_stop14_{loss}_loss.csv") for loss in ("facing", "oriented", "unoriented")}
    lines = ["# Normal loss at equal steps (bench/bench_table5.py's three runs, stop 14: KMLP normal weight 0.5, "
             "N_max 128)", "",
             "Image MSE (16 views, 128 px) after the same steps, one run each; 'facing' = normal targets flipped "
             "toward the ray (this product's default), 'oriented' = as the mesh winds them (the paper), "
             "'unoriented' = L1 to the nearer of +-normal.", "",
             "| mesh | method | T | facing | oriented | unoriented |", "|---|---|---|---|---|---|"]
    keys = dict.fromkeys((r["mesh"], r["method"], r["log2_table"]) for rows in runs.values() for r in rows)
    for key in keys:
        cells = []
        for loss in runs:
            row = next((r for r in runs[loss] if (r["mesh"], r["method"], r["log2_table"]) == key), None)
            cells.append(f"{float(row['mse']):.5f}" if row else "-")
        lines.append(f"| {key[0]} | {key[1]} | 2^{key[2]} | " + " | ".join(cells) + " |")
    (RESULTS / "normal_loss.md").write_text("\n".join(lines) + "\n")


def write_md(rows: list[dict], steps: int, stem: str = "table5", normal_loss: str = "facing",
             n_max: str = "auto") -> None:
    grid = "the grid chosen per mesh" if n_max == "auto" else f"N_max {n_max}"
    lines = [f"# Table 5 at equal steps (bench/bench_table5.py --n-max {n_max}), {normal_loss} normal loss, {grid}", "",
             f"{steps} training steps per model on this 2-core CPU; MSE over 16 views at 128 px. 'reaches at' = the "
             "bytes at which the method's MSE equals base's, interpolated (log-log) between its measured sizes, over "
             "base's bytes (float32 storage, as the paper stores; the default-storage column is the same model's size "
             "in this product's 8-bit format).",
             "", "| mesh | method | T | N_max | normal weight | MSE | IoU | float32 file B | default-storage B | train s |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['mesh']} | {r['method']} | 2^{r['log2_table']} | {r.get('n_max') or 128} | "
                     f"{r.get('normal_weight') or '-'} | {float(r['mse']):.5f} | "
                     f"{float(r['iou']):.4f} | {int(r['file_bytes_float32']):,} | "
                     f"{int(r['file_bytes_default_storage']):,} | {float(r['train_s']):.0f} |")
    lines += ["", "| mesh | base MSE | I reaches at | II reaches at | III reaches at (bytes / base) |",
              "|---|---|---|---|---|"]
    for mesh in dict.fromkeys(r["mesh"] for r in rows):
        mine = [r for r in rows if r["mesh"] == mesh]
        base = next((r for r in mine if r["method"] == "base"), None)
        if base is None:
            continue
        cells = []
        for method in ("I", "II", "III"):
            pts = sorted((int(r["file_bytes_float32"]), float(r["mse"])) for r in mine if r["method"] == method)
            b = bytes_to_reach(pts, float(base["mse"]))
            cells.append("- (not run)" if not pts else "not reached" if b is None
                         else f"{b / int(base['file_bytes_float32']):.3f}x")
        lines.append(f"| {mesh} | {float(base['mse']):.5f} | " + " | ".join(cells) + " |")
    (RESULTS / f"{stem}.md").write_text("\n".join(lines) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=1200)
    ap.add_argument("--meshes", nargs="+", default=["bunny", "knot", "spiky", "gyroid", "studs"])
    ap.add_argument("--methods", nargs="+", default=["base", "I", "II", "III"],
                    help="method steps to run (base and III answer the Table 5 question alone)")
    ap.add_argument("--normal-loss", choices=["facing", "oriented", "unoriented"], default="facing")
    ap.add_argument("--n-max", default="auto", help="'auto' (chosen per mesh and table) or a resolution (128: the "
                    "paper's)")
    args = ap.parse_args()
    kernels.keep_freed_memory()
    n_max = None if args.n_max == "auto" else int(args.n_max)
    stem = ("table5" if args.normal_loss == "facing" else f"table5_{args.normal_loss}_loss") + (
        "" if n_max is None else f"_nmax{n_max}")
    path = RESULTS / f"{stem}.csv"
    done = {(r["mesh"], r["method"], r["log2_table"]) for r in read_rows(path)}
    for mesh_name in args.meshes:
        mesh = None
        for method, log2 in PLAN:
            if method not in args.methods or (mesh_name, method, str(log2)) in done:
                continue
            mesh = mesh or bench_mesh(mesh_name)
            s = preset(method).with_overrides(steps=args.steps, log2_table=log2, table_bits=32, network_bits=32,
                                              node_bits=32, force=True, normal_loss=args.normal_loss)
            s.time_limit_s, s.n_max = None, n_max
            t = time.perf_counter()
            res = compress_mesh(mesh, s, None)
            row = {"mesh": mesh_name, "method": method, "log2_table": log2, "n_max": res.settings.n_max,
                   "normal_weight": res.model.cfg.network.normal_weight, "steps": res.training.steps,
                   "train_s": round(res.training.seconds, 1), "mse": res.quality.mse,
                   "iou": res.quality.silhouette_iou, "file_bytes_float32": res.file_bytes,
                   "file_bytes_default_storage": estimate_file_bytes(s.with_overrides(table_bits=8, network_bits=8,
                                                                                      node_bits=8)),
                   "created": time.strftime("%Y-%m-%dT%H:%M:%S")}
            append_row(path, {k: row[k] for k in FIELDS})
            print(row, f"({time.perf_counter() - t:.0f} s)", flush=True)
            write_md(read_rows(path), args.steps, stem, args.normal_loss, args.n_max)


if __name__ == "__main__":
    main()
