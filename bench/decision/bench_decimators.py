"""The decimators, side by side by the product's one metric: fast-simplification (the quadric decimation the product
used), meshoptimizer's plain `simplify`, and the product's decimation (`geometry.decimation.decimate`: meshoptimizer
with the look's seams and coordinates). Each at the same requested triangle counts, scored on the held-out views
(16 at 256 px) as plain triangles and as the compact mesh a verdict weighs.

    .venv/bin/python -m bench.decision.bench_decimators --assets bunny dragon48k dragon engine gyroid

Writes bench/results/decimators.{csv,md}: per asset and count, each decimator's triangles, image MSE, compact
bytes and seconds, and the ratio of the product's MSE to the better of the two references.
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from bench.harness import append_rows, markdown_table, product_scorer, read_rows, result_path, stamp, write_markdown


def fast_simplification(mesh, count):
    import fast_simplification as fs
    from nbvh_core.geometry.mesh import mesh_like

    v, f = fs.simplify(mesh.vertices.astype(np.float64), mesh.faces, target_reduction=1 - count / mesh.n_triangles)
    return mesh_like(mesh, v, f)


def meshopt_plain(mesh, count):
    from nbvh_core.geometry.decimation import simplify_indices
    from nbvh_core.geometry.mesh import mesh_like

    return mesh_like(mesh, mesh.vertices, simplify_indices(mesh.vertices, mesh.faces, count))


def product(mesh, count):
    from nbvh_core.geometry.decimation import decimate

    return decimate(mesh, count)


DECIMATORS = {"fast-simplification": fast_simplification, "meshopt-simplify": meshopt_plain, "product": product}


def load(name: str):
    from nbvh_core.geometry.bundled_samples import sample_path
    from nbvh_core.geometry.mesh import load_mesh

    try:
        return load_mesh(sample_path(name))
    except (KeyError, FileNotFoundError, ValueError):
        from bench.real_assets import asset_path

        return load_mesh(asset_path(name))


def run(assets: list[str], shares: list[float], views: int | None, size: int | None) -> list[dict]:
    from nbvh_core.geometry.compact_mesh import compact_mesh

    rows, run_stamp = [], stamp()
    for name in assets:
        mesh = load(name)
        scorer = product_scorer(mesh, n_views=views, resolution=size)
        for share in shares:
            count = max(int(mesh.n_triangles * share), 64)
            for label, fn in DECIMATORS.items():
                t = time.perf_counter()
                dec = fn(mesh, count)
                seconds = time.perf_counter() - t
                nbytes, decoded = compact_mesh(dec)
                row = {"asset": name, "input_triangles": mesh.n_triangles, "requested": count, "decimator": label,
                       "triangles": dec.n_triangles, "mse": scorer.score_mesh(dec).mse,
                       "compact_bytes": nbytes, "compact_mse": scorer.score_mesh(decoded).mse,
                       "seconds": round(seconds, 3)}
                rows.append(row)
                print(row, flush=True)
        append_rows(result_path("decimators.csv"), [r for r in rows if r["asset"] == name], run_stamp)
    return rows


def report(rows: list[dict]) -> None:
    lines = ["The decimators at equal requested triangle counts, by the product's metric (held-out views; MSE of the",
             "plain decimation). ratio = the product's MSE / the better of fast-simplification and meshopt-simplify.",
             ""]
    table = []
    keys = sorted({(r["asset"], int(r["requested"])) for r in rows})
    for asset, count in keys:
        by = {r["decimator"]: r for r in rows if r["asset"] == asset and int(r["requested"]) == count}
        if len(by) < 3:
            continue
        best = min(float(by["fast-simplification"]["mse"]), float(by["meshopt-simplify"]["mse"]))
        table.append([asset, by["product"]["input_triangles"], count]
                     + [f"{int(by[d]['triangles']):,} / {float(by[d]['mse']):.6f}" for d in DECIMATORS]
                     + [f"{float(by['product']['mse']) / max(best, 1e-12):.2f}"])
    lines += markdown_table(["asset", "input", "requested", "fast-simplification (tris / MSE)",
                             "meshopt-simplify", "product (look kept)", "ratio"], table)
    write_markdown(result_path("decimators.md"), lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--assets", nargs="+", default=["bunny", "dragon48k", "dragon", "engine", "gyroid"])
    ap.add_argument("--shares", type=float, nargs="+", default=[0.02, 0.08, 0.3],
                    help="requested triangles as shares of the input")
    ap.add_argument("--views", type=int, help="held-out views (default: a run's final evaluation's)")
    ap.add_argument("--size", type=int, help="pixels per side (default: a run's final evaluation's)")
    args = ap.parse_args()
    run(args.assets, args.shares, args.views, args.size)
    report(read_rows(result_path("decimators.csv")))


if __name__ == "__main__":
    main()
