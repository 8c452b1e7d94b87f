"""Bytes against image MSE for model variants: the default preset's method with named overrides (bits per table
value, per network weight, table size, nodes, the quantization-aware share of training), each trained at one
wall-clock budget and scored as stored by the one metric (`harness.product_scorer`: 16 held-out views at 256 px).

    .venv/bin/python -m bench.quality.bench_frontier --meshes bunny --seconds 200 \\
        --variants "t8n8=table_bits:8,network_bits:8" "t4n4=table_bits:4,network_bits:4,qat_fraction:0.5"

A variant is LABEL=field:value,...; a field is any `Settings` field (ints, floats, strings as written). The mesh is
a bench mesh (`bench_meshes.bench_mesh`) or a real asset (`real_assets.asset_path`). Resumable: one row per (mesh,
seconds, label) in bench/results/frontier.csv; frontier.md and frontier.png (file bytes against MSE, one marker per
variant, the frontier of each mesh drawn) are rewritten after every row. Train on an otherwise idle CPU (the budget
is wall-clock).
"""
from __future__ import annotations

import argparse
import json
import time

from bench.meshes import named_mesh
from bench.harness import (RESULTS, SMOKE, markdown_table, measure_missing, product_scorer, save_bytes_mse_chart,
                           write_markdown)
from nbvh_core.app.pipeline import compress_mesh, preset

OUT = RESULTS / "frontier.csv"


def parse_variant(text: str) -> tuple[str, dict]:
    """'LABEL=field:value,field:value' -> (label, {field: value}) with numbers parsed."""
    label, _, spec = text.partition("=")
    overrides = {}
    for item in filter(None, spec.split(",")):
        key, _, value = item.partition(":")
        try:
            overrides[key] = json.loads(value)
        except json.JSONDecodeError:
            overrides[key] = value
    return label, overrides


def measure(name: str, seconds: float, label: str, overrides: dict) -> dict:
    mesh = named_mesh(name)
    t0 = time.perf_counter()
    smoke = dict(eval_views=1, eval_resolution=32) if SMOKE else {}  # a smoke run checks the script, not numbers
    s = preset("default").with_overrides(force=True, time_limit_s=seconds, **smoke, **overrides)
    res = compress_mesh(mesh, s, None)
    q = product_scorer(mesh, res.tracer, n_views=s.eval_views if SMOKE else None,
                       resolution=s.eval_resolution if SMOKE else None).score_model(res.model)[0]
    comps = res.components
    return {"mesh": name, "triangles": mesh.n_triangles, "train_s": seconds, "variant": label,
            "overrides": json.dumps(overrides, sort_keys=True), "file_bytes": len(res.data),
            "bvh_bytes": comps.get("bvh", 0), "features_bytes": comps.get("features", 0),
            "network_bytes": comps.get("network", 0), "header_bytes": comps.get("header", 0),
            "mse": round(q.mse, 7), "silhouette_iou": round(q.silhouette_iou, 4), "steps": res.training.steps,
            "seconds": round(time.perf_counter() - t0, 1)}


def pareto(points: list[tuple[int, float]]) -> list[tuple[int, float]]:
    """The points no other point beats in both bytes and MSE, by bytes."""
    out, best = [], float("inf")
    for b, m in sorted(points):
        if m < best:
            out.append((b, m))
            best = m
    return out


def report(rows: list[dict]) -> None:
    table = [[r["mesh"], f"{float(r['train_s']):g}", r["variant"], r["overrides"], f"{int(r['file_bytes']):,}",
              f"{int(r['features_bytes']):,}", f"{int(r['network_bytes']):,}", f"{int(r['bvh_bytes']):,}",
              f"{int(r['header_bytes']):,}", f"{float(r['mse']):.6f}", r["steps"]] for r in rows]
    write_markdown(RESULTS / "frontier.md", [
        "# Model variants: file bytes against image MSE (bench/quality/bench_frontier.py)", "",
        "The default preset's method with the overrides shown, at one wall-clock budget; each model scored as stored "
        "on 16 held-out views at 256 px (the metric every contender gets).", "",
        *markdown_table(["mesh", "train s", "variant", "overrides", "file bytes", "features", "network", "bvh",
                         "header", "MSE", "steps"], table)])
    chart(rows)


def chart(rows: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.0, 4.8))
    groups = sorted({(r["mesh"], float(r["train_s"])) for r in rows})
    for i, (mesh, seconds) in enumerate(groups):  # a frontier per mesh and budget
        mine = [r for r in rows if r["mesh"] == mesh and float(r["train_s"]) == seconds]
        pts = [(int(r["file_bytes"]), float(r["mse"])) for r in mine]
        ax.plot(*zip(*pareto(pts)), "-", color=f"C{i}", alpha=0.6, label=f"{mesh}, {seconds:g} s: frontier")
        for r, (b, m) in zip(mine, pts):
            ax.plot(b, m, "o", color=f"C{i}", ms=4)
            ax.annotate(r["variant"], (b, m), fontsize=6, xytext=(3, 2), textcoords="offset points")
    save_bytes_mse_chart(fig, ax, "Model variants: bytes against error", RESULTS / "frontier.png")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--meshes", nargs="+", default=["bunny"])
    ap.add_argument("--seconds", type=float, default=200.0)
    ap.add_argument("--variants", nargs="+", required=True, help="LABEL=field:value,... (Settings fields)")
    args = ap.parse_args()
    variants = [parse_variant(text) for text in args.variants]
    cases = [((name, args.seconds, label), (name, args.seconds, label, overrides))
             for name in args.meshes for label, overrides in variants]
    measure_missing(OUT, cases, lambda r: (r["mesh"], float(r["train_s"]), r["variant"]), measure, report)


if __name__ == "__main__":
    main()
