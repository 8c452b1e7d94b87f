"""How reliably a run with a target meets it: the CLI's `compress MESH --target-mse X --force` (the need-driven
default: one growing training, its checks, the held-out evaluation) repeated over seeds, each run's file bytes,
held-out and check-view MSE, steps, growth, how many checks sent training back to the best check's weights, and the
checks' trajectory ([training s, log2 T, check MSE], ...) in one row. Answers "does the bunny meet 0.0004 in <= 95,000 B within the default budget, and in how many runs of how many?"
with a count rather than one lucky run.

    .venv/bin/python -m bench.decision.bench_target_runs --mesh bunny --target 0.0004 --seeds 0 1 2 3

Rows land in bench/results/target_runs.csv as each run ends (resumable: a (mesh, target, seed, commit) already
there is skipped); bench/results/target_runs.md summarises each (mesh, target, commit). One run at a time on an
otherwise idle machine: the training has a time budget, so a busy CPU trains fewer steps.
"""
from __future__ import annotations

import argparse
import json
import statistics

from bench.harness import append_rows, markdown_table, read_rows, result_path, stamp, write_markdown
from bench.meshes import named_mesh

CSV = "target_runs.csv"


def one_run(mesh_name: str, target: float, seed: int, time_limit_s: float | None) -> dict:
    """One `compress --target-mse target --force` run; its row (no file written)."""
    from nbvh_core.app.pipeline import compress_mesh
    from nbvh_core.planning.settings import settings_from_request

    request = {"target_mse": target, "seed": seed}
    if time_limit_s is not None:
        request["time_limit_s"] = time_limit_s
    settings = settings_from_request(request).with_overrides(force=True)
    res = compress_mesh(named_mesh(mesh_name), settings, None)
    checks = res.decisions.to_dict()["checks"]
    return {"mesh": mesh_name, "target": target, "seed": seed, "file_bytes": res.file_bytes,
            "mse_held_out": res.quality.mse, "mse_check_views": res.decisions.mse_check_views,
            "target_met": bool(res.target_met), "log2_table": res.settings.log2_table, "steps": res.training.steps,
            "train_s": round(res.training.seconds, 1), "checks": len(checks),
            "stopped_early": res.training.stopped_early,
            "rolled_back": sum(c["action"] == "roll back" for c in checks),
            "check_trajectory": json.dumps([[c["seconds"], c["log2_table"], round(c["mse"], 7)] for c in checks]),
            # what each check projected for the end of the budget (None before two checks): the checks' weak decision
            "check_projections": json.dumps([None if c.get("projected_mse") is None else round(c["projected_mse"], 7)
                                             for c in checks])}


def summarise(rows: list[dict]) -> list[str]:
    """One line per (mesh, target, commit): runs, met, bytes, held-out MSE (min / median / max)."""
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["mesh"], r["target"], r["commit"]), []).append(r)
    table = []
    for (mesh, target, commit), rs in groups.items():
        mses = sorted(float(r["mse_held_out"]) for r in rs)
        met = sum(r["target_met"] in (True, "True") for r in rs)
        sizes = sorted({int(r["file_bytes"]) for r in rs})
        table.append([mesh, target, commit, f"{met} of {len(rs)}",
                      ", ".join(f"{b:,}" for b in sizes),
                      f"{mses[0]:.5f} / {statistics.median(mses):.5f} / {mses[-1]:.5f}",
                      f"{statistics.mean(int(r['steps']) for r in rs):,.0f}"])
    return markdown_table(["mesh", "target", "commit", "met", "file bytes", "held-out MSE min / median / max",
                           "mean steps"], table)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--mesh", default="bunny")
    p.add_argument("--target", type=float, default=0.0004)
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    p.add_argument("--time-limit", type=float, default=None, help="seconds of training (default: the default's)")
    args = p.parse_args()
    path = result_path(CSV)
    run_stamp = stamp()
    done = {(r["mesh"], float(r["target"]), int(r["seed"]), r["commit"]) for r in read_rows(path)}
    for seed in args.seeds:
        if (args.mesh, args.target, seed, run_stamp["commit"]) in done:
            continue
        row = one_run(args.mesh, args.target, seed, args.time_limit)
        append_rows(path, [row], run_stamp)
        print(row, flush=True)
    write_markdown(result_path("target_runs.md"),
                   ["# Runs with a target, repeated over seeds", "",
                    "`compress MESH --target-mse X --force` as the CLI runs it; held-out MSE on 16 views at 256 px.",
                    "", *summarise(read_rows(path))], run_stamp)


if __name__ == "__main__":
    main()
