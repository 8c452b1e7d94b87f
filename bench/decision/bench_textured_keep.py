"""A real textured scan where a decimation wins, through the need-driven default, as a user gets it back.

The Fuze bottle (a real scan: 1,000 triangles and one photographed 1024 px atlas, `real_assets.py`) over-tessellated
by midpoint subdivision (each triangle into 4, `--levels` times: 256,000 triangles at 4; the surface is unchanged)
and written as a textured .glb; then `nbvh compress SCAN.glb -o OUT/` with no options. Recorded: what it decided,
the bytes the verdict counted and the bytes written, the kept .glb loaded back (trimesh, through the product's
reader): its triangles, texture coordinates and image; the colour at interior points of the kept triangles against
the source's colour at the nearest source surface point; the kept mesh's FLIP and colour MSE against the source on
the held-out views (from NAME.verdict.json).

    NBVH_GIT_MIRRORS=... .venv/bin/python -m bench.decision.bench_textured_keep [--levels 4]

Writes bench/results/textured_keep.{csv,md}.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.harness import ROOT, SMOKE, markdown_table, result_path, stamp, write_markdown, write_rows


def subdivide(mesh, levels: int):
    """Midpoint subdivision of `mesh` with its look (corner coordinates interpolated on each face): the same surface
    in 4^levels times the triangles; midpoints shared between neighbouring faces (no cracks)."""
    from nbvh_core.geometry.look import Look
    from nbvh_core.geometry.mesh import mesh_from_arrays

    v = mesh.transform.to_original(mesh.vertices)
    f, uv, slots = mesh.faces.astype(np.int64), mesh.look.corner_uvs, mesh.look.face_slots
    for _ in range(levels):
        edges = np.sort(np.stack([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], 1).reshape(-1, 2), 1)
        unique, inverse = np.unique(edges, axis=0, return_inverse=True)
        mid = len(v) + inverse.reshape(-1, 3)  # midpoint of edge (0,1), (1,2), (2,0) per face
        v = np.concatenate([v, 0.5 * (v[unique[:, 0]] + v[unique[:, 1]])])
        m01, m12, m20 = mid[:, 0], mid[:, 1], mid[:, 2]
        u01, u12, u20 = 0.5 * (uv[:, 0] + uv[:, 1]), 0.5 * (uv[:, 1] + uv[:, 2]), 0.5 * (uv[:, 2] + uv[:, 0])
        f = np.concatenate([np.stack([f[:, 0], m01, m20], 1), np.stack([m01, f[:, 1], m12], 1),
                            np.stack([m20, m12, f[:, 2]], 1), np.stack([m01, m12, m20], 1)])
        uv = np.concatenate([np.stack([uv[:, 0], u01, u20], 1), np.stack([u01, uv[:, 1], u12], 1),
                             np.stack([u20, u12, uv[:, 2]], 1), np.stack([u01, u12, u20], 1)])
        slots = np.tile(slots, 4)
    return mesh_from_arrays(v, f, name=f"{mesh.name}{len(f) // 1000}k",
                            look=Look(slots.astype(np.int32), uv.astype(np.float32), mesh.look.materials))


def colour_agreement(source, kept, n: int = 4000, seed: int = 0) -> dict:
    """Linear-RGB albedo at n random interior points of the kept mesh's triangles against the source's albedo at the
    source surface point straight across (a ray along the kept triangle's normal, both ways, traced exactly): mean,
    95th percentile and max of the per-point max channel gap, and the 95th percentile of the distance across
    (normalised units)."""
    from nbvh_core.geometry.exact import ExactTracer
    from nbvh_core.geometry.look import hit_albedo

    rng = np.random.default_rng(seed)
    tri = rng.integers(0, kept.n_triangles, n)
    bary = rng.dirichlet(np.ones(3), n).astype(np.float32)
    pts = np.einsum("nk,nkc->nc", bary, kept.vertices[kept.faces[tri]]).astype(np.float32)
    got = hit_albedo(kept.look, kept.vertices, kept.faces, tri, pts)
    normal = kept.face_normals(tri)  # those triangles' only: the same bits (tests/test_mesh.py)
    tracer, lift = ExactTracer(source), 0.01
    best_t = np.full(n, np.inf)
    src_tri, src_pts = np.zeros(n, np.int64), pts.copy()
    for sign in (1.0, -1.0):
        o = (pts - sign * lift * normal).astype(np.float32)
        d = (sign * normal).astype(np.float32)
        fh = tracer.first_hit(o, d)
        closer = fh.hit & (np.abs(fh.t - lift) < best_t)
        best_t[closer] = np.abs(fh.t[closer] - lift)
        src_tri[closer] = fh.tri[closer]
        src_pts[closer] = o[closer] + fh.t[closer, None] * d[closer]
    found = np.isfinite(best_t)
    want = hit_albedo(source.look, source.vertices, source.faces, src_tri[found], src_pts[found])
    gap = np.abs(got[found] - want).max(1)
    return {"points": int(found.sum()), "colour_gap_mean": float(gap.mean()),
            "colour_gap_p95": float(np.percentile(gap, 95)), "colour_gap_max": float(gap.max()),
            "surface_gap_p95": float(np.percentile(best_t[found], 95))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--levels", type=int, default=1 if SMOKE else 4)
    ap.add_argument("--asset", default="fuze",
                    help="the real scan (fuze), or a generated textured asset of geometry.demo_assets (globe, crate)")
    ap.add_argument("--time-limit", type=float, default=None, help="training budget (default: the product's)")
    args = ap.parse_args()
    from nbvh_core.geometry.glb import encode_glb
    from nbvh_core.geometry.mesh import load_mesh
    from bench.real_assets import asset_path

    from nbvh_core.geometry import demo_assets

    base = demo_assets.ASSETS[args.asset]() if args.asset in demo_assets.ASSETS else load_mesh(asset_path(args.asset))
    source = subdivide(base, args.levels)
    run_stamp = stamp()
    with tempfile.TemporaryDirectory() as tmp:
        scan = Path(tmp) / f"{source.name}.glb"
        scan.write_bytes(encode_glb(source))
        out = Path(tmp) / "out"
        cmd = [sys.executable, "-m", "nbvh_core", "compress", str(scan), "-o", str(out) + "/"]
        if args.time_limit:
            cmd += ["--time-limit", str(args.time_limit)]
        t = time.perf_counter()
        proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
        wall = time.perf_counter() - t
        row = {"asset": f"{args.asset} x4^{args.levels}", "triangles": source.n_triangles, "exit": proc.returncode,
               "wall_s": round(wall, 1)}
        why_path, glb = out / f"{source.name}.verdict.json", out / f"{source.name}.glb"
        if proc.returncode == 4 and why_path.exists() and glb.exists():
            why = json.loads(why_path.read_text())
            kept = load_mesh(glb)
            row.update(decided=why["recommendation"], kept_triangles=kept.n_triangles,
                       counted_compact_bytes=why["counted_compact_bytes"],
                       written_compact_bytes=why["files"].get(f"{source.name}.compact.cmsh"),
                       glb_bytes=glb.stat().st_size, glb_textured=bool(kept.look is not None and kept.look.textured),
                       **{k: why.get("kept_quality", {}).get(k) for k in ("mse", "colour_mse", "flip")},
                       **colour_agreement(source, kept))
        else:
            row["note"] = (proc.stderr.strip().splitlines() or [""])[-1][:200]
    print(row, flush=True)
    write_rows(result_path("textured_keep.csv"), [row], run_stamp)
    write_markdown(result_path("textured_keep.md"),
                   ["The Fuze scan over-tessellated, through `nbvh compress SCAN.glb -o OUT/` (the default).", ""]
                   + markdown_table(list(row), [list(row.values())]), run_stamp)


if __name__ == "__main__":
    main()
