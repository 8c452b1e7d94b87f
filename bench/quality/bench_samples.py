"""Compress every bundled sample with one preset and tabulate size, quality, time and speed (forced: the model of
each, whatever the verdict).

    .venv/bin/python -m bench.quality.bench_samples [--preset default] [--out out/samples]
    .venv/bin/python -m bench.quality.bench_samples --summarise out/default     # only tabulate existing NAME.report.json reports

Each sample goes through `python -m nbvh_core compress` (the CLI users run), which writes NAME.nbvh,
NAME.report.json, NAME.preview.png and NAME.reference.png. Writes bench/results/samples_<preset>.md and .csv.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

from nbvh_core.geometry.bundled_samples import SAMPLE_NAMES
from bench.harness import RESULTS, write_markdown, write_rows


def summarise(folder: Path, preset: str, wall: dict) -> None:
    rows = []
    for name in SAMPLE_NAMES:
        path = folder / f"{name}.report.json"
        if not path.exists():
            continue
        r = json.loads(path.read_text())
        q, t = r["quality"], r["training"]
        rows.append({
            "asset": name, "nbvh_bytes": r["file_bytes"], "resident_mesh_bytes": r["mesh_resident_bytes"]["total"],
            "ratio_resident": round(r["mesh_resident_bytes"]["total"] / r["file_bytes"], 2),
            "source_file_bytes": r["source_file_bytes"], "mse": round(q["mse"], 5),
            "silhouette_iou": round(q["silhouette_iou"], 4), "depth_error": round(q["depth_error"], 5),
            "train_s": round(t["seconds"], 1), "steps": t["steps"], "train_samples_per_s": round(t["samples_per_s"]),
            "neural_rays_per_s": round(q["neural_rays_per_s"]), "embree_rays_per_s": round(q["reference_rays_per_s"]),
            "wall_s": wall.get(name, ""),
            "meets_targets": q["silhouette_iou"] >= 0.95 and q["mse"] <= 0.01,
        })
    if not rows:
        raise SystemExit(f"no reports in {folder}")
    out = RESULTS / f"samples_{preset}.csv"
    write_rows(out, rows)
    s = json.loads((folder / f"{rows[0]['asset']}.report.json").read_text())["settings"]
    lines = [f"# Bundled samples, preset `{preset}`\n",
             f"Settings: {s['encoding']} (T=2^{s['log2_table']}) + {s['network']} (k={s['k']}), {s['labels']} labels, "
             f"{s['nodes']} BVH nodes, lr {s['lr']}, {s['time_limit_s']} s training; quality over {s['eval_views']} orbit "
             f"views at {s['eval_resolution']} px. Machine: 2-core x86_64 CPU, torch 2.13.0 CPU. Resident mesh = "
             "float32 vertices + int32 indices + float32 vertex normals + a BVH with <= 4 triangles per leaf.\n",
             "| asset | .nbvh | resident mesh | ratio | MSE | sil. IoU | depth err | train | steps | train samples/s | neural rays/s | Embree rays/s | wall | targets met |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['asset']} | {r['nbvh_bytes'] / 1024:,.0f} KB | {r['resident_mesh_bytes'] / 1024:,.0f} KB | "
                     f"{r['ratio_resident']}x | {r['mse']} | {r['silhouette_iou']} | {r['depth_error']} | {r['train_s']} s | "
                     f"{r['steps']} | {r['train_samples_per_s']:,} | {r['neural_rays_per_s']:,} | {r['embree_rays_per_s']:,} | "
                     f"{r['wall_s']} s | {'yes' if r['meets_targets'] else 'no'} |")
    write_markdown(out.with_suffix(".md"), lines)
    print("\n".join(lines))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--preset", default="default")
    ap.add_argument("--out", default=str(ROOT / "out" / "samples"))
    ap.add_argument("--summarise", help="tabulate the NAME.report.json reports in this folder instead of compressing")
    args = ap.parse_args()
    if args.summarise:
        folder = Path(args.summarise)
        wall = {}
        for name in SAMPLE_NAMES:
            tf = folder / f"{name}.time"
            if tf.exists() and tf.read_text().strip():
                wall[name] = float(tf.read_text().split()[-3])
        summarise(folder, args.preset, wall)
        return
    folder = Path(args.out)
    folder.mkdir(parents=True, exist_ok=True)
    wall = {}
    for name in SAMPLE_NAMES:
        t = time.perf_counter()
        subprocess.run([sys.executable, "-m", "nbvh_core", "compress", name, "-o", str(folder / f"{name}.nbvh"),
                        "--preset", args.preset, "--force", "--events"], check=True, stdout=subprocess.DEVNULL)
        wall[name] = round(time.perf_counter() - t, 1)
    summarise(folder, args.preset, wall)


if __name__ == "__main__":
    main()
