"""Heavy assets through the need-driven default: wall per stage, peak memory, and what shipped against the compact
decimation at equal measured quality.

    .venv/bin/python -m bench.decision.bench_heavy --lattices 180 320 560 --assets dragon

Per asset (generated lattices of fine repeated detail, `bench_meshes.lattice(n)`: ~1.0M, 3.3M and 10M triangles
at n = 180, 320, 560; real ones from `real_assets.py`), the mesh is written to a binary PLY and compressed as a
user would: `nbvh compress FILE -o OUT/ --events` (level standard, 200 s of training). Each stage's wall is taken
from the arrival of the run's phase events (load: from the process's start to the plan, its imports, the file read
and the predictor's measures of the mesh; then plan, bvh, train, ...); the peak resident memory from the run's
own report (NAME.report.json, or NAME.verdict.json when it kept a mesh) and from the OS; the decision and the ratio
(the alternative's bytes at the shipped MSE / the shipped bytes, on the run's own measured curve) from its final
verdict, or its verdict before training.

Rows land in bench/results/heavy.csv (one per asset, replaced when measured at another commit); heavy.md has the
table. One run at a time, on an otherwise idle machine.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench.harness import RESULTS, ROOT, SMOKE, commit_of, markdown_table, num, read_rows, write_markdown, write_rows

CSV = RESULTS / ("heavy_smoke.csv" if SMOKE else "heavy.csv")


def source(name: str, work: Path) -> Path:
    """The asset as a file: lattice-N generated (cached by bench_meshes), else a real asset."""
    if name.startswith("lattice-"):
        from bench.meshes import lattice
        from nbvh_core.geometry.mesh import mesh_file_bytes

        path = work / f"{name}.ply"
        if not path.exists():
            path.write_bytes(mesh_file_bytes(lattice(int(name.split("-")[1]))))
        return path
    from bench.real_assets import asset_path

    return asset_path(name)


def _rss(pid: int) -> int:
    """The process's resident bytes now (Linux /proc; 0 where unreadable)."""
    try:
        with open(f"/proc/{pid}/status") as f:
            return next((int(ln.split()[1]) * 1024 for ln in f if ln.startswith("VmRSS:")), 0)
    except OSError:
        return 0


def run(path: Path, out: Path, time_limit: float | None) -> tuple[int, float, dict, str, list]:
    """The CLI on `path`: (exit code, wall s, seconds per stage from the phase events, the verdict's line, each phase
    event's step in order as (phase: its message's first words, seconds, peak resident bytes, polled every 0.2 s))."""
    import threading

    extra = ["--time-limit", str(time_limit)] if time_limit else []
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "nbvh_core", "compress", str(path), "-o", f"{out}/", "--overwrite",
                             "--events", *extra], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    stages, current, since = {}, "load", t0
    steps = [["load", 0.0, 0]]  # the last is the step running; the poller raises its peak
    step_since = t0

    def next_step(name: str, now: float) -> None:
        nonlocal step_since
        steps[-1][1] = now - step_since
        steps.append([name, 0.0, 0])
        step_since = now

    def poll() -> None:
        while proc.poll() is None:
            steps[-1][2] = max(steps[-1][2], _rss(proc.pid))
            time.sleep(0.2)

    poller = threading.Thread(target=poll, daemon=True)
    poller.start()
    for line in proc.stdout:
        try:
            ev = json.loads(line)
        except ValueError:
            continue
        if ev.get("event") == "phase":
            now = time.perf_counter()
            stages[current] = stages.get(current, 0.0) + now - since
            current, since = ev["phase"], now
            next_step(f"{ev['phase']}: {' '.join(str(ev.get('message', '')).split()[:4])}", now)
        elif ev.get("event") == "progress" and ev.get("phase") == "plan" and ev.get("message"):
            next_step(f"plan: {ev['message']}", time.perf_counter())  # each measurement of the plan
    err = proc.stderr.read()
    code = proc.wait()
    poller.join()
    wall = time.perf_counter() - t0
    stages[current] = stages.get(current, 0.0) + time.perf_counter() - since
    steps[-1][1] = time.perf_counter() - step_since
    verdict = next((ln for ln in err.splitlines() if ln.startswith(("verdict:", "not worth", "kept as", "decided"))),
                   err.strip().splitlines()[-1] if err.strip() else "")
    return code, wall, {k: round(v, 1) for k, v in stages.items()}, verdict, steps


def measure(name: str, args, work: Path) -> None:
    from nbvh_core.geometry.mesh import load_mesh

    path = source(name, work)
    triangles = load_mesh(path).n_triangles
    out = work / name
    out.mkdir(exist_ok=True)
    code, wall, stages, verdict, steps = run(path, out, args.time_limit)
    if code not in (0, 4):
        print(f"{name}: exit {code}: {verdict}", file=sys.stderr)
        return
    # The child's resident memory as polled every 0.2 s (getrusage's children's ru_maxrss counted this process's
    # own, the generated mesh included: 18 GB beside the run's 5 GB at 20M).
    polled_peak = max(p for _, _, p in steps)
    stem = Path(path.stem).stem if path.suffix == ".gz" else path.stem  # the CLI's name for NAME.ply.gz: NAME
    report = out / f"{stem}.report.json"
    record = json.loads((report if report.exists() else out / f"{stem}.verdict.json").read_text())
    final = (record.get("decisions") or {}).get("final") or record.get("final") or {}
    peak = (record.get("memory") or {}).get("peak_resident_bytes")
    shipped = final.get("shipped") or ("model" if report.exists() else record.get("recommendation"))
    row = {"asset": name, "triangles": triangles, "exit_code": code, "wall_s": round(wall, 1),
           "load_s": stages.get("load", ""), "plan_s": stages.get("plan", ""), "bvh_s": stages.get("bvh", ""),
           "train_s": stages.get("train", ""), "rest_s": round(wall - sum(stages.get(k, 0.0) for k in
                                                                          ("load", "plan", "bvh", "train")), 1),
           "peak_bytes": peak or "", "peak_per_triangle": round(peak / triangles, 1) if peak else "",
           "polled_peak_bytes": polled_peak, "shipped": shipped, "model_bytes": final.get("model_bytes", ""),
           "model_mse": final.get("model_mse", ""), "alternative_bytes": final.get("alternative_bytes") or "",
           "ratio": round(final["ratio"], 3) if final.get("ratio") else (
               f"> {final['alternative_above'] / final['model_bytes']:.2f}" if final.get("alternative_above") else ""),
           "verdict": (final.get("message") or record.get("message") or verdict)[:300],
           "steps": " | ".join(f"{k} {t:.1f} s {p / 2**30:.2f} GiB" for k, t, p in steps if t >= 0.5 or p > 2**30)}
    rows = [*(r for r in read_rows(CSV) if r["asset"] != name), row]
    write_rows(CSV, sorted(rows, key=lambda r: int(r["triangles"])))  # by size: the README reads them in order
    print({k: row[k] for k in ("asset", "triangles", "wall_s", "plan_s", "bvh_s", "train_s", "peak_per_triangle",
                               "shipped", "ratio")}, flush=True)


def report() -> None:
    rows = read_rows(CSV)
    table = [[r["asset"], f"{int(r['triangles']):,}", r["wall_s"], r["load_s"], r["plan_s"], r["bvh_s"],
              r["train_s"], r["rest_s"], f"{num(r, 'peak_bytes') / 2**30:.2f}" if r["peak_bytes"] else "-",
              r["peak_per_triangle"] or "-", r["shipped"], f"{int(num(r, 'model_bytes')):,}" if r["model_bytes"] else "-",
              f"{num(r, 'model_mse'):.5f}" if r["model_mse"] else "-", r["ratio"] or "-", r["commit"]] for r in rows]
    write_markdown(CSV.with_suffix(".md"), [
        "# Heavy assets through the default (level standard, 200 s of training)", "",
        "Wall seconds per stage from the run's phase events; peak resident memory from the run's report. ratio = "
        "the compact decimation's bytes at the model's held-out MSE / the model's bytes (the run's own final "
        "verdict; > 1: the model is smaller; > x: no measured decimation reaches the model's MSE, and the largest "
        "measured, which misses it, is x times the model's bytes).", "",
        *markdown_table(["asset", "triangles", "wall s", "load s", "plan s", "bvh s", "train s", "rest s",
                         "peak GiB", "peak B/triangle", "shipped", "model bytes", "model MSE", "ratio", "commit"],
                        table), "", "What each run's final verdict said:", "",
        *[f"- {r['asset']}: {r['verdict']}" for r in rows], "",
        "Each phase of each run (its first words, seconds, peak resident memory polled every 0.2 s; steps under "
        "0.5 s and 1 GiB left out):", "",
        *[f"- {r['asset']}: {r.get('steps') or '-'}" for r in rows]])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--lattices", nargs="*", type=int, default=[180, 320, 560], help="lattice resolutions n")
    p.add_argument("--assets", nargs="*", default=[], help="real assets (real_assets.py)")
    p.add_argument("--time-limit", type=float, default=None, help="training budget (default: the product's)")
    p.add_argument("--work", default=None, help="folder for the inputs and outputs (default: a temporary one)")
    args = p.parse_args()
    prior = {r["asset"]: r for r in read_rows(CSV)}
    with tempfile.TemporaryDirectory(prefix="nbvh-heavy-") as tmp:
        work = Path(args.work) if args.work else Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        for name in [f"lattice-{n}" for n in args.lattices] + list(args.assets):
            if name not in prior or prior[name]["commit"] != commit_of(ROOT):
                measure(name, args, work)
    report()


if __name__ == "__main__":
    main()
