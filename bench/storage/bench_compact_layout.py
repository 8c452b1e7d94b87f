"""The compact ray-traceable mesh's own size and exactness, on real scans and generated shapes.

    .venv/bin/python -m bench.storage.bench_compact_layout --assets bunny dragon48k dragon dragon871k engine spiky gyroid studs

Per asset: bytes per triangle of `compact_mesh.encode_compact` (everything: header, cluster BVH, cluster records,
positions, topology) and where they go, encode and decode seconds, Draco 11-bit bytes of the same mesh (storage
only, decoded before tracing), and the decoded mesh's image MSE against the source (16 views at 256 px: the
grid's own error). Rows in bench/results/compact_layout.csv, the table in compact_layout.md.
"""
from __future__ import annotations

import argparse
import time

from bench.meshes import bench_mesh
from bench.harness import RESULTS, SMOKE, append_row, markdown_table, num, read_rows, write_markdown
from bench.real_assets import REAL_ASSETS, asset_path

CSV = RESULTS / ("compact_layout_smoke.csv" if SMOKE else "compact_layout.csv")


def load(name: str):
    from nbvh_core.geometry.mesh import load_mesh

    return load_mesh(asset_path(name)) if name in REAL_ASSETS or name == "bunny" else bench_mesh(name)


def measure(name: str, views: int, size: int) -> dict:
    import numpy as np

    from nbvh_core.geometry import compact_mesh as cm
    from nbvh_core.geometry.bvh import build_full_tree
    from nbvh_core.geometry.exact import ExactTracer
    from nbvh_core.geometry.mesh import Mesh
    from nbvh_core.rendering.metrics import ViewScorer

    mesh = load(name)
    tree = build_full_tree(mesh)
    t = time.perf_counter()
    data = cm.encode_compact(mesh, tree)
    encode_s = time.perf_counter() - t
    t = time.perf_counter()
    dec = cm.decode_compact(data)
    decode_s = time.perf_counter() - t
    n, clusters, nodes = mesh.n_triangles, int(dec.cluster_of_face.max()) + 1, len(dec.node_link)
    tri = dec.vertices[dec.faces].astype(np.float64)
    keep = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1) > 0
    decoded = Mesh(vertices=dec.vertices, faces=dec.faces[keep], transform=mesh.transform, name=mesh.name)
    mse = ViewScorer(ExactTracer(mesh), mesh.transform, views, size, held_out=True).score_mesh(decoded).mse
    try:
        import DracoPy

        draco = len(DracoPy.encode(mesh.vertices, mesh.faces, quantization_bits=11, compression_level=7))
    except ImportError:
        draco = ""
    payload = len(data) - 48 - cm.NODE_BYTES * nodes - cm.CLUSTER_BYTES * clusters
    return {"asset": name, "triangles": n, "bytes": len(data), "bytes_per_triangle": round(len(data) / n, 3),
            "bvh_per_triangle": round(cm.NODE_BYTES * nodes / n, 3),
            "records_per_triangle": round(cm.CLUSTER_BYTES * clusters / n, 3),
            "payload_per_triangle": round(payload / n, 3), "triangles_per_cluster": round(n / clusters, 1),
            "vertices_per_triangle": round(len(dec.vertices) / n, 3), "encode_s": round(encode_s, 2),
            "decode_s": round(decode_s, 2), "draco11_bytes": draco, "grid_mse": mse, "views": views, "size": size}


def report() -> None:
    rows = read_rows(CSV)
    table = [[r["asset"], f"{int(r['triangles']):,}", f"{int(r['bytes']):,}", r["bytes_per_triangle"],
              r["bvh_per_triangle"], r["records_per_triangle"], r["payload_per_triangle"], r["triangles_per_cluster"],
              f"{int(num(r, 'draco11_bytes')):,}" if r["draco11_bytes"] else "-", f"{num(r, 'grid_mse'):.1e}",
              r["encode_s"], r["decode_s"]] for r in rows]
    write_markdown(CSV.with_suffix(".md"), [
        "# The compact ray-traceable mesh: bytes per triangle with its BVH", "",
        *markdown_table(["asset", "triangles", "bytes", "B/tri", "BVH B/tri", "records B/tri", "positions + "
                         "topology B/tri", "tris/cluster", "Draco 11-bit (storage)", "grid MSE", "encode s",
                         "decode s"], table)])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--assets", nargs="+", default=["bunny", "dragon48k", "dragon", "engine", "spiky", "gyroid"])
    p.add_argument("--views", type=int, default=2 if SMOKE else 16)
    p.add_argument("--size", type=int, default=32 if SMOKE else 256)
    args = p.parse_args()
    done = {r["asset"] for r in read_rows(CSV)}
    for name in args.assets:
        if name not in done:
            row = measure(name, args.views, args.size)
            append_row(CSV, row)
            print(row, flush=True)
    report()


if __name__ == "__main__":
    main()
