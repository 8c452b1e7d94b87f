"""Fit the size predictor (nbvh_core/sizing.py) on the benchmark meshes and check it against a grid search.

    .venv/bin/python bench/fit_sizing.py            # runs the missing grid points, fits, writes the results
    .venv/bin/python bench/fit_sizing.py --no-run   # fit and tables from what bench/results/quality.csv has

Data: the user preset (`default`: HashGrid + MLP + consistent labels, 8 features, int8 weight rows, the grid's
N_max from the mesh, 2047 nodes) at T = 2^8..2^13 and at 1023 / 4095 nodes (T = 2^11) on every benchmark mesh, trained the quality benchmark's budget (15 s) and scored
with its metric (rows part=GRID_PART in quality.csv; a new part name re-measures the grid, e.g. after the training
got faster: 15 s buy more steps).

Fit: log MSE on [1, log2 T, log area, occupancy, roughness, log10 triangles] (sizing.fit_size_model). Checked
leave-one-mesh-out: for each mesh, the fit without it serves three targets (the named levels preview, standard,
high) the way compress_mesh does: the predictor's first choice, then `sizing.search_size` (train, measure,
calibrate, step) with the grid's measured MSE standing in for each training; compared with the smallest grid
configuration whose measured MSE meets the target.
Writes nbvh_core/sizing_fit.json (fit on all meshes), bench/results/sizing.csv and sizing.md.
"""
from __future__ import annotations

import argparse
import csv
import dataclasses
import itertools
import json
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

import bench_quality as bq  # noqa: E402
from bench_meshes import bench_mesh  # noqa: E402
from nbvh_core import kernels  # noqa: E402
from nbvh_core.pipeline import estimate_file_bytes, preset  # noqa: E402
from nbvh_core.sizing import (FEATURE_NAMES, FIT_PATH, QUALITY_LEVELS,  # noqa: E402
                              TARGET_TRAININGS, choose_table_and_nodes, fit_size_model, mesh_features, search_size)

#: From the smallest table the search may choose (2^8: a size the grid lacks would end a simulated search
#: unmeasured) to the largest.
GRID = (8, 9, 10, 11, 12, 13)
NODE_GRID = (1023, 2047, 4095)
NODE_T = 11  # the table size the node count is varied at
METHOD = "default"
#: Rows of this grid measurement (grid2: after the fused training step; grid3: the presets' 8
#: features, int8 weights and mesh-sized grid, with facing normal targets - its open surfaces (terrain, sheet) came
#: out 4-15x worse than grid2's, which is how that loss's failure was found; grid4: the normals as wound).
GRID_PART = "grid4"


def grid_rows(plan: bq.Plan) -> dict:
    """{(mesh, log2): (mse, bytes)} of the user preset, seed 0, at the benchmark budget."""
    out = {}
    for r in bq.read_rows(plan.csv("quality")):
        if (r["method"] == METHOD and r["seed"] == "0" and r["part"] == GRID_PART and not r.get("diverged")
                and float(r["train_s"]) == plan.train_s):
            out[(r["mesh"], int(r["log2_table"]))] = (float(r["mse"]), int(r["file_bytes"]))
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--no-run", action="store_true")
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    kernels.keep_freed_memory()  # as the CLI does: freed blocks stay in the heap (see the function)
    plan = bq.Plan(args.quick)
    if not args.no_run:
        done = {(r["part"], r["mesh"], r["method"], r["log2_table"], r["seed"], r["train_s"])
                for r in bq.read_rows(plan.csv("quality"))}
        have = grid_rows(plan)
        cache = bq.MeshCache(plan)
        for mesh_name in plan.meshes:
            for l2 in GRID:
                if (mesh_name, l2) not in have:
                    bq.run_neural(plan, cache, GRID_PART, mesh_name, METHOD, l2, 0, plan.train_s, done)
            for nodes in NODE_GRID:  # the node count, varied at the middle table size
                if nodes != preset(METHOD).nodes:
                    bq.run_neural(plan, cache, f"{GRID_PART}_n{nodes}", mesh_name, METHOD, NODE_T, 0, plan.train_s,
                                  done, nodes=nodes)
    data = grid_rows(plan)
    meshes = [m for m in plan.meshes if any((m, l2) in data for l2 in GRID)]
    feats = {m: mesh_features(bench_mesh(m)) for m in meshes}
    rows = [(l2, feats[m], data[(m, l2)][0]) for m in meshes for l2 in GRID if (m, l2) in data]

    def loo(names):
        """Leave-one-mesh-out fits and their residuals for a feature subset."""
        fits_, resid = {}, []
        for m in meshes:
            f = fit_size_model([r for r in rows if r[1] is not feats[m]], METHOD, plan.train_s, features=names)
            fits_[m] = f
            resid += [math.log(mse) - f.predict_log_mse(l2, feats[m]) for l2, fe, mse in rows if fe is feats[m]]
        return fits_, float(np.sqrt(np.mean(np.square(resid))))

    # Eight meshes cannot carry six coefficients: keep the feature subset with the smallest leave-one-mesh-out error.
    subsets = [list(c) for k in range(len(FEATURE_NAMES) + 1) for c in itertools.combinations(FEATURE_NAMES, k)]
    scored = sorted(((loo(names)[1], names) for names in subsets), key=lambda t: t[0])
    best_err, best_names = scored[0]
    fits, _ = loo(best_names)
    full = fit_size_model(rows, METHOD, plan.train_s, features=best_names)
    full.residual_std = best_err
    full.meshes = meshes
    # The node count: measured at T = 2^10 with 1023 / 2047 / 4095 nodes; its effect is the mean slope of log MSE
    # per doubling of the node count (one number; leave-one-mesh-out for the checks below).
    ref = preset(METHOD).nodes
    configs = {}  # (mesh, log2, nodes) -> (mse, bytes): every measured configuration
    for (m, l2), v in data.items():
        configs[(m, l2, ref)] = v
    for r in bq.read_rows(plan.csv("quality")):
        if r["part"].startswith(f"{GRID_PART}_n") and r["method"] == METHOD and not r.get("diverged") \
                and float(r["train_s"]) == plan.train_s:
            configs[(r["mesh"], int(r["log2_table"]), int(r["nodes"]))] = (float(r["mse"]), int(r["file_bytes"]))

    def node_slopes(m):
        out = []
        for n in NODE_GRID:
            if n != ref and (m, NODE_T, n) in configs and (m, NODE_T, ref) in configs:
                out.append((math.log(configs[(m, NODE_T, n)][0]) - math.log(configs[(m, NODE_T, ref)][0]))
                           / (math.log2(n + 1) - math.log2(ref + 1)))
        return out

    slopes = {m: node_slopes(m) for m in meshes}
    all_slopes = [x for m in meshes for x in slopes[m]]
    slope_mean = float(np.mean(all_slopes)) if all_slopes else 0.0
    slope_se = float(np.std(all_slopes) / math.sqrt(len(all_slopes))) if len(all_slopes) > 1 else math.inf
    # Only a node effect the data can tell from noise is used (|mean slope| > 2 standard errors); otherwise the
    # chooser keeps the fitted node count rather than trading table rows for nodes on noise.
    use_nodes = abs(slope_mean) > 2 * slope_se
    full.nodes_coef = slope_mean if use_nodes else 0.0
    full.nodes_ref = ref
    for m in meshes:
        other = [x for o in meshes if o != m for x in slopes[o]]
        fits[m].nodes_coef = float(np.mean(other)) if (use_nodes and other) else 0.0
        fits[m].nodes_ref = ref
    base = preset(METHOD)
    size_cache: dict = {}

    def size_of(l2, n):
        if (l2, n) not in size_cache:
            size_cache[(l2, n)] = estimate_file_bytes(dataclasses.replace(base, log2_table=l2, nodes=n))
        return size_cache[(l2, n)]

    def choose(f, m, target):
        return choose_table_and_nodes(f, feats[m], target, size_of)

    def grid_best(m, target):
        meeting = [(v[1], l2, n) for (mm, l2, n), v in configs.items() if mm == m and v[0] <= target]
        return min(meeting) if meeting else None

    def serve(f, m, target) -> dict:
        """What compress_mesh does for mesh m and a target: the fit's first choice, then search_size with the grid's
        measured MSE for each 'training' (sizes the grid lacks end the search: counted as not measured)."""
        l2, n, pred, reachable = choose(f, m, target)

        def measure(t):
            got = configs.get((m, t, n))
            if got is None:
                raise KeyError(t)
            return got[0]

        try:
            final, measured = search_size(f, feats[m], target, l2, measure, nodes=n if f.nodes_coef else None)
        except KeyError:
            return {"first": (l2, n), "pred": pred, "measured": {}, "final": None, "trainings": 0}
        return {"first": (l2, n), "pred": pred, "measured": measured, "final": (final, n), "trainings": len(measured)}

    def score(margin: float) -> tuple[int, int, float]:
        """(cases meeting the target within 25% of the grid's best, the same for the first choice alone, mean
        trainings) with this margin, every choice by the fit without that mesh."""
        ok = ok_first = 0
        trainings = []
        for m in meshes:
            f = dataclasses.replace(fits[m], residual_std=full.residual_std, margin=margin)
            for target in QUALITY_LEVELS.values():
                best = grid_best(m, target)
                r = serve(f, m, target)
                trainings.append(r["trainings"])
                for key, counter in (("final", "ok"), ("first", "ok_first")):
                    got = configs.get((m, *r[key])) if r[key] else None
                    if best and got and got[0] <= target and got[1] <= 1.25 * best[0]:
                        if counter == "ok":
                            ok += 1
                        else:
                            ok_first += 1
        return ok, ok_first, float(np.mean(trainings))

    # The safety margin is the one global knob: the most successes of the whole procedure (ties: fewer trainings).
    margins = (0.0, 0.25, 0.5, 0.75, 1.0)
    margin_scores = {mg: score(mg) for mg in margins}
    full.margin = max(margins, key=lambda mg: (margin_scores[mg][0], -margin_scores[mg][2], mg))
    table = []
    for m in meshes:
        f = fits[m]
        f.residual_std, f.margin = full.residual_std, full.margin
        for level, target in QUALITY_LEVELS.items():
            r = serve(f, m, target)
            best = grid_best(m, target)
            l2, n = r["final"] if r["final"] else r["first"]
            got = configs.get((m, l2, n)) if r["final"] else None
            first = configs.get((m, *r["first"]))
            chosen_bytes = got[1] if got else size_of(l2, n)
            table.append({"mesh": m, "target": level, "target_mse": target,
                          "first_log2": r["first"][0], "first_mse": first[0] if first else "",
                          "predicted_mse": round(r["pred"], 6),
                          "trail": " -> ".join(f"2^{t}: {v:.5f}" for t, v in r["measured"].items()),
                          "trainings": r["trainings"], "chosen_log2": l2, "chosen_nodes": n,
                          "chosen_bytes": chosen_bytes, "measured_mse_at_choice": got[0] if got else "",
                          "grid_best": f"2^{best[1]}, {best[2]} nodes" if best else "",
                          "grid_best_bytes": best[0] if best else "",
                          "ratio": round(chosen_bytes / best[0], 3) if best else "",
                          "within_25pct": (chosen_bytes <= 1.25 * best[0]) if best else "",
                          "target_met": (got[0] <= target) if got else ""})
    fit_out = FIT_PATH if not plan.quick else bq.RESULTS / "sizing_fit_quick.json"  # quick never replaces the fit
    fit_out.write_text(json.dumps(dataclasses.asdict(full), indent=2) + "\n")
    out = bq.RESULTS / f"sizing{plan.suffix}.csv"
    with open(out, "w", newline="") as fh:
        w = csv.DictWriter(fh, list(table[0]))
        w.writeheader()
        w.writerows(table)
    n_first_only = margin_scores[full.margin][1]
    L = [f"# Automatic sizing: predicted size, measured and corrected, vs grid search{' (quick)' if plan.quick else ''}\n",
         f"User preset (HashGrid + MLP + consistent, {base.nodes} nodes), T = 2^{GRID[0]}..2^{GRID[-1]}, trained "
         f"{plan.train_s:g} s each on the 2-core CPU with the fused training step, scored on {plan.views} views "
         f"at {plan.res} px (rows part={GRID_PART} in quality.csv). Fit (nbvh_core/sizing_fit.json): log MSE = c . "
         f"[1, log2 T, {', '.join(best_names) or 'no mesh feature'}]; coefficients "
         f"{', '.join(f'{c:.3f}' for c in full.coef)}. Feature subset chosen by leave-one-mesh-out RMS error in log "
         "space (" + "; ".join(f"[{', '.join(n) or 'T only'}] {e:.2f}" for e, n in scored[:4]) + "; the full set "
         f"{next(e for e, n in scored if len(n) == len(FEATURE_NAMES)):.2f}).\n",
         "How a target is served (compress_mesh, sizing.search_size): the fit picks the smallest size predicted to "
         f"meet it with a safety factor exp(margin x {full.residual_std:.2f}); that size is trained and measured; the "
         "measurement calibrates the prediction for this mesh (its error is mostly a per-mesh offset); a miss trains "
         "the smallest size the calibrated prediction says meets the target, a hit with room (calibrated prediction "
         f"one size smaller still meets it) trains one size smaller; at most {TARGET_TRAININGS} trainings; the smallest "
         "size that met is kept. Here each 'training' is the grid's measured MSE at that size, and every choice is "
         "made by the fit WITHOUT that mesh. Margin (in residual stds) chosen by the count of cases that end within "
         "25% of the grid's best and meet the target, then by fewer trainings: "
         + ", ".join(f"{mg:g}: {c[0]} ({c[2]:.2f} trainings)" for mg, c in margin_scores.items())
         + f" -> {full.margin:g}. Command: `.venv/bin/python bench/fit_sizing.py`.\n",
         "## Mesh features\n", "| mesh | triangles | area | occupancy | roughness |", "|---|---|---|---|---|"]
    for m in meshes:
        f = feats[m]
        L.append(f"| {m} | {f.triangles:,} | {f.area:.2f} | {f.occupancy:.3f} | {f.roughness:.3f} |")
    others = [n for n in NODE_GRID if n != ref]
    L += [f"\n## Measured grid (image MSE by T at {ref} nodes; by node count at T=2^{NODE_T})\n",
          "| mesh | " + " | ".join(f"2^{l}" for l in GRID) + " | " + " | ".join(f"{n} nodes" for n in others) + " |",
          "|---|" + "---|" * (len(GRID) + len(others))]
    for m in meshes:
        L.append(f"| {m} | " + " | ".join(f"{data[(m, l)][0]:.5f}" if (m, l) in data else "-" for l in GRID) + " | "
                 + " | ".join(f"{configs[(m, NODE_T, n)][0]:.5f}" if (m, NODE_T, n) in configs else "-" for n in others)
                 + " |")
    L.append(f"\nNode effect: log MSE changes by {slope_mean:+.3f} +- {slope_se:.3f} (standard error) per doubling of "
             f"the node count (slopes over meshes at T=2^{NODE_T}). "
             + ("The chooser trades nodes against table rows by predicted MSE per byte." if use_nodes else
                f"That cannot be told from noise at this training budget, so the chooser keeps {ref} nodes and "
                "chooses T (a node fit is used automatically when the data show an effect)."))
    L += ["\n## Three targets per mesh\n",
          "| mesh | target | first choice (predicted, measured) | trainings: measured | kept | bytes | grid's smallest meeting it | bytes | kept / smallest | within 25% | target met |",
          "|---|---|---|---|---|---|---|---|---|---|---|"]
    for t in table:
        first = f"2^{t['first_log2']} ({t['predicted_mse']:.5f}, " + (f"{t['first_mse']:.5f})" if t["first_mse"] != "" else "-)")
        L.append(f"| {t['mesh']} | {t['target']} ({t['target_mse']:g}) | {first} | {t['trainings']}: {t['trail'] or '-'} | "
                 f"2^{t['chosen_log2']} | {t['chosen_bytes']:,} | {t['grid_best'] or 'none in grid'} | "
                 f"{t['grid_best_bytes'] or '-'} | {t['ratio'] or '-'} | {t['within_25pct']} | {t['target_met']} |")
    within = [t for t in table if t["within_25pct"] != ""]
    n_ok = sum(1 for t in within if t["within_25pct"])
    n_met = sum(1 for t in within if t["target_met"] is True)
    n_both = sum(1 for t in within if t["target_met"] is True and t["within_25pct"])
    one = sum(1 for t in table if t["trainings"] == 1)
    mean_tr = float(np.mean([t["trainings"] for t in table]))
    L.append(f"\nOf the {len(within)} (mesh, target) cases where some grid configuration meets the target: the kept "
             f"size meets it in {n_met}, is within 25% of the grid's smallest in {n_ok}, both in **{n_both}** (the "
             f"predictor's first choice alone: both in {n_first_only}). Trainings per case: {mean_tr:.2f} on average, "
             f"one in {one} of {len(table)}. In the other {len(table) - len(within)} cases no size up to 2^{GRID[-1]} "
             f"meets the target at this budget; the search then ends at the largest size and the report says the "
             "target was missed.")
    (bq.RESULTS / f"sizing{plan.suffix}.md").write_text("\n".join(L) + "\n")
    print("\n".join(L))


if __name__ == "__main__":
    main()
