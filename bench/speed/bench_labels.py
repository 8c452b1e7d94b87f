"""What exact training labels cost on the host, by thread count: the exact tracer's first hits on random rays and
the training's whole labelling (rays drawn, first hits, the leaves each ray enters, all hits inside them), against
the samples per second a training step consumes. A card trains only as fast as the host labels, unless it reuses
labels (`Settings.label_reuse`, a card's spare passes): this says how far apart the two rates are on a machine.

    .venv/bin/python -m bench.speed.bench_labels [--assets bunny dragon] [--threads 1 2 4 8 16] [--chunks 5]

Per asset: the exact tracer's build seconds and the resident memory it added (VmRSS before and after), then per
thread count (the kernels' OpenMP threads, `torch.set_num_threads`; Embree's queries through embreex use up to 8)
the median over `--chunks` labelling chunks of the default preset's size (2,048 rays x 32 steps): the draw's (in as
many parts as threads, at least 2, as a card's host draws) and the labels' seconds, first-hit rays/s, label
samples/s (drawn and labelled); the same streamed as a card's training takes them (`Batches` labelling ahead, pinned
where there is a card), by one labelling thread and by the card's count for that many cores (`label_workers`); then
the default preset's training on the host's CPU at that many threads (`--train-steps`): how a many-core CPU scales.
On a card, the same chunks drawn by that many threads and labelled on the card (`training/card_labels.py`): label
samples/s, the card tracer's first-hit rays/s and the samples/s streamed to a training.
Writes bench/results/labels.csv and labels.md (the device check writes its own under bench/results/gpu/).
"""
from __future__ import annotations

import argparse
import os
import statistics
import time

import numpy as np
import torch

from bench.harness import RESULTS, SMOKE, markdown_table, write_markdown, write_rows
from bench.meshes import named_mesh
from nbvh_core.app.pipeline import preset
from nbvh_core.geometry.bvh import build_bvh
from nbvh_core.geometry.exact import ExactTracer
from nbvh_core.protocol.memory import return_free_memory
from nbvh_core.training.ray_batches import Batches, chunk_steps, label_workers
from nbvh_core.neural.model import NeuralBVH
from nbvh_core.training.rays import label_samples
from nbvh_core.training.train import train

OUT = RESULTS / ("labels_smoke.csv" if SMOKE else "labels.csv")


def resident_bytes() -> int:
    """This process's resident memory now (VmRSS), 0 where /proc is missing."""
    try:
        for line in open("/proc/self/status"):
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def chunk_costs(bvh, tracer, cfg, threads: int, chunks: int) -> dict:
    """Median seconds of the draw, the first hits and the labels over `chunks` chunks at `threads` threads (the
    first, which warms caches, not counted), and the samples per chunk."""
    torch.set_num_threads(threads)
    batches = Batches(bvh, tracer, cfg, np.random.default_rng(0), draw_parts=max(2, threads))  # as a card's host
    n_rays = cfg.rays_per_step * cfg.label_steps
    times: dict[str, list] = {"draw": [], "first": [], "label": [], "samples": []}
    for _ in range(chunks + 1):
        t = time.perf_counter()
        o, d = batches._draw(n_rays)
        t_drawn = time.perf_counter()
        tracer.first_hit(o, d)
        t_first = time.perf_counter()
        got = label_samples(bvh, tracer, o, d, cfg.labels, tree=batches.tree, normal_loss=cfg.normal_loss)
        for key, value in (("draw", t_drawn - t), ("first", t_first - t_drawn),
                           ("label", time.perf_counter() - t_first), ("samples", len(got))):
            times[key].append(value)
    batches.close()
    return {k: statistics.median(v[1:]) for k, v in times.items()} | {"draw_parts": batches.draw_parts}


def stream_rate(bvh, tracer, cfg, threads: int, workers: int, chunks: int) -> float:
    """Label samples/s as a card's training takes them at `threads` threads: `workers` labelling threads ahead of a
    consumer that takes each batch at once, over `chunks` chunks after the first."""
    torch.set_num_threads(threads)
    batches = Batches(bvh, tracer, cfg, np.random.default_rng(0), prefetch=True, pin=torch.cuda.is_available(),
                      draw_parts=max(2, threads), label_workers=workers)
    try:
        for _ in range(chunk_steps(cfg)):  # the first chunk: its wait is the pool's start, not its pace
            batches.next()
        t, samples = time.perf_counter(), 0
        for _ in range(chunk_steps(cfg) * chunks):
            samples += len(batches.next())
        return samples / (time.perf_counter() - t)
    finally:
        batches.close()


def card_costs(bvh, tracer, cfg, threads: int, chunks: int, device: str | None = None) -> dict:
    """On a card: label samples/s of chunks drawn by `threads` host threads and labelled on the card (median over
    `chunks` after the first, which compiles the kernels), the card tracer's first-hit rays/s, and the samples/s
    streamed to a training (one labelling thread ahead, as the training runs it); {} without a card. device: 'cpu'
    runs the same under Triton's interpreter (its test)."""
    from nbvh_core.training.card_labels import CardLabels

    device = device or ("cuda" if torch.cuda.is_available() else None)
    if device is None:
        return {}

    def sync():
        if device == "cuda":
            torch.cuda.synchronize()

    torch.set_num_threads(threads)
    card = CardLabels(tracer.on_card(device, getattr(bvh, "full", None)))
    batches = Batches(bvh, tracer, cfg, np.random.default_rng(0), draw_parts=max(2, threads))
    n_rays = cfg.rays_per_step * chunk_steps(cfg)
    times: dict[str, list] = {"draw": [], "label": [], "samples": [], "first": []}
    for _ in range(chunks + 1):  # the first compiles the kernels: not counted
        t_start = time.perf_counter()
        o, d = batches._draw(n_rays)
        t_drawn = time.perf_counter()
        got = card.label(bvh, o, d, cfg.labels, normal_loss=cfg.normal_loss)
        sync()
        t_labelled = time.perf_counter()
        o_card, d_card = torch.from_numpy(o).to(device), torch.from_numpy(d).to(device)
        sync()
        t_first = time.perf_counter()
        card.tracer.nearest(o_card, d_card)
        sync()
        for key, value in (("draw", t_drawn - t_start), ("label", t_labelled - t_drawn), ("samples", len(got)),
                           ("first", n_rays / (time.perf_counter() - t_first))):
            times[key].append(value)
    batches.close()
    draw, label_s, samples = (statistics.median(times[k][1:]) for k in ("draw", "label", "samples"))
    stream = Batches(bvh, tracer, cfg, np.random.default_rng(0), prefetch=True, draw_parts=max(2, threads),
                     card_labels=card)  # one labelling thread, as a training on the card runs it
    try:
        for _ in range(chunk_steps(cfg)):
            stream.next()
        t, streamed = time.perf_counter(), 0
        for _ in range(chunk_steps(cfg) * chunks):
            streamed += len(stream.next())
        sync()
        streamed_rate = streamed / (time.perf_counter() - t)
    finally:
        stream.close()
    return {"card_label_s": round(label_s, 5), "card_label_samples_per_s": round(samples / (draw + label_s)),
            "card_first_hit_rays_per_s": round(statistics.median(times["first"][1:])),
            "card_streamed_samples_per_s": round(streamed_rate), "card_tracer_bytes": card.tracer.resident_bytes}


def train_rate(mesh, bvh, tracer, s, threads: int, steps: int) -> float:
    """The default preset's training on the CPU at `threads` threads: leaf samples/s over `steps` steps."""
    torch.set_num_threads(threads)
    torch.manual_seed(0)
    cfg = s.train_config()
    cfg.steps, cfg.time_limit_s, cfg.device = steps, None, "cpu"
    return train(NeuralBVH(bvh.nodes, s.model_config(), mesh.transform), bvh, tracer, cfg).samples_per_s


def label_rows(name: str, thread_counts: list[int], chunks: int, train_steps: int) -> list[dict]:
    """One row per thread count for asset `name` (see the module docstring)."""
    mesh = named_mesh(name)
    s = preset("default")
    cfg = s.train_config()
    bvh = build_bvh(mesh, s.nodes)
    return_free_memory()  # what an earlier asset freed would read as this tracer's negative bytes
    before, t0 = resident_bytes(), time.perf_counter()
    tracer = ExactTracer(mesh)
    tracer.first_hit(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32) / np.sqrt(3.0))  # builds lazily
    build_s, tracer_bytes = time.perf_counter() - t0, resident_bytes() - before
    n_rays = cfg.rays_per_step * cfg.label_steps
    rows = []
    for n in thread_counts:
        c = chunk_costs(bvh, tracer, cfg, n, chunks)
        workers = label_workers(n)
        rows.append({"asset": name, "triangles": mesh.n_triangles, "threads": n, "draw_parts": c["draw_parts"],
                     "host_cpus": os.cpu_count(), "tracer": tracer.scene_kind, "tracer_build_s": round(build_s, 3),
                     "tracer_bytes": tracer_bytes, "rays_per_chunk": n_rays, "samples_per_chunk": c["samples"],
                     "draw_s": round(c["draw"], 4), "first_hit_rays_per_s": round(n_rays / c["first"]),
                     "label_s": round(c["label"], 4),
                     "label_samples_per_s": round(c["samples"] / (c["draw"] + c["label"])),
                     "streamed_1_worker_samples_per_s": round(stream_rate(bvh, tracer, cfg, n, 1, chunks)),
                     "label_workers": workers,
                     "streamed_samples_per_s": round(stream_rate(bvh, tracer, cfg, n, workers, chunks)),
                     "cpu_train_samples_per_s": round(train_rate(mesh, bvh, tracer, s, n, train_steps))
                     if train_steps else "", **card_costs(bvh, tracer, cfg, n, chunks)})
        print(rows[-1], flush=True)
    return rows


def report(rows: list[dict]) -> None:
    table = [[r["asset"], f"{int(r['triangles']):,}", r["threads"], r["tracer"],
              f"{int(r['tracer_bytes']) / 2**20:,.0f} MiB", f"{float(r['tracer_build_s']):.2f}",
              f"{float(r['draw_s']) * 1000:.1f}", f"{float(r['label_s']) * 1000:.1f}",
              f"{int(r['first_hit_rays_per_s']):,}", f"{int(r['label_samples_per_s']):,}",
              f"{int(r['streamed_1_worker_samples_per_s']):,}",
              f"{int(r['streamed_samples_per_s']):,} ({r['label_workers']})",
              f"{int(float(r['cpu_train_samples_per_s'])):,}" if r.get("cpu_train_samples_per_s") else ""]
             for r in rows]
    card = any(r.get("card_label_samples_per_s") for r in rows)
    if card:  # made on a card
        for line, r in zip(table, rows):
            line.append(f"{int(r['card_label_samples_per_s']):,} ({int(r['card_streamed_samples_per_s']):,})")
    write_markdown(OUT.with_suffix(".md"), [
        "# What labels cost on the host (bench/speed/bench_labels.py)\n",
        "Per chunk of the default preset (2,048 rays x 32 steps), median of the chunks: the draw, the labels "
        "(first hits, the leaves each ray enters, all hits inside them), first-hit rays/s of the exact tracer alone, "
        "and label samples/s (drawn and labelled); streamed: as a card's training takes them, by one labelling thread "
        "and by the card's count of them at that many cores (in brackets). The tracer's memory is the resident memory "
        "its build added. "
        "CPU training: the default preset's whole step on this host's CPU at that many threads (labels included).\n",
        *markdown_table(["asset", "triangles", "threads", "tracer", "tracer memory", "build s", "draw ms",
                         "labels ms", "first-hit rays/s", "label samples/s", "streamed, 1 thread",
                         "streamed (labelling threads)", "CPU training samples/s"]
                        + (["on the card (streamed)"] if card else []), table)])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--assets", nargs="+", default=["blob"] if SMOKE else ["bunny", "dragon"])
    cpus = os.cpu_count() or 1
    ap.add_argument("--threads", nargs="+", type=int,
                    default=[1] if SMOKE else [n for n in (1, 2, 4, 8, 16, 32, 64) if n <= cpus])
    ap.add_argument("--chunks", type=int, default=1 if SMOKE else 5)
    ap.add_argument("--train-steps", type=int, default=3 if SMOKE else 100,
                    help="steps of CPU training per thread count (0: none)")
    args = ap.parse_args()
    rows = [r for name in args.assets for r in label_rows(name, args.threads, args.chunks, args.train_steps)]
    write_rows(OUT, rows)
    report(rows)


if __name__ == "__main__":
    main()
