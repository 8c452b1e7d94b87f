"""One training that grows its table against the sizes a user could have fixed: at a preset's own time budget and
a quality level, the smallest fixed table meeting the level (a grid of trainings, one per size), the growing run
(size_search "grow": one training, starting small and doubling its table in place until the level is met), and
today's retrain search (up to TARGET_TRAININGS trainings).

    .venv/bin/python -m bench.decision.bench_grow --meshes bunny spiky gyroid studs --preset preview --quality standard

Rows land in bench/results/grow.csv as they finish (a rerun resumes); grow.md compares, per mesh, the growing
run's file with the smallest fixed size that met the level and its wall time with one fixed training's.
"""
from __future__ import annotations

import argparse
import time

from bench.meshes import bench_mesh
from bench.harness import RESULTS, SMOKE, append_row, markdown_table, num, read_rows, write_markdown
from nbvh_core import kernels
from nbvh_core.app.pipeline import compress_mesh, preset
from nbvh_core.protocol.quality_levels import QUALITY_LEVELS

CSV = RESULTS / "grow.csv"


def run(mesh_name: str, mode: str, settings, mesh) -> dict:
    t0 = time.perf_counter()
    res = compress_mesh(mesh, settings)
    q = res.quality
    return {"mesh": mesh_name, "mode": mode, "log2_table": res.settings.log2_table, "file_bytes": res.file_bytes,
            "mse": q.mse, "iou": q.silhouette_iou, "met": q.mse <= (settings.target_mse or QUALITY_LEVELS["standard"]),
            "train_s": round(res.seconds.get("train", res.training.seconds), 1), "steps": res.training.steps,
            "wall_s": round(time.perf_counter() - t0, 1), "grew": " ".join(f"2^{g[2]}@{g[1]}s" for g in res.training.grew),
            "why": res.why[-300:]}


def measure(mesh_name: str, args, done: set) -> None:
    mesh = bench_mesh(mesh_name)
    base = preset(args.preset).with_overrides(force=True, time_limit_s=args.time_limit)
    level = QUALITY_LEVELS[args.quality]
    plans = [(f"fixed 2^{l2}", base.with_overrides(log2_table=l2)) for l2 in args.sizes]
    plans += [("grow", base.with_overrides(target_mse=level, size_search="grow")),
              ("retrain", base.with_overrides(target_mse=level, size_search="retrain"))]
    for mode, s in plans:
        if (mesh_name, mode, args.preset, args.quality) in done:
            continue
        row = {"preset": args.preset, "quality": args.quality, "target_mse": level, **run(mesh_name, mode, s, mesh)}
        if mode.startswith("fixed"):
            row["met"] = row["mse"] <= level
        append_row(CSV, row)
        print({k: row[k] for k in ("mesh", "mode", "log2_table", "file_bytes", "mse", "met", "wall_s", "grew")},
              flush=True)


def report(args) -> None:
    rows = [r for r in read_rows(CSV) if r["preset"] == args.preset and r["quality"] == args.quality]
    table = []
    for mesh_name in dict.fromkeys(r["mesh"] for r in rows):
        own = [r for r in rows if r["mesh"] == mesh_name]
        fixed = [r for r in own if r["mode"].startswith("fixed")]
        met = [r for r in fixed if r["met"] == "True"]
        best = min(met, key=lambda r: num(r, "file_bytes")) if met else None
        own_size = preset(args.preset).log2_table  # one training at the preset's own size: what a user waits today
        one = next((r for r in fixed if int(r["log2_table"]) == own_size), None)
        for r in (x for x in own if not x["mode"].startswith("fixed")):
            mode = r["mode"]
            ratio = f"{num(r, 'file_bytes') / num(best, 'file_bytes'):.2f}x" if best else "-"
            wall = f"{num(r, 'wall_s') / num(one, 'wall_s'):.2f}x" if one else "-"
            table.append([mesh_name, mode, f"2^{r['log2_table']}", f"{int(r['file_bytes']):,}", f"{num(r, 'mse'):.5f}",
                          r["met"], f"2^{best['log2_table']} {int(best['file_bytes']):,} B" if best else "none met",
                          ratio, r["wall_s"], wall, r["grew"] or "-"])
    lines = [f"# One growing training against fixed sizes (preset `{args.preset}`, level `{args.quality}` = MSE "
             f"{QUALITY_LEVELS[args.quality]:g})", "",
             "Per mesh: the growing run (one training) and the retrain search, against the smallest fixed table that "
             "met the level when trained for the same budget (the grid's rows in grow.csv). File ratio: the run's "
             ".nbvh bytes / the smallest meeting fixed size's. Wall ratio: the run's wall time / one fixed training's "
             "at the preset's own size).", "",
             *markdown_table(["mesh", "run", "T", "bytes", "MSE", "met", "smallest fixed meeting it", "file ratio",
                              "wall s", "wall ratio", "growth"], table)]
    write_markdown(RESULTS / "grow.md", lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--meshes", nargs="+", default=["bunny", "spiky", "gyroid", "studs"])
    ap.add_argument("--preset", default="preview")
    ap.add_argument("--quality", default="standard", choices=list(QUALITY_LEVELS))
    ap.add_argument("--sizes", type=int, nargs="+", default=[7, 8, 9, 10, 11], help="the fixed grid (log2 T)")
    ap.add_argument("--time-limit", type=float, help="override the preset's budget (not for headline numbers)")
    args = ap.parse_args()
    if SMOKE:
        args.sizes = args.sizes[:1]
    kernels.keep_freed_memory()
    done = {(r["mesh"], r["mode"], r["preset"], r["quality"]) for r in read_rows(CSV)}
    for name in args.meshes:
        measure(name, args, done)
    report(args)


if __name__ == "__main__":
    main()
