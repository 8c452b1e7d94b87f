"""The appearance head alone, on exact surface labels: how fast it trains on a device and how well its patches and
coordinates land (no geometry model: what the head can do, apart from the geometry's error).

    .venv/bin/python -m bench.look.bench_look_head [--assets globe,ring,crate] [--seconds 9] [--device cpu|cuda]
                                              [--batch 1024 8192]

For each generated asset (`nbvh_core.geometry.demo_assets`): the head the product makes for it (default
`AppearanceConfig`), trained `--seconds` on a pool of 32k exact labels (`train_head`, as a run does), stored at 8-bit
table / float16 weights (`finalize_head`), then scored on 20,000 fresh exact labels: the patch right, and coordinates
within half a 512 px texel, away from UV seams (> 1% of the asset's size) on slots that sample an image.

Rows append to bench/results/look_head.csv (stamped; the device named in the row).
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from bench.harness import RESULTS, SMOKE, append_rows
from nbvh_core.geometry import demo_assets
from nbvh_core.geometry.exact import ExactTracer
from nbvh_core.geometry.uv_patches import seam_distance, seam_edges
from nbvh_core.neural.appearance import AppearanceConfig, finalize_head, make_head
from nbvh_core.training.appearance_training import SurfaceLabels, train_head

OUT = RESULTS / "look_head.csv"
TEXELS = 512


def run_asset(name: str, seconds: float, device: str, batch: int) -> dict:
    torch.manual_seed(0)
    mesh = demo_assets.ASSETS[name]()
    tracer = ExactTracer(mesh)
    head, face_patch = make_head(mesh, AppearanceConfig())
    head = head.to(device)
    labels = SurfaceLabels(mesh, tracer, np.random.default_rng(0), face_patch)
    t0 = time.perf_counter()
    trained = train_head(head, labels, seconds=seconds, batch=batch, pool_size=1 << 14 if SMOKE else 1 << 15)
    wall = time.perf_counter() - t0
    finalize_head(head, 8, 16)
    p, patch, uv = SurfaceLabels(mesh, tracer, np.random.default_rng(1), face_patch).draw(2_000 if SMOKE else 20_000)
    points = torch.from_numpy(p).to(device)
    with torch.no_grad():
        logits, residual = head(points)
        chosen = logits.argmax(1) if logits is not None else torch.zeros(len(p), dtype=torch.int64, device=device)
    row = {"asset": name, "device": device, "batch": batch, "triangles": mesh.n_triangles, "patches": head.cfg.patches,
           "mapped_patches": head.cfg.mapped_patches, "patch_degree": head.cfg.patch_degree,
           "seconds": round(wall, 2), "steps": trained.steps, "steps_per_s": round(trained.steps / max(wall, 1e-9), 1),
           "patch_right": round(float((chosen.cpu().numpy() == patch).mean()), 4)}
    if uv is not None:
        _, predicted = head.predict(points)
        sampled = mesh.look.image_slots[head.patch_slot.cpu().numpy()[patch]]
        away = seam_distance(p, seam_edges(mesh.vertices, mesh.faces, mesh.look.corner_uvs)) > 0.01
        texels = np.abs(predicted - uv).max(1)[away & sampled] * TEXELS
        row.update(uv_half_texel=round(float((texels < 0.5).mean()), 4),
                   uv_median_texels=round(float(np.median(texels)), 4))
    return row


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--assets", default="globe,ring,crate")
    ap.add_argument("--seconds", type=float, default=9.0, help="the head's training budget (a preview run gives 9 s)")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--batch", type=int, nargs="+", default=[1 << 10], help="labels a step (train_head's default: 1,024)")
    args = ap.parse_args()
    for batch in args.batch:
        for name in args.assets.split(","):
            row = run_asset(name, args.seconds, args.device, batch)
            append_rows(OUT, [row])
            print(row, flush=True)


if __name__ == "__main__":
    main()
