"""A library batch on a local multi-node Ray cluster against the embedded run, on the same 8 assets.

    .venv/bin/python -m bench.speed.bench_batch_cluster [--time-limit 30] [--preset preview]
        # -> bench/results/batch_cluster.{csv,md}

The 8 benchmark meshes (bench_meshes.py) are written as .npz into a library folder, then compressed twice with
`nbvh batch`: (1) embedded Ray (`ray.init()` inside the batch, this machine's 2 CPUs); (2) a cluster started here
with `ray start`: a head node with 0 CPUs (it schedules, it trains nothing) and 2 worker nodes of 1 CPU each, joined
with `--address`. Both have two 1-CPU slots, so the wall times compare the scheduling overhead of a real cluster
(separate raylets, object transfer between nodes) at equal compute; both must give the same bytes and, within the
noise of time-limited training, the same MSE. RAY_AUTH_MODE=disabled: a local test cluster (a real one keeps
Ray's token authentication: `ray get-auth-token --generate`, the same token on every node).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]

from bench.meshes import BENCH_MESHES, bench_mesh
from bench.harness import RESULTS, write_markdown, write_rows

PORT = 6391
RAY = str(Path(sys.executable).with_name("ray"))


def write_library(folder: Path, names: list[str]) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        m = bench_mesh(name)
        np.savez(folder / f"{name}.npz", vertices=m.transform.to_original(m.vertices).astype(np.float32), faces=m.faces)


def batch(lib: Path, out: Path, args, env: dict, extra: list[str]) -> float:
    cmd = [sys.executable, "-m", "nbvh_core", "batch", str(lib), "-o", str(out), "--preset", args.preset,
           "--time-limit", str(args.time_limit), "--events", *extra]
    t = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT)
    wall = time.perf_counter() - t
    if proc.returncode != 0:
        raise SystemExit(f"batch failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    return wall


def start_cluster(env: dict) -> None:
    subprocess.run([RAY, "stop", "--force"], capture_output=True, env=env)
    common = ["--disable-usage-stats"]
    subprocess.run([RAY, "start", "--head", "--num-cpus", "0", "--port", str(PORT), "--include-dashboard", "false",
                    *common], check=True, capture_output=True, env=env)
    for _ in range(2):
        subprocess.run([RAY, "start", "--address", f"127.0.0.1:{PORT}", "--num-cpus", "1", *common], check=True,
                       capture_output=True, env=env)


def rows_of(out: Path) -> dict:
    return {r["name"]: r for r in json.loads((out / "report.json").read_text())["rows"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--time-limit", type=float, default=30.0)
    ap.add_argument("--preset", default="preview")
    ap.add_argument("--assets", nargs="+", default=list(BENCH_MESHES), help="bench meshes in the library")
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="nbvh-batch-bench-"))
    lib = work / "library"
    write_library(lib, args.assets)
    env = dict(os.environ, RAY_AUTH_MODE="disabled")
    wall_embedded = batch(lib, work / "embedded", args, env, ["--num-cpus", "2"])
    print(f"embedded: {wall_embedded:.1f} s", flush=True)
    start_cluster(env)
    try:
        wall_cluster = batch(lib, work / "cluster", args, env, ["--address", f"127.0.0.1:{PORT}"])
    finally:
        subprocess.run([RAY, "stop", "--force"], capture_output=True, env=env)
    print(f"cluster: {wall_cluster:.1f} s", flush=True)
    emb, clu = rows_of(work / "embedded"), rows_of(work / "cluster")
    out_rows = []
    for name in args.assets:
        e, c = emb[name], clu[name]
        out_rows.append({"asset": name, "triangles": e["triangles"], "status_embedded": e["status"],
                         "status_cluster": c["status"], "bytes_embedded": e["model_bytes"],
                         "bytes_cluster": c["model_bytes"], "mse_embedded": e["mse"], "mse_cluster": c["mse"],
                         "worker_cluster": c["worker"], "train_s_embedded": e["train_seconds"],
                         "train_s_cluster": c["train_seconds"]})
    write_rows(RESULTS / "batch_cluster.csv", out_rows)
    lines = ["# Library batch: local 3-node Ray cluster vs embedded Ray (bench/speed/bench_batch_cluster.py)", "",
             f"{len(args.assets)} assets (bench_meshes.py), preset `{args.preset}`, {args.time_limit:g} s training each, one run on "
             "this 2-core CPU. Embedded: `nbvh batch LIB -o OUT --num-cpus 2`. Cluster: `ray start --head "
             f"--num-cpus 0 --port {PORT}` + 2 x `ray start --address 127.0.0.1:{PORT} --num-cpus 1`, then "
             f"`nbvh batch LIB -o OUT --address 127.0.0.1:{PORT}`.", "",
             f"Wall time: embedded **{wall_embedded:.1f} s**, cluster **{wall_cluster:.1f} s** "
             f"({wall_cluster / wall_embedded:.2f}x).", "",
             "| asset | triangles | status (emb / cluster) | .nbvh bytes (emb / cluster) | MSE (emb / cluster) | "
             "cluster worker |", "|---|---|---|---|---|---|"]
    for r in out_rows:
        mse = (f"{r['mse_embedded']:.5f} / {r['mse_cluster']:.5f}" if r["mse_embedded"] is not None
               and r["mse_cluster"] is not None else "- / -")
        b = (f"{r['bytes_embedded']:,} / {r['bytes_cluster']:,}" if r["bytes_embedded"] else "- / -")
        lines.append(f"| {r['asset']} | {r['triangles']:,} | {r['status_embedded']} / {r['status_cluster']} | {b} | "
                     f"{mse} | {r['worker_cluster'] or '-'} |")
    write_markdown(RESULTS / "batch_cluster.md", lines)
    shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
