"""What reusing labelled training rays costs and buys: the default preset trained with each chunk of labelled rays
handed out 1, 2, 4, ... times (`Settings.label_reuse`, each pass in a new ray order), at equal steps (the cost in
quality per step) and at equal wall-clock seconds (what the steps the labels no longer take buy on this machine).

    .venv/bin/python -m bench.quality.bench_label_reuse --meshes bunny spiky --reuse 1 2 4 8 --steps 6000 --seconds 60

Scored as stored by the one metric (`harness.product_scorer`: 16 held-out views at 256 px). Resumable: one row per
(mesh, budget, reuse) in bench/results/label_reuse.csv; label_reuse.md is rewritten after every row. Train on an
otherwise idle CPU (the seconds budget is wall-clock).
"""
from __future__ import annotations

import argparse
import dataclasses
import time

from bench.harness import RESULTS, SMOKE, markdown_table, measure_missing, product_scorer, write_markdown
from bench.meshes import named_mesh
from nbvh_core.app.pipeline import compress_mesh, preset

OUT = RESULTS / ("label_reuse_smoke.csv" if SMOKE else "label_reuse.csv")


def measure(name: str, budget: str, amount: float, reuse: int) -> dict:
    """One training of the default preset on `name` with `reuse` passes per labelled chunk, for `amount` steps
    (budget 'steps') or seconds (budget 'seconds'), scored as stored."""
    mesh = named_mesh(name)
    smoke = dict(eval_views=1, eval_resolution=32) if SMOKE else {}
    s = preset("default").with_overrides(force=True, label_reuse=reuse, **smoke)
    s = dataclasses.replace(s, steps=int(amount), time_limit_s=None) if budget == "steps" else \
        dataclasses.replace(s, steps=None, time_limit_s=float(amount))
    t0 = time.perf_counter()
    res = compress_mesh(mesh, s, None)
    q = product_scorer(mesh, res.tracer, n_views=s.eval_views if SMOKE else None,
                       resolution=s.eval_resolution if SMOKE else None).score_model(res.model)[0]
    tr = res.training
    return {"mesh": name, "triangles": mesh.n_triangles, "budget": budget, "amount": amount, "reuse": reuse,
            "steps": tr.steps, "train_s": round(tr.seconds, 1), "trained_samples_per_s": round(tr.samples_per_s),
            "labelled_samples": round(tr.samples / reuse), "file_bytes": len(res.data), "mse": round(q.mse, 7),
            "silhouette_iou": round(q.silhouette_iou, 4), "wall_s": round(time.perf_counter() - t0, 1)}


def report(rows: list[dict]) -> None:
    base = {(r["mesh"], r["budget"], r["amount"]): float(r["mse"]) for r in rows if str(r["reuse"]) == "1"}
    table = [[r["mesh"], r["budget"], r["amount"], r["reuse"], r["steps"], r["train_s"],
              f"{int(float(r['trained_samples_per_s'])):,}", f"{int(float(r['labelled_samples'])):,}",
              r["mse"], (f"{float(r['mse']) / base[k]:.3f}" if (k := (r["mesh"], r["budget"], r["amount"])) in base
                         else "")]
             for r in rows]
    write_markdown(OUT.with_suffix(".md"), [
        "# Reusing labelled rays (bench/quality/bench_label_reuse.py)\n",
        "The default preset with each labelled chunk handed out `reuse` times (each pass in a new ray order): at "
        "equal steps, what reuse costs per step; at equal seconds, what the label work saved buys here. MSE as "
        "stored, 16 held-out views at 256 px; `vs 1`: over reuse 1's MSE at the same budget.\n",
        *markdown_table(["mesh", "budget", "amount", "reuse", "steps", "train s", "trained samples/s",
                         "labelled samples", "MSE", "vs 1"], table)])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--meshes", nargs="+", default=["bunny"])
    ap.add_argument("--reuse", nargs="+", type=int, default=[1, 2, 4, 8])
    ap.add_argument("--steps", type=int, default=20 if SMOKE else 6000, help="the equal-steps budget (0: none)")
    ap.add_argument("--seconds", type=float, default=2.0 if SMOKE else 60.0, help="the equal-time budget (0: none)")
    args = ap.parse_args()
    budgets = [b for b in (("steps", args.steps), ("seconds", args.seconds)) if b[1]]
    cases = [((m, b, str(float(a)), str(r)), (m, b, a, r)) for m in args.meshes for b, a in budgets
             for r in args.reuse]
    measure_missing(OUT, cases, lambda r: (r["mesh"], r["budget"], str(float(r["amount"])), str(r["reuse"])),
                    measure, report)


if __name__ == "__main__":
    main()
