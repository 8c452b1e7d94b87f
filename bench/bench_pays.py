"""Does compression pay at the user's budget? Neural model (a preset, its real time budget) vs the quadric
decimation of the same image MSE, on resident bytes; and vs Draco on storage bytes. One metric for every contender:
`metrics.evaluate` (16 orbit views, 128 px, Embree reference), the one the pipeline reports.

    .venv/bin/python bench/bench_pays.py --meshes bunny --presets default [--table-bits 8 32]

Resumable: one CSV row per (mesh, preset, storage), appended as it lands (bench/results/pays.csv); a rerun skips
rows already there. `bench/results/pays.md` is rewritten from the CSV after every row.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

import numpy as np  # noqa: E402

from bench_quality import append_row, read_rows  # noqa: E402
from nbvh_core import kernels  # noqa: E402
from nbvh_core.exact import ExactTracer  # noqa: E402
from nbvh_core.metrics import evaluate_renderer  # noqa: E402
from nbvh_core.pipeline import compress_mesh, preset  # noqa: E402
from nbvh_core.render import render_reference  # noqa: E402
from nbvh_core.sizing import decimate, mesh_resident_bytes  # noqa: E402

RESULTS = ROOT / "bench" / "results"
FIELDS = ["mesh", "triangles", "preset", "storage", "train_s", "steps", "file_bytes", "model_resident_bytes",
          "mse", "mse_float32", "iou", "mesh_resident_bytes", "equal_mse_decimation_triangles",
          "equal_mse_decimation_resident_bytes", "ratio_resident_decimation_to_model",
          "ratio_resident_decimation_to_file", "draco11_bytes", "equal_mse_decimation_draco11_bytes", "compute_path",
          "created"]


def load_bench_mesh(name: str):
    from bench_meshes import bench_mesh

    return bench_mesh(name)


def decimation_mse(mesh, tracer, triangles: int, views: int, res: int) -> tuple[float, int, int, int]:
    """(MSE, triangles, resident bytes, Draco-11 bytes) of the quadric decimation to ~triangles."""
    import DracoPy

    dec = decimate(mesh, triangles)
    dt = ExactTracer(dec)
    q, _ = evaluate_renderer(lambda cam, w, h: render_reference(dt, cam, w, h), tracer, mesh.transform, views, res)
    draco = len(DracoPy.encode(dec.vertices, dec.faces, quantization_bits=11, compression_level=7))
    return q.mse, dec.n_triangles, mesh_resident_bytes(dec)["total"], draco


def equal_mse_decimation(mesh, tracer, target: float, views: int, res: int) -> dict:
    """The smallest decimation whose MSE <= target, found by bisection on the log of the triangle count (the
    decimation error falls with the count, up to noise), interpolated between the bracketing counts."""
    lo, hi = 100, int(mesh.n_triangles * 0.95)
    m_hi = decimation_mse(mesh, tracer, hi, views, res)
    if m_hi[0] > target:
        return {"triangles": mesh.n_triangles, "resident": mesh_resident_bytes(mesh)["total"], "draco": None,
                "note": "no decimation reaches it"}
    best = m_hi
    for _ in range(9):
        mid = int(np.sqrt(lo * hi))
        if mid <= lo or mid >= hi:
            break
        m = decimation_mse(mesh, tracer, mid, views, res)
        if m[0] <= target:
            hi, best = mid, m
        else:
            lo = mid
    return {"triangles": best[1], "resident": best[2], "draco": best[3], "mse": best[0]}


def write_md(rows: list[dict]) -> None:
    lines = ["# Does compression pay? (bench/bench_pays.py)", "",
             "Neural model at the preset's own time budget vs the quadric decimation of the same image MSE (16 views,"
             " 128 px, same metric), on this 2-core CPU. Resident = what a ray tracer holds to trace (mesh: vertices,"
             " indices, normals, BVH; model: decoded nodes, table as held, network as held: float16 since the kernels read it so, float32 in rows measured before). File = the .nbvh.", "",
             "| mesh | preset | storage | train s | file B | model resident B | MSE (stored) | MSE (float32) | IoU "
             "| equal-MSE decimation | its resident B | decimation / model resident | decimation / file "
             "| Draco-11 of the mesh | of the decimation |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['mesh']} | {r['preset']} | {r['storage']} | {float(r['train_s']):.0f} | "
                     f"{int(r['file_bytes']):,} | {int(r['model_resident_bytes']):,} | {float(r['mse']):.5f} | "
                     f"{float(r['mse_float32']):.5f} | {float(r['iou']):.4f} | "
                     f"{int(r['equal_mse_decimation_triangles']):,} tris | "
                     f"{int(r['equal_mse_decimation_resident_bytes']):,} | "
                     f"{float(r['ratio_resident_decimation_to_model']):.2f}x | "
                     f"{float(r['ratio_resident_decimation_to_file']):.2f}x | {r['draco11_bytes']} | "
                     f"{r['equal_mse_decimation_draco11_bytes']} |")
    (RESULTS / "pays.md").write_text("\n".join(lines) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--meshes", nargs="+", default=["bunny"])
    ap.add_argument("--presets", nargs="+", default=["default"])
    ap.add_argument("--table-bits", type=int, nargs="+", default=[8])
    ap.add_argument("--network-bits", type=int, choices=[32, 16, 8],
                    help="bits per network weight (default: the preset's with quantized tables, else 32)")
    ap.add_argument("--time-limit", type=float, help="override the preset's budget (not for headline numbers)")
    ap.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                    help="Settings overrides for a configuration study, e.g. width=32 log2_table=12 (named in the row)")
    ap.add_argument("--csv", default=str(RESULTS / "pays.csv"))
    args = ap.parse_args()
    kernels.keep_freed_memory()
    path = Path(args.csv)
    done = {(r["mesh"], r["preset"], r["storage"]) for r in read_rows(path)}
    for mesh_name in args.meshes:
        mesh = load_bench_mesh(mesh_name)
        tracer = ExactTracer(mesh)
        for preset_name in args.presets:
            for bits in args.table_bits:
                base = preset(preset_name)
                over = {"table_bits": bits, "network_bits": args.network_bits or (base.network_bits if bits < 32 else 32),
                        "node_bits": 8 if bits < 32 else 32}
                if args.time_limit:
                    over["time_limit_s"] = args.time_limit
                extra = {}
                for item in args.set:
                    key, value = item.split("=", 1)
                    extra[key] = type(getattr(base, key))(value) if getattr(base, key) is not None else float(value)
                s = base.with_overrides(**over, **extra)
                storage = f"t{s.table_bits}/w{s.network_bits}/n{s.node_bits}"
                if extra:
                    storage += " " + " ".join(f"{k}={v}" for k, v in sorted(extra.items()))
                if (mesh_name, preset_name, storage) in done:
                    continue
                print(f"{mesh_name} {preset_name} {storage}: training {s.time_limit_s} s", flush=True)
                res = compress_mesh(mesh, s, None, compare_float32=True)
                q = res.quality
                dec = equal_mse_decimation(mesh, tracer, q.mse, s.eval_views, s.eval_resolution)
                resident = sum(res.model.resident_bytes().values())
                row = {"mesh": mesh_name, "triangles": mesh.n_triangles, "preset": preset_name, "storage": storage,
                       "train_s": round(res.training.seconds, 1), "steps": res.training.steps,
                       "file_bytes": res.file_bytes, "model_resident_bytes": resident, "mse": q.mse,
                       "mse_float32": res.seconds.get("mse_float32"), "iou": q.silhouette_iou,
                       "mesh_resident_bytes": mesh_resident_bytes(mesh)["total"],
                       "equal_mse_decimation_triangles": dec["triangles"],
                       "equal_mse_decimation_resident_bytes": dec["resident"],
                       "ratio_resident_decimation_to_model": dec["resident"] / resident,
                       "ratio_resident_decimation_to_file": dec["resident"] / res.file_bytes,
                       "draco11_bytes": res.assessment.get("alternatives", {}).get("draco11_bytes"),
                       "equal_mse_decimation_draco11_bytes": dec.get("draco"),
                       "compute_path": res.training.compute_path, "created": time.strftime("%Y-%m-%dT%H:%M:%S")}
                append_row(path, {k: row[k] for k in FIELDS})
                print(json.dumps(row), flush=True)
                write_md(read_rows(path))


if __name__ == "__main__":
    main()
