"""Storage bytes against Draco: the model's two variants (the traceable .nbvh, read in place; its storage variant,
xz on disk and decoded at load: `nbvh pack`) beside the compact decimation of the same image MSE in its two
variants (the compact ray-traceable mesh; that mesh xz'd) and Draco 11-bit of the same decimation (storage only:
decoded and a BVH built before tracing). One metric for all: `harness.product_scorer` (16 held-out views, 256 px).

    .venv/bin/python -m bench.storage.bench_storage [--meshes bunny spiky knot gyroid] [--preset default] [--seconds 200]
        [--table-bits 8|6|4]   (default: the preset's)

The decimation: `geometry.decimation.decimate` (meshoptimizer), bisected on the triangle count until its decoded compact mesh
reaches the model's MSE. Resumable: one row per (mesh, preset, seconds, table bits, the preset's model shape, the file format) in
bench/results/storage.csv; storage.md and
the chart storage.png are rewritten after every row. Train on an otherwise idle CPU (the budget is wall-clock).
"""
from __future__ import annotations

import argparse
import lzma
import math
import time

from bench.meshes import named_mesh
from bench.harness import RESULTS, append_rows, markdown_table, product_scorer, read_rows, save_figure, write_markdown
from nbvh_core.app.pipeline import compress_mesh, preset
from nbvh_core.geometry.compact_mesh import compact_mesh, encode_compact
from nbvh_core.geometry.decimation import decimate
from nbvh_core.storage import container
from nbvh_core.storage.packed import pack

OUT = RESULTS / "storage.csv"
BISECTIONS = 8


def xz(data: bytes) -> int:
    return len(lzma.compress(data, format=lzma.FORMAT_XZ, preset=9 | lzma.PRESET_EXTREME))


def equal_mse_decimation(mesh, scorer, target: float) -> tuple:
    """(decimation, its compact MSE): the fewest triangles (within the bisection) whose decoded compact mesh reaches
    `target` on the scorer's views; the whole mesh when no decimation up to 70% does."""
    lo, hi = 50, int(mesh.n_triangles * 0.7)
    best = decimate(mesh, hi)
    best_mse = scorer.score_mesh(compact_mesh(best)[1]).mse
    if best_mse > target:
        return mesh, scorer.score_mesh(compact_mesh(mesh)[1]).mse
    for _ in range(BISECTIONS):
        mid = int(math.sqrt(lo * hi))
        if mid in (lo, hi):
            break
        dec = decimate(mesh, mid)
        mse = scorer.score_mesh(compact_mesh(dec)[1]).mse
        if mse <= target:
            hi, best, best_mse = mid, dec, mse
        else:
            lo = mid
    return best, best_mse


def measure(name: str, preset_name: str, seconds: float, table_bits: int) -> dict:
    import DracoPy

    mesh = named_mesh(name)
    t0 = time.perf_counter()
    s = preset(preset_name).with_overrides(force=True, time_limit_s=seconds, table_bits=table_bits)
    res = compress_mesh(mesh, s, None)
    scorer = product_scorer(mesh, res.tracer)
    dec, dec_mse = equal_mse_decimation(mesh, scorer, res.quality.mse)
    compact = encode_compact(dec)
    whole = encode_compact(mesh)

    def draco(m) -> int:
        return len(DracoPy.encode(m.vertices, m.faces, quantization_bits=11, compression_level=7))

    return {"mesh": name, "triangles": mesh.n_triangles, "preset": preset_name, "train_s": seconds,
            "table_bits": table_bits, "shape": shape_of(preset_name), "format": FORMAT,
            "model_mse": round(res.quality.mse, 7), "model_bytes": len(res.data), "model_packed_bytes": len(pack(res.data)),
            "decimation_triangles": dec.n_triangles, "decimation_compact_mse": round(dec_mse, 7),
            "decimation_compact_bytes": len(compact), "decimation_compact_xz_bytes": xz(compact),
            "decimation_draco11_bytes": draco(dec), "mesh_compact_bytes": len(whole),
            "mesh_compact_xz_bytes": xz(whole), "mesh_draco11_bytes": draco(mesh),
            "seconds": round(time.perf_counter() - t0, 1)}


def shape_of(preset_name: str) -> str:
    """The model's shape a preset trains: levels x features, hidden layers."""
    s = preset(preset_name)
    return f"{s.levels}x{s.features}, {s.hidden} hidden, k {s.k}"


def row_shape(row: dict) -> str:
    """A row's model shape (rows measured before the column existed: the presets' 4 x 8, 4 hidden; before k was
    named: k 8)."""
    shape = row.get("shape") or "4x8, 4 hidden"
    return shape if ", k " in shape else f"{shape}, k 8"


#: The .nbvh format the rows are written in (2.5 stores the BVH's shape in 1 bit a node instead of 4 bytes of links).
FORMAT = "{}.{}".format(*container.writer_version())


def row_format(row: dict) -> str:
    """A row's file format (rows measured before the column existed: 2.4)."""
    return row.get("format") or "2.4"


def _bits(row: dict) -> int:
    """A row's bits per feature value (rows measured before the option existed: 8)."""
    return int(row.get("table_bits") or 8)


def report(rows: list[dict]) -> None:
    table = [[r["mesh"], f"{int(r['triangles']):,}",
              f"{r['preset']}, {row_shape(r)}, {_bits(r)}-bit table, format {row_format(r)}", f"{float(r['model_mse']):.5f}",
              f"{int(r['model_bytes']):,}", f"{int(r['model_packed_bytes']):,}",
              f"{int(r['decimation_triangles']):,}", f"{int(r['decimation_compact_bytes']):,}",
              f"{int(r['decimation_compact_xz_bytes']):,}", f"{int(r['decimation_draco11_bytes']):,}",
              f"{int(r['decimation_compact_bytes']) / int(r['model_bytes']):.2f}x",
              f"{int(r['decimation_draco11_bytes']) / int(r['model_packed_bytes']):.2f}x"] for r in rows]
    write_markdown(RESULTS / "storage.md", [
        "# Storage bytes: the model's two variants, the compact decimation's two, Draco (bench/storage/bench_storage.py)", "",
        "Each row: a model trained at its preset's budget, its image MSE on 16 held-out views at 256 px, and the "
        "quadric decimation whose decoded compact mesh reaches that MSE. Ratios above 1: the model is smaller.", "",
        *markdown_table(["mesh", "triangles", "preset", "model MSE", "model (traceable)", "model (xz)",
                         "decimation tris", "compact", "compact xz", "Draco 11-bit", "compact / model",
                         "Draco / model xz"], table)])
    chart(rows)


def chart(rows: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    keys = [("model_bytes", "model, traceable (.nbvh)", "crimson"), ("model_packed_bytes", "model, xz (nbvh pack)", "salmon"),
            ("decimation_compact_bytes", "decimation, compact mesh", "C1"),
            ("decimation_compact_xz_bytes", "decimation, compact mesh xz", "navajowhite"),
            ("decimation_draco11_bytes", "decimation, Draco 11-bit", "C2")]
    fig, ax = plt.subplots(figsize=(2.2 + 1.6 * len(rows), 4.8))
    x = np.arange(len(rows))
    for i, (key, label, colour) in enumerate(keys):
        ax.bar(x + (i - 2) * 0.16, [int(r[key]) for r in rows], 0.16, label=label, color=colour)
    ax.set_xticks(x, [f"{r['mesh']} {row_shape(r).split(',')[0]} {_bits(r)}-bit\nMSE {float(r['model_mse']):.5f}" for r in rows], fontsize=8)
    ax.set_yscale("log")
    ax.set_ylabel("bytes at the model's MSE")
    ax.set_title("Storage at equal image MSE (16 held-out views, 256 px)", fontsize=10)
    ax.grid(True, axis="y", which="both", alpha=0.3)
    fig.legend(*ax.get_legend_handles_labels(), loc="lower center", ncol=3, fontsize=7)
    fig.tight_layout(rect=(0, 0.16, 1, 1))
    save_figure(fig, RESULTS / "storage.png")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--meshes", nargs="+", default=["bunny", "spiky", "knot", "gyroid"])
    ap.add_argument("--preset", default="default")
    ap.add_argument("--seconds", type=float, default=200.0)
    ap.add_argument("--table-bits", type=int, default=None, choices=[8, 6, 4], help="default: the preset's")
    args = ap.parse_args()
    args.table_bits = args.table_bits or preset(args.preset).table_bits
    done = {(r["mesh"], r["preset"], float(r["train_s"]), _bits(r), row_shape(r), row_format(r))
            for r in read_rows(OUT)}
    for name in args.meshes:
        if (name, args.preset, args.seconds, args.table_bits, shape_of(args.preset), FORMAT) in done:
            continue
        row = measure(name, args.preset, args.seconds, args.table_bits)
        append_rows(OUT, [row])
        print(row, flush=True)
        report(read_rows(OUT))
    if read_rows(OUT):
        report(read_rows(OUT))


if __name__ == "__main__":
    main()
