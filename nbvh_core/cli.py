"""Command line: `python -m nbvh_core COMMAND ...` (also installed as `nbvh`).

Commands:
  inspect MESH|SAMPLE --out DIR   build the BVH, generate labelled training rays (both modes), write
                                  DIR/report.json, DIR/reference.png (paper shading) and DIR/leaves.png
                                  (each pixel coloured by the BVH leaf that owns the visible triangle).
  samples                         list the bundled sample meshes.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np


def _resolve_mesh(arg: str) -> Path:
    from .samples_dir import SAMPLE_NAMES, sample_path

    if arg in SAMPLE_NAMES:
        return sample_path(arg)
    return Path(arg)


def cmd_inspect(args: argparse.Namespace) -> int:
    import torch

    from .bvh import build_full_tree, cut_tree, resident_bvh_nodes
    from .exact import ExactTracer
    from .mesh import load_mesh
    from .render import Camera, render_reference, save_png
    from .samples import generate_training_samples

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        mesh = load_mesh(_resolve_mesh(args.mesh))
    for w in caught:
        print(f"warning: {w.message}", file=sys.stderr)
    t_load = time.perf_counter() - t0
    print(f"{mesh.name}: {mesh.n_vertices} vertices, {mesh.n_triangles} triangles (loaded in {t_load:.2f} s)")

    t0 = time.perf_counter()
    tree = build_full_tree(mesh)
    bvh = cut_tree(tree, args.nodes)
    t_bvh = time.perf_counter() - t0
    print(f"BVH: {bvh.n_nodes} nodes ({bvh.nbytes} B), {bvh.n_leaves} leaves, depth {bvh.max_depth}, "
          f"built in {t_bvh:.2f} s")

    tracer = ExactTracer(mesh)
    sample_stats = {}
    for mode in ("ownership", "consistent"):
        t0 = time.perf_counter()
        s = generate_training_samples(bvh, tracer, args.rays, mode, seed=args.seed)
        dt = time.perf_counter() - t0
        sample_stats[mode] = dict(s.stats, seconds=round(dt, 3), samples_per_s=round(len(s) / dt),
                                  mean_leaves_per_ray=round(len(s) / args.rays, 2))
        print(f"training rays ({mode}): {args.rays} rays -> {len(s)} samples, {int(s.hit.sum())} hits, "
              f"{len(s) / dt:,.0f} samples/s")

    cam = Camera(position=np.array([0.5 + 1.25, 0.5 + 0.8, 0.5 + 1.25]), target=np.full(3, 0.5),
                 up=np.array([0.0, 1.0, 0.0]))
    ref = render_reference(tracer, cam, args.size, args.size)
    save_png(out / "reference.png", ref.image)
    # Leaf colouring: owner leaf of the visible triangle, random colour per leaf, modulated by the shading.
    o, d = cam.rays(args.size, args.size)
    fh = tracer.first_hit(o, d)
    palette = np.random.default_rng(1).uniform(0.25, 1.0, size=(bvh.n_leaves, 3))
    colour = np.zeros((len(o), 3))
    colour[fh.hit] = palette[bvh.tri_leaf[fh.tri[fh.hit]]] * (0.3 + 0.7 * ref.image.reshape(-1)[fh.hit, None])
    save_png(out / "leaves.png", colour.reshape(args.size, args.size, 3))

    vertex_bytes = mesh.n_vertices * 12
    index_bytes = mesh.n_triangles * 12
    normal_bytes = mesh.n_vertices * 12
    resident_nodes = resident_bvh_nodes(tree, 4)
    report = {
        "mesh": {"name": mesh.name, "vertices": mesh.n_vertices, "triangles": mesh.n_triangles,
                 "repairs": list(mesh.repairs), "transform": mesh.transform.to_dict(),
                 "surface_area_normalised": round(mesh.surface_area(), 4), "load_seconds": round(t_load, 3)},
        "bvh": {"budget": args.nodes, "nodes": bvh.n_nodes, "leaves": bvh.n_leaves, "bytes": bvh.nbytes,
                "max_depth": bvh.max_depth, "build_seconds": round(t_bvh, 3),
                "triangles_per_leaf": {"min": int(bvh.leaf_tri_count.min()), "max": int(bvh.leaf_tri_count.max()),
                                       "mean": round(float(bvh.leaf_tri_count.mean()), 2)}},
        "resident_mesh_bytes": {"vertices_f32": vertex_bytes, "indices_i32": index_bytes,
                                "normals_f32": normal_bytes, "bvh_nodes_leaf4": resident_nodes,
                                "bvh_bytes_leaf4": resident_nodes * 32,
                                "total": vertex_bytes + index_bytes + normal_bytes + resident_nodes * 32},
        "training_samples": sample_stats,
        "exact_backend": tracer.backend,
        "torch": torch.__version__,
    }
    (out / "report.json").write_text(json.dumps(report, indent=2))
    print(f"wrote {out / 'report.json'}, {out / 'reference.png'}, {out / 'leaves.png'}")
    return 0


def cmd_samples(args: argparse.Namespace) -> int:
    from .samples_dir import SAMPLE_NAMES, sample_path

    for name, what in SAMPLE_NAMES.items():
        p = sample_path(name)
        print(f"{name:8s} {what:45s} {p}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="nbvh", description="Neural BVH geometry compression")
    sub = p.add_subparsers(dest="command", required=True)
    q = sub.add_parser("inspect", help="BVH + training rays of a mesh: report and images")
    q.add_argument("mesh", help="mesh file (OBJ/PLY/STL/OFF/GLB/glTF, optionally .gz) or a bundled sample name")
    q.add_argument("--out", required=True, help="output folder")
    q.add_argument("--nodes", type=int, default=4096, help="BVH node budget (1..65535, default 4096)")
    q.add_argument("--rays", type=int, default=50_000, help="training rays to generate per label mode")
    q.add_argument("--seed", type=int, default=0)
    q.add_argument("--size", type=int, default=384, help="image size in pixels")
    q.set_defaults(func=cmd_inspect)
    s = sub.add_parser("samples", help="list the bundled sample meshes")
    s.set_defaults(func=cmd_samples)
    return p


def main(argv: list[str] | None = None) -> int:
    from .mesh import MeshError

    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except MeshError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
