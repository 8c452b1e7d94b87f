"""Neural model vs the equal-MSE decimation held as a compact ray-traceable mesh (`nbvh_core/geometry/compact_mesh.py`):
for each model row of bench/results/pays.csv (a preset trained at its own budget, its image MSE, and the quadric
decimation found to meet that MSE), the decimation is rebuilt (deterministic), encoded compactly, decoded, and scored
with the product's metric (`harness.product_scorer`: 16 held-out views, 256 px, Embree reference).

    .venv/bin/python -m bench.storage.bench_compact [--storage "t8/w8/n8 n_max=auto:64"]   # -> bench/results/compact.csv

Columns: the model's file bytes and MSE (from pays.csv), the decimation's triangles, plain resident bytes (~44 B per
triangle), compact bytes (exact) and bytes per triangle, the decoded compact mesh's MSE, and the ratios
plain / model file and compact / model file (above 1: the model is smaller).
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path
from bench.harness import RESULTS, append_rows, product_scorer, read_rows

ROOT = Path(__file__).resolve().parents[2]


def compact_row(pays: dict) -> dict:
    """One pays.csv row -> its compact-mesh comparison."""
    from bench.meshes import bench_mesh
    from nbvh_core.geometry.compact_mesh import compact_mesh
    from nbvh_core.geometry.decimation import decimate
    from nbvh_core.planning.sizing import mesh_resident_bytes

    mesh = bench_mesh(pays["mesh"])
    t0 = time.perf_counter()
    dec = decimate(mesh, int(pays["equal_mse_decimation_triangles"]))
    nbytes, decoded = compact_mesh(dec)
    q = product_scorer(mesh).score_mesh(decoded)
    file_bytes = int(pays["file_bytes"])
    plain = mesh_resident_bytes(dec)["total"]
    return {"mesh": pays["mesh"], "triangles": mesh.n_triangles, "preset": pays["preset"], "storage": pays["storage"],
            "model_file_bytes": file_bytes, "model_mse": float(pays["mse"]), "decimation_triangles": dec.n_triangles,
            "plain_bytes": plain, "compact_bytes": nbytes, "compact_bytes_per_triangle": round(nbytes / dec.n_triangles, 2),
            "compact_mse": round(q.mse, 6), "ratio_plain_to_model": round(plain / file_bytes, 2),
            "ratio_compact_to_model": round(nbytes / file_bytes, 2),
            "draco11_decimation_bytes": pays.get("equal_mse_decimation_draco11_bytes"),
            "seconds": round(time.perf_counter() - t0, 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--storage", default="t8/w8/n8 n_max=auto:64", help="the pays.csv rows to compare (storage column)")
    ap.add_argument("--out", default=str(RESULTS / "compact.csv"))
    args = ap.parse_args()
    rows = [r for r in read_rows(RESULTS / "pays.csv") if r["storage"] == args.storage]
    done = {(r["mesh"], r["preset"], r["storage"]) for r in read_rows(args.out)}
    for pays in rows:
        if (pays["mesh"], pays["preset"], pays["storage"]) in done:
            continue
        row = compact_row(pays)
        print(row, flush=True)
        append_rows(args.out, [row])  # one row as it lands: a rerun resumes


if __name__ == "__main__":
    main()
