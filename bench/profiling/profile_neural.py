"""Where the time goes: one training step and one neural render, split by stage, for each config.

    .venv/bin/python -m bench.profiling.profile_neural [--asset bunny] [--rays 4096] [--size 256] [--paths reference,fast]

Training step stages: ray sampling + exact labelling (Embree, traversal), encoding forward, network forward +
loss, backward (all of it), optimizer step. Render stages: traversal (LeafStream.next), segment points +
encoding, network, bookkeeping (the rest). On the fast path an MLP model also gets a "fused" row: what training and
`NeuralBVH.query` really run there (neural/fused_mlp.py: encoding, network, loss and backward in one kernel call, so
those stages are one number). Medians of several repeats. Writes bench/results/profile.md.
"""
from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]

from nbvh_core import kernels
from nbvh_core.geometry.bvh import build_bvh
from nbvh_core.geometry.exact import ExactTracer
from nbvh_core.geometry.mesh import load_mesh
from nbvh_core.neural.model import NeuralBVH
from nbvh_core.app.pipeline import preset
from nbvh_core.rendering.render import orbit_cameras
from nbvh_core.training.rays import RayConfig, label_samples, root_box, sample_rays
from nbvh_core.geometry.bundled_samples import sample_path
from nbvh_core.geometry.traversal import LeafStream, TorchBVH
from bench.harness import RESULTS, write_markdown

CONFIGS = [("hashgrid", "mlp", 11), ("hashgrid", "kmlp", 11), ("hashvqad", "mlp", 10), ("hashvqad", "kmlp", 10)]


def timed(fn):
    t = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t


def profile_train(model, bvh, tracer, tree, n_rays, repeat=5, fused=False):
    """Median seconds per stage of a training step. fused: the fused step (fused_mlp.train_step: encoding,
    network, loss and backward in one call; torch's fused Adam as train() uses there)."""
    from nbvh_core.neural import fused_mlp as mlp

    rng = np.random.default_rng(0)
    lo, hi = root_box(bvh)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3, fused=fused or None)
    names = ("rays+labels", "fused", "optimizer") if fused else \
        ("rays+labels", "encoding fwd", "network fwd+loss", "backward", "optimizer")
    stages = {k: [] for k in names}
    n_samples = []
    for _ in range(repeat):
        s, dt = timed(lambda: label_samples(bvh, tracer, *sample_rays(lo, hi, n_rays, rng, RayConfig()),
                                            "consistent", tree=tree))
        stages["rays+labels"].append(dt)
        n_samples.append(len(s))
        if fused:
            opt.zero_grad(set_to_none=True)
            _, dt = timed(lambda: mlp.train_step(model, s))
            stages["fused"].append(dt)
        else:
            r = s.ray
            pts = model.segment_points(s.rays_o[r], s.rays_d[r], s.t_enter, s.t_exit)
            b, k, _ = pts.shape
            feats, dt = timed(lambda: model.encoding(pts.reshape(-1, 3)).reshape(b, k, -1))
            stages["encoding fwd"].append(dt)
            (loss, _), dt = timed(lambda: model.network.loss(model.network(feats), s.hit, s.local_t, s.normal))
            stages["network fwd+loss"].append(dt)
            opt.zero_grad()
            _, dt = timed(loss.backward)
            stages["backward"].append(dt)
        _, dt = timed(opt.step)
        stages["optimizer"].append(dt)
    med = {k: statistics.median(v) for k, v in stages.items()}
    return med, statistics.median(n_samples)


def profile_render(model, size, fused=False):
    """Seconds per stage of one render. fused: NeuralBVH.query's fast path for MLP models (one kernel call per
    wave: encoding + network, reported as 'fused')."""
    cam = orbit_cameras(1)[0]
    o, d = (torch.from_numpy(a) for a in cam.rays(size, size))
    packed = model._fused_network() if fused else None
    stream = LeafStream(model.tree(), o, d)
    t = {"traversal": 0.0, "encoding": 0.0, "network": 0.0, "fused": 0.0}
    segments = 0
    t0 = time.perf_counter()
    with torch.no_grad():
        while True:
            (ray, _, te, tx), dt = timed(stream.next)
            t["traversal"] += dt
            if ray.numel() == 0:
                break
            segments += ray.numel()
            if fused:
                raw, dt = timed(lambda: model._fused_raw(packed, o, d, ray, te, tx))
                t["fused"] += dt
                prob = model.network.decode(raw)[0]
            else:
                pts = model.segment_points(o[ray], d[ray], te, tx)
                b, k, _ = pts.shape
                feats, dt = timed(lambda: model.encoding(pts.reshape(-1, 3)).reshape(b, k, -1))
                t["encoding"] += dt
                (prob, _, _), dt = timed(lambda: model.network.decode(model.network(feats)))
                t["network"] += dt
            stream.stop(ray[prob > 0.5])
    total = time.perf_counter() - t0
    t["bookkeeping"] = total - sum(t.values())
    t["total"] = total
    return t, segments


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--asset", default="bunny")
    ap.add_argument("--rays", type=int, default=4096)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--paths", default="reference,fast", help="comma-separated: reference, fast")
    ap.add_argument("--out", default=str(RESULTS / "profile.md"))
    args = ap.parse_args()
    kernels.keep_freed_memory()  # as the CLI does: freed blocks stay in the heap (see the function)
    paths = args.paths.split(",")
    mesh = load_mesh(sample_path(args.asset))
    s = preset("default")
    bvh = build_bvh(mesh, s.nodes)
    tracer = ExactTracer(mesh)
    tree = TorchBVH.from_bvh(bvh)
    lines = [f"# Profile: one training step and one {args.size}x{args.size} render, by stage\n",
             f"Asset `{args.asset}` ({mesh.n_triangles:,} triangles), {s.nodes} nodes, {args.rays} rays per step, "
             f"2-core CPU, torch {torch.__version__} ({torch.get_num_threads()} threads); paths: "
             + "; ".join(f"{p} = {kernels.describe() if p == 'fast' else 'reference (pure torch)'}" for p in paths) + ". "
             "Models are untrained (random weights), so which leaf stops a ray is arbitrary: the render rows show the "
             "cost split per segment, not a trained model's rays/s (see samples_default.md for those). Command: "
             f"`.venv/bin/python -m bench.profiling.profile_neural --asset {args.asset}`.\n",
             "## Training step (median of 5)\n",
             "| config | path | samples | rays+labels | encoding fwd | network fwd+loss | backward | optimizer | total | samples/s |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    render_lines = ["\n## Render\n", "| config | path | segments | traversal | encoding | network | bookkeeping | total | rays/s | segments/s |",
                    "|---|---|---|---|---|---|---|---|---|---|"]
    for (enc, net, log2), path in ((c, p) for c in CONFIGS for p in paths):
        with kernels.using_path(path):
            torch.manual_seed(0)
            model = NeuralBVH(bvh.nodes, s.with_overrides(encoding=enc, network=net, log2_table=log2).model_config(),
                              mesh.transform)
            med, n = profile_train(model, bvh, tracer, tree, args.rays)
            total = sum(med.values())
            lines.append(f"| {enc}+{net} (T=2^{log2}) | {path} | {n:,.0f} | " + " | ".join(f"{1000 * v:.0f} ms" for v in med.values())
                         + f" | {1000 * total:.0f} ms | {n / total:,.0f} |")
            if enc == "hashvqad":
                model.encoding.freeze()
            model.eval()
            rt, segs = profile_render(model, args.size)
            render_lines.append(f"| {enc}+{net} | {path} | {segs:,} | " + " | ".join(f"{1000 * rt[k]:.0f} ms" for k in
                                                                         ("traversal", "encoding", "network", "bookkeeping", "total"))
                                + f" | {args.size ** 2 / rt['total']:,.0f} | {segs / rt['total']:,.0f} |")
            print(lines[-1], render_lines[-1], flush=True)
            if path == "fast" and model._fused_network() is not None:
                torch.manual_seed(0)
                model = NeuralBVH(bvh.nodes, s.with_overrides(encoding=enc, network=net, log2_table=log2).model_config(),
                                  mesh.transform)
                med, n = profile_train(model, bvh, tracer, tree, args.rays, fused=True)
                total = sum(med.values())
                lines.append(f"| {enc}+{net} (T=2^{log2}) | fast, fused step | {n:,.0f} | {1000 * med['rays+labels']:.0f} ms "
                             f"| fused: {1000 * med['fused']:.0f} ms (encoding, network, loss, backward) | | | "
                             f"{1000 * med['optimizer']:.0f} ms | {1000 * total:.0f} ms | {n / total:,.0f} |")
                if enc == "hashvqad":
                    model.encoding.freeze()  # as the other render rows (and every saved model)
                model.eval()
                rt, segs = profile_render(model, args.size, fused=True)
                render_lines.append(f"| {enc}+{net} | fast, fused query | {segs:,} | {1000 * rt['traversal']:.0f} ms | "
                                    f"fused: {1000 * rt['fused']:.0f} ms (encoding + network) | | "
                                    f"{1000 * rt['bookkeeping']:.0f} ms | {1000 * rt['total']:.0f} ms | "
                                    f"{args.size ** 2 / rt['total']:,.0f} | {segs / rt['total']:,.0f} |")
                print(lines[-1], render_lines[-1], flush=True)
    out = Path(args.out)
    write_markdown(out, lines + render_lines)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
