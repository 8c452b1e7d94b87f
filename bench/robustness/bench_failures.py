"""The failure matrix: every method the product offers on every failure class, through `compress_mesh`.

    .venv/bin/python -m bench.robustness.bench_failures --time-limit 10

Methods: the need-driven default (level standard; it may keep the mesh; forced under a training condition), the
paper's base / I / II / III, and HashVQAD with the MLP; the fixed methods are forced (a model whatever the
verdict), so each cell shows what the method itself does. Classes (`failure_classes.py`): meshes where methods break (thin walls, an open sheet, dense
repeated detail, a huge offset, a tiny scale, inside-out winding, every face twice, 1,000 pieces, long slivers,
non-manifold edges, a zero-thickness plane, one triangle, 1M+ triangles) and training conditions on the blob (the
learning rate x10 and x100, 4-bit tables, a divergence injected late). Each cell records: how it ended (a model,
a kept mesh, or the one-line error), the held-out MSE and silhouette IoU of what it made (16 views at 256 px; for
a kept mesh, its measured decimation), the training steps it took in its budget, which guard fired (restart,
recovery, roll back, growth), the wall seconds and what the product said. Run it on an otherwise idle machine: the
budget is in seconds, so a busy machine gives fewer steps.

Rows land in bench/results/failures.csv (resumable per cell and commit); failures.md has the matrix and
failures.png the chart (log10 MSE per cell, how each ended).
"""
from __future__ import annotations

import argparse
import contextlib
import json
import math
import time

from bench.robustness.failure_classes import CONDITIONS, MESH_CLASSES, failure_mesh
from bench.harness import SMOKE, append_rows, markdown_table, num, read_rows, result_path, save_figure, stamp, write_markdown

CSV = "failures_smoke.csv" if SMOKE else "failures.csv"
METHODS = ("default", "base", "I", "II", "III", "hashvqad+mlp")


def settings_for(method: str, condition: str | None, time_limit: float):
    from nbvh_core.planning.settings import preset, settings_from_request

    if method == "default":  # forced under a training condition: the blob alone would keep its decimation
        s = settings_from_request({"time_limit_s": time_limit, "force": condition is not None})
    elif method == "hashvqad+mlp":
        s = preset("default").with_overrides(encoding="hashvqad", time_limit_s=time_limit, force=True)
    else:
        s = preset(method).with_overrides(time_limit_s=time_limit, steps=None, force=True)
    if condition == "learning rate x10":
        s = s.with_overrides(lr=s.lr * 10)
    elif condition == "learning rate x100":
        s = s.with_overrides(lr=min(s.lr * 100, 10.0))
    elif condition == "4-bit tables":
        s = s.with_overrides(table_bits=4)
    return s


def one_cell(method: str, case: str, time_limit: float) -> dict:
    from nbvh_core.app.pipeline import compress_mesh
    from nbvh_core.geometry.mesh import mesh_from_arrays
    from nbvh_core.protocol.process import NotWorthCompressing

    condition = case if case in CONDITIONS else None
    t0 = time.perf_counter()
    row = {"method": method, "case": case, "time_limit_s": time_limit}
    try:
        mesh = (_blob_mesh() if condition is not None
                else mesh_from_arrays(*failure_mesh(case), name=case.replace(" ", "_")))
        settings = settings_for(method, condition, time_limit)
        with _late_divergence(condition == "divergence injected late", time_limit):
            res = compress_mesh(mesh, settings, None)
        checks = res.decisions.to_dict()["checks"]
        fired = sorted({n.kind for n in res.notes if n.kind not in ("plan", "search")}
                       | ({"roll back"} if any(c.get("action") == "roll back" for c in checks) else set()))
        row.update(ended="model", mse=res.quality.mse, iou=res.quality.silhouette_iou, bytes=res.file_bytes,
                   steps=res.training.steps, fired=" ".join(fired), said=res.why[:200])
    except NotWorthCompressing as kept:
        a = kept.assessment
        dec = a.alternatives.decimation
        row.update(ended=f"kept ({a.recommendation})", mse=dec.compact_mse_held_out if dec else "", iou="",
                   bytes=dec.compact_bytes if dec else a.compact_bytes, fired="", said=str(kept)[:200])
    except Exception as exc:  # a cell that fails is a row: the point of the matrix
        row.update(ended=f"error: {type(exc).__name__}", mse="", iou="", bytes="", fired="",
                   said=str(exc).splitlines()[0][:200] if str(exc) else type(exc).__name__)
    row["wall_s"] = round(time.perf_counter() - t0, 1)
    return row


def _blob_mesh():
    from nbvh_core.geometry.bundled_samples import sample_path
    from nbvh_core.geometry.mesh import load_mesh

    return load_mesh(sample_path("blob"))


@contextlib.contextmanager
def _late_divergence(active: bool, time_limit: float):
    if not active:
        yield
        return
    from bench.robustness.bench_recovery import diverges_once

    with diverges_once(0.6 * time_limit):
        yield


def chart(rows: list[dict], path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    cases = [c for c in (*MESH_CLASSES, *CONDITIONS) if any(r["case"] == c for r in rows)]
    methods = [m for m in METHODS if any(r["method"] == m for r in rows)]
    grid = np.full((len(methods), len(cases)), np.nan)
    fig, ax = plt.subplots(figsize=(1.0 + 0.62 * len(cases), 1.4 + 0.45 * len(methods)))
    for r in rows:
        if r["method"] in methods and r["case"] in cases and r["mse"] not in ("", None):
            grid[methods.index(r["method"]), cases.index(r["case"])] = math.log10(max(num(r, "mse"), 1e-7))
    im = ax.imshow(grid, cmap="viridis_r", aspect="auto", vmin=-5, vmax=-0.5)
    for r in rows:
        if r["method"] in methods and r["case"] in cases:
            mark = {"model": "", "kept (decimate)": "D", "kept (mesh)": "M"}.get(r["ended"], "X")
            mark += "*" if r.get("fired") else ""
            ax.text(cases.index(r["case"]), methods.index(r["method"]), mark, ha="center", va="center", fontsize=7,
                    color="red" if mark.startswith("X") else "white")
    ax.set_xticks(range(len(cases)), cases, rotation=55, ha="right", fontsize=7)
    ax.set_yticks(range(len(methods)), methods, fontsize=8)
    fig.colorbar(im, ax=ax, label="log10 held-out image MSE")
    ax.set_title("Failure matrix: D/M kept a decimation / the mesh, X error, * a guard fired", fontsize=9)
    fig.tight_layout()
    save_figure(fig, path)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--time-limit", type=float, default=10.0, help="seconds of training per cell")
    p.add_argument("--methods", nargs="*", default=list(METHODS))
    p.add_argument("--cases", nargs="*", default=[*MESH_CLASSES, *CONDITIONS])
    args = p.parse_args()
    path, run_stamp = result_path(CSV), stamp()
    done = {(r["method"], r["case"]) for r in read_rows(path) if r["commit"] == run_stamp["commit"]}
    for case in args.cases:
        for method in args.methods:
            if (method, case) in done:
                continue
            row = one_cell(method, case, args.time_limit)
            append_rows(path, [row], run_stamp)
            print(json.dumps({k: row[k] for k in ("method", "case", "ended", "mse", "fired", "wall_s")}), flush=True)
    rows = [r for r in read_rows(path) if r["commit"] == run_stamp["commit"]]
    chart(rows, result_path(CSV.replace(".csv", ".png")))
    table = [[r["case"], r["method"], r["ended"], f"{num(r, 'mse'):.5f}" if r["mse"] else "-",
              f"{num(r, 'iou'):.3f}" if r["iou"] else "-", r.get("steps") or "-", r["fired"] or "-", r["wall_s"],
              r["said"][:90]] for r in rows]
    write_markdown(result_path(CSV.replace(".csv", ".md")), [
        f"# The failure matrix ({len({r['method'] for r in rows})} methods x {len({r['case'] for r in rows})} "
        f"classes, {rows[0]['time_limit_s'] if rows else '-'} s of training per cell)", "",
        "ended: a model, a kept decimation or mesh (the need-driven default), or the error's type. MSE / IoU: "
        "16 held-out views at 256 px (a kept mesh: its measured decimation). fired: the guards that acted.", "",
        *markdown_table(["class", "method", "ended", "MSE", "IoU", "steps", "fired", "wall s", "what it said"],
                        table)],
        run_stamp)


if __name__ == "__main__":
    main()
