"""Does compression pay at the user's budget? Neural model (a preset, its real time budget) vs the quadric
decimation of the same image MSE, on resident bytes; and vs Draco on storage bytes. One metric for every contender:
`harness.product_scorer` (16 held-out orbit views, 256 px, Embree reference), the one the pipeline reports.

    .venv/bin/python -m bench.decision.bench_pays --meshes bunny --presets default [--table-bits 8 32]
    .venv/bin/python -m bench.decision.bench_pays --charts    # only the charts, from pays.csv and baselines.csv

Resumable: one CSV row per (mesh, preset, storage), appended as it lands (bench/results/pays.csv); a rerun skips
rows already there. `bench/results/pays.md` is rewritten from the CSV after every row.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

import numpy as np

from bench.meshes import bench_grid, bench_mesh
from bench.harness import RESULTS, append_row, product_scorer, read_rows, save_figure, write_markdown
from nbvh_core import kernels
from nbvh_core.geometry.exact import ExactTracer
from nbvh_core.app.pipeline import compress_mesh, estimate_file_bytes, preset
from nbvh_core.planning.settings import NORMAL_LOSS_BY_NETWORK
from nbvh_core.geometry.decimation import decimate
from nbvh_core.planning.mesh_measures import choose_resolution
from nbvh_core.planning.sizing import mesh_resident_bytes

FIELDS = ["mesh", "triangles", "preset", "storage", "train_s", "steps", "file_bytes", "model_resident_bytes",
          "mse", "mse_float32", "iou", "mesh_resident_bytes", "equal_mse_decimation_triangles",
          "equal_mse_decimation_resident_bytes", "ratio_resident_decimation_to_model",
          "ratio_resident_decimation_to_file", "draco11_bytes", "equal_mse_decimation_draco11_bytes", "compute_path",
          "created"]


def decimation_mse(mesh, tracer, triangles: int, views: int, res: int) -> tuple[float, int, int, int]:
    """(MSE, triangles, resident bytes, Draco-11 bytes) of the quadric decimation to ~triangles."""
    import DracoPy

    dec = decimate(mesh, triangles)
    q = product_scorer(mesh, tracer, views, res).score_mesh(dec)
    draco = len(DracoPy.encode(dec.vertices, dec.faces, quantization_bits=11, compression_level=7))
    return q.mse, dec.n_triangles, mesh_resident_bytes(dec)["total"], draco


def equal_mse_decimation(mesh, tracer, target: float, views: int, res: int) -> dict:
    """The smallest decimation whose MSE <= target, found by bisection on the log of the triangle count (the
    decimation error falls with the count, up to noise), interpolated between the bracketing counts."""
    lo, hi = 100, int(mesh.n_triangles * 0.95)
    m_hi = decimation_mse(mesh, tracer, hi, views, res)
    if m_hi[0] > target:
        return {"triangles": mesh.n_triangles, "resident": mesh_resident_bytes(mesh)["total"], "draco": None,
                "note": "no decimation reaches it"}
    best = m_hi
    for _ in range(9):
        mid = int(np.sqrt(lo * hi))
        if mid <= lo or mid >= hi:
            break
        m = decimation_mse(mesh, tracer, mid, views, res)
        if m[0] <= target:
            hi, best = mid, m
        else:
            lo = mid
    return {"triangles": best[1], "resident": best[2], "draco": best[3], "mse": best[0]}


def write_md(rows: list[dict]) -> None:
    lines = ["# Does compression pay? (bench/decision/bench_pays.py)", "",
             "Neural model at the preset's own time budget vs the quadric decimation of the same image MSE (16 views,"
             " 128 px, same metric), on this 2-core CPU. Resident = what a ray tracer holds to trace (mesh: vertices,"
             " indices, normals, BVH; model: decoded nodes, table as held, network as held: float16 since the kernels read it so, float32 in rows measured before). File = the .nbvh.", "",
             "| mesh | preset | storage | train s | file B | model resident B | MSE (stored) | MSE (float32) | IoU "
             "| equal-MSE decimation | its resident B | decimation / model resident | decimation / file "
             "| Draco-11 of the mesh | of the decimation |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['mesh']} | {r['preset']} | {r['storage']} | {float(r['train_s']):.0f} | "
                     f"{int(r['file_bytes']):,} | {int(r['model_resident_bytes']):,} | {float(r['mse']):.5f} | "
                     f"{float(r['mse_float32']):.5f} | {float(r['iou']):.4f} | "
                     f"{int(r['equal_mse_decimation_triangles']):,} tris | "
                     f"{int(r['equal_mse_decimation_resident_bytes']):,} | "
                     f"{float(r['ratio_resident_decimation_to_model']):.2f}x | "
                     f"{float(r['ratio_resident_decimation_to_file']):.2f}x | {r['draco11_bytes']} | "
                     f"{r['equal_mse_decimation_draco11_bytes']} |")
    write_markdown(RESULTS / "pays.md", lines)


def row_variant(row: dict) -> tuple[bool, bool]:
    """(current, earlier) of a pays.csv row: current = the preset as it is now (no --set overrides, the grid chosen
    from the mesh, the network's own normal targets, and the file the preset's sizes make today, within a header's
    few hundred bytes: a row of an earlier preset with the same tags is not current); earlier = the facing-normal rows
    (grid chosen from the mesh, facing normal targets, before the tag was written)."""
    tags = row["storage"].split(" ")
    overrides = [t for t in tags[1:] if not t.startswith(("n_max=", "normals="))]
    auto_grid = any(t.startswith("n_max=auto") for t in tags)
    s = preset(row["preset"])
    bits = f"t{s.table_bits}/w{s.network_bits}/n{s.node_bits}"
    current = (not overrides and auto_grid and tags[0] == bits
               and f"normals={NORMAL_LOSS_BY_NETWORK[s.network]}" in tags
               and abs(int(row["file_bytes"]) - estimate_file_bytes(s)) < 1024)
    earlier = auto_grid and not any(t.startswith("normals=") for t in tags)
    return current, earlier


def charts(rows: list[dict]) -> None:
    """bench/results/rd_budget_{resident,storage}.png: per mesh, every neural row of pays.csv (each preset and
    method step at its real budget; the latest storage the presets use marked) against the quadric decimations
    (resident bytes: what a ray tracer holds) and Draco (storage bytes: what must be decoded first), all scored with
    the one metric. Decimation and Draco curves from bench_quality's baselines.csv plus each row's equal-MSE
    decimation point."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    base = read_rows(RESULTS / "baselines.csv")
    meshes = list(dict.fromkeys(r["mesh"] for r in rows))
    marks = {"preview": "v", "default": "o", "high": "^", "base": "s", "I": "P", "II": "X", "III": "D"}
    for axis in ("resident", "storage"):
        cols = min(3, len(meshes))
        nrows = -(-len(meshes) // cols)
        fig, axes = plt.subplots(nrows, cols, figsize=(4.6 * cols, 3.6 * nrows), squeeze=False)
        for ax, mesh in zip(axes.flat, meshes):
            mine = [r for r in rows if r["mesh"] == mesh]
            dec = sorted((float(r[f"{axis}_bytes"]), float(r["mse"])) for r in base
                         if r["mesh"] == mesh and r["baseline"] == "decimate+draco11" and float(r["mse"]) > 0)
            eq_key = "equal_mse_decimation_resident_bytes" if axis == "resident" else "equal_mse_decimation_draco11_bytes"
            eq = sorted((float(r[eq_key]), float(r["mse"])) for r in mine if r.get(eq_key) not in (None, "", "None"))
            label = "quadric decimation" + (" (resident)" if axis == "resident" else " + Draco 11 (file)")
            ax.plot(*zip(*sorted(dec + eq)), "^--", color="tab:purple", ms=4, label=label) if dec + eq else None
            if axis == "storage":
                draco = sorted((float(r["storage_bytes"]), float(r["mse"])) for r in base
                               if r["mesh"] == mesh and r["baseline"] == "draco" and float(r["mse"]) > 0)
                if draco:
                    ax.plot(*zip(*draco), "s--", color="black", ms=4, label="Draco of the full mesh (bits)")
            else:
                ax.axvline(float(mine[0]["mesh_resident_bytes"]), color="gray", ls=":", label="full mesh, resident")
            for r in mine:
                x = float(r["model_resident_bytes"] if axis == "resident" else r["file_bytes"])
                current, earlier = row_variant(r)
                color, label = (("tab:red", f"neural {r['preset']} {float(r['train_s']):.0f} s (now)") if current
                                else ("tab:orange", f"neural {r['preset']}, facing normal targets") if earlier
                                else ("tab:blue", "other and earlier configurations"))
                ax.plot(x, float(r["mse"]), marks.get(r["preset"], "o"), ms=8 if current else 6 if earlier else 5,
                        color=color, alpha=1.0 if current or earlier else 0.5, label=label)
            handles, labels = ax.get_legend_handles_labels()
            unique = dict(zip(labels, handles))  # one legend entry per label
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_title(f"{mesh} ({int(mine[0]['triangles']):,} triangles)", fontsize=9)
            ax.set_xlabel(f"{axis} bytes")
            ax.set_ylabel("image MSE")
            ax.grid(alpha=0.3, which="both")
            ax.legend(unique.values(), unique.keys(), fontsize=6)
        for ax in list(axes.flat)[len(meshes):]:
            ax.axis("off")
        fig.suptitle(f"Neural models at their presets' real budgets (red: the presets now; orange: with facing normal "
                     f"targets; blue: other and earlier configurations) vs decimation / Draco, {axis} bytes, one metric",
                     fontsize=9)
        fig.tight_layout()
        save_figure(fig, RESULTS / f"rd_budget_{axis}.png", dpi=90)
        plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--meshes", nargs="+", default=["bunny"])
    ap.add_argument("--presets", nargs="+", default=["default"])
    ap.add_argument("--table-bits", type=int, nargs="+", default=[8])
    ap.add_argument("--network-bits", type=int, choices=[32, 16, 8],
                    help="bits per network weight (default: the preset's with quantized tables, else 32)")
    ap.add_argument("--time-limit", type=float, help="override the preset's budget (not for headline numbers)")
    ap.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                    help="Settings overrides for a configuration study, e.g. width=32 log2_table=12 (named in the row)")
    ap.add_argument("--csv", default=str(RESULTS / "pays.csv"))
    ap.add_argument("--charts", action="store_true", help="only rewrite the table and redraw the charts from the CSVs")
    args = ap.parse_args()
    if args.charts:  # also the table: rows merged in from other checkouts' runs
        write_md(read_rows(Path(args.csv)))
        charts(read_rows(Path(args.csv)))
        return
    kernels.keep_freed_memory()
    path = Path(args.csv)
    done = {(r["mesh"], r["preset"], r["storage"]) for r in read_rows(path)}
    for mesh_name in args.meshes:
        mesh = bench_mesh(mesh_name)
        tracer = ExactTracer(mesh)
        for preset_name in args.presets:
            for bits in args.table_bits:
                base = preset(preset_name)
                # force: the model is measured against decimation whatever the verdict would say
                over = {"table_bits": bits, "network_bits": args.network_bits or (base.network_bits if bits < 32 else 32),
                        "node_bits": 8 if bits < 32 else 32, "force": True}
                if args.time_limit:
                    over["time_limit_s"] = args.time_limit
                extra = {}
                for item in args.set:
                    key, value = item.split("=", 1)
                    kind = int if key in ("n_min", "n_max") else type(getattr(base, key))
                    extra[key] = kind(value) if getattr(base, key) is not None or kind is int else float(value)
                s = base.with_overrides(**over, **extra)
                storage = f"t{s.table_bits}/w{s.network_bits}/n{s.node_bits}"
                if extra:
                    storage += " " + " ".join(f"{k}={v}" for k, v in sorted(extra.items()))
                if s.n_max is None:  # the grid chosen from the mesh: name it, so the row is not the 128 one
                    storage += f" n_max=auto:{choose_resolution(bench_grid(mesh_name), s.log2_table)[0]}"
                storage += f" normals={s.resolved_normal_loss()}"  # rows without the tag: facing normals
                if (mesh_name, preset_name, storage) in done:
                    continue
                print(f"{mesh_name} {preset_name} {storage}: training {s.time_limit_s} s", flush=True)
                res = compress_mesh(mesh, s, None, compare_float32=True)
                q = res.quality
                dec = equal_mse_decimation(mesh, tracer, q.mse, s.eval_views, s.eval_resolution)
                resident = sum(res.model.resident_bytes().values())
                row = {"mesh": mesh_name, "triangles": mesh.n_triangles, "preset": preset_name, "storage": storage,
                       "train_s": round(res.training.seconds, 1), "steps": res.training.steps,
                       "file_bytes": res.file_bytes, "model_resident_bytes": resident, "mse": q.mse,
                       "mse_float32": res.seconds.get("mse_float32"), "iou": q.silhouette_iou,
                       "mesh_resident_bytes": mesh_resident_bytes(mesh)["total"],
                       "equal_mse_decimation_triangles": dec["triangles"],
                       "equal_mse_decimation_resident_bytes": dec["resident"],
                       "ratio_resident_decimation_to_model": dec["resident"] / resident,
                       "ratio_resident_decimation_to_file": dec["resident"] / res.file_bytes,
                       "draco11_bytes": res.assessment.alternatives.draco11_bytes,
                       "equal_mse_decimation_draco11_bytes": dec.get("draco"),
                       "compute_path": res.training.compute_path, "created": time.strftime("%Y-%m-%dT%H:%M:%S")}
                append_row(path, {k: row[k] for k in FIELDS})
                print(json.dumps(row), flush=True)
                write_md(read_rows(path))
                charts(read_rows(path))


if __name__ == "__main__":
    main()
