"""Accuracy against bytes, time and speed: the paper's method steps, the baselines users would pick instead, and
stability where methods fail. One command regenerates everything:

    .venv/bin/python -m bench.quality.bench_quality            # full run (tens of minutes on the 2-core CPU)
    .venv/bin/python -m bench.quality.bench_quality --quick    # smoke run (a minute): 2 meshes, tiny budgets
    .venv/bin/python -m bench.quality.bench_quality --charts   # tables and charts again from the CSVs

Parts (rows are appended to CSVs as they finish; a rerun skips rows already there, so a stopped run resumes):

* sweep (quality.csv): every benchmark mesh (bench_meshes.py) x the paper's steps base / I / II / III at several
  table sizes T (real .nbvh bytes from `compress_mesh`), trained for the same wall-clock budget on the fast path,
  scored with the paper's metric (orbit views, Embree reference), plus render rays/s and Embree rays/s in the same
  run, and failure-subset errors (below). Seeds 1 and 2 repeat the middle size on some meshes (stability).
* budgets (quality.csv, part=time): the default preset at several training budgets (MSE against training time).
* baselines (baselines.csv): Draco (DracoPy) of the original mesh at several quantisation bits, and quadric
  decimation (`geometry.decimation.decimate`) to several triangle counts followed by Draco at 11 bits; each decoded mesh is
  ray traced with Embree and scored with the same metric. Two memory axes: storage bytes (the Draco file) and
  resident bytes while ray tracing (float32 vertices + normals, int32 indices, a BVH with <= 4 triangles per
  leaf: `sizing.mesh_resident_bytes`); the neural model is traced as stored, so its two axes are the same.
* divergence (divergence.csv): each method at a learning rate 100x too high: is the divergence detected?

Failure subsets (per trained model, on 20k rays from the training distribution and 8k rays that start near the
surface): `late` - rays whose true first hit lies in the 4th or later leaf they enter (the paper's known weakness);
`grazing` - true hit at |cos| < 0.2; `thin` - a second surface within 0.02 (unit box) behind the first hit;
`near_start` - rays starting 0.003 from the surface; `all` - the whole training distribution. Errors: hit error
(predicted hit != true hit, % of rays) and mean depth error where both hit. Open surfaces are the meshes terrain
and sheet (rows by mesh).
"""
from __future__ import annotations

import argparse
import copy
import math
import time

import numpy as np
import torch

from bench.meshes import BENCH_MESHES, bench_mesh
from bench.harness import RESULTS, append_row, num, read_rows, save_figure, write_markdown
from nbvh_core import kernels
from nbvh_core.app.pipeline import compress_mesh, preset
from nbvh_core.geometry.exact import ExactTracer
from nbvh_core.geometry.decimation import decimate
from nbvh_core.geometry.mesh import mesh_like
from nbvh_core.planning.sizing import mesh_resident_bytes
from nbvh_core.rendering.metrics import ViewScorer
from nbvh_core.training.train import TrainingDiverged
from bench.quality.rd_runs import METHODS, SIZES, SUBSETS, MeshCache, Plan, interp_bytes_for_mse, run_neural


def run_sweep(plan: Plan) -> None:
    done = {(r["part"], r["mesh"], r["method"], r["log2_table"], r["seed"], r["train_s"]) for r in read_rows(plan.csv("quality"))}
    cache = MeshCache(plan)
    for mesh_name in plan.meshes:
        for method in METHODS:
            sizes = SIZES[preset(method).encoding]
            for log2 in (sizes if method in plan.full_sizes_methods else sizes[1:2]):
                run_neural(plan, cache, "sweep", mesh_name, method, log2, 0, plan.train_s, done)
            if mesh_name in plan.seed_meshes:
                for seed in plan.seeds:
                    run_neural(plan, cache, "sweep", mesh_name, method, sizes[1], seed, plan.train_s, done)
        if mesh_name in plan.time_meshes:
            for budget in plan.time_budgets:
                run_neural(plan, cache, "time", mesh_name, "default", preset("default").log2_table, 0, budget, done)


def run_baselines(plan: Plan) -> None:
    import DracoPy

    done = {(r["mesh"], r["baseline"], r["param"]) for r in read_rows(plan.csv("baselines"))}
    for mesh_name in plan.meshes:
        mesh = None
        for kind, params in (("draco", plan.draco_bits), ("decimate+draco11", plan.decimate_to)):
            for param in params:
                if (mesh_name, kind, str(param)) in done:
                    continue
                if mesh is None:
                    mesh = bench_mesh(mesh_name)
                    tracer = ExactTracer(mesh)
                v, f = mesh.vertices.astype(np.float64), mesh.faces
                if kind == "draco":
                    bits = param
                else:
                    if param >= mesh.n_triangles:
                        continue
                    dec = decimate(mesh, param)
                    v, f, bits = dec.vertices, dec.faces, 11
                t0 = time.perf_counter()
                blob = DracoPy.encode(v, f, quantization_bits=bits, compression_level=10)
                enc_s = time.perf_counter() - t0
                t0 = time.perf_counter()
                decoded = DracoPy.decode(blob)
                dec_s = time.perf_counter() - t0
                cand = mesh_like(mesh, np.asarray(decoded.points), np.asarray(decoded.faces))
                q = ViewScorer(tracer, mesh.transform, plan.views, plan.res, held_out=True).score_mesh(cand)
                row = {"mesh": mesh_name, "baseline": kind, "param": param, "triangles": cand.n_triangles,
                       "storage_bytes": len(blob), "resident_bytes": mesh_resident_bytes(cand)["total"],
                       "original_resident_bytes": mesh_resident_bytes(mesh)["total"], "mse": q.mse,
                       "iou": q.silhouette_iou, "depth_err": q.depth_error, "encode_s": round(enc_s, 3),
                       "decode_s": round(dec_s, 3)}
                append_row(plan.csv("baselines"), row)
                print(f"baseline {mesh_name} {kind} {param}: {len(blob):,} B mse {q.mse:.5f}", flush=True)


def run_divergence(plan: Plan) -> None:
    done = {(r["mesh"], r["method"]) for r in read_rows(plan.csv("divergence"))}
    mesh_name = "bunny" if not plan.quick else "blob"
    for method in METHODS:
        if (mesh_name, method) in done:
            continue
        mesh = bench_mesh(mesh_name)
        s = preset(method)
        s = s.with_overrides(lr=s.lr * 100, steps=60 if plan.quick else 200, time_limit_s=None,
                             eval_views=plan.views, eval_resolution=plan.res, force=True)  # stability, not the verdict
        row = {"mesh": mesh_name, "method": method, "lr": s.lr, "steps": s.steps}
        try:
            res = compress_mesh(mesh, s)
            restarted = "restarted" in res.why
            row.update(outcome=(f"divergence detected, restarted, trained at lr {res.settings.lr:g}" if restarted
                                else "trained at that lr"), mse=res.quality.mse,
                       detail=res.why.split("; ", 1)[1] if restarted else f"final loss {res.training.final_loss:.4g}")
        except TrainingDiverged as exc:
            row.update(outcome="divergence detected after every restart, nothing saved", mse="", detail=str(exc))
        append_row(plan.csv("divergence"), row)
        print(f"divergence {method}: {row['outcome']} {row['detail']}", flush=True)


def report(plan: Plan) -> str:
    """quality.md from the CSVs: method steps, III against base, the baselines, stability, failure subsets,
    divergence."""
    rows = [r for r in read_rows(plan.csv("quality")) if not r.get("diverged")]
    order = {m: i for i, m in enumerate(BENCH_MESHES)}
    sweep = sorted((r for r in rows if r["part"] == "sweep"),
                   key=lambda r: (order.get(r["mesh"], 99), METHODS.index(r["method"]), int(r["log2_table"]), int(r["seed"])))
    L = [f"# Quality benchmark: method steps, baselines, stability{' (quick smoke run)' if plan.quick else ''}\n",
         f"2-core CPU, torch {torch.__version__}, {kernels.describe()}. Every neural model trained {plan.train_s:g} s "
         f"wall-clock (fast path), scored on {plan.views} orbit views at {plan.res} px (image MSE of the paper's "
         "shading, silhouette IoU). Bytes are real .nbvh file sizes. Command: `.venv/bin/python -m bench.quality.bench_quality"
         + (" --quick" if plan.quick else "") + "`.\n"]
    L += _steps_lines(sweep) + _reach_lines(plan, sweep)
    L += _baseline_lines(plan, sweep, read_rows(plan.csv("baselines")))
    L += _stability_lines(plan, sweep) + _failure_lines(sweep)
    L += _divergence_lines(plan, read_rows(plan.csv("divergence")))
    return write_markdown(RESULTS / f"quality{plan.suffix}.md", L).read_text()


def _middle(r) -> bool:
    return int(r["log2_table"]) == SIZES[r["encoding"]][1]


def _steps_lines(sweep: list) -> list[str]:
    """Main table: seed 0, middle sizes."""
    L = ["## Method steps at the middle size (seed 0)\n",
         "| mesh | triangles | method | T | .nbvh bytes | MSE | IoU | steps | train samples/s | neural rays/s | Embree rays/s |",
         "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in sweep:
        if r["seed"] == "0" and _middle(r):
            L.append(f"| {r['mesh']} | {int(r['triangles']):,} | {r['method']} | 2^{r['log2_table']} | {int(r['file_bytes']):,} | "
                     f"{num(r, 'mse'):.5f} | {num(r, 'iou'):.3f} | {r['steps']} | {int(r['samples_per_s']):,} | "
                     f"{int(r['neural_rays_per_s']):,} | {int(r['embree_rays_per_s']):,} |")
    return L


def _reach_lines(plan: Plan, sweep: list) -> list[str]:
    """Paper ordering: bytes III needs to reach base's MSE at base's middle size."""
    L = ["\n## Does III reach base quality at a fraction of its bytes?\n",
          "For each mesh: base's MSE at its middle size (T=2^10), and the bytes III needs for that MSE (log-log "
          "interpolation along III's sizes; 'not reached' when even its largest size is worse).\n",
          "| mesh | base bytes | base MSE | III bytes for that MSE | ratio III / base |", "|---|---|---|---|---|"]
    ratios = []
    for mesh_name in plan.meshes:
        b = [r for r in sweep if r["mesh"] == mesh_name and r["method"] == "base" and r["seed"] == "0"
             and int(r["log2_table"]) == SIZES["hashgrid"][1]]
        c = [(num(r, "file_bytes"), num(r, "mse")) for r in sweep if r["mesh"] == mesh_name and r["method"] == "III"
             and r["seed"] == "0"]
        if not b or not c:
            continue
        target, bb = num(b[0], "mse"), num(b[0], "file_bytes")
        need = interp_bytes_for_mse(c, target)
        if need is None:
            L.append(f"| {mesh_name} | {bb:,.0f} | {target:.5f} | not reached (best III: {min(m for _, m in c):.5f}) | - |")
        else:
            ratios.append(need / bb)
            L.append(f"| {mesh_name} | {bb:,.0f} | {target:.5f} | {need:,.0f} | {need / bb:.2f} |")
    n_mesh = len([m for m in plan.meshes if any(r["mesh"] == m for r in sweep)])
    L.append(f"\nIII reached base's quality on {len(ratios)} of {n_mesh} meshes"
             + (f", at {np.median(ratios):.2f}x base's bytes (median)." if ratios else "."))
    return L


def _baseline_lines(plan: Plan, sweep: list, base: list) -> list[str]:
    """Baselines vs neural at matched bytes."""
    L = ["\n## Against the baselines (storage and resident bytes)\n",
          "Neural: the best seed-0 model per mesh. Draco 11-bit: the original mesh's file. Decimation + Draco: the "
          "smallest decimation whose MSE is at most the neural model's. Resident = what a ray tracer holds (the "
          "neural model is traced as stored).\n",
          "| mesh | neural bytes | neural MSE | Draco 11-bit bytes (MSE) | decimated+Draco for <= neural MSE: storage / resident bytes | original resident bytes | neural vs Draco storage | neural vs resident original mesh | neural vs resident decimation of equal MSE |",
          "|---|---|---|---|---|---|---|---|---|"]
    for mesh_name in plan.meshes:
        ns = [r for r in sweep if r["mesh"] == mesh_name and r["seed"] == "0"]
        bs = [r for r in base if r["mesh"] == mesh_name]
        if not ns or not bs:
            continue
        best = min(ns, key=lambda r: num(r, "mse"))
        nb, nm = num(best, "file_bytes"), num(best, "mse")
        d11 = [r for r in bs if r["baseline"] == "draco" and r["param"] == "11"]
        dec = sorted((r for r in bs if r["baseline"] == "decimate+draco11" and num(r, "mse") <= nm),
                     key=lambda r: num(r, "storage_bytes"))
        orig = num(bs[0], "original_resident_bytes")
        d11s = f"{int(d11[0]['storage_bytes']):,} ({num(d11[0], 'mse'):.5f})" if d11 else "-"
        decs = (f"{int(dec[0]['triangles']):,} tris: {int(dec[0]['storage_bytes']):,} / {int(dec[0]['resident_bytes']):,}"
                if dec else "none of the decimations is that bad")
        vs_d = f"{nb / num(d11[0], 'storage_bytes'):.1f}x larger" if d11 else "-"
        vs_r = f"{orig / nb:.1f}x smaller" if orig >= nb else f"{nb / orig:.1f}x LARGER"
        vs_dec = (f"{nb / num(dec[0], 'resident_bytes'):.1f}x larger" if dec and nb > num(dec[0], "resident_bytes")
                  else f"{num(dec[0], 'resident_bytes') / nb:.1f}x smaller" if dec else "-")
        L.append(f"| {mesh_name} | {nb:,.0f} | {nm:.5f} ({best['method']}, T=2^{best['log2_table']}) | {d11s} | {decs} | "
                 f"{orig:,.0f} | {vs_d} | {vs_r} | {vs_dec} |")
    return L


def _stability_lines(plan: Plan, sweep: list) -> list[str]:
    """Stability over seeds."""
    L = ["\n## Stability: 3 seeds (middle size), mean +- std\n",
          "| mesh | method | MSE | IoU | " + " | ".join(f"{s} hit err % / depth err" for s in SUBSETS) + " |",
          "|---|---|---|---|" + "---|" * len(SUBSETS)]
    for mesh_name in plan.seed_meshes:
        for method in METHODS:
            rs = [r for r in sweep if r["mesh"] == mesh_name and r["method"] == method
                  and int(r["log2_table"]) == SIZES[r["encoding"]][1]]
            if len(rs) < 2:
                continue

            def ms(key):
                v = np.array([num(r, key) for r in rs])
                return f"{np.nanmean(v):.4g} +- {np.nanstd(v):.2g}"

            L.append(f"| {mesh_name} | {method} (n={len(rs)}) | {ms('mse')} | {ms('iou')} | "
                     + " | ".join(f"{ms(s + '_hit_err')} / {ms(s + '_depth_err')}" for s in SUBSETS) + " |")
    return L


def _failure_lines(sweep: list) -> list[str]:
    """Failure subsets by method over all meshes, and open against closed surfaces."""
    L = ["\n## Where methods fail: failure subsets, all meshes, seed 0, middle size (mean over meshes)\n",
          "| method | " + " | ".join(f"{s} hit err %" for s in SUBSETS) + " | " + " | ".join(f"{s} depth err" for s in SUBSETS) + " |",
          "|---|" + "---|" * (2 * len(SUBSETS))]
    for method in METHODS:
        rs = [r for r in sweep if r["method"] == method and r["seed"] == "0" and int(r["log2_table"]) == SIZES[r["encoding"]][1]]
        if not rs:
            continue
        L.append(f"| {method} | " + " | ".join(f"{np.nanmean([num(r, s + '_hit_err') for r in rs]):.2f}" for s in SUBSETS)
                 + " | " + " | ".join(f"{np.nanmean([num(r, s + '_depth_err') for r in rs]):.4f}" for s in SUBSETS) + " |")
    L += ["\nOpen surfaces (terrain, sheet) against closed ones, same columns, by mesh:\n",
          "| mesh | method | all hit err % | late hit err % | near_start hit err % | MSE |", "|---|---|---|---|---|---|"]
    for r in sweep:
        if r["seed"] == "0" and int(r["log2_table"]) == SIZES[r["encoding"]][1]:
            L.append(f"| {r['mesh']} | {r['method']} | {num(r, 'all_hit_err'):.2f} | {num(r, 'late_hit_err'):.2f} | "
                     f"{num(r, 'near_start_hit_err'):.2f} | {num(r, 'mse'):.5f} |")
    return L


def _divergence_lines(plan: Plan, div: list) -> list[str]:
    """The divergence runs (learning rate 100x) and diverged runs in the sweep."""
    L = []
    if div:
        L += ["\n## Divergence: learning rate 100x the preset's\n",
              "Training raises `TrainingDiverged` on a NaN/inf loss or parameter, a loss that jumps 50x above its running "
              "mean, rises 3x above the untrained model's, or never falls below it in 50+ steps; `compress_mesh` then "
              "restarts from scratch at a 10x lower learning rate (twice at most) and records it in the result's `why`.\n",
              "| mesh | method | lr | steps | outcome | MSE | detail |", "|---|---|---|---|---|---|---|"]
        for r in div:
            L.append(f"| {r['mesh']} | {r['method']} | {num(r, 'lr'):g} | {r['steps']} | {r['outcome']} | "
                     f"{num(r, 'mse'):.5f} | {r['detail']} |")
    diverged = [r for r in read_rows(plan.csv("quality")) if r.get("diverged")]
    L.append(f"\nDiverged runs in the sweep itself: {len(diverged)}"
             + ("" if not diverged else ": " + "; ".join(f"{r['mesh']} {r['method']} T=2^{r['log2_table']} seed "
                                                       f"{r['seed']}: {r['diverged']}" for r in diverged)))
    return L


def _log_axes(ax, xlabel: str, ylabel: str, title: str) -> None:
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, which="both")


def charts(plan: Plan) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in read_rows(plan.csv("quality")) if not r.get("diverged")]
    base = read_rows(plan.csv("baselines"))
    sweep = [r for r in rows if r["part"] == "sweep" and r["seed"] == "0"]
    meshes = [m for m in plan.meshes if any(r["mesh"] == m for r in sweep)]
    colors = {"base": "tab:blue", "I": "tab:orange", "II": "tab:green", "III": "tab:red", "default": "tab:cyan",
              "draco": "black",
              "decimate+draco11": "tab:purple"}
    for axis in ("storage", "resident"):
        cols = min(4, len(meshes))
        nrows = math.ceil(len(meshes) / cols)
        fig, axes = plt.subplots(nrows, cols, figsize=(4 * cols, 3.3 * nrows), squeeze=False)
        for ax, mesh_name in zip(axes.flat, meshes):
            for method in METHODS:
                pts = sorted((num(r, "file_bytes"), num(r, "mse")) for r in sweep if r["mesh"] == mesh_name and r["method"] == method)
                if pts:
                    ax.plot(*zip(*pts), "o-", color=colors[method], label=f"{method} (neural)")
            for kind, label in (("draco", "Draco (bits)"), ("decimate+draco11", "decimate + Draco 11")):
                pts = sorted((num(r, f"{axis}_bytes"), num(r, "mse")) for r in base if r["mesh"] == mesh_name
                             and r["baseline"] == kind and num(r, "mse") > 0)
                if pts:
                    ax.plot(*zip(*pts), "s--" if kind == "draco" else "^--", color=colors[kind], label=label, ms=4)
            if axis == "resident":
                orig = [num(r, "original_resident_bytes") for r in base if r["mesh"] == mesh_name]
                if orig:
                    ax.axvline(orig[0], color="gray", ls=":", label="original mesh, resident")
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_title(mesh_name)
            ax.set_xlabel(f"{axis} bytes")
            ax.set_ylabel("image MSE")
            ax.grid(alpha=0.3, which="both")
        for ax in list(axes.flat)[len(meshes):]:
            ax.axis("off")
        axes.flat[0].legend(fontsize=7)
        fig.suptitle(f"Rate-distortion, {axis} bytes: neural steps (same {plan.train_s:g} s budget) vs Draco and "
                     "decimation" + (" - Draco files must be decoded and a BVH built before tracing" if axis == "resident" else ""),
                     fontsize=10)
        fig.tight_layout()
        save_figure(fig, RESULTS / f"rd_{axis}{plan.suffix}.png", dpi=90)
        plt.close(fig)
    # MSE against training time; render speed against MSE.
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 3.8))
    for mesh_name in plan.time_meshes:
        pts = sorted((num(r, "train_s"), num(r, "mse")) for r in rows if r["part"] == "time" and r["mesh"] == mesh_name)
        if pts:
            a1.plot(*zip(*pts), "o-", label=f"{mesh_name} (default preset)")
    _log_axes(a1, "training seconds (2-core CPU)", "image MSE", "MSE against training time")
    for method in METHODS:
        pts = [(num(r, "mse"), num(r, "neural_rays_per_s")) for r in sweep if r["method"] == method]
        if pts:
            a2.scatter(*zip(*pts), color=colors[method], label=method, s=14)
    emb = [num(r, "embree_rays_per_s") for r in sweep]
    if emb:
        a2.axhline(np.median(emb), color="black", ls="--", label="Embree (median, same runs)")
    _log_axes(a2, "image MSE", "render rays/s", "Render speed against accuracy")
    fig.tight_layout()
    save_figure(fig, RESULTS / f"speed_accuracy{plan.suffix}.png", dpi=90)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="smoke run: 2 meshes, tiny budgets (about a minute)")
    ap.add_argument("--charts", action="store_true", help="only rebuild tables and charts from the CSVs")
    ap.add_argument("--parts", default="baselines,sweep,divergence", help="comma-separated parts to run")
    ap.add_argument("--meshes", nargs="+", help="run the parts for these meshes (e.g. the heavy lattice's baselines "
                    "for bench_pays' charts); the report and charts keep the benchmark meshes")
    ap.add_argument("--decimate-to", type=int, nargs="+", help="triangle counts of the decimation baselines")
    args = ap.parse_args()
    kernels.keep_freed_memory()  # as the CLI does: freed blocks stay in the heap (see the function)
    plan = Plan(args.quick)
    run_plan = copy.copy(plan)  # what runs may be narrowed by flags; the report keeps the full plan
    run_plan.meshes = tuple(args.meshes) if args.meshes else plan.meshes
    run_plan.decimate_to = tuple(args.decimate_to) if args.decimate_to else plan.decimate_to
    t0 = time.perf_counter()
    if not args.charts:
        for part in args.parts.split(","):
            {"baselines": run_baselines, "sweep": run_sweep, "divergence": run_divergence}[part](run_plan)
    text = report(plan)
    charts(plan)
    print(text)
    print(f"total {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
