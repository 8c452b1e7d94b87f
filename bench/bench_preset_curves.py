"""Speed against accuracy for each user preset: training seconds vs image MSE (and the file's bytes), the preset
trained for fractions of its own budget, on one mesh, scored with the one metric (16 views at 128 px).

    .venv/bin/python bench/bench_preset_curves.py [--mesh bunny] [--budgets preview=15,30,60 default=25,50,100,200]

Resumable: one row per (mesh, preset, seconds) in bench/results/preset_curves.csv, appended as it lands; the chart
bench/results/preset_curves.png and preset_curves.md are rewritten after every row.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from bench_meshes import bench_mesh  # noqa: E402
from bench_quality import append_row, read_rows  # noqa: E402
from nbvh_core import kernels  # noqa: E402
from nbvh_core.pipeline import compress_mesh, preset  # noqa: E402

RESULTS = ROOT / "bench" / "results"
DEFAULT_BUDGETS = {"preview": [15, 30, 60], "default": [25, 50, 100, 200], "high": [100, 300]}


def write_outputs(rows: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for name in DEFAULT_BUDGETS:
        pts = sorted((float(r["train_s"]), float(r["mse"])) for r in rows if r["preset"] == name)
        if pts:
            ax.plot([p[0] for p in pts], [p[1] for p in pts], "o-", label=f"{name} ({rows[0]['mesh']})")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("training seconds (this 2-core CPU)")
    ax.set_ylabel("image MSE (16 views, 128 px)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(RESULTS / "preset_curves.png", dpi=110)
    plt.close(fig)
    lines = ["# Speed against accuracy per preset (bench/bench_preset_curves.py)", "",
             "Each user preset trained for fractions of its own budget on one mesh; the metric is the pipeline's "
             "(16 orbit views at 128 px against Embree). One run per point on this 2-core CPU.", "",
             "| mesh | preset | training s | steps | .nbvh bytes | MSE | IoU |", "|---|---|---|---|---|---|---|"]
    for r in sorted(rows, key=lambda r: (r["preset"], float(r["train_s"]))):
        lines.append(f"| {r['mesh']} | {r['preset']} | {float(r['train_s']):.0f} | {int(r['steps']):,} | "
                     f"{int(r['file_bytes']):,} | {float(r['mse']):.5f} | {float(r['iou']):.4f} |")
    (RESULTS / "preset_curves.md").write_text("\n".join(lines) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh", default="bunny")
    ap.add_argument("--budgets", nargs="*", default=[], metavar="PRESET=S,S,...")
    ap.add_argument("--csv", default=str(RESULTS / "preset_curves.csv"))
    args = ap.parse_args()
    budgets = dict(DEFAULT_BUDGETS)
    for item in args.budgets:
        name, values = item.split("=", 1)
        budgets[name] = [float(v) for v in values.split(",")]
    kernels.keep_freed_memory()
    path = Path(args.csv)
    done = {(r["mesh"], r["preset"], float(r["time_limit_s"])) for r in read_rows(path)}
    mesh = bench_mesh(args.mesh)
    for name, seconds in budgets.items():
        for t in seconds:
            if (args.mesh, name, float(t)) in done:
                continue
            print(f"{args.mesh} {name} {t} s", flush=True)
            res = compress_mesh(mesh, preset(name).with_overrides(time_limit_s=float(t), force=True), None)
            append_row(path, {"mesh": args.mesh, "preset": name, "time_limit_s": float(t),
                              "train_s": round(res.training.seconds, 1), "steps": res.training.steps,
                              "file_bytes": res.file_bytes, "mse": res.quality.mse,
                              "iou": res.quality.silhouette_iou, "created": time.strftime("%Y-%m-%dT%H:%M:%S")})
            write_outputs(read_rows(path))


if __name__ == "__main__":
    main()
