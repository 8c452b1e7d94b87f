"""Speed against accuracy: a preset trained for fractions of its own budget up to the full one, each model's
held-out image MSE against its training seconds, and what its bytes buy against the alternative the product weighs
(the smallest compact decimation meeting that MSE, measured by `app.alternatives.alternatives` on the same views:
16 held-out views at 256 px, the one metric). Every model is forced (shipped whatever the verdict) so the curve is
complete; the ratio says where the verdict would ship it (above 1: the model is smaller).

    .venv/bin/python -m bench.quality.bench_preset_curves [--meshes bunny spiky] [--budgets default=25,50,100,200]

Resumable: one row per (mesh, preset, seconds) in bench/results/preset_curves.csv, appended as it lands; the chart
bench/results/preset_curves.png and preset_curves.md are rewritten after every row. Needs an otherwise idle CPU
(a time budget buys fewer steps on a busy one).
"""
from __future__ import annotations

import argparse
import math

from bench.meshes import named_mesh
from bench.harness import RESULTS, append_rows, markdown_table, read_rows, save_figure, stamp, write_markdown
from nbvh_core import kernels
from nbvh_core.app.alternatives import alternatives
from nbvh_core.app.pipeline import compress_mesh, preset
from nbvh_core.geometry.exact import ExactTracer
from nbvh_core.planning.settings import Settings
from nbvh_core.rendering.metrics import MetricConfig, view_sets

DEFAULT_BUDGETS = {"default": [25, 50, 100, 200]}
VIEWS, RESOLUTION = Settings().eval_views, Settings().eval_resolution  # the product's one metric


def equal_mse_decimation(mesh, tracer, mse: float) -> dict:
    """The smallest compact decimation whose image MSE meets `mse` on the check and held-out views, as the product
    measures its alternative (the ladder, one above, the bisection): {'triangles', 'compact_bytes', 'mse'}, or the
    whole mesh's bytes when none does."""
    checks, held_out = view_sets(tracer, mesh.transform, MetricConfig(views=VIEWS, resolution=RESOLUTION))
    alt = alternatives(mesh, mse, checks, held_out)
    dec = alt.decimation
    if dec is None:
        whole = alt.mesh_compact
        return {"triangles": whole.triangles, "compact_bytes": whole.compact_bytes, "mse": math.nan}
    return {"triangles": dec.triangles, "compact_bytes": dec.compact_bytes + (dec.look_bytes or 0),
            "mse": dec.compact_mse_held_out}


def chart(rows: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import NullFormatter

    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.2))
    for key in sorted({(r["mesh"], r["preset"]) for r in rows}):
        mine = sorted((float(r["train_s"]), r) for r in rows if (r["mesh"], r["preset"]) == key)
        xs = [x for x, _ in mine]
        label = f"{key[0]}, {key[1]}"
        ax.plot(xs, [float(r["mse"]) for _, r in mine], "o-", label=label)
        bx.plot(xs, [float(r["decimation_to_model"]) for _, r in mine], "o-", label=label)
    ax.axhline(0.0005, color="grey", ls=":", lw=0.8, label="level standard (0.0005)")
    ax.set_yscale("log")
    ax.set_ylabel(f"held-out image MSE ({VIEWS} views, {RESOLUTION} px)")
    bx.axhline(1.0, color="grey", ls="--", lw=0.8, label="above: the model is smaller")
    bx.set_ylabel("decimation bytes / model bytes (equal MSE)")
    budgets = sorted({float(r["train_s"]) for r in rows})
    for a in (ax, bx):
        a.set_xscale("log")
        a.set_xticks(budgets)
        a.set_xticklabels([f"{t:.0f}" for t in budgets])
        a.xaxis.set_minor_formatter(NullFormatter())
        a.set_xlabel("training seconds (2-core CPU)")
        a.grid(True, which="both", alpha=0.3)
        a.legend(fontsize=8)
    fig.suptitle("Speed against accuracy: the model's training time, its error, and what its bytes buy")
    fig.tight_layout()
    save_figure(fig, RESULTS / "preset_curves.png", run_stamp=_last_stamp(rows))
    plt.close(fig)


def _last_stamp(rows: list[dict]) -> dict:
    return {k: rows[-1][k] for k in ("commit", "machine", "kernel_plan", "command", "utc") if k in rows[-1]}


def write_outputs(rows: list[dict]) -> None:
    chart(rows)
    table = markdown_table(
        ["mesh", "preset", "training s", "steps", "file B", "held-out MSE", "equal-MSE decimation (triangles, B)",
         "decimation / model", "render rays/s"],
        [[r["mesh"], r["preset"], f"{float(r['train_s']):.0f}", f"{int(r['steps']):,}", f"{int(r['file_bytes']):,}",
          f"{float(r['mse']):.5f}", f"{int(r['decimation_triangles']):,}, {int(r['decimation_bytes']):,}",
          f"{float(r['decimation_to_model']):.2f}x", f"{int(float(r['neural_rays_per_s'])):,}"] for r in rows])
    write_markdown(RESULTS / "preset_curves.md",
                   ["# Speed against accuracy (bench/quality/bench_preset_curves.py)", "",
                    "A preset trained for fractions of its own budget (the last point: the preset as users run it), "
                    "forced; each model scored as stored on 16 held-out views at 256 px, and weighed against the "
                    "smallest compact decimation meeting its MSE on the same views (the product's alternative). "
                    "One run per point.", "", *table,
                    "", "![speed against accuracy](preset_curves.png)"], _last_stamp(rows))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--meshes", nargs="+", default=["bunny", "spiky"])
    ap.add_argument("--budgets", nargs="*", default=[], metavar="PRESET=S,S,...",
                    help="the presets and seconds to run (default: " + " ".join(
                        f"{k}={','.join(map(str, v))}" for k, v in DEFAULT_BUDGETS.items()) + ")")
    args = ap.parse_args()
    budgets = {} if args.budgets else dict(DEFAULT_BUDGETS)
    for item in args.budgets:
        name, values = item.split("=", 1)
        budgets[name] = [float(v) for v in values.split(",")]
    kernels.keep_freed_memory()
    path = RESULTS / "preset_curves.csv"
    run = stamp()
    done = {(r["mesh"], r["preset"], float(r["time_limit_s"])) for r in read_rows(path) if r["commit"] == run["commit"]}
    for mesh_name in args.meshes:
        mesh = named_mesh(mesh_name)
        tracer = ExactTracer(mesh)
        for name, seconds in budgets.items():
            for t in seconds:
                if (mesh_name, name, float(t)) in done:
                    continue
                print(f"{mesh_name} {name} {t} s", flush=True)
                s = preset(name).with_overrides(time_limit_s=float(t), force=True, eval_views=VIEWS,
                                                eval_resolution=RESOLUTION)
                res = compress_mesh(mesh, s, None)
                q = res.quality
                dec = equal_mse_decimation(mesh, tracer, q.mse)
                append_rows(path, [{"mesh": mesh_name, "preset": name, "time_limit_s": float(t),
                                    "train_s": round(res.training.seconds, 1), "steps": res.training.steps,
                                    "file_bytes": res.file_bytes, "mse": q.mse, "iou": q.silhouette_iou,
                                    "decimation_triangles": dec["triangles"], "decimation_bytes": dec["compact_bytes"],
                                    "decimation_mse": dec["mse"],
                                    "decimation_to_model": round(dec["compact_bytes"] / res.file_bytes, 3),
                                    "neural_rays_per_s": round(q.neural_rays_per_s)}], run)
                write_outputs([r for r in read_rows(path) if r["commit"] == run["commit"]])


if __name__ == "__main__":
    main()
