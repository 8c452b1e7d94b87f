"""Speed against accuracy for each user preset: training seconds vs image MSE, and what the bytes buy (the model's
resident bytes against the quadric decimation of the same MSE), the preset trained for fractions of its own budget
up to the full one, on one mesh, scored with the one metric (16 views at 128 px, every preset alike: the preview
preset's own report uses 8 views).

    .venv/bin/python bench/bench_preset_curves.py [--mesh bunny] [--budgets preview=15,30,60 default=25,50,100,200]

Resumable: one row per (mesh, preset, seconds) in bench/results/preset_curves.csv, appended as it lands; the chart
bench/results/preset_curves.png and preset_curves.md are rewritten after every row. Needs an otherwise idle CPU
(a time budget buys fewer steps on a busy one). An older run (16-feature presets, facing normals) is preset_curves_16features_facing.*.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

from bench_meshes import bench_mesh
from bench_pays import equal_mse_decimation
from harness import RESULTS, append_row, read_rows, save_figure, write_markdown
from nbvh_core import kernels
from nbvh_core.geometry.exact import ExactTracer
from nbvh_core.app.pipeline import compress_mesh, preset
from nbvh_core.planning.settings import Settings

DEFAULT_BUDGETS = {"preview": [15, 30, 60], "default": [25, 50, 100, 200], "high": [100, 300, 600]}
VIEWS, RESOLUTION = Settings().eval_views, Settings().eval_resolution  # the product's one metric


def write_outputs(rows: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.2))
    for name in DEFAULT_BUDGETS:
        mine = sorted((float(r["train_s"]), r) for r in rows if r["preset"] == name)
        if not mine:
            continue
        xs = [x for x, _ in mine]
        ax.plot(xs, [float(r["mse"]) for _, r in mine], "o-", label=f"{name} ({rows[0]['mesh']})")
        bx.plot(xs, [float(r["ratio_resident_decimation_to_model"]) for _, r in mine], "o-", label=name)
    ax.set_yscale("log")
    ax.set_ylabel(f"image MSE ({VIEWS} views, {RESOLUTION} px)")
    bx.set_ylabel("x smaller resident than the equal-MSE decimation")
    bx.axhline(4.0, color="grey", ls="--", lw=0.8, label="4x (the default preset's target)")
    from matplotlib.ticker import NullFormatter

    budgets = sorted({t for v in DEFAULT_BUDGETS.values() for t in v})
    for a in (ax, bx):
        a.set_xscale("log")
        a.set_xticks(budgets)
        a.set_xticklabels([str(t) for t in budgets])
        a.xaxis.set_minor_formatter(NullFormatter())
        a.set_xlabel("training seconds (this 2-core CPU)")
        a.grid(True, which="both", alpha=0.3)
        a.legend()
    fig.tight_layout()
    save_figure(fig, RESULTS / "preset_curves.png")
    plt.close(fig)
    lines = ["# Speed against accuracy per preset (bench/bench_preset_curves.py)", "",
             "Each user preset trained for fractions of its own budget (the last point: the preset as users run it) "
             "on one mesh; every point scored with the one metric (16 orbit views at 128 px against Embree), and set "
             "against the quadric decimation of the same MSE on resident bytes (what a ray tracer holds). One run "
             "per point on this 2-core CPU.", "",
             "| mesh | preset | training s | steps | .nbvh B | model resident B | MSE | IoU | equal-MSE decimation "
             "(triangles, resident B) | x smaller | render rays/s |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in sorted(rows, key=lambda r: (list(DEFAULT_BUDGETS).index(r["preset"]) if r["preset"] in DEFAULT_BUDGETS
                                         else 9, float(r["train_s"]))):
        lines.append(f"| {r['mesh']} | {r['preset']} | {float(r['train_s']):.0f} | {int(r['steps']):,} | "
                     f"{int(r['file_bytes']):,} | {int(r['model_resident_bytes']):,} | {float(r['mse']):.5f} | "
                     f"{float(r['iou']):.4f} | {int(r['equal_mse_decimation_triangles']):,}, "
                     f"{int(r['equal_mse_decimation_resident_bytes']):,} | "
                     f"{float(r['ratio_resident_decimation_to_model']):.2f}x | {int(float(r['neural_rays_per_s'])):,} |")
    write_markdown(RESULTS / "preset_curves.md", lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh", default="bunny")
    ap.add_argument("--budgets", nargs="*", default=[], metavar="PRESET=S,S,...",
                    help="the presets and seconds to run (default: " + " ".join(
                        f"{k}={','.join(map(str, v))}" for k, v in DEFAULT_BUDGETS.items()) + ")")
    ap.add_argument("--csv", default=str(RESULTS / "preset_curves.csv"))
    args = ap.parse_args()
    budgets = {} if args.budgets else dict(DEFAULT_BUDGETS)
    for item in args.budgets:
        name, values = item.split("=", 1)
        budgets[name] = [float(v) for v in values.split(",")]
    kernels.keep_freed_memory()
    path = Path(args.csv)
    done = {(r["mesh"], r["preset"], float(r["time_limit_s"])) for r in read_rows(path)}
    mesh = bench_mesh(args.mesh)
    tracer = ExactTracer(mesh)
    for name, seconds in budgets.items():
        for t in seconds:
            if (args.mesh, name, float(t)) in done:
                continue
            print(f"{args.mesh} {name} {t} s", flush=True)
            s = preset(name).with_overrides(time_limit_s=float(t), force=True, eval_views=VIEWS,
                                            eval_resolution=RESOLUTION)
            res = compress_mesh(mesh, s, None)
            q = res.quality
            dec = equal_mse_decimation(mesh, tracer, q.mse, VIEWS, RESOLUTION)
            resident = sum(res.model.resident_bytes().values())
            append_row(path, {"mesh": args.mesh, "preset": name, "time_limit_s": float(t),
                              "train_s": round(res.training.seconds, 1), "steps": res.training.steps,
                              "file_bytes": res.file_bytes, "model_resident_bytes": resident, "mse": q.mse,
                              "iou": q.silhouette_iou, "equal_mse_decimation_triangles": dec["triangles"],
                              "equal_mse_decimation_resident_bytes": dec["resident"],
                              "ratio_resident_decimation_to_model": round(dec["resident"] / resident, 3),
                              "neural_rays_per_s": round(q.neural_rays_per_s),
                              "created": time.strftime("%Y-%m-%dT%H:%M:%S")})
            write_outputs(read_rows(path))


if __name__ == "__main__":
    main()
