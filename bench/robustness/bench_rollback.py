"""Stability where a training fails: a target run whose feature table is struck once by noise mid-training (a
stand-in for the rare run that leaves a good state for a worse one, like the bunny's seed 9), with the checks' roll
back (`decision.checks.ROLLBACK_FACTOR`) and without it. Each row: the run's file bytes, held-out MSE, whether it met
the target, how many checks went back, and the checks' trajectory.

    .venv/bin/python -m bench.robustness.bench_rollback --mesh bunny --target 0.0004 --seed 0 --strike-at 0.62 --noise 1.0

The strike adds Gaussian noise of `noise` x the table's standard deviation to every row (a fixed generator) at the
first step past `strike-at` of the budget: between the bunny's 121 s and 137 s checks at 200 s. Rows land in
bench/results/rollback.csv (resumable per variant and commit); one run at a time on an otherwise idle machine.
"""
from __future__ import annotations

import argparse
import contextlib
import json

import torch

import nbvh_core.decision.checks as checks
import nbvh_core.training.encoding_phases as phases
from bench.harness import append_rows, markdown_table, read_rows, result_path, stamp, write_markdown
from bench.decision.bench_target_runs import one_run

CSV = "rollback.csv"


@contextlib.contextmanager
def struck_once(at: float, noise: float):
    """Inside: the training's phases add noise to the table at the first step past `at` of the budget; yields a list
    that gets the budget fraction at which it struck."""
    struck: list = []
    original = phases.EncodingPhases.before_step

    def striking(self, fraction: float) -> str:
        if not struck and fraction >= at:
            table = self.model.encoding.table
            g = torch.Generator().manual_seed(123)
            with torch.no_grad():
                table.add_(torch.randn(table.shape, generator=g).to(table.device) * float(table.std()) * noise)
            struck.append(round(fraction, 3))
        return original(self, fraction)

    phases.EncodingPhases.before_step = striking
    try:
        yield struck
    finally:
        phases.EncodingPhases.before_step = original


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--mesh", default="bunny")
    p.add_argument("--target", type=float, default=0.0004)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--strike-at", type=float, default=0.62)
    p.add_argument("--noise", type=float, default=1.0)
    p.add_argument("--time-limit", type=float, default=None, help="seconds of training (default: the default's)")
    args = p.parse_args()
    path, run_stamp = result_path(CSV), stamp()
    done = {(r["variant"], r["commit"], float(r["noise"])) for r in read_rows(path)}
    factor = checks.ROLLBACK_FACTOR
    for variant in ("roll back", "no roll back"):
        if (variant, run_stamp["commit"], args.noise) in done:
            continue
        checks.ROLLBACK_FACTOR = factor if variant == "roll back" else float("inf")
        with struck_once(args.strike_at, args.noise) as struck:
            row = one_run(args.mesh, args.target, args.seed, args.time_limit)
        append_rows(path, [{"variant": variant, "strike_at": args.strike_at, "struck_at": struck[0] if struck else None,
                            "noise": args.noise, **row}], run_stamp)
        print(variant, json.dumps({k: row[k] for k in ("mse_held_out", "target_met", "rolled_back")}), flush=True)
    rows = read_rows(path)
    write_markdown(result_path("rollback.md"), [
        "# A training struck mid-way, with and without the checks' roll back", "",
        "Held-out MSE on 16 views at 256 px; the checks' trajectory in rollback.csv.", "",
        *markdown_table(["variant", "mesh", "target", "seed", "noise x table std", "struck at", "held-out MSE", "met",
                         "went back", "commit"],
                        [[r["variant"], r["mesh"], r["target"], r["seed"], r["noise"], r["struck_at"],
                          f"{float(r['mse_held_out']):.5f}", r["target_met"], r.get("rolled_back", ""), r["commit"]]
                         for r in rows])], run_stamp)


if __name__ == "__main__":
    main()
