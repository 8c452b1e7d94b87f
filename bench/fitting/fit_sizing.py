"""Fit the size predictor (nbvh_core/planning/sizing.py) on the benchmark meshes and check it against a grid search.

    .venv/bin/python -m bench.fitting.fit_sizing            # runs the missing grid points, fits, writes the results
    .venv/bin/python -m bench.fitting.fit_sizing --no-run   # fit and tables from what bench/results/quality.csv has

Data: the user preset (`default`: HashGrid + MLP + consistent labels, 8 features, int8 weight rows, the grid's
N_max from the mesh, 2047 nodes) at T = 2^8..2^13 and at 1023 / 4095 nodes (T = 2^11) on every benchmark mesh, trained the quality benchmark's budget (15 s) and scored
with its metric (rows part=GRID_PART in quality.csv; a new part name re-measures the grid, e.g. after the training
got faster: 15 s buy more steps).

Fit: log MSE on [1, log2 T, log area, occupancy, roughness, log10 triangles] (sizing.fit_size_model). Checked
leave-one-mesh-out: for each mesh, the fit without it serves three targets (the named levels preview, standard,
high) the way compress_mesh does: the predictor's first choice, then `decision.size_search` (train, measure,
calibrate, step) with the grid's measured MSE standing in for each training; compared with the smallest grid
configuration whose measured MSE meets the target.
Writes nbvh_core/planning/sizing_fit.json (fit on all meshes), bench/results/sizing.csv and sizing.md.
"""
from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import math
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]

from bench.quality import rd_runs as rd
from bench.harness import RESULTS, read_rows, write_markdown, write_rows
from bench.meshes import bench_mesh
from nbvh_core import kernels
from nbvh_core.app.pipeline import estimate_file_bytes, preset
from nbvh_core.decision.size_search import search_size
from nbvh_core.planning.mesh_measures import FEATURE_NAMES, mesh_features
from nbvh_core.planning.sizing import (FIT_PATH, LOG2_RANGE, QUALITY_LEVELS, choose_table_and_nodes, fit_size_model,
                                       predictor)
from nbvh_core.protocol.quality_levels import TARGET_TRAININGS

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


def grid_rows(plan: rd.Plan) -> dict:
    """{(mesh, log2): (mse, bytes)} of the user preset, seed 0, at the benchmark budget."""
    out = {}
    for r in read_rows(plan.csv("quality")):
        if (r["method"] == METHOD and r["seed"] == "0" and r["part"] == GRID_PART and not r.get("diverged")
                and float(r["train_s"]) == plan.train_s):
            out[(r["mesh"], int(r["log2_table"]))] = (float(r["mse"]), int(r["file_bytes"]))
    return out


def run_missing(plan: rd.Plan) -> None:
    """Train the grid points quality.csv lacks (T grid at the preset's nodes; the node grid at NODE_T)."""
    done = {(r["part"], r["mesh"], r["method"], r["log2_table"], r["seed"], r["train_s"])
            for r in read_rows(plan.csv("quality"))}
    have = grid_rows(plan)
    cache = rd.MeshCache(plan)
    for mesh_name in plan.meshes:
        for l2 in GRID:
            if (mesh_name, l2) not in have:
                rd.run_neural(plan, cache, GRID_PART, mesh_name, METHOD, l2, 0, plan.train_s, done)
        for nodes in NODE_GRID:  # the node count, varied at the middle table size
            if nodes != preset(METHOD).nodes:
                rd.run_neural(plan, cache, f"{GRID_PART}_n{nodes}", mesh_name, METHOD, NODE_T, 0, plan.train_s,
                              done, nodes=nodes)


class Study:
    """The measured grid, the fits (all meshes, and each mesh left out) and how they serve the quality levels."""

    def __init__(self, plan: rd.Plan):
        self.plan = plan
        self.data = grid_rows(plan)
        self.meshes = [m for m in plan.meshes if any((m, l2) in self.data for l2 in GRID)]
        self.feats = {m: mesh_features(bench_mesh(m)) for m in self.meshes}
        self.rows = [(l2, self.feats[m], self.data[(m, l2)][0]) for m in self.meshes for l2 in GRID
                     if (m, l2) in self.data]
        self.base = preset(METHOD)
        self.ref = self.base.nodes
        self.configs = self._configs()  # (mesh, log2, nodes) -> (mse, bytes): every measured configuration
        self._sizes: dict = {}

    def _configs(self) -> dict:
        configs = {(m, l2, self.ref): v for (m, l2), v in self.data.items()}
        for r in read_rows(self.plan.csv("quality")):
            if r["part"].startswith(f"{GRID_PART}_n") and r["method"] == METHOD and not r.get("diverged") \
                    and float(r["train_s"]) == self.plan.train_s:
                configs[(r["mesh"], int(r["log2_table"]), int(r["nodes"]))] = (float(r["mse"]), int(r["file_bytes"]))
        return configs

    # -- the fit ----------------------------------------------------------------------------------------------
    def loo(self, names) -> tuple[dict, float]:
        """Leave-one-mesh-out fits and their RMS residual in log space for a feature subset."""
        fits_, resid = {}, []
        for m in self.meshes:
            f = fit_size_model([r for r in self.rows if r[1] is not self.feats[m]], METHOD, self.plan.train_s,
                               features=names)
            fits_[m] = f
            resid += [math.log(mse) - f.predict_log_mse(l2, self.feats[m]) for l2, fe, mse in self.rows
                      if fe is self.feats[m]]
        return fits_, float(np.sqrt(np.mean(np.square(resid))))

    def fit(self) -> None:
        """Eight meshes cannot carry six coefficients: keep the feature subset with the smallest leave-one-mesh-out
        error; then the node effect."""
        subsets = [list(c) for k in range(len(FEATURE_NAMES) + 1) for c in itertools.combinations(FEATURE_NAMES, k)]
        self.scored = sorted(((self.loo(names)[1], names) for names in subsets), key=lambda t: t[0])
        best_err, self.best_names = self.scored[0]
        self.fits, _ = self.loo(self.best_names)
        self.full = fit_size_model(self.rows, METHOD, self.plan.train_s, features=self.best_names)
        self.full.residual_std = best_err
        self.full.meshes = self.meshes
        self._node_effect()

    def _node_slopes(self, m) -> list[float]:
        out = []
        for n in NODE_GRID:
            if n != self.ref and (m, NODE_T, n) in self.configs and (m, NODE_T, self.ref) in self.configs:
                out.append((math.log(self.configs[(m, NODE_T, n)][0]) - math.log(self.configs[(m, NODE_T, self.ref)][0]))
                           / (math.log2(n + 1) - math.log2(self.ref + 1)))
        return out

    def _node_effect(self) -> None:
        """The node count: measured at T = 2^NODE_T with the NODE_GRID counts; its effect is the mean slope of log
        MSE per doubling of the node count (one number; leave-one-mesh-out for the checks). Only an effect the data
        can tell from noise (|mean slope| > 2 standard errors) is used; otherwise the chooser keeps the fitted node
        count rather than trading table rows for nodes on noise."""
        slopes = {m: self._node_slopes(m) for m in self.meshes}
        every = [x for m in self.meshes for x in slopes[m]]
        self.slope_mean = float(np.mean(every)) if every else 0.0
        self.slope_se = float(np.std(every) / math.sqrt(len(every))) if len(every) > 1 else math.inf
        self.use_nodes = abs(self.slope_mean) > 2 * self.slope_se
        self.full.nodes_coef = self.slope_mean if self.use_nodes else 0.0
        self.full.nodes_ref = self.ref
        for m in self.meshes:
            other = [x for o in self.meshes if o != m for x in slopes[o]]
            self.fits[m].nodes_coef = float(np.mean(other)) if (self.use_nodes and other) else 0.0
            self.fits[m].nodes_ref = self.ref

    # -- serving the levels -----------------------------------------------------------------------------------
    def size_of(self, l2, n) -> int:
        if (l2, n) not in self._sizes:
            self._sizes[(l2, n)] = estimate_file_bytes(dataclasses.replace(self.base, log2_table=l2, nodes=n))
        return self._sizes[(l2, n)]

    def grid_best(self, m, target):
        meeting = [(v[1], l2, n) for (mm, l2, n), v in self.configs.items() if mm == m and v[0] <= target]
        return min(meeting) if meeting else None

    def serve(self, f, m, target) -> dict:
        """What compress_mesh does for mesh m and a target: the fit's first choice, then search_size with the grid's
        measured MSE for each 'training' (sizes the grid lacks end the search: counted as not measured)."""
        l2, n, pred, reachable = choose_table_and_nodes(f, self.feats[m], target, self.size_of)

        def measure(t):
            got = self.configs.get((m, t, n))
            if got is None:
                raise KeyError(t)
            return got[0]

        try:
            final, measured = search_size(predictor(f, self.feats[m], n if f.nodes_coef else None), target, l2,
                                          measure, LOG2_RANGE)
        except KeyError:
            return {"first": (l2, n), "pred": pred, "measured": {}, "final": None, "trainings": 0}
        return {"first": (l2, n), "pred": pred, "measured": measured, "final": (final, n), "trainings": len(measured)}

    def score(self, margin: float) -> tuple[int, int, float]:
        """(cases meeting the target within 25% of the grid's best, the same for the first choice alone, mean
        trainings) with this margin, every choice by the fit without that mesh."""
        ok = {"final": 0, "first": 0}
        trainings = []
        for m in self.meshes:
            f = dataclasses.replace(self.fits[m], residual_std=self.full.residual_std, margin=margin)
            for target in QUALITY_LEVELS.values():
                best = self.grid_best(m, target)
                r = self.serve(f, m, target)
                trainings.append(r["trainings"])
                for key in ok:
                    got = self.configs.get((m, *r[key])) if r[key] else None
                    ok[key] += bool(best and got and got[0] <= target and got[1] <= 1.25 * best[0])
        return ok["final"], ok["first"], float(np.mean(trainings))

    def choose_margin(self) -> None:
        """The safety margin is the one global knob: the most successes of the whole procedure (ties: fewer
        trainings)."""
        margins = (0.0, 0.25, 0.5, 0.75, 1.0)
        self.margin_scores = {mg: self.score(mg) for mg in margins}
        self.full.margin = max(margins, key=lambda mg: (self.margin_scores[mg][0], -self.margin_scores[mg][2], mg))

    def table(self) -> list[dict]:
        """One row per (mesh, level): the first choice, the search's trail, what is kept, the grid's best."""
        out = []
        for m in self.meshes:
            f = self.fits[m]
            f.residual_std, f.margin = self.full.residual_std, self.full.margin
            for level, target in QUALITY_LEVELS.items():
                out.append(self._table_row(f, m, level, target))
        return out

    def _table_row(self, f, m, level, target) -> dict:
        r = self.serve(f, m, target)
        best = self.grid_best(m, target)
        l2, n = r["final"] if r["final"] else r["first"]
        got = self.configs.get((m, l2, n)) if r["final"] else None
        first = self.configs.get((m, *r["first"]))
        chosen_bytes = got[1] if got else self.size_of(l2, n)
        return {"mesh": m, "target": level, "target_mse": target,
                "first_log2": r["first"][0], "first_mse": first[0] if first else "",
                "predicted_mse": round(r["pred"], 6),
                "trail": " -> ".join(f"2^{t}: {v:.5f}" for t, v in r["measured"].items()),
                "trainings": r["trainings"], "chosen_log2": l2, "chosen_nodes": n,
                "chosen_bytes": chosen_bytes, "measured_mse_at_choice": got[0] if got else "",
                "grid_best": f"2^{best[1]}, {best[2]} nodes" if best else "",
                "grid_best_bytes": best[0] if best else "",
                "ratio": round(chosen_bytes / best[0], 3) if best else "",
                "within_25pct": (chosen_bytes <= 1.25 * best[0]) if best else "",
                "target_met": (got[0] <= target) if got else ""}


def report(study: Study, table: list[dict]) -> list[str]:
    """The Markdown of sizing.md: the fit, how a target is served, the features, the grid, the three targets."""
    plan, full, scored = study.plan, study.full, study.scored
    L = [f"# Automatic sizing: predicted size, measured and corrected, vs grid search{' (quick)' if plan.quick else ''}\n",
         f"User preset (HashGrid + MLP + consistent, {study.base.nodes} nodes), T = 2^{GRID[0]}..2^{GRID[-1]}, trained "
         f"{plan.train_s:g} s each on the 2-core CPU with the fused training step, scored on {plan.views} views "
         f"at {plan.res} px (rows part={GRID_PART} in quality.csv). Fit (nbvh_core/planning/sizing_fit.json): log MSE = c . "
         f"[1, log2 T, {', '.join(study.best_names) or 'no mesh feature'}]; coefficients "
         f"{', '.join(f'{c:.3f}' for c in full.coef)}. Feature subset chosen by leave-one-mesh-out RMS error in log "
         "space (" + "; ".join(f"[{', '.join(n) or 'T only'}] {e:.2f}" for e, n in scored[:4]) + "; the full set "
         f"{next(e for e, n in scored if len(n) == len(FEATURE_NAMES)):.2f}).\n",
         "How a target is served (compress_mesh, decision.size_search): the fit picks the smallest size predicted to "
         f"meet it with a safety factor exp(margin x {full.residual_std:.2f}); that size is trained and measured; the "
         "measurement calibrates the prediction for this mesh (its error is mostly a per-mesh offset); a miss trains "
         "the smallest size the calibrated prediction says meets the target, a hit with room (calibrated prediction "
         f"one size smaller still meets it) trains one size smaller; at most {TARGET_TRAININGS} trainings; the smallest "
         "size that met is kept. Here each 'training' is the grid's measured MSE at that size, and every choice is "
         "made by the fit WITHOUT that mesh. Margin (in residual stds) chosen by the count of cases that end within "
         "25% of the grid's best and meet the target, then by fewer trainings: "
         + ", ".join(f"{mg:g}: {c[0]} ({c[2]:.2f} trainings)" for mg, c in study.margin_scores.items())
         + f" -> {full.margin:g}. Command: `.venv/bin/python -m bench.fitting.fit_sizing`.\n",
         "## Mesh features\n", "| mesh | triangles | area | occupancy | roughness |", "|---|---|---|---|---|"]
    for m in study.meshes:
        f = study.feats[m]
        L.append(f"| {m} | {f.triangles:,} | {f.area:.2f} | {f.occupancy:.3f} | {f.roughness:.3f} |")
    return L + _grid_lines(study) + _target_lines(study, table)


def _grid_lines(study: Study) -> list[str]:
    ref, data, configs = study.ref, study.data, study.configs
    others = [n for n in NODE_GRID if n != ref]
    L = [f"\n## Measured grid (image MSE by T at {ref} nodes; by node count at T=2^{NODE_T})\n",
         "| mesh | " + " | ".join(f"2^{l}" for l in GRID) + " | " + " | ".join(f"{n} nodes" for n in others) + " |",
         "|---|" + "---|" * (len(GRID) + len(others))]
    for m in study.meshes:
        L.append(f"| {m} | " + " | ".join(f"{data[(m, l)][0]:.5f}" if (m, l) in data else "-" for l in GRID) + " | "
                 + " | ".join(f"{configs[(m, NODE_T, n)][0]:.5f}" if (m, NODE_T, n) in configs else "-" for n in others)
                 + " |")
    L.append(f"\nNode effect: log MSE changes by {study.slope_mean:+.3f} +- {study.slope_se:.3f} (standard error) per "
             f"doubling of the node count (slopes over meshes at T=2^{NODE_T}). "
             + ("The chooser trades nodes against table rows by predicted MSE per byte." if study.use_nodes else
                f"That cannot be told from noise at this training budget, so the chooser keeps {ref} nodes and "
                "chooses T (a node fit is used automatically when the data show an effect)."))
    return L


def _target_lines(study: Study, table: list[dict]) -> list[str]:
    L = ["\n## Three targets per mesh\n",
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
             f"predictor's first choice alone: both in {study.margin_scores[study.full.margin][1]}). Trainings per "
             f"case: {mean_tr:.2f} on average, one in {one} of {len(table)}. In the other {len(table) - len(within)} "
             f"cases no size up to 2^{GRID[-1]} meets the target at this budget; the search then ends at the largest "
             "size and the report says the target was missed.")
    return L


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--no-run", action="store_true")
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    kernels.keep_freed_memory()  # as the CLI does: freed blocks stay in the heap (see the function)
    plan = rd.Plan(args.quick)
    if not args.no_run:
        run_missing(plan)
    study = Study(plan)
    study.fit()
    study.choose_margin()
    table = study.table()
    fit_out = FIT_PATH if not plan.quick else RESULTS / "sizing_fit_quick.json"  # quick never replaces the fit
    fit_out.write_text(json.dumps(dataclasses.asdict(study.full), indent=2) + "\n")
    out = RESULTS / f"sizing{plan.suffix}.csv"
    write_rows(out, table)
    lines = report(study, table)
    write_markdown(RESULTS / f"sizing{plan.suffix}.md", lines)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
