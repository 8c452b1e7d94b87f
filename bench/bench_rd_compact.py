"""Bytes against image error for every contender on the bench meshes: quadric decimations at several triangle
counts, each held plainly (~44 B per triangle), as a compact ray-traceable mesh (`nbvh_core/geometry/compact_mesh.py`,
scored on its decoded triangles) and as Draco 11-bit (storage only), beside the neural models of pays.csv (each
preset trained at its own budget). One metric for all: 16 orbit views at 128 px against the full mesh (Embree).

    .venv/bin/python bench/bench_rd_compact.py [--meshes bunny spiky ...]   # -> bench/results/rd_compact.{csv,png}
    .venv/bin/python bench/bench_rd_compact.py --chart                      # the chart only, from the CSV

Resumable: one CSV row per (mesh, triangles), appended as it lands.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path
from harness import RESULTS, append_rows, read_rows

ROOT = Path(__file__).resolve().parents[1]
OUT = RESULTS / "rd_compact.csv"
COUNTS = (1000, 4000, 16000, 64000, 256000)
MESHES = ("bunny", "spiky", "gyroid", "knot", "terrain", "lattice")
#: pays.csv rows of the current presets (wound normals for the MLP) and, for the knot, the earlier facing rows.
NEURAL_STORAGE = ("t8/w8/n8 n_max=auto:64 normals=oriented", "t8/w8/n8 n_max=auto:64")


def measure(name: str, done: set) -> None:
    """Append the rows of one mesh's decimations not yet in the CSV."""
    import DracoPy

    from bench_meshes import bench_mesh
    from nbvh_core.geometry.compact_mesh import compact_mesh
    from nbvh_core.geometry.exact import ExactTracer
    from nbvh_core.rendering.metrics import evaluate_renderer
    from nbvh_core.rendering.render import render_reference
    from nbvh_core.planning.sizing import decimate, mesh_resident_bytes

    mesh = bench_mesh(name)
    reference = ExactTracer(mesh)
    for count in COUNTS:
        if count >= 0.7 * mesh.n_triangles or (name, str(count)) in done:
            continue
        t0 = time.perf_counter()
        dec = decimate(mesh, count)
        nbytes, decoded = compact_mesh(dec)
        tracer = ExactTracer(decoded)
        q, _ = evaluate_renderer(lambda cam, w, h: render_reference(tracer, cam, w, h), reference, mesh.transform,
                                 16, 128)
        row = {"mesh": name, "requested": count, "triangles": dec.n_triangles, "compact_mse": q.mse,
               "plain_bytes": mesh_resident_bytes(dec)["total"], "compact_bytes": nbytes,
               "draco11_bytes": len(DracoPy.encode(dec.vertices, dec.faces, quantization_bits=11,
                                                   compression_level=7)),
               "seconds": round(time.perf_counter() - t0, 1)}
        append_rows(OUT, [row])
        print(name, count, q.mse, nbytes, flush=True)


def chart(path: Path) -> None:
    """One panel per mesh: MSE against bytes, log-log."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = read_rows(OUT)
    neural = [r for r in read_rows(RESULTS / "pays.csv") if r["storage"] in NEURAL_STORAGE]
    meshes = [m for m in MESHES if any(r["mesh"] == m for r in rows)]
    fig, axes = plt.subplots(2, 3, figsize=(13, 8))
    for ax, name in zip(axes.ravel(), meshes):
        dec = sorted((r for r in rows if r["mesh"] == name), key=lambda r: int(r["triangles"]))
        mse = [float(r["compact_mse"]) for r in dec]
        for key, label, style in (("plain_bytes", "decimation, plain (~44 B/tri)", "o-"),
                                  ("compact_bytes", "decimation, compact mesh", "s-"),
                                  ("draco11_bytes", "decimation, Draco 11-bit (storage)", "^--")):
            ax.plot([int(r[key]) for r in dec], mse, style, label=label, ms=4)
        own = [r for r in neural if r["mesh"] == name]
        current = [r for r in own if r["storage"] == NEURAL_STORAGE[0]] or own
        ax.plot([int(r["file_bytes"]) for r in current], [float(r["mse"]) for r in current], "*", ms=12,
                color="crimson", label="neural (presets at their budgets)")
        for r in current:
            ax.annotate(r["preset"], (int(r["file_bytes"]), float(r["mse"])), fontsize=7, xytext=(4, 4),
                        textcoords="offset points")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_title(name)
        ax.set_xlabel("bytes")
        ax.set_ylabel("image MSE (16 views, 128 px)")
        ax.grid(True, which="both", alpha=0.3)
    axes.ravel()[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--meshes", nargs="*", default=list(MESHES))
    ap.add_argument("--chart", action="store_true", help="only redraw the chart from the CSV")
    args = ap.parse_args()
    if not args.chart:
        done = {(r["mesh"], r["requested"]) for r in read_rows(OUT)}
        for name in args.meshes:
            measure(name, done)
    chart(RESULTS / "rd_compact.png")


if __name__ == "__main__":
    main()
