"""The shared measurement library of the rate-distortion benchmarks (bench_quality, bench_leaf_sampling,
fit_sizing): the plan of a run, the benchmark meshes' tracers and failure-subset rays, one neural training row,
and reading a (bytes, MSE) curve."""
from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import torch

from bench.meshes import BENCH_MESHES, bench_mesh
from bench.harness import RESULTS, append_row
from nbvh_core.app.pipeline import compress_mesh, preset
from nbvh_core.geometry.bvh import build_bvh
from nbvh_core.geometry.exact import ExactTracer
from nbvh_core.geometry.mesh import Mesh
from nbvh_core.planning.settings import Settings
from nbvh_core.geometry.traversal import TorchBVH, leaves_along_rays
from nbvh_core.training.rays import RayConfig, root_box, sample_rays
from nbvh_core.training.train import TrainingDiverged

METHODS = ("base", "I", "II", "III", "default")  # the paper's steps + the user preset (HashGrid + MLP + consistent)
# Table sizes (log2 T) per encoding, chosen so the two encodings span the same bytes: HashGrid T rows of 16 floats
# per level; HashVQAD T rows + an index of 128 T 4-bit codes per level (twice the bytes of its rows).
SIZES = {"hashgrid": (8, 10, 12), "hashvqad": (7, 9, 11)}
SUBSETS = ("all", "late", "grazing", "thin", "near_start")


class Plan:
    def __init__(self, quick: bool):
        self.quick = quick
        self.meshes = ("blob", "knot") if quick else BENCH_MESHES
        self.train_s = 1.0 if quick else 15.0  # quick: a smoke run checks the parts run and stamp, not quality
        self.views, self.res = (4, 48) if quick else (Settings().eval_views, Settings().eval_resolution)
        # All sizes for III and the user preset (rate-distortion curves); the middle size for base, I, II.
        self.full_sizes_methods = ("III", "default") if not quick else ("default",)
        self.seed_meshes = ("knot",) if quick else ("bunny", "knot")
        self.seeds = (1,) if quick else (1, 2)
        self.time_budgets = (0.5, 1.0) if quick else (5.0, 15.0, 45.0)
        self.time_meshes = ("blob",) if quick else ("bunny",)
        self.draco_bits = (8, 11) if quick else (7, 8, 9, 10, 11, 14)
        self.decimate_to = (1000,) if quick else (500, 1000, 2500, 10000, 40000)
        self.failure_rays = (4000, 2000) if quick else (20000, 8000)
        self.suffix = "_quick" if quick else ""

    def csv(self, name: str) -> Path:
        return RESULTS / f"{name}{self.suffix}.csv"


# ------------------------------------------------------------------------------------------------ failure subsets
def failure_rays(mesh: Mesh, bvh, tracer: ExactTracer, n_dist: int, n_near: int, seed: int = 12345) -> dict:
    """The evaluation rays and their subset masks (see module docstring); computed once per mesh."""
    rng = np.random.default_rng(seed)
    lo, hi = root_box(bvh)
    o, d = sample_rays(lo, hi, n_dist, rng, RayConfig())
    # Rays starting 0.003 off the surface (either side), uniform directions.
    tri = mesh.triangles().astype(np.float64)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    pick = rng.choice(len(tri), size=n_near, p=area / area.sum())
    u, v = rng.random(n_near), rng.random(n_near)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    p = tri[pick, 0] + u[:, None] * (tri[pick, 1] - tri[pick, 0]) + v[:, None] * (tri[pick, 2] - tri[pick, 0])
    side = np.where(rng.random(n_near) < 0.5, -1.0, 1.0)
    o_near = p + 0.003 * side[:, None] * tracer.normals(pick)
    d_near = rng.normal(size=(n_near, 3))
    d_near /= np.linalg.norm(d_near, axis=1, keepdims=True)
    o_all = np.concatenate([o, o_near]).astype(np.float32)
    d_all = np.concatenate([d, d_near]).astype(np.float32)
    fh = tracer.first_hit(o_all, d_all)
    t_true = np.where(fh.hit, fh.t, np.inf).astype(np.float32)
    # Leaves entered up to the true hit: the hit's leaf is the last of them.
    tree = TorchBVH.from_bvh(bvh)
    lh = leaves_along_rays(tree, torch.from_numpy(o_all), torch.from_numpy(d_all),
                           torch.from_numpy(np.where(fh.hit, t_true, 0).astype(np.float32)))
    entered = lh.counts().numpy()
    cos = np.abs(np.einsum("ij,ij->i", fh.normal, d_all))
    behind = tracer.all_hits(o_all, d_all, t_max=np.where(fh.hit, t_true + 0.02, 0).astype(np.float32))
    n_behind = np.bincount(behind.ray, minlength=len(o_all))
    is_dist = np.arange(len(o_all)) < n_dist
    masks = {"all": is_dist, "late": is_dist & fh.hit & (entered >= 4), "grazing": is_dist & fh.hit & (cos < 0.2),
             "thin": is_dist & fh.hit & (n_behind >= 2), "near_start": ~is_dist}
    return {"o": torch.from_numpy(o_all), "d": torch.from_numpy(d_all), "hit": fh.hit, "t": t_true, "masks": masks}


def failure_errors(model, fr: dict) -> dict:
    q = model.query(fr["o"], fr["d"])
    hit, t = q.hit.cpu().numpy(), q.t.cpu().numpy()
    out = {}
    for name, m in fr["masks"].items():
        n = int(m.sum())
        out[f"{name}_n"] = n
        out[f"{name}_hit_err"] = float((hit[m] != fr["hit"][m]).mean() * 100) if n else math.nan
        both = m & hit & fr["hit"]
        out[f"{name}_depth_err"] = float(np.abs(t[both] - fr["t"][both]).mean()) if both.any() else math.nan
    return out


# ----------------------------------------------------------------------------------------------------------- parts
class MeshCache:
    def __init__(self, plan: Plan):
        self.plan, self.cache = plan, {}

    def get(self, name: str):
        if name not in self.cache:
            mesh = bench_mesh(name)
            bvh = build_bvh(mesh, preset("default").nodes)
            tracer = ExactTracer(mesh)
            self.cache = {name: (mesh, tracer, failure_rays(mesh, bvh, tracer, *self.plan.failure_rays))}
        return self.cache[name]


def run_neural(plan: Plan, cache: MeshCache, part: str, mesh_name: str, method: str, log2: int, seed: int,
               train_s: float, done: set, nodes: int | None = None) -> None:
    key = (part, mesh_name, method, str(log2), str(seed), f"{train_s:g}")
    if key in done:
        return
    mesh, tracer, fr = cache.get(mesh_name)
    # force: a grid point is measured whatever the verdict says of a model this size
    s = preset(method).with_overrides(log2_table=log2, seed=seed, time_limit_s=train_s, eval_views=plan.views,
                                      eval_resolution=plan.res, nodes=nodes, force=True)
    t0 = time.perf_counter()
    row = {"part": part, "mesh": mesh_name, "method": method, "log2_table": log2, "seed": seed, "train_s": f"{train_s:g}",
           "encoding": s.encoding, "network": s.network, "labels": s.labels, "nodes": s.nodes,
           "triangles": mesh.n_triangles}
    try:
        res = compress_mesh(mesh, s)
    except TrainingDiverged as exc:
        row.update(diverged=str(exc))
        append_row(plan.csv("quality"), row)
        return
    q = res.quality
    row.update(diverged="", file_bytes=res.file_bytes, steps=res.training.steps,
               samples_per_s=round(res.training.samples_per_s), mse=q.mse, iou=q.silhouette_iou,
               depth_err=q.depth_error, neural_rays_per_s=round(q.neural_rays_per_s),
               embree_rays_per_s=round(q.reference_rays_per_s), path=res.training.compute_path,
               wall_s=round(time.perf_counter() - t0, 1))
    row.update({k: (round(v, 6) if isinstance(v, float) else v) for k, v in failure_errors(res.model, fr).items()})
    append_row(plan.csv("quality"), row)
    print(f"{part} {mesh_name} {method} T=2^{log2} seed {seed}: {res.file_bytes:,} B mse {q.mse:.5f} "
          f"iou {q.silhouette_iou:.3f} ({row['wall_s']} s)", flush=True)


# ------------------------------------------------------------------------------------------------ tables, charts
def interp_bytes_for_mse(points: list[tuple[float, float]], target: float) -> float | None:
    """Bytes at which a (bytes, mse) curve reaches `target`, by log-log interpolation; None when it never does."""
    pts = sorted(points)
    for (b0, m0), (b1, m1) in zip(pts, pts[1:]):
        if m0 >= target >= m1 and m0 > 0 and m1 > 0 and m0 != m1:
            a = (math.log(target) - math.log(m0)) / (math.log(m1) - math.log(m0))
            return math.exp(math.log(b0) + a * (math.log(b1) - math.log(b0)))
    if pts and pts[0][1] <= target:
        return pts[0][0]  # already at the smallest size (an upper bound on what it needs)
    return None
