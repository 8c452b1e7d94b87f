"""Stability where a training fails late: a run whose training diverges once at a given share of its budget (a
network weight turned NaN, the step's loss NaN: what a too-high learning rate or a bad batch does), answered by
going back to the last healthy state at a 10x lower learning rate inside the same budget (`training.recovery`, the
default) or by starting over from scratch at that lower rate (the answer before it, still the one for a divergence
before the first healthy state). Each row: wall seconds of the whole run, training steps, held-out MSE, file bytes.

    .venv/bin/python -m bench.robustness.bench_recovery --mesh bunny --preset default --time-limit 60 --fail-at 0.6

A fixed-size run (the preset's sizes, no target), so both answers train the same model. Rows land in
bench/results/recovery.csv (resumable per variant and commit); one run at a time on an otherwise idle machine.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import time

import torch

import nbvh_core.training.recovery as recovery
import nbvh_core.training.train as training
from bench.harness import append_rows, markdown_table, read_rows, result_path, stamp, write_markdown
from bench.meshes import named_mesh

CSV = "recovery.csv"


@contextlib.contextmanager
def diverges_once(after_s: float):
    """Inside: the first training step taken `after_s` seconds after the first one turns a network weight NaN and
    reports a NaN loss; yields a list that gets the seconds at which it struck."""
    real_make_step, struck = training.make_step, []

    def make_step(model, device, plan):
        step, start = real_make_step(model, device, plan), []

        def failing(batch, want_raw):
            start.append(start[0] if start else time.perf_counter())
            loss, parts = step(batch, want_raw)
            if not struck and time.perf_counter() - start[0] >= after_s:
                with torch.no_grad():
                    next(model.network.parameters()).fill_(float("nan"))
                struck.append(round(time.perf_counter() - start[0], 1))
                return float("nan"), parts
            return loss, parts
        return failing

    training.make_step = make_step
    try:
        yield struck
    finally:
        training.make_step = real_make_step


@contextlib.contextmanager
def recoveries(allowed: bool):
    """Inside: the training may go back (the default) or not (it ends with TrainingDiverged: the run starts over)."""
    real_init = recovery.Recovery.__init__

    def init(self, guard, schedule, count, events, form):
        real_init(self, guard, schedule, count if allowed else 0, events, form)

    recovery.Recovery.__init__ = init
    try:
        yield
    finally:
        recovery.Recovery.__init__ = real_init


def one_run(mesh_name: str, preset_name: str, time_limit_s: float, fail_at: float, allowed: bool) -> dict:
    from nbvh_core.app.pipeline import compress_mesh, preset

    # a budget in seconds; forced: both answers ship their model, whatever a decimation of its bytes reads
    settings = preset(preset_name).with_overrides(time_limit_s=time_limit_s, steps=10**9, force=True)
    t = time.perf_counter()
    with recoveries(allowed), diverges_once(fail_at * time_limit_s) as struck:
        res = compress_mesh(named_mesh(mesh_name), settings, None)
    return {"mesh": mesh_name, "preset": preset_name, "time_limit_s": time_limit_s, "fail_at": fail_at,
            "struck_s": struck[0] if struck else None, "wall_s": round(time.perf_counter() - t, 1),
            "train_s": round(res.training.seconds, 1), "steps": res.training.steps, "mse_held_out": res.quality.mse,
            "file_bytes": res.file_bytes, "notes": json.dumps([n.kind for n in res.notes])}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--mesh", default="bunny")
    p.add_argument("--preset", default="default")
    p.add_argument("--time-limit", type=float, default=60.0, help="seconds of training")
    p.add_argument("--fail-at", type=float, default=0.6, help="share of the budget at which the training diverges")
    args = p.parse_args()
    path, run_stamp = result_path(CSV), stamp()
    done = {(r["variant"], r["mesh"], r["commit"]) for r in read_rows(path)}
    for variant in ("go back", "start over"):
        if (variant, args.mesh, run_stamp["commit"]) in done:
            continue
        row = one_run(args.mesh, args.preset, args.time_limit, args.fail_at, variant == "go back")
        append_rows(path, [{"variant": variant, **row}], run_stamp)
        print(variant, json.dumps(row), flush=True)
    rows = read_rows(path)
    write_markdown(result_path("recovery.md"), [
        "# A training that diverges late: back to its last healthy state, or start over", "",
        "Held-out MSE on the run's own view set; wall seconds of the whole run (training, evaluation, file).", "",
        *markdown_table(["variant", "mesh", "preset", "budget s", "diverged at s", "wall s", "steps", "held-out MSE",
                         "bytes", "notes", "commit"],
                        [[r["variant"], r["mesh"], r["preset"], r["time_limit_s"], r["struck_s"], r["wall_s"],
                          r["steps"], f"{float(r['mse_held_out']):.5f}", r["file_bytes"], r["notes"], r["commit"]]
                         for r in rows])], run_stamp)


if __name__ == "__main__":
    main()
