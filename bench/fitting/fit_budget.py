"""Refit the size predictor with the training budget as an input, from measurements at the budgets users run.

    .venv/bin/python -m bench.fitting.fit_budget          # fit, check leave-one-mesh-out, write sizing_fit.json + the report

The 15 s grid (bench/fitting/fit_sizing.py, quality.csv part grid4: T = 2^8..2^13, 8 meshes) alone predicts the MSE of a
15 s training; a user's training runs 60-600 s, and a larger table gains more from the longer budget (at 60 s the
bunny's MSE falls ~2x per doubling of T from 2^9 on, at 15 s ~1.3x). Here the same linear model in log space gets two
more inputs, L = ln(budget / 15 s) and (log2 T - 10) x L, fitted jointly on:

* quality.csv grid4 rows (15 s, the default preset's method, 2,047 nodes),
* grow.csv's fixed-size rows (60 s, the preview preset, 1,023 nodes; bunny, spiky, gyroid, studs at 2^6..2^13),
* compact.csv's preset rows with the current normals (preview 60 s at 2^11, default 200 s at 2^12, high 600 s at
  2^13; bunny, spiky, gyroid, terrain, knot, lattice).

Then the presets' present shape (10 levels of 4 features at 6 bits, 2 hidden layers, k = 4; frontier.csv's
CURRENT_SHAPE_VARIANTS: 60 s on five meshes, 200 s on the bunny) reaches a given MSE with a smaller table than the
shapes those rows were measured with. `shape_shift` is the mean of its
rows' ln(measured / predicted) (each mesh weighed once), added to every prediction; its leave-one-mesh-out error is
reported. The shift is fitted against the slopes as they are, so a rerun gives the same shift.

Writes nbvh_core/planning/sizing_fit.json (coef, budget_coef, residual_std, train_s = 15, shape_shift) and
bench/results/sizing_budget.md (residuals by budget; leave-one-mesh-out errors). The 15 s grid rows
(quality.csv) left the results with the unstamped files (git show e8ddca1:bench/results/quality.csv); without
them the slopes are kept as shipped and only the shift is refitted.
"""
from __future__ import annotations

import argparse
import json
import math

import numpy as np

from bench.meshes import named_mesh
from bench.harness import RESULTS, ROOT, SMOKE, markdown_table, read_rows, write_markdown
from nbvh_core.planning.settings import PRESETS
from nbvh_core.planning.mesh_measures import mesh_features
from nbvh_core.planning.sizing import FIT_PATH, SizeFit, load_fit, predictor_inputs

BASE_S = 15.0
GRID_PART = "grid4"
#: frontier.csv's variants of the presets' present shape (10 levels of 4 features at 6 bits, 2,048 rays per step):
#: `l10b6f4t11h2k4` at 60 s on five meshes, `l10b6s0`/`l10b6s1` the bunny at 200 s with two seeds.
CURRENT_SHAPE_VARIANTS = ("l10b6f4t11h2k4", "l10b6s0", "l10b6s1")
#: The measurements are read from the committed results (a smoke run's results folder is empty).
SOURCES = ROOT / "bench" / "results"


def _rows() -> list[tuple[str, int, float, float]]:
    """(mesh, log2 T, budget s, measured MSE) from the three result files."""
    out = []
    for r in read_rows(SOURCES / "quality.csv"):
        if r["part"] == GRID_PART and r["method"] == "default" and r["seed"] == "0" and not r.get("diverged"):
            out.append((r["mesh"], int(r["log2_table"]), float(r["train_s"]), float(r["mse"])))
    for r in read_rows(SOURCES / "grow.csv"):
        if r["mode"].startswith("fixed"):
            out.append((r["mesh"], int(r["log2_table"]), float(PRESETS[r["preset"]].time_limit_s), float(r["mse"])))
    for r in read_rows(SOURCES / "compact.csv"):
        if "normals=oriented" in r["storage"] and r["preset"] in ("preview", "default", "high"):
            p = PRESETS[r["preset"]]
            out.append((r["mesh"], p.log2_table, float(p.time_limit_s), float(r["model_mse"])))
    return out


def _present_rows() -> list[tuple[str, int, float, float]]:
    """(mesh, log2 T, budget s, measured MSE) of the presets' present shape (frontier.csv)."""
    return [(r["mesh"], PRESETS["default"].log2_table, float(r["train_s"]), float(r["mse"]))
            for r in read_rows(SOURCES / "frontier.csv") if r["variant"] in CURRENT_SHAPE_VARIANTS]


def shape_shift(rows, residual) -> float:
    """The mean over meshes of each mesh's mean residual(row) (ln measured / predicted): every mesh weighs once."""
    by_mesh: dict = {}
    for r in rows:
        by_mesh.setdefault(r[0], []).append(residual(r))
    return float(np.mean([np.mean(v) for v in by_mesh.values()]))


def _design(l2: int, feats, names, budget: float) -> np.ndarray:
    lb = math.log(budget / BASE_S)
    return np.concatenate([[1.0, float(l2)], predictor_inputs(feats, names), [lb, (l2 - 10) * lb]])


def fit(rows, feats: dict, names, ridge: float = 1e-3) -> np.ndarray:
    x = np.array([_design(l2, feats[m], names, b) for m, l2, b, _ in rows])
    y = np.log([mse for *_, mse in rows])
    return np.linalg.solve(x.T @ x + ridge * np.eye(x.shape[1]), x.T @ y)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--no-write", action="store_true", help="report only; keep sizing_fit.json")
    args = ap.parse_args()
    old = load_fit()
    names = old.features if old else ["roughness", "log10_triangles"]
    rows, present = _rows(), _present_rows()
    if SMOKE:  # a tiny subset: the script runs end to end, the shipped fit is left alone
        rows, args.no_write = [r for r in rows if r[0] in ("bunny", "spiky")], True
        present = [r for r in present if r[0] == "bunny"]
    feats = {m: mesh_features(named_mesh(m)) for m in sorted({r[0] for r in rows + present})}
    refit = any(r[2] == BASE_S for r in rows)  # the 15 s grid anchors the budget's slope
    coef = fit(rows, feats, names) if refit else np.array(old.coef + old.budget_coef)
    pred = lambda c, m, l2, b: float(_design(l2, feats[m], names, b) @ c)  # noqa: E731
    resid = [math.log(mse) - pred(coef, m, l2, b) for m, l2, b, mse in rows]
    std = float(np.std(resid)) if refit else old.residual_std
    gap = lambda r: math.log(r[3]) - pred(coef, r[0], r[1], r[2])  # noqa: E731
    shift = shape_shift(present, gap)
    shift_loo = [math.log(mse) - pred(coef, m, l2, b) - shape_shift([r for r in present if r[0] != m], gap)
                 for m, l2, b, mse in present]
    lines = ["# The size predictor with the budget as an input (bench/fitting/fit_budget.py)", "",
             (f"{len(rows)} measurements on {len({r[0] for r in rows})} meshes" if refit else
              "The slopes as shipped (the 15 s grid rows they were fitted on are not in the results)")
             + f"; ln MSE = coef . [1, log2 T, {', '.join(names)}, L, (log2 T - 10) L] + shape_shift, "
             f"L = ln(budget / {BASE_S:g} s). Coefficients: " + ", ".join(f"{c:.4f}" for c in coef)
             + f"; residual std {std:.3f} (in ln MSE).", "",
             f"The presets' present shape ({len(present)} rows on {len({r[0] for r in present})} meshes, "
             f"frontier.csv {', '.join(CURRENT_SHAPE_VARIANTS)}): shape_shift {shift:+.3f}, an MSE "
             f"{math.exp(shift):.2f}x the slopes' prediction. Each row's ln(measured / predicted), the shift fitted "
             f"without its mesh (mean abs {np.mean(np.abs(shift_loo)):.2f}):", ""]
    lines += markdown_table(["mesh", "budget", "measured MSE", "predicted", "ln error (LOO)"],
                            [[m, f"{b:g} s", f"{mse:.4g}", f"{math.exp(pred(coef, m, l2, b) + shift):.4g}",
                              f"{e:+.2f}"] for (m, l2, b, mse), e in zip(present, shift_loo)])
    if refit:
        loo = []
        for held in sorted({r[0] for r in rows}):
            c = fit([r for r in rows if r[0] != held], feats, names)
            loo += [(held, b, math.log(mse) - pred(c, held, l2, b)) for m, l2, b, mse in rows if m == held]
        lines += ["", "The slopes' rows, errors by budget (ln of measured / predicted; leave-one-mesh-out: the mesh's "
                  "rows predicted by a fit without it):", ""]
        table = []
        for b in sorted({r[2] for r in rows}):
            r_in = [d for d, r in zip(resid, rows) if r[2] == b]
            r_out = [d for _, bb, d in loo if bb == b]
            table.append([f"{b:g} s", len(r_in), f"{np.mean(r_in):+.2f}", f"{np.std(r_in):.2f}",
                          f"{np.mean(np.abs(r_out)):.2f}", f"{np.max(np.abs(r_out)):.2f}"])
        lines += markdown_table(["budget", "rows", "mean error", "std", "LOO mean abs", "LOO max abs"], table)
        lines += ["", "Leave-one-mesh-out by mesh (mean abs error, ln):", ""]
        lines += markdown_table(["mesh", "rows", "LOO mean abs"],
                                [[m, sum(1 for h, *_ in loo if h == m),
                                  f"{np.mean([abs(d) for h, _, d in loo if h == m]):.2f}"]
                                 for m in sorted({r[0] for r in rows})])
    write_markdown(RESULTS / ("sizing_budget_smoke.md" if SMOKE else "sizing_budget.md"), lines)
    print("\n".join(lines))
    if not args.no_write:
        data = json.loads(FIT_PATH.read_text())
        data.update(coef=[float(c) for c in coef[:-2]], budget_coef=[float(c) for c in coef[-2:]],
                    residual_std=std, train_s=BASE_S, features=list(names), shape_shift=shift)
        FIT_PATH.write_text(json.dumps(data, indent=2) + "\n")
        SizeFit(**data)  # still loads
        print(f"wrote {FIT_PATH}")


if __name__ == "__main__":
    main()
