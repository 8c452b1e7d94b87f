"""The need-driven default against what a user could have fixed, through the command line as a user runs it.

    .venv/bin/python -m bench.decision.bench_need --meshes knot gear spiky sheet gyroid studs

Per mesh (written to a PLY first, so every run reads a file like a user's):
* `default`: `nbvh compress MESH -o OUT` with no options: the verdict, then (when a model is worth it) one training
  that grows its table until the default quality level is met. A verdict of "keep as a mesh" must come in seconds
  with the alternative written (NAME.glb when a decimation wins).
* `preset default`: `--preset default --force`, one training of the default preset (T=2^12, 2,047 nodes, 200 s): the
  wall time a user waited before.
* `fixed 2^k`: `--preset default --log2-table k --nodes N --force` (N: the nodes the default run chose), at the
  default run's own size and from one size below it down to the first size that misses the level: the smallest
  fixed table that meets it at the same budget.

Rows land in bench/results/need.csv as they finish (a rerun resumes); need.md has the per-mesh comparison.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench.meshes import bench_mesh
from bench.harness import RESULTS, ROOT, SMOKE, append_row, markdown_table, num, read_rows, write_markdown
from nbvh_core.geometry.mesh import mesh_file_bytes
from nbvh_core.protocol.quality_levels import DEFAULT_LEVEL, QUALITY_LEVELS

CSV = RESULTS / ("need_smoke.csv" if SMOKE else "need.csv")


def cli(mesh_file: Path, out: Path, extra: list[str]) -> tuple[int, float, dict]:
    """One `nbvh compress` run: (exit code, wall seconds, its report or {})."""
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "nbvh_core", "compress", str(mesh_file), "-o", str(out),
                           "--overwrite", *extra], cwd=ROOT, capture_output=True, text=True)
    wall = time.perf_counter() - t
    report = out.with_suffix(".report.json")
    data = json.loads(report.read_text()) if report.exists() and proc.returncode == 0 else {}
    if proc.returncode not in (0, 4):
        print(proc.stderr[-2000:], file=sys.stderr)
    lines = proc.stderr.strip().splitlines()
    data["stderr_tail"] = next((ln for ln in lines if ln.startswith("not worth compressing")), lines[-1] if lines
                               else "")[:400]
    return proc.returncode, wall, data


def row_of(mesh: str, mode: str, rc: int, wall: float, data: dict, out: Path, level: float) -> dict:
    q = data.get("quality") or {}
    s = data.get("settings") or {}
    alt = [p for p in (out.with_name(out.stem + ".glb"), out.with_name(out.stem + ".compact.cmsh"))
           if p.exists()]
    return {"mesh": mesh, "mode": mode, "level": level, "exit_code": rc, "wall_s": round(wall, 1),
            "log2_table": s.get("log2_table", ""), "nodes": s.get("nodes", ""), "file_bytes": data.get("file_bytes", ""),
            "mse": q.get("mse", ""), "met": (q["mse"] <= level) if q else "",
            "train_s": (data.get("training") or {}).get("seconds", ""),
            "alternative_written": " + ".join(p.name for p in alt),
            "checks": json.dumps(_checks_with_bytes(data)),
            "alternative_bytes": " + ".join(str(p.stat().st_size) for p in alt),
            "verdict": data.get("stderr_tail", "") if rc == 4 else (data.get("why") or "")[-300:]}


def _checks_with_bytes(data: dict) -> list:
    """The run's quality checks as [seconds, log2 T, MSE, file bytes at that size] (a growing training's path)."""
    from nbvh_core.planning.settings import estimate_file_bytes, settings_from_dict

    checks = (data.get("training") or {}).get("checks") or []
    if not checks:
        return []
    s = settings_from_dict(data["settings"])
    return [[sec, l2, mse, estimate_file_bytes(s.with_overrides(log2_table=l2))] for sec, l2, mse in checks]


def measure(name: str, args, done: set, work: Path) -> None:
    level = QUALITY_LEVELS[DEFAULT_LEVEL]
    mesh_file = work / f"{name}.ply"
    if not mesh_file.exists():
        mesh_file.write_bytes(mesh_file_bytes(bench_mesh(name)))
    tiny = ["--time-limit", str(args.time_limit)] if args.time_limit else []
    tiny += ["--mesh-layout", args.mesh_layout] if args.mesh_layout else []

    def run(mode: str, extra: list[str]) -> dict:
        prior = [r for r in read_rows(CSV) if r["mesh"] == name and r["mode"] == mode]
        if prior:
            return prior[-1]
        out = work / mode.replace(" ", "_").replace("^", "") / f"{name}.nbvh"
        out.parent.mkdir(exist_ok=True)
        rc, wall, data = cli(mesh_file, out, extra + tiny)
        row = {**row_of(name, mode, rc, wall, data, out, level), "mesh_layout": args.mesh_layout or "compact"}
        append_row(CSV, row)
        print({k: row[k] for k in ("mesh", "mode", "exit_code", "wall_s", "log2_table", "file_bytes", "mse", "met")},
              flush=True)
        return row

    default = run("default", [])
    if str(default["exit_code"]) != "0":
        return  # the verdict: nothing trained, nothing to compare
    if args.retrain:
        run("retrain search", ["--size-search", "retrain"])
    one = run("preset default", ["--preset", "default", "--force"])
    nodes, top = str(default["nodes"]), int(default["log2_table"])
    for l2 in range(top - 1, 5, -1):
        same = str(l2) == str(one["log2_table"]) and nodes == str(one["nodes"])  # the preset's own size: run once
        r = one if same else run(f"fixed 2^{l2}", ["--preset", "default", "--log2-table", str(l2), "--nodes", nodes,
                                                  "--force"])
        if r["met"] != "True" and r["met"] is not True:
            break
    if not (str(top) == str(one["log2_table"]) and nodes == str(one["nodes"])):  # the default's own size, fixed
        run(f"fixed 2^{top}", ["--preset", "default", "--log2-table", str(top), "--nodes", nodes, "--force"])


def report() -> None:
    rows = read_rows(CSV)
    table = []
    for name in dict.fromkeys(r["mesh"] for r in rows):
        own = {r["mode"]: r for r in rows if r["mesh"] == name}
        d = own.get("default")
        if d is None:  # its default run not (yet) measured
            continue
        if d["exit_code"] != "0":
            table.append([name, "keep as a mesh", d["wall_s"], "-", "-", "-", d["alternative_written"] or "-", "-",
                          d["verdict"][:160]])
            continue
        one = own.get("preset default")
        fixed = [r for m, r in own.items() if (m.startswith("fixed") or m == "preset default") and r["met"] == "True"]
        best = min(fixed, key=lambda r: num(r, "file_bytes")) if fixed else None
        for r in (d, own.get("retrain search")):
            if r is None:
                continue
            table.append([name, f"{'default' if r is d else 'retrain search'}: 2^{r['log2_table']}, "
                                f"{int(r['file_bytes']):,} B, MSE {num(r, 'mse'):.5f}"
                          + ("" if r["met"] == "True" else " (missed)"), r["wall_s"],
                          f"{best['mode']}: {int(best['file_bytes']):,} B" if best else "none met",
                          f"{num(r, 'file_bytes') / num(best, 'file_bytes'):.2f}x" if best else "-",
                          f"{num(r, 'wall_s') / num(one, 'wall_s'):.2f}x" if one else "-",
                          "-", f"{int(one['file_bytes']):,} B, MSE {num(one, 'mse'):.5f}" if one else "-",
                          r["verdict"][-160:]])
    lines = ["# The need-driven default against fixed sizes (bench/decision/bench_need.py)", "",
             f"Every run is `nbvh compress` on the mesh as a PLY; the default has no options (level {DEFAULT_LEVEL} = "
             f"MSE {QUALITY_LEVELS[DEFAULT_LEVEL]:g}, the default preset's 200 s). File ratio: the default's file / the "
             "smallest fixed size that met the level at the same budget (fixed runs from the default's own size down "
             "to the first miss, and the default preset's 2^12). Wall ratio: the default's wall time / one `--preset default` run.",
             "", *markdown_table(["mesh", "default run", "wall s", "smallest fixed meeting the level", "file ratio",
                                  "wall ratio", "alternative written", "one default-preset run", "verdict / why"],
                                 table)]
    write_markdown(RESULTS / ("need_smoke.md" if SMOKE else "need.md"), lines)
    print("\n".join(lines))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--meshes", nargs="+", default=["knot", "gear", "spiky", "sheet", "gyroid", "studs"])
    ap.add_argument("--work", help="scratch folder (default: a temporary one)")
    ap.add_argument("--time-limit", type=float, help="override every run's budget (smoke runs only)")
    ap.add_argument("--mesh-layout", choices=["compact", "plain"],
                    help="every run weighs the mesh in this layout (default: the product's default, compact)")
    ap.add_argument("--retrain", action="store_true",
                    help="also the retrain search (--size-search retrain: up to 3 trainings) at the default level")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(args.work or tmp)
        work.mkdir(parents=True, exist_ok=True)
        for name in args.meshes:
            measure(name, args, set(), work)
    report()


if __name__ == "__main__":
    main()
