"""Speed of the neural path: fast (fused kernels) against reference (pure torch) and Embree, in one run.

    .venv/bin/python -m bench.speed.bench_speed [--asset bunny] [--train-s 60] [--quick] [--device cpu|cuda]

1. Trains one model with the preset (default: `default`) on the fast path for --train-s seconds, so that rays end at
   realistic leaves (a random model stops rays arbitrarily).
2. Training throughput: the same steps (same seed and rays) on each path, leaf samples/s (median step time).
3. Rendering: 512x512 and 1000x1000 images from one orbit view on each path (same model): seconds, rays/s, leaf
   segments/s, and Embree's first hits on the same primary rays (our embreex wrapper, normals included).
4. Arithmetic limit: FLOPs per segment of the model (`NeuralBVH.flops_per_segment`) against the measured peak of
   a large float32 matrix multiply (torch.mm 4096^3) in the same run: limit segments/s = peak / FLOPs per segment.

Writes bench/results/speed.md, speed.csv, speed.png (or speed_quick.* with --quick).
"""
from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]

from nbvh_core import kernels
from nbvh_core.geometry.bvh import build_bvh
from nbvh_core.geometry.exact import ExactTracer
from nbvh_core.geometry.mesh import load_mesh
from nbvh_core.kernels.plan import CARD_LABELS_ENV, TRAINING_LAYERS_ENV
from nbvh_core.neural.model import NeuralBVH
from nbvh_core.app.pipeline import preset
from nbvh_core.planning.card_batch import rays_per_step as card_rays_per_step
from nbvh_core.rendering.render import orbit_cameras
from nbvh_core.geometry.bundled_samples import sample_path
from nbvh_core.training.train import train
from bench.harness import RESULTS, save_figure, write_markdown, write_rows


def matmul_peak_gflops(device: torch.device, n: int = 4096, repeat: int = 5) -> float:
    a, b = torch.randn(n, n, device=device), torch.randn(n, n, device=device)
    for _ in range(2):
        a @ b
    sync(device)
    t = time.perf_counter()
    for _ in range(repeat):
        a @ b
    sync(device)
    return 2 * n ** 3 * repeat / (time.perf_counter() - t) / 1e9


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


def fresh_training(bvh, s, mesh, device, steps: int, rays_per_step: int | None = None) -> tuple:
    """A fresh model of preset `s` (seed 0) and its training config for `steps` steps on `device`, at
    `rays_per_step` (None: the product's batch on this device)."""
    torch.manual_seed(0)
    m = NeuralBVH(bvh.nodes, s.model_config(), mesh.transform)
    cfg = s.train_config()
    cfg.steps, cfg.time_limit_s, cfg.device = steps, None, str(device)
    cfg.rays_per_step = rays_per_step or card_rays_per_step(str(device))
    return m, cfg


def train_throughput(bvh, tracer, s, mesh, device, steps: int, rays_per_step: int | None = None) -> dict:
    """The real training loop (`train.train`) for `steps` steps from a fresh model on the current path: a 'train'
    row (leaf samples/s, seconds, the path it recorded, the batch, the share of batches a card's spare passes
    served again). Same seed, so both paths see the same rays."""
    m, cfg = fresh_training(bvh, s, mesh, device, steps, rays_per_step)
    res = train(m, bvh, tracer, cfg)
    return {"what": "train", "path": res.compute_path, "size": "", "seconds": res.seconds, "items": steps,
            "per_s": res.samples_per_s, "unit": "leaf samples/s", "rays_per_step": cfg.rays_per_step,
            "reused_share": round(res.reused_batches / max(1, res.steps), 3),
            "layers": kernels.training_layers_kernel(m.network.net, device), "labels": kernels.label_kernel(device)}


def host_syncs(bvh, tracer, s, mesh, device, steps: int) -> dict:
    """A card's training for `steps` steps under torch's sync debug mode: the operations that made the host wait for
    the card (a 'syncs' row: per step, and the first few call sites). Apart from the throughput runs: the mode's
    warnings cost time. The loop reads its loss every 16 steps and checks its units every 50: ~0.08 per step."""
    import warnings

    m, cfg = fresh_training(bvh, s, mesh, device, steps)
    sites: list[str] = []

    def note(message, category, filename, lineno, file=None, line=None):
        if "synchroniz" in str(message):  # torch names the Python line that asked
            sites.append(f"{Path(filename).name}:{lineno}")

    with warnings.catch_warnings():
        warnings.simplefilter("always")
        warnings.showwarning = note
        torch.cuda.set_sync_debug_mode("warn")
        try:
            res = train(m, bvh, tracer, cfg)
        finally:
            torch.cuda.set_sync_debug_mode("default")
    common = sorted(set(sites), key=sites.count, reverse=True)[:3]
    return {"what": "syncs", "path": res.compute_path, "size": "", "seconds": res.seconds, "items": steps,
            "per_s": round(len(sites) / max(1, steps), 4), "unit": "host syncs per step",
            "rays_per_step": cfg.rays_per_step, "sync_sites": "; ".join(common)}


def train_rows(bvh, tracer, s, mesh, device, args) -> list[dict]:
    """Training rates: each path at the device's batch, then the fast path at each batch of --batch-ladder (what a
    step's fixed cost leaves)."""
    rows = []
    for path in kernels.PATHS:
        with kernels.using_path(path):
            rows.append(train_throughput(bvh, tracer, s, mesh, device, args.steps))
        print(rows[-1], flush=True)
    for rays in args.batch_ladder:
        rows.append(train_throughput(bvh, tracer, s, mesh, device, args.steps, rays))
        print(rows[-1], flush=True)
    if device.type == "cuda":
        try:  # a count, not a figure the rest depends on: its failure is its row's
            rows.append(host_syncs(bvh, tracer, s, mesh, device, 64))
        except Exception as exc:
            rows.append({"what": "syncs", "path": "", "size": "", "seconds": "", "items": 64, "per_s": "",
                         "unit": "host syncs per step", "sync_sites": f"not counted: {exc}"[:200]})
        print(rows[-1], flush=True)
    # the same steps with one of the card's choices undone, for the choice: torch's layers (cuBLAS under autograd)
    # instead of the Triton MLP's; labels made on the host instead of the card
    for undone, env, value in ((rows[0]["layers"] == "triton", TRAINING_LAYERS_ENV, "torch"),
                               (rows[0]["labels"] == "card", CARD_LABELS_ENV, "host")):
        if undone:
            os.environ[env] = value
            try:
                rows.append(train_throughput(bvh, tracer, s, mesh, device, args.steps))
            finally:
                del os.environ[env]
            print(rows[-1], flush=True)
    return rows


def render_time(model, o, d, device, repeat: int):
    """Best-of-`repeat` seconds to query all rays, and the last query's result (`QueryResult`)."""
    best, q = float("inf"), None
    for _ in range(repeat):
        sync(device)
        t = time.perf_counter()
        q = model.query(o, d)
        sync(device)
        best = min(best, time.perf_counter() - t)
    return best, q


def agreement(q, ref) -> dict:
    """How a path's first hits agree with the reference path's on the same rays: the share of rays whose hit
    decision is the same, and the largest |t| difference (model units) where both hit."""
    both = q.hit & ref.hit
    t_err = float((q.t[both] - ref.t[both]).abs().max()) if bool(both.any()) else 0.0
    return {"hit_agreement": float((q.hit == ref.hit).float().mean()), "t_max_error": t_err}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--asset", default="bunny")
    ap.add_argument("--preset", default="default")
    ap.add_argument("--train-s", type=float, default=60.0)
    ap.add_argument("--steps", type=int, default=150, help="training steps per path for the throughput")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--quick", action="store_true", help="smoke run: tiny budgets, 128x128 renders")
    ap.add_argument("--batch-ladder", nargs="*", type=int, default=[],
                    help="also the fast path's training rate at these rays per step (e.g. 2048 8192 32768 131072)")
    args = ap.parse_args()
    kernels.keep_freed_memory()  # as the CLI does: freed blocks stay in the heap (see the function)
    device = torch.device(args.device)
    if args.quick:
        args.train_s, args.steps = min(args.train_s, 5.0), 10
    sizes = (128,) if args.quick else (512, 1000)
    mesh = load_mesh(sample_path(args.asset))
    s = preset(args.preset)
    bvh = build_bvh(mesh, s.nodes)
    tracer = ExactTracer(mesh)
    peak = matmul_peak_gflops(device)
    torch.manual_seed(0)
    model = NeuralBVH(bvh.nodes, s.model_config(), mesh.transform)
    tc = s.train_config()
    tc.steps, tc.time_limit_s, tc.device = None, args.train_s, args.device
    tc.rays_per_step = card_rays_per_step(args.device)
    with kernels.using_path("fast"):
        tr = train(model, bvh, tracer, tc)
    model.eval()
    flops = model.flops_per_segment()
    per_seg = sum(flops.values())
    rows = train_rows(bvh, tracer, s, mesh, device, args)
    cam = orbit_cameras(4)[1]
    for size in sizes:
        o_np, d_np = cam.rays(size, size)
        o, d = torch.from_numpy(o_np).to(device), torch.from_numpy(d_np).to(device)
        results = {}
        for path in kernels.PATHS:
            with kernels.using_path(path):
                sec, q = render_time(model, o, d, device, 1 if (path == "reference" and size > 512) else 3)
                used = kernels.describe(device) + f", query {kernels.query_kernel(model, device)}"
            results[path] = q
            hits, segs = int(q.hit.sum()), q.leaves_evaluated
            rows.append({"what": "render", "path": used, "size": size, "seconds": sec,
                         "items": size * size, "per_s": size * size / sec, "unit": "rays/s", "segments": segs,
                         "segments_per_s": segs / sec, "gflops": segs * per_seg / sec / 1e9, "hits": hits})
            print(rows[-1], flush=True)
        rows[-len(kernels.PATHS)].update(agreement(results["fast"], results["reference"]))
        if device.type == "cpu":
            model.half_tables = True
            sec, q = render_time(model, o, d, device, 3)
            hits, segs = int(q.hit.sum()), q.leaves_evaluated
            model.half_tables = False
            rows.append({"what": "render", "path": kernels.describe(device) + ", float16 tables", "size": size,
                         "seconds": sec, "items": size * size, "per_s": size * size / sec, "unit": "rays/s",
                         "segments": segs, "segments_per_s": segs / sec, "gflops": segs * per_seg / sec / 1e9,
                         "hits": hits})
            print(rows[-1], flush=True)
        best = float("inf")
        for _ in range(3):
            t = time.perf_counter()
            fh = tracer.first_hit(o_np, d_np)
            best = min(best, time.perf_counter() - t)
        rows.append({"what": "render", "path": f"Embree ({tracer.scene_kind}, CPU)", "size": size, "seconds": best,
                     "items": size * size, "per_s": size * size / best, "unit": "rays/s", "hits": int(fh.hit.sum())})
        print(rows[-1], flush=True)
    from nbvh_core.rendering.metrics import evaluate

    q32, _ = evaluate(model, tracer, 16, 128)
    model.half_tables = True
    q16, _ = evaluate(model, tracer, 16, 128)
    model.half_tables = False
    half_note = (f"float16 feature rows (inference only, `NeuralBVH.half_tables`): image MSE {q16.mse:.6f} vs "
                 f"{q32.mse:.6f} with float32 rows, silhouette IoU {q16.silhouette_iou:.4f} vs {q32.silhouette_iou:.4f} "
                 "(16 orbit views at 128 px, same model).")
    print(half_note)
    write(rows, args, mesh, s, tr, flops, peak, device, half_note)


def write(rows, args, mesh, s, tr, flops, peak, device, half_note: str = "") -> None:
    suffix = "_quick" if args.quick else ""
    out = RESULTS
    out.mkdir(parents=True, exist_ok=True)
    keys = ["what", "path", "size", "seconds", "items", "per_s", "unit", "segments", "segments_per_s", "gflops", "hits",
            "rays_per_step", "reused_share", "layers", "sync_sites"]
    write_rows(out / f"speed{suffix}.csv", [{k: r.get(k, "") for k in keys} for r in rows])
    per_seg = sum(flops.values())
    limit = peak * 1e9 / per_seg
    fast_train = next(r for r in rows if r["what"] == "train" and r["path"].startswith("fast"))
    ref_train = next(r for r in rows if r["what"] == "train" and r["path"].startswith("reference"))
    dev_name = torch.cuda.get_device_name(device) if device.type == "cuda" else f"{platform.machine()} CPU, {torch.get_num_threads()} threads"
    lines = [f"# Speed: fast path vs reference path vs Embree ({args.asset}, preset `{args.preset}`)\n",
             f"Device: {dev_name}; torch {torch.__version__}. Command: `.venv/bin/python -m bench.speed.bench_speed "
             f"--asset {args.asset} --preset {args.preset} --train-s {args.train_s:g}"
             + (" --quick" if args.quick else "") + (f" --device {args.device}" if args.device != "cpu" else "") + "`.",
             f"Model: {mesh.n_triangles:,}-triangle mesh, {s.nodes} nodes, {s.encoding}+{s.network}, T=2^{s.log2_table}, "
             f"trained {tr.seconds:.0f} s on the fast path ({tr.steps} steps, {tr.samples_per_s:,.0f} samples/s).\n",
             f"## Training (the real loop, `train.train`, {args.steps} steps from a fresh model, same seed and rays on "
             "both paths)\n",
             "| path | rays/step | steps | seconds | leaf samples/s | batches served again |", "|---|---|---|---|---|---|"]
    for r in rows:
        if r["what"] == "train":
            lines.append(f"| {r['path']} | {r['rays_per_step']:,} | {r['items']} | {r['seconds']:.1f} | "
                         f"{r['per_s']:,.0f} | {r['reused_share']:.0%} |")
    lines.append(f"\n**Fast / reference training speed: {fast_train['per_s'] / ref_train['per_s']:.1f}x** (same run).\n")
    lines += [f"Host syncs per step on the card (torch's sync debug mode, {r['items']} steps): {r['per_s']} "
              f"(most at {r['sync_sites'] or 'none'}).\n" for r in rows if r["what"] == "syncs"]
    lines += ["## Rendering (one orbit view, same model; best of 3, reference 1000x1000 once)\n",
              "| size | path | seconds | rays/s | segments | segments/s | GFLOP/s | % of limit |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if r["what"] == "render":
            if "segments" in r:
                lines.append(f"| {r['size']}x{r['size']} | {r['path']} | {r['seconds']:.3f} | {r['per_s']:,.0f} | "
                             f"{r['segments']:,} | {r['segments_per_s']:,.0f} | {r['gflops']:.1f} | "
                             f"{100 * r['segments_per_s'] / limit:.0f}% |")
            else:
                lines.append(f"| {r['size']}x{r['size']} | {r['path']} | {r['seconds']:.3f} | {r['per_s']:,.0f} | | | | |")
    lines.append(f"\n{half_note}")
    for size in sorted({r["size"] for r in rows if r["what"] == "render"}):
        f_ = next(r for r in rows if r["what"] == "render" and r["size"] == size and r["path"].startswith("fast"))
        r_ = next(r for r in rows if r["what"] == "render" and r["size"] == size and r["path"].startswith("reference"))
        e_ = next(r for r in rows if r["what"] == "render" and r["size"] == size and r["path"].startswith("Embree"))
        lines.append(f"\n{size}x{size}: fast / reference **{r_['seconds'] / f_['seconds']:.1f}x**; fast / Embree "
                     f"{f_['per_s'] / e_['per_s']:.3f}x (Embree {e_['per_s'] / f_['per_s']:.0f}x faster).")
    lines += ["\n## Arithmetic limit\n",
              f"FLOPs per leaf segment: encoding {flops['encoding']:,} (k x L x 8 corners x F multiply-adds; hash "
              f"arithmetic not counted) + network {flops['network']:,} (all Linear layers) = {per_seg:,}. Measured "
              f"float32 matmul peak (torch.mm 4096^3, same run): {peak:.0f} GFLOP/s, so the limit is "
              f"{limit:,.0f} segments/s; the % column above is segments/s over that limit (whole query: traversal, "
              "encoding, network and bookkeeping included)."]
    write_markdown(out / f"speed{suffix}.md", lines)
    chart(rows, out / f"speed{suffix}.png")
    print("\n".join(lines))


def chart(rows, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    renders = [r for r in rows if r["what"] == "render"]
    sizes = sorted({r["size"] for r in renders})
    fig, ax = plt.subplots(figsize=(7, 3.6))
    names = ["reference", "fast", "float16", "Embree"]
    for i, name in enumerate(names):
        vals = [next((r["per_s"] for r in renders if r["size"] == s and (name in r["path"] if name == "float16" else
                      r["path"].startswith(name) and "float16" not in r["path"])), 0) for s in sizes]
        ax.bar(np.arange(len(sizes)) + (i - 1.5) * 0.2, vals, 0.2, label=name)
    ax.set_yscale("log")
    ax.set_xticks(range(len(sizes)), [f"{s}x{s}" for s in sizes])
    ax.set_ylabel("primary rays/s (log)")
    ax.set_title("Neural render: reference vs fast path vs Embree (same run)")
    ax.legend()
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)


if __name__ == "__main__":
    main()
