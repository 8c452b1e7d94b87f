"""The one prepared check for a lent card (H100 / H200), at most ~5 minutes, run in every session that has one:

1. kernel agreement on the card: tests/test_triton_kernels.py on CUDA tensors (no interpreter);
2. speed: `bench_speed.py --device cuda` (the Triton path - the ray query one kernel - against torch on the card,
   Embree on the host's cores: renders at 512 and 1000 px with the share of rays that decide as the reference,
   training samples/s) and the same on the host's CPU (the fused C++ path);
3. the bunny at level standard on the card (`nbvh compress bunny --quality standard --device cuda`): wall seconds,
   whether the level was met, bytes.

Writes bench/results/gpu/: summary.csv (one row per figure: figure, value, device, commit, machine, command; the
figures render_1mp_ms, render_hit_agreement, train_samples_per_s, bunny_standard_wall_s, kernel_tests_passed), speed*.{csv,md}
from each speed run and the compress log. A figure whose step failed is written empty with the reason.

    .venv/bin/python -m bench.device_check             # on the card (device tool: one call, timeout 420 s)
    .venv/bin/python -m bench.device_check --smoke     # anywhere: the same steps at toy sizes on the CPU
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from bench.harness import ROOT, stamp, write_rows


def _run(cmd: list[str], env: dict, timeout: float) -> tuple[int, str, float]:
    t = time.perf_counter()
    try:
        proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout)
        return proc.returncode, proc.stdout + proc.stderr, time.perf_counter() - t
    except subprocess.TimeoutExpired as exc:
        return 124, f"timed out after {timeout:.0f} s: {exc}", time.perf_counter() - t


def _speed_rows(folder: Path, name: str) -> list[dict]:
    path = folder / name
    return list(csv.DictReader(open(path))) if path.exists() else []


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true",
                    help="toy sizes on the CPU, the speed runs left out (tests/test_bench_smoke.py runs those itself)")
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "gpu"))
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    device = "cpu" if args.smoke else "cuda"
    py = sys.executable
    env = {**os.environ, "NBVH_BENCH_RESULTS": str(out)}
    figures: list[dict] = []

    def figure(name: str, value, note: str = "") -> None:
        figures.append({"figure": name, "value": value, "device": device, "note": note})
        print(name, value, note, flush=True)

    # 1. The kernels against the reference, on the card's tensors.
    test_env = {**env, "TRITON_INTERPRET": "1" if args.smoke else "0"}
    code, log, _ = _run([py, "-m", "pytest", "tests/test_triton_kernels.py", "-q", "-p", "no:cacheprovider"]
                        + (["-k", "grid_lookup"] if args.smoke else []), test_env, 240)
    tail = log.strip().splitlines()[-1] if log.strip() else ""
    figure("kernel_tests_passed", int(code == 0), tail[:200])
    # 2. Speed on the card (Triton vs torch, Embree on the host) and on the host's CPU (fused C++).
    quick = ["--quick", "--train-s", "2", "--steps", "3"] if args.smoke else ["--train-s", "30", "--steps", "100"]
    for dev in ([] if args.smoke else ["cuda", "cpu"]):  # bench_speed has its own smoke run
        code, log, seconds = _run([py, "-m", "bench.speed.bench_speed", "--device", dev, *quick], env, 240)
        (out / f"speed_{dev}.log").write_text(log[-20000:])
        if code != 0:
            figure(f"speed_{dev}_failed", "", log.strip().splitlines()[-1][:200] if log.strip() else "")
    rows = _speed_rows(out, "speed_quick.csv" if args.smoke else "speed.csv")
    size = "128" if args.smoke else "1000"
    fast = [r for r in rows if r["what"] == "render" and r["size"] == size and r["path"].startswith("fast")]
    figure("render_1mp_ms", round(float(fast[0]["seconds"]) * 1000, 3) if fast else "",
           fast[0]["path"] if fast else "no fast-path render row")
    agree = fast[0].get("hit_agreement", "") if fast else ""
    figure("render_hit_agreement", agree, f"share of rays deciding as the reference path (t max error "
                                          f"{fast[0].get('t_max_error', '')})" if fast else "no fast-path render row")
    train = [r for r in rows if r["what"] == "train" and "reference" not in r["path"]]
    figure("train_samples_per_s", round(float(train[0]["per_s"])) if train else "",
           train[0]["path"] if train else "no training row")
    # 3. The bunny at level standard, as a user runs it.
    target = ["--target-mse", "0.05", "--time-limit", "2"] if args.smoke else ["--quality", "standard"]
    code, log, seconds = _run([py, "-m", "nbvh_core", "compress", "bunny", "-o", str(out / "bunny") + "/",
                               "--device", device, "--overwrite", *target], env, 420)
    (out / "bunny_standard.log").write_text(log[-20000:])
    report = out / "bunny" / "bunny.report.json"
    met = json.loads(report.read_text()).get("target_met") if code == 0 and report.exists() else None
    figure("bunny_standard_wall_s", round(seconds, 1), f"exit {code}, level met: {met}")
    run_stamp = stamp()
    write_rows(out / ("summary_smoke.csv" if args.smoke else "summary.csv"),
               figures, run_stamp)


if __name__ == "__main__":
    main()
