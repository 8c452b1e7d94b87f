"""NBVH render engine speed, through the real worker process and its protocol (what Blender's viewport waits on):
viewport frames per second at 480x270 for one and for three models (shadows from a sun, the camera orbiting, one
request after another), the first coarse frame's latency, and the final render time at 1920x1080 - each beside
the same scene drawn from the meshes by Embree in the same worker (geometry "mesh").

    .venv/bin/python -m bench.speed.bench_engine MODELS_DIR [--frames 12]

MODELS_DIR: blob/bunny/studs .npz + .nbvh (blender_tests/engine_scene.py's layout; made there with the `tiny` preset
when missing). Writes bench/results/engine.csv and engine.md.
"""
from __future__ import annotations

import argparse
import math
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from bench.harness import RESULTS, SMOKE, write_markdown, write_rows
from nbvh_core.rendering.scene_render import look_at, perspective, view_projection
from addon.render_client import RenderWorker  # after harness: the add-on package is reached through the repository root

PLACES = {"bunny": (0.0, 0.0), "blob": (-1.4, 0.0), "studs": (1.4, 0.0)}


def scene(models: Path, names: list[str], geometry: str) -> dict:
    objects = []
    for name in names:
        v = np.load(models / f"{name}.npz")["vertices"]
        s = 1.1 / float(np.ptp(v, axis=0).max())
        m = np.eye(4)
        m[:3, :3] *= s
        m[:3, 3] = np.array([*PLACES[name], 0.0]) - s * (v.max(0) + v.min(0)) / 2
        objects.append({"name": name, "matrix": m.tolist(), "model": str(models / f"{name}.nbvh"),
                        "mesh": str(models / f"{name}.npz")})
    return {"objects": objects, "geometry": geometry, "world": [0.05, 0.05, 0.05],
            "lights": [{"kind": "sun", "power": 3.0, "direction": [-0.3, 0.4, -0.85]}]}


def orbit(i: int, n: int, width: int, height: int) -> np.ndarray:
    a = 2 * math.pi * i / n
    eye = (4.5 * math.sin(a), -4.5 * math.cos(a), 2.0)
    return view_projection(look_at(eye, (0.0, 0.0, 0.3)), perspective(math.radians(40), width / height))


def timed_frames(worker: RenderWorker, n: int, width: int, height: int, levels) -> tuple[list[float], list[float]]:
    """Seconds per frame (request sent -> finest frame read) and to the first (coarsest) frame, n views."""
    full, first = [], []
    for i in range(n):
        t0 = time.perf_counter()
        worker.request("bench", orbit(i, n, width, height), width, height, levels=levels)
        ch = worker.channels["bench"]
        got_first = None
        while ch.pending:
            if worker.poll() and got_first is None:
                got_first = time.perf_counter() - t0
            if not worker.alive:
                raise RuntimeError(worker.last_error())
            time.sleep(0.0005)
        if ch.error:
            raise RuntimeError(ch.error)
        full.append(time.perf_counter() - t0)
        first.append(got_first if got_first is not None else full[-1])
    return full, first


def make_models(folder: Path) -> None:
    """blob/bunny/studs .npz + .nbvh with the tiny preset, for a run without trained models (the smoke test)."""
    from nbvh_core.app.pipeline import compress_mesh, preset
    from nbvh_core.geometry.bundled_samples import sample_path
    from nbvh_core.geometry.mesh import load_mesh

    folder.mkdir(parents=True, exist_ok=True)
    for name in PLACES:
        if (folder / f"{name}.nbvh").exists():
            continue
        mesh = load_mesh(sample_path(name))
        np.savez(folder / f"{name}.npz", vertices=mesh.transform.to_original(mesh.vertices).astype(np.float32),
                 faces=mesh.faces)
        compress_mesh(mesh, preset("tiny").with_overrides(force=True), folder / f"{name}.nbvh", evaluate_quality=False)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("models", type=Path)
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()
    make_models(args.models)
    final_w, final_h = (192, 108) if SMOKE else (1920, 1080)
    rows = []
    worker = RenderWorker(sys.executable)
    try:
        for names in (["bunny"], ["blob", "bunny", "studs"]):
            for geometry in ("neural", "mesh"):
                sid = worker.set_scene(scene(args.models, names, geometry))
                worker.wait(lambda: worker.scene_done >= sid, timeout=120)
                assert not worker.warnings, worker.warnings
                timed_frames(worker, 2, 480, 270, (1,))  # warm up (kernels, caches)
                full, _ = timed_frames(worker, args.frames, 480, 270, (1,))
                prog, first = timed_frames(worker, args.frames, 480, 270, (4, 2, 1))
                t0 = time.perf_counter()
                worker.request("final", orbit(0, 1, final_w, final_h), final_w, final_h, levels=(1,), samples=1,
                               bands=16)
                worker.wait(lambda: not worker.channels["final"].pending, timeout=1200)
                final1 = time.perf_counter() - t0
                t0 = time.perf_counter()
                worker.request("final", orbit(0, 1, final_w, final_h), final_w, final_h, levels=(1,), samples=4,
                               bands=16)
                worker.wait(lambda: not worker.channels["final"].pending, timeout=2400)
                final4 = time.perf_counter() - t0
                row = {"objects": len(names), "geometry": geometry,
                       "viewport_fps_480x270": round(1 / statistics.median(full), 2),
                       "progressive_first_frame_ms": round(1000 * statistics.median(first), 1),
                       "progressive_full_s": round(statistics.median(prog), 3),
                       "final_1920x1080_1spp_s": round(final1, 2), "final_1920x1080_4spp_s": round(final4, 2)}
                rows.append(row)
                print(row, flush=True)
    finally:
        worker.stop()
    args.out.mkdir(parents=True, exist_ok=True)
    write_rows(args.out / "engine.csv", rows)
    lines = ["# NBVH render engine speed (bench/speed/bench_engine.py)", "",
             f"Through the render worker process and its protocol, on {platform.processor() or platform.machine()} "
             f"({__import__('os').cpu_count()} cores), one run. Shadows from one sun; the camera orbits; "
             f"{args.frames} frames per row, median. 'mesh' = the same objects from their meshes (Embree) in the same "
             "worker. Progressive = levels 1/4, 1/2, 1.", "",
             "| objects | geometry | viewport fps 480x270 | first coarse frame ms | progressive full s | "
             "final 1920x1080 1 spp s | final 4 spp s |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['objects']} | {r['geometry']} | {r['viewport_fps_480x270']} | "
                     f"{r['progressive_first_frame_ms']} | {r['progressive_full_s']} | {r['final_1920x1080_1spp_s']} | "
                     f"{r['final_1920x1080_4spp_s']} |")
    write_markdown(args.out / "engine.md", lines)
    print(f"wrote {args.out / 'engine.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
