"""Where a model's image error comes from: silhouette, depth or normals (the same 16 views and 128 px as the metric).

    .venv/bin/python -m bench.quality.error_split terrain --preset default --steps 1000 [--set normal_loss=facing ...]

Trains one model (float32 storage, a fixed step count) and splits the shaded image's squared error per pixel:
silhouette = pixels where exactly one of the reference and the model hits; of the pixels both hit, the normal part is
what swapping the reference normal in removes, the depth part what is left (the hit point moves the light
direction). Also the share of both-hit pixels whose normal is off by more than 18 degrees (cos < 0.95), both turned
toward the viewer. Found KMLP's starved normal term and the facing targets' failure on open surfaces.
"""
from __future__ import annotations

import argparse
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

import numpy as np
import torch

from bench.meshes import bench_mesh
from nbvh_core import kernels
from nbvh_core.app.pipeline import compress_mesh, preset
from nbvh_core.rendering.render import orbit_cameras, shade


def parse_value(text: str):
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def error_split(model, tracer, views: int = 16, res: int = 128) -> dict[str, float]:
    """{'mse', 'silhouette', 'depth', 'normal' (parts of the MSE, summing to it), 'normals_off' (share of both-hit
    pixels whose normal is > 18 degrees off)} over `views` orbit views at res x res."""
    parts = dict(mse=0.0, silhouette=0.0, depth=0.0, normal=0.0)
    cos_all = []
    for cam in orbit_cameras(views):
        o, d = cam.rays(res, res)
        ref = tracer.first_hit(o, d)
        with torch.no_grad():
            q = model.query(torch.from_numpy(o), torch.from_numpy(d))
        hit, t, n = q.hit.numpy(), q.t.numpy(), q.normal.numpy()
        err = (shade(o, d, ref.hit, ref.t, ref.normal) - shade(o, d, hit, t, n)) ** 2
        both = ref.hit & hit
        n_ref = n.copy()
        n_ref[both] = ref.normal[both]
        err_ref_normal = (shade(o, d, ref.hit, ref.t, ref.normal) - shade(o, d, hit, t, n_ref)) ** 2
        parts["mse"] += err.mean() / views
        parts["silhouette"] += err[ref.hit != hit].sum() / err.size / views
        parts["depth"] += err_ref_normal[both].sum() / err.size / views
        parts["normal"] += (err[both].sum() - err_ref_normal[both].sum()) / err.size / views
        a = ref.normal[both] / np.linalg.norm(ref.normal[both], axis=1, keepdims=True)
        a = np.where((a * d[both]).sum(1, keepdims=True) > 0, -a, a)
        b = n[both] / np.maximum(np.linalg.norm(n[both], axis=1, keepdims=True), 1e-12)
        b = np.where((b * d[both]).sum(1, keepdims=True) > 0, -b, b)
        cos_all.append((a * b).sum(1))
    cos = np.concatenate(cos_all)
    parts["normals_off"] = float(np.mean(cos < 0.95)) if cos.size else 0.0
    return parts


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mesh")
    ap.add_argument("--preset", default="default")
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE", help="settings overrides")
    args = ap.parse_args()
    kernels.keep_freed_memory()
    extra = {k: parse_value(v) for k, v in (item.split("=", 1) for item in args.set)}
    s = preset(args.preset).with_overrides(steps=args.steps, table_bits=32, network_bits=32, node_bits=32,
                                           force=True, **extra)
    s.time_limit_s = None
    res = compress_mesh(bench_mesh(args.mesh), s, None)
    p = error_split(res.model, res.tracer)
    print(f"{args.mesh} {args.preset} {' '.join(args.set)}: {res.training.steps} steps, MSE {p['mse']:.5f} = "
          f"silhouette {p['silhouette']:.5f} + depth {p['depth']:.5f} + normal {p['normal']:.5f}; normals > 18 deg "
          f"off on {100 * p['normals_off']:.1f}% of both-hit pixels; IoU {res.quality.silhouette_iou:.4f}")


if __name__ == "__main__":
    main()
