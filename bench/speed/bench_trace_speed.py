"""Tracing speed of stored models, side by side in one process: each .nbvh file loaded as a tracer holds it and
rendered from the same orbit views, in turn (A B A B ...), so the machine's drift falls on both alike.

    .venv/bin/python -m bench.speed.bench_trace_speed OLD.nbvh NEW.nbvh [--size 512] [--repeats 5] [--views 4]

Per file: its bytes, the model's shape (levels x features, hidden layers, k points), the median seconds per frame
over repeats x views and primary rays per second; the ratio to the first file. Rows are appended to
bench/results/trace_speed.csv (stamped) and trace_speed.md is rewritten.
"""
from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

from bench.harness import RESULTS, SMOKE, append_rows, markdown_table, read_rows, write_markdown
from nbvh_core.rendering.render import orbit_cameras, render_neural
from nbvh_core.storage.fileformat import load_nbvh

OUT = RESULTS / ("trace_speed_smoke.csv" if SMOKE else "trace_speed.csv")


def shape_of(model) -> str:
    """levels x features, hidden layers, k points of a loaded model."""
    enc, net = model.cfg.encoding, model.cfg.network
    return f"{enc.levels}x{enc.features}, {net.hidden} hidden, k {net.k}, T=2^{enc.log2_table}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("models", nargs="+", type=Path)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--make-tiny", action="store_true", help="train a tiny blob model into each missing path (smoke)")
    args = ap.parse_args()
    if args.make_tiny:
        from bench.meshes import bench_mesh
        from nbvh_core.app.pipeline import compress_mesh, preset

        for path in args.models:
            if not path.exists():
                path.parent.mkdir(parents=True, exist_ok=True)
                compress_mesh(bench_mesh("blob"), preset("tiny").with_overrides(force=True), path,
                              evaluate_quality=False)
    models = [load_nbvh(p) for p in args.models]
    cams = orbit_cameras(args.views)
    for m in models:  # warm-up: kernels built, caches filled
        render_neural(m, cams[0], args.size, args.size)
    seconds: list[list[float]] = [[] for _ in models]
    for _ in range(args.repeats):
        for cam in cams:
            for i, m in enumerate(models):
                t = time.perf_counter()
                render_neural(m, cam, args.size, args.size)
                seconds[i].append(time.perf_counter() - t)
    base = statistics.median(seconds[0])
    rows = []
    for path, m, s in zip(args.models, models, seconds):
        med = statistics.median(s)
        rows.append({"file": path.name, "bytes": path.stat().st_size, "shape": shape_of(m), "size": args.size,
                     "frames": len(s), "median_s": round(med, 4), "min_s": round(min(s), 4),
                     "max_s": round(max(s), 4), "rays_per_s": round(args.size ** 2 / med),
                     "vs_first": round(med / base, 3)})
        print(rows[-1], flush=True)
    append_rows(OUT, rows)
    table = [[r["utc"], r["file"], f"{int(r['bytes']):,}", r["shape"], r["size"], r["frames"], r["median_s"],
              r["min_s"], r["max_s"], f"{int(r['rays_per_s']):,}", r["vs_first"]] for r in read_rows(OUT)]
    write_markdown(OUT.with_suffix(".md"), [
        "# Tracing speed of stored models (bench/speed/bench_trace_speed.py)", "",
        "Each file loaded as a tracer holds it and rendered from the same orbit views in turn, in one process; "
        "seconds per frame (median, min, max over repeats x views); `vs_first`: the median over the first file's "
        "of the same run.", "",
        *markdown_table(["utc", "file", "bytes", "shape", "px", "frames", "median s", "min s", "max s", "rays/s",
                         "vs first"], table)])


if __name__ == "__main__":
    main()
