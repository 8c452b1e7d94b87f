"""The one prepared check for a lent card (H100 / H200), run in every session that has one, in two calls:

    .venv/bin/python -m bench.device_check --prepare       # here, after the last commit: .device_assets/
    bash scripts/device_check.sh                           # call 1 on the card (~5 min)
    bash scripts/device_check.sh --stages need             # call 2 on the card (~6-9 min)
    .venv/bin/python -m bench.device_check --smoke         # anywhere: the same steps at toy sizes on the CPU

With the device tool: run(command="bash scripts/device_check.sh", carry=[".device_assets"], timeout_s=420), then
the same with "--stages need" and timeout_s=590. The script installs the carried packages into the card's Python,
builds the fused CPU kernels, runs this check and packs bench/results/gpu/ into $OUT/gpu_results.tgz.

Stages (call 1: kernels, speed, bunny, labels, within 300 s; call 2: need, within 560 s):
1. kernels: tests/test_triton_kernels.py and test_card_labels.py on CUDA tensors (no interpreter);
2. speed: `bench_speed.py --device cuda` (the Triton path - the ray query one kernel - against torch on the card,
   Embree on the host's cores: renders at 512 and 1000 px with the share of rays that decide as the reference,
   training samples/s with the Triton MLP's layers and with torch's, and the training's rate at 2^11 to 2^17 rays
   per step) and the same on the host's CPU;
3. labels: `bench_labels.py` at 1 to all threads: what exact labels cost on the host and on the card against what
   the card trains, and how the CPU's own training scales with its cores;
4. bunny: the bunny at level standard on the card (`nbvh compress bunny --quality standard --device cuda`): wall
   seconds, whether the level was met, bytes;
5. need: the need-driven default (`bench_shipped.py`: level standard, 200 s, as a user runs it) on the bunny, the
   202k dragon, spiky and the gyroid on the card, beside the CPU's rows of bench/results/shipped.csv.

Writes bench/results/gpu/: summary.csv (one row per figure: figure, value, device, commit, machine, command; the
figures render_1mp_ms, render_hit_agreement, render_vs_embree_host, train_samples_per_s, train_samples_per_s_at_N,
train_samples_per_s_torch_layers (the same steps with torch's layers instead of the Triton MLP's),
train_samples_per_s_host_labels (the same steps labelled on the host instead of the card),
card_label_samples_per_s_N_threads (labels made on the card, the rays drawn by N host threads),
train_host_syncs_per_step (torch's sync debug mode over 64 steps on the card),
label_samples_per_s_N_threads, label_stream_samples_per_s_N_threads, cpu_train_samples_per_s_N_threads,
bunny_standard_wall_s, kernel_tests_passed and
need_ASSET_{shipped,shipped_bytes,mse,ratio,wall_s} for the card and the CPU), and each stage's own files (speed*.{csv,md}, labels.{csv,md}, shipped.{csv,md}, logs). A figure whose step failed is written
empty with the reason; a stage that would start past --budget-s is skipped and says so.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

from bench.harness import ROOT, append_rows, read_rows, stamp

STAGES = ("kernels", "speed", "labels", "bunny", "need")
FIRST_CALL = ("kernels", "speed", "bunny", "labels")
#: The need-driven default's assets on the card, and where the real ones travel to the card's machine.
NEED_ASSETS = ("bunny", "dragon", "spiky", "gyroid")
DEVICE_ASSETS = ROOT / ".device_assets"
LADDER = ("2048", "8192", "32768", "131072")


def _run(cmd: list[str], env: dict, timeout: float) -> tuple[int, str, float]:
    t = time.perf_counter()
    try:
        proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=max(1.0, timeout))
        return proc.returncode, proc.stdout + proc.stderr, time.perf_counter() - t
    except subprocess.TimeoutExpired as exc:
        return 124, f"timed out after {timeout:.0f} s: {exc}", time.perf_counter() - t


def _last_line(log: str) -> str:
    return log.strip().splitlines()[-1][:200] if log.strip() else ""


class Check:
    """One run of the check: its options, its environment, the figures so far and the time left."""

    def __init__(self, args):
        self.args, self.smoke = args, args.smoke
        self.out = Path(args.out)
        self.out.mkdir(parents=True, exist_ok=True)
        self.device = "cpu" if args.smoke else "cuda"
        self.py = sys.executable
        self.env = {**os.environ, "NBVH_BENCH_RESULTS": str(self.out)}
        if DEVICE_ASSETS.is_dir():  # carried from the machine that prepared them (the card's reaches no registry)
            self.env["NBVH_ASSET_CACHE"] = str(DEVICE_ASSETS / "real_assets")
        self.deadline = time.perf_counter() + args.budget_s
        self.figures: list[dict] = []

    def figure(self, name: str, value, note: str = "", device: str | None = None) -> None:
        self.figures.append({"figure": name, "value": value, "device": device or self.device, "note": note})
        print(name, value, note, flush=True)

    def left(self) -> float:
        return self.deadline - time.perf_counter()

    def run(self, cmd: list[str], timeout: float, env: dict | None = None) -> tuple[int, str, float]:
        return _run([self.py, *cmd], env or self.env, min(timeout, self.left()))


def stage_kernels(c: Check) -> None:
    """The kernels against the reference, on the card's tensors (the interpreter's in a smoke run)."""
    env = {**c.env, "TRITON_INTERPRET": "1" if c.smoke else "0"}
    code, log, _ = c.run(["-m", "pytest", "tests/test_triton_kernels.py", "tests/test_card_labels.py", "-q", "-p",
                          "no:cacheprovider"]
                         + (["-k", "grid_lookup"] if c.smoke else []), 240, env)
    c.figure("kernel_tests_passed", int(code == 0), _last_line(log))


def stage_speed(c: Check) -> None:
    """Speed on the card (Triton vs torch, Embree on the host, the batch ladder) and on the host's CPU."""
    quick = ["--quick", "--train-s", "2", "--steps", "3"] if c.smoke else ["--train-s", "20", "--steps", "100"]
    for dev in ([] if c.smoke else ["cuda", "cpu"]):  # bench_speed has its own smoke run
        ladder = ["--batch-ladder", *LADDER] if dev == "cuda" else []
        code, log, _ = c.run(["-m", "bench.speed.bench_speed", "--device", dev, *quick, *ladder], 240)
        (c.out / f"speed_{dev}.log").write_text(log[-20000:])
        if code != 0:
            c.figure(f"speed_{dev}_failed", "", _last_line(log))
        elif dev == "cuda":  # the CPU's run rewrites speed.csv: keep the card's
            shutil.copy(c.out / "speed.csv", c.out / "speed_cuda.csv")
    path = c.out / ("speed_quick.csv" if c.smoke else "speed_cuda.csv")
    rows = read_rows(path) if path.exists() else []
    size = "128" if c.smoke else "1000"
    fast = [r for r in rows if r["what"] == "render" and r["size"] == size and r["path"].startswith("fast")]
    c.figure("render_1mp_ms", round(float(fast[0]["seconds"]) * 1000, 3) if fast else "",
             fast[0]["path"] if fast else "no fast-path render row")
    agree = fast[0].get("hit_agreement", "") if fast else ""
    c.figure("render_hit_agreement", agree, f"share of rays deciding as the reference path (t max error "
                                            f"{fast[0].get('t_max_error', '')})" if fast else "no fast-path render row")
    embree = [r for r in rows if r["what"] == "render" and r["size"] == size and r["path"].startswith("Embree")]
    if fast and embree:
        c.figure("render_vs_embree_host", round(float(embree[0]["seconds"]) / float(fast[0]["seconds"]), 3),
                 f"Embree's seconds over the card's on the same rays ({embree[0]['path']})")
    for r in (r for r in rows if r["what"] == "syncs"):
        c.figure("train_host_syncs_per_step", r["per_s"], f"torch's sync debug mode over {r['items']} steps; most "
                                                          f"at {r.get('sync_sites') or 'none'}")
    train = [r for r in rows if r["what"] == "train" and "reference" not in r["path"]]
    c.figure("train_samples_per_s", round(float(train[0]["per_s"])) if train else "",
             f"{train[0]['path']}; batches served again: {train[0].get('reused_share', '')}" if train
             else "no training row")
    for r in train[1:]:
        torch_layers = r.get("layers") == "torch" and train[0].get("layers") == "triton"
        host_labels = r.get("labels") == "host" and train[0].get("labels") == "card"
        name = ("train_samples_per_s_torch_layers" if torch_layers else "train_samples_per_s_host_labels"
                if host_labels else f"train_samples_per_s_at_{r['rays_per_step']}")
        c.figure(name, round(float(r["per_s"])), f"rays per step {r['rays_per_step']}; "
                 + ("the layers torch's (cuBLAS under autograd), not the Triton MLP's; " if torch_layers else "")
                 + ("labels made on the host (Embree), not the card; " if host_labels else "")
                 + f"batches served again: {r.get('reused_share', '')}")


def stage_labels(c: Check) -> None:
    """What exact labels cost on the host, from one thread to all of them."""
    threads = ["1"] if c.smoke else [str(n) for n in (1, 2, 4, 8, 16, 32, 64) if n <= (os.cpu_count() or 1)]
    code, log, _ = c.run(["-m", "bench.speed.bench_labels", "--assets", "blob" if c.smoke else "bunny",
                          "--threads", *threads, "--chunks", "1" if c.smoke else "3"], 120)
    (c.out / "labels.log").write_text(log[-20000:])
    rows = read_rows(c.out / "labels.csv") if code == 0 else []  # the check runs it at its own sizes, not as a smoke run
    if not rows:
        c.figure("label_samples_per_s", "", _last_line(log), device="host")
    for r in rows:
        c.figure(f"label_samples_per_s_{r['threads']}_threads", r["label_samples_per_s"],
                 f"{r['asset']}; first-hit rays/s {r['first_hit_rays_per_s']}; draw {r['draw_s']} s and labels "
                 f"{r['label_s']} s per {r['rays_per_chunk']} rays", device="host")
        c.figure(f"label_stream_samples_per_s_{r['threads']}_threads", r.get("streamed_samples_per_s", ""),
                 f"{r['asset']}; streamed to the training by {r.get('label_workers', '')} labelling threads (one: "
                 f"{r.get('streamed_1_worker_samples_per_s', '')})", device="host")
        if r.get("card_label_samples_per_s"):
            c.figure(f"card_label_samples_per_s_{r['threads']}_threads", r["card_label_samples_per_s"],
                     f"{r['asset']}; labelled on the card, drawn by {r['threads']} host threads; first-hit rays/s "
                     f"{r.get('card_first_hit_rays_per_s', '')}; streamed {r.get('card_streamed_samples_per_s', '')}")
        c.figure(f"cpu_train_samples_per_s_{r['threads']}_threads", r.get("cpu_train_samples_per_s", ""),
                 f"{r['asset']}; the default preset's training on the host's CPU", device="host")


def stage_bunny(c: Check) -> None:
    """The bunny at level standard, as a user runs it."""
    target = ["--target-mse", "0.05", "--time-limit", "2"] if c.smoke else ["--quality", "standard"]
    code, log, seconds = c.run(["-m", "nbvh_core", "compress", "bunny", "-o", str(c.out / "bunny") + "/",
                                "--device", c.device, "--overwrite", *target], 420)
    (c.out / "bunny_standard.log").write_text(log[-20000:])
    report = c.out / "bunny" / "bunny.report.json"
    met = json.loads(report.read_text()).get("target_met") if code == 0 and report.exists() else None
    c.figure("bunny_standard_wall_s", round(seconds, 1), f"exit {code}, level met: {met}")


def stage_need(c: Check) -> None:
    """The need-driven default on the four assets on the card, beside the CPU's rows of shipped.csv."""
    assets = ["blob"] if c.smoke else list(NEED_ASSETS)
    extra = ["--time-limit", "1"] if c.smoke else []
    env = {**c.env, "NBVH_BENCH_SMOKE": "1"} if c.smoke else c.env
    logs = {}
    for asset in assets:  # one run each: what landed stays when the budget ends in the middle
        if c.left() < 30:
            logs[asset] = f"skipped: past --budget-s {c.args.budget_s:g}"
            continue
        code, log, _ = c.run(["-m", "bench.decision.bench_shipped", "--assets", asset, "--work",
                              str(c.out / "need"), *extra], 580, env)
        logs[asset] = _last_line(log)
        (c.out / f"need_{asset}.log").write_text(log[-20000:])
    card = {r["asset"]: r for r in read_rows(c.out / ("shipped_smoke.csv" if c.smoke else "shipped.csv"))}
    cpu = {r["asset"]: r for r in read_rows(ROOT / "bench" / "results" / "shipped.csv")}
    for asset in assets:
        for where, rows in (("card", card), ("cpu", cpu)):
            r = rows.get(asset)
            device = c.device if where == "card" else f"cpu ({r['commit']}, {r['machine']})" if r else "cpu"
            if r is None:
                c.figure(f"need_{asset}_shipped", "", f"no row ({logs.get(asset, '') if where == 'card' else 'none'})",
                         device=device)
                continue
            for field in ("shipped", "shipped_bytes", "mse", "ratio", "wall_s"):
                c.figure(f"need_{asset}_{field}", r.get(field, ""), "", device=device)


#: What the card's machine lacks of nbvh_core's requirements, for its Python (3.12 with torch, numpy, scipy, pillow,
#: safetensors): wheels where PyPI has them, meshoptimizer's source (built there: its image has a compiler).
DEVICE_PYTHON = "3.12"
DEVICE_WHEELS = ("embreex==4.4.0.post1", "trimesh==5.2.0", "DracoPy==2.2.0", "flip-evaluator==1.7")
DEVICE_SOURCES = ("meshoptimizer==0.2.30a0",)


def prepare() -> None:
    """Fetch what the card's machine cannot (it reaches no registry) into .device_assets/, which git ignores and the
    device tool carries: the packages its Python lacks (wheels/), the real assets the need stage reads
    (real_assets/), and the commit the copy is of (commit: its git folder may be another's)."""
    wheels = DEVICE_ASSETS / "wheels"
    wheels.mkdir(parents=True, exist_ok=True)
    download = [sys.executable, "-m", "pip", "download", "-q", "--no-deps", "--dest", str(wheels)]
    platforms = [a for p in ("manylinux2014_x86_64", "manylinux_2_28_x86_64", "linux_x86_64") for a in ("--platform", p)]
    for spec in DEVICE_WHEELS:
        subprocess.run([*download, "--python-version", DEVICE_PYTHON, *platforms, "--only-binary=:all:", spec],
                       check=True)
    for spec in DEVICE_SOURCES:
        subprocess.run([*download, "--no-binary", spec.split("=")[0], spec], check=True)
    from bench.harness import commit_of

    (DEVICE_ASSETS / "commit").write_text(commit_of(ROOT))
    os.environ["NBVH_ASSET_CACHE"] = str(DEVICE_ASSETS / "real_assets")
    from bench.real_assets import REAL_ASSETS, asset_path

    keep = {asset_path(name).resolve() for name in NEED_ASSETS if name in REAL_ASSETS}
    for other in (DEVICE_ASSETS / "real_assets").rglob("*"):  # the packages' other files stay behind
        if other.is_file() and other.resolve() not in keep:
            other.unlink()
    for path in sorted(keep):
        print(path, path.stat().st_size, "bytes")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true",
                    help="toy sizes on the CPU, the speed runs left out (tests/test_bench_smoke.py runs those itself)")
    ap.add_argument("--stages", nargs="+", choices=STAGES, default=list(FIRST_CALL))
    ap.add_argument("--budget-s", type=float, default=None,
                    help="stages that would start past this are skipped (default: 300 s, the need stage alone 560 s)")
    ap.add_argument("--prepare", action="store_true",
                    help="only fetch what the card's machine cannot into .device_assets/ (packages, assets, commit)")
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "gpu"))
    args = ap.parse_args()
    if args.prepare:
        prepare()
        return
    if args.budget_s is None:
        args.budget_s = 560.0 if args.stages == ["need"] else 300.0
    check = Check(args)
    stages = {"kernels": stage_kernels, "speed": stage_speed, "labels": stage_labels, "bunny": stage_bunny,
              "need": stage_need}
    for name in args.stages:
        if check.left() < 10:
            check.figure(f"{name}_skipped", "", f"past --budget-s {args.budget_s:g}")
            continue
        stages[name](check)
    # Appended, not replaced: the two calls' figures land in one file.
    append_rows(check.out / ("summary_smoke.csv" if args.smoke else "summary.csv"), check.figures, stamp())


if __name__ == "__main__":
    main()
