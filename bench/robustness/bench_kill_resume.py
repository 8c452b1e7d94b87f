"""Kill and resume at the user's budget: a default-preset run killed with SIGKILL at 70% of its training, resumed
from its periodic checkpoint, against uninterrupted runs of the same command (their spread is the run-to-run
noise of a time-budgeted training).

    .venv/bin/python -m bench.robustness.bench_kill_resume --mesh bunny --preset default --straight 2
        -> bench/results/kill_resume.csv (one row per run, stamped with commit and machine)

Per run: image MSE and silhouette IoU (the file's own evaluation), training steps and seconds; for the killed run
also the training seconds at the kill, the checkpoint's seconds (their difference is what the kill lost; at most
one checkpoint period, 60 s by default) and the steps redone.
"""
from __future__ import annotations

import argparse
import json
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from bench.harness import RESULTS, append_rows

ROOT = Path(__file__).resolve().parents[2]


#: compress options every run of this benchmark takes (--time-limit, --checkpoint-every for a short run)
RUN_OPTIONS: list[str] = []


def _compress(mesh: str, out: Path, preset: str, extra: list[str]) -> list[str]:
    return [sys.executable, "-m", "nbvh_core", "compress", mesh, "-o", str(out), "--preset", preset, "--force",
            "--overwrite", "--events", *RUN_OPTIONS, *extra]


def _quality(out: Path) -> dict:
    from nbvh_core.storage.fileformat import load_nbvh

    meta = load_nbvh(out).metadata
    q, t = meta["quality"], meta["training"]
    return {"mse": q["mse"], "iou": q["silhouette_iou"], "steps": t["steps"], "train_s": round(t["seconds"], 1)}


def killed_run(mesh: str, preset: str, at: float, folder: Path) -> dict:
    """Start a run, SIGKILL it once its progress passes `at`, resume it from its checkpoint; the resumed result."""
    out = folder / "killed.nbvh"
    ck = folder / ".killed.nbvh.checkpoint"
    proc = subprocess.Popen(_compress(mesh, out, preset, []), cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True)
    killed_at = None
    for line in proc.stdout:
        try:
            event = json.loads(line)
        except ValueError:
            continue
        if event.get("event") == "progress" and event.get("phase") != "evaluate" and event.get("fraction", 0) >= at:
            proc.send_signal(signal.SIGKILL)  # no handler runs: only the periodic checkpoint survives
            killed_at = event
            break
    proc.wait()
    if killed_at is None or not ck.exists():
        raise SystemExit(f"the run ended before {at:.0%} or left no checkpoint")
    from nbvh_core.storage.checkpoint import read_checkpoint

    header = read_checkpoint(ck).header
    kill_s = float(killed_at["elapsed_s"])
    t0 = time.perf_counter()
    r = subprocess.run(_compress(mesh, out, preset, ["--resume", str(ck)]), cwd=ROOT, capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"resume failed: {r.stderr.strip()[-300:]}")
    row = _quality(out)
    row.update({"run": "killed+resumed", "kill_fraction": round(float(killed_at["fraction"]), 3),
                "kill_step": killed_at.get("step"), "kill_train_s": round(kill_s, 1),
                "checkpoint_step": header["step"], "checkpoint_train_s": round(header["elapsed"], 1),
                "lost_s": round(kill_s - header["elapsed"], 1), "resume_wall_s": round(time.perf_counter() - t0, 1)})
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh", default="bunny")
    ap.add_argument("--preset", default="default")
    ap.add_argument("--at", type=float, default=0.7, help="training fraction at which the run is killed")
    ap.add_argument("--straight", type=int, default=2, help="uninterrupted runs (the noise)")
    ap.add_argument("--out", default=str(RESULTS / "kill_resume.csv"))
    ap.add_argument("--time-limit", type=float, help="override the preset's budget (s; not for headline numbers)")
    ap.add_argument("--checkpoint-every", type=float, help="seconds between checkpoints (default: the product's)")
    args = ap.parse_args()

    for flag, value in (("--time-limit", args.time_limit), ("--checkpoint-every", args.checkpoint_every)):
        if value is not None:
            RUN_OPTIONS.extend([flag, f"{value:g}"])
    asked = {"mesh": args.mesh, "preset": args.preset}
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for i in range(args.straight):
            out = folder / f"straight{i}.nbvh"
            r = subprocess.run(_compress(args.mesh, out, args.preset, []), cwd=ROOT, capture_output=True, text=True)
            if r.returncode != 0:
                raise SystemExit(r.stderr.strip()[-300:])
            rows.append({**asked, "run": f"uninterrupted {i + 1}", **_quality(out)})
            print(rows[-1], flush=True)
        rows.append({**asked, **killed_run(args.mesh, args.preset, args.at, folder)})
        print(rows[-1], flush=True)
    append_rows(args.out, rows)


if __name__ == "__main__":
    main()
