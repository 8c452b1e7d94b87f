"""Bits per feature value against table size at equal bytes: the default preset's method trained at one budget with
8-bit tables and with 4-bit tables (quantization-aware: the last 25% trains through the clipped 4-bit grid), at
table sizes where the two meet in file bytes (4-bit at 2^(k+1) holds the feature bytes of 8-bit at 2^k). Each
model scored as stored by the one metric (`harness.product_scorer`: 16 held-out views at 256 px).

    .venv/bin/python -m bench.quality.bench_table_bits [--meshes bunny spiky gyroid] [--seconds 60] [--pairs 8:11 4:12 8:12 4:13]

Resumable: one row per (mesh, seconds, bits, log2 T) in bench/results/table_bits.csv; table_bits.md and the chart
table_bits.png (file bytes against MSE, one line per bit width and mesh) are rewritten after every row. Train on an
otherwise idle CPU (the budget is wall-clock).
"""
from __future__ import annotations

import argparse
import time

from bench.meshes import bench_mesh
from bench.harness import (RESULTS, markdown_table, measure_missing, product_scorer, save_bytes_mse_chart,
                           write_markdown)
from nbvh_core.app.pipeline import compress_mesh, preset

OUT = RESULTS / "table_bits.csv"


def measure(name: str, seconds: float, bits: int, log2_table: int) -> dict:
    mesh = bench_mesh(name)
    t0 = time.perf_counter()
    s = preset("default").with_overrides(force=True, time_limit_s=seconds, table_bits=bits, log2_table=log2_table)
    res = compress_mesh(mesh, s, None)
    q = product_scorer(mesh, res.tracer).score_model(res.model)[0]
    return {"mesh": name, "triangles": mesh.n_triangles, "train_s": seconds, "table_bits": bits,
            "log2_table": log2_table, "file_bytes": len(res.data), "features_bytes": res.components["features"],
            "mse": round(q.mse, 7), "silhouette_iou": round(q.silhouette_iou, 4), "steps": res.training.steps,
            "seconds": round(time.perf_counter() - t0, 1)}


def report(rows: list[dict]) -> None:
    table = [[r["mesh"], f"{float(r['train_s']):g}", r["table_bits"], f"2^{r['log2_table']}",
              f"{int(r['file_bytes']):,}", f"{int(r['features_bytes']):,}", f"{float(r['mse']):.6f}", r["steps"]]
             for r in rows]
    write_markdown(RESULTS / "table_bits.md", [
        "# 8-bit against 4-bit feature tables at equal file bytes (bench/quality/bench_table_bits.py)", "",
        "The default preset's method at one wall-clock budget; each model scored as stored on 16 held-out views at "
        "256 px. A 4-bit table at 2^(k+1) rows holds the bytes of an 8-bit one at 2^k.", "",
        *markdown_table(["mesh", "train s", "table bits", "T", "file bytes", "features bytes", "MSE", "steps"],
                        table)])
    chart(rows)


def chart(rows: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    for i, mesh in enumerate(sorted({r["mesh"] for r in rows})):
        for bits, style in (("8", "-o"), ("4", "--s")):
            pts = sorted((int(r["file_bytes"]), float(r["mse"])) for r in rows
                         if r["mesh"] == mesh and str(r["table_bits"]) == bits)
            if pts:
                ax.plot(*zip(*pts), style, color=f"C{i}", label=f"{mesh}, {bits}-bit table")
    save_bytes_mse_chart(fig, ax, "Feature bits against table size at equal bytes", RESULTS / "table_bits.png")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--meshes", nargs="+", default=["bunny", "spiky", "gyroid"])
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--pairs", nargs="+", default=["8:11", "4:12", "8:12", "4:13"],
                    help="bits:log2 T of each model to train")
    args = ap.parse_args()
    pairs = [tuple(int(x) for x in pair.split(":")) for pair in args.pairs]
    cases = [((name, args.seconds, bits, log2), (name, args.seconds, bits, log2))
             for name in args.meshes for bits, log2 in pairs]
    measure_missing(OUT, cases, lambda r: (r["mesh"], float(r["train_s"]), int(r["table_bits"]), int(r["log2_table"])),
                    measure, report)


if __name__ == "__main__":
    main()
