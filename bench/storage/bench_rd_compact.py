"""Bytes against image error for every contender on the bench meshes: quadric decimations at several triangle
counts, each held plainly (~44 B per triangle), as a compact ray-traceable mesh (`nbvh_core/geometry/compact_mesh.py`,
scored on its decoded triangles) and as Draco 11-bit (storage only), beside the neural models of bench_storage (a
preset at its own budget, traceable and packed). One metric for all: the product's `ViewScorer`, 16 held-out orbit
views at 256 px against the full mesh (Embree).

    .venv/bin/python -m bench.storage.bench_rd_compact [--meshes bunny spiky ...]   # -> bench/results/rd_compact.{csv,png}
    .venv/bin/python -m bench.storage.bench_rd_compact --chart                      # the chart only, from the CSV

Resumable: one CSV row per (mesh, triangles), appended as it lands.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path
from bench.storage.bench_storage import row_format, row_shape
from bench.harness import RESULTS, append_rows, read_rows, save_figure

ROOT = Path(__file__).resolve().parents[2]
OUT = RESULTS / "rd_compact.csv"
COUNTS = (1000, 4000, 16000, 64000, 256000)
MESHES = ("bunny", "spiky", "gyroid", "knot", "terrain", "lattice", "gear", "sheet")
VIEWS, SIZE = 16, 256


def measure(name: str, done: set) -> None:
    """Append the rows of one mesh's decimations not yet in the CSV."""
    import DracoPy

    from bench.meshes import bench_mesh
    from nbvh_core.geometry.compact_mesh import compact_mesh
    from nbvh_core.geometry.exact import ExactTracer
    from nbvh_core.rendering.metrics import ViewScorer
    from nbvh_core.geometry.decimation import decimate
    from nbvh_core.planning.sizing import mesh_resident_bytes

    mesh = bench_mesh(name)
    scorer = ViewScorer(ExactTracer(mesh), mesh.transform, VIEWS, SIZE, held_out=True)
    if (name, "full") not in done:  # the whole mesh: exact, drawn as its bytes (vertical lines)
        nbytes, _ = compact_mesh(mesh)
        append_rows(OUT, [{"mesh": name, "requested": "full", "triangles": mesh.n_triangles, "compact_mse": 0.0,
                           "plain_bytes": mesh_resident_bytes(mesh)["total"], "compact_bytes": nbytes,
                           "draco11_bytes": len(DracoPy.encode(mesh.vertices, mesh.faces, quantization_bits=11,
                                                               compression_level=7)), "seconds": 0}])
    for count in COUNTS:
        if count >= 0.7 * mesh.n_triangles or (name, str(count)) in done:
            continue
        t0 = time.perf_counter()
        dec = decimate(mesh, count)
        if dec.n_triangles > 0.9 * mesh.n_triangles:  # the simplifier kept (nearly) everything: no decimation
            continue
        nbytes, decoded = compact_mesh(dec)
        q = scorer.score_mesh(decoded)
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
    neural = read_rows(RESULTS / "storage.csv")  # bench_storage: the models on this chart's metric
    meshes = [m for m in MESHES if any(r["mesh"] == m for r in rows)]
    fig, axes = plt.subplots(2, 4, figsize=(17, 8))
    for ax in axes.ravel()[len(meshes):]:
        ax.axis("off")
    for ax, name in zip(axes.ravel(), meshes):
        full = next((r for r in rows if r["mesh"] == name and r["requested"] == "full"), None)
        if full:
            ax.axvline(int(full["plain_bytes"]), color="C0", ls=":", lw=1, label="whole mesh, plain")
            ax.axvline(int(full["compact_bytes"]), color="C1", ls=":", lw=1, label="whole mesh, compact")
        dec = sorted((r for r in rows if r["mesh"] == name and r["requested"] != "full"),
                     key=lambda r: int(r["triangles"]))
        mse = [float(r["compact_mse"]) for r in dec]
        for key, label, style in (("plain_bytes", "decimation, plain (~44 B/tri)", "o-"),
                                  ("compact_bytes", "decimation, compact mesh", "s-"),
                                  ("draco11_bytes", "decimation, Draco 11-bit (storage)", "^--")):
            ax.plot([int(r[key]) for r in dec], mse, style, label=label, ms=4)
        current = [r for r in neural if r["mesh"] == name]
        for i, r in enumerate(current):  # earlier model shapes and formats faded, the newest row named
            newest = i == len(current) - 1
            alpha = 1.0 if newest else 0.3
            ax.plot([int(r["model_bytes"])], [float(r["model_mse"])], "*", ms=12, color="crimson", alpha=alpha,
                    label="neural, traceable .nbvh (preset at its budget)" if newest else None)
            ax.plot([int(r["model_packed_bytes"])], [float(r["model_mse"])], "*", ms=10, color="salmon", alpha=alpha,
                    label="neural, storage variant (xz, decoded at load)" if newest else None)
            if newest:
                ax.annotate(f"{r['preset']} {row_shape(r)}, format {row_format(r)}", (int(r["model_bytes"]),
                            float(r["model_mse"])), fontsize=7, xytext=(4, 4), textcoords="offset points")
        if not any(y > 0 for line in ax.get_lines() for y in line.get_ydata()[:1] if line.get_marker() != "None"):
            ax.set_ylim(1e-5, 0.1)  # nothing measured yet but the whole mesh's bytes (exact: MSE 0)
            ax.text(0.5, 0.5, "no decimation reduces it (the simplifier keeps\nits sharp edges); the whole mesh is exact",
                    transform=ax.transAxes, ha="center", fontsize=8)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_title(name)
        ax.set_xlabel("bytes")
        ax.set_ylabel(f"image MSE ({VIEWS} held-out views, {SIZE} px)")
        ax.grid(True, which="both", alpha=0.3)
    handles = {}
    for ax in axes.ravel():
        for h, label in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(label, h)
    fig.legend(list(handles.values()), list(handles), loc="lower center", ncol=5, fontsize=8)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    save_figure(fig, path)


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
