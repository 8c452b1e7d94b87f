"""Exact ray queries against the mesh: the ground truth for training labels and reference images.

`ExactTracer` uses Embree (through embreex) and falls back, with a warning, to a vectorised Moller-Trumbore
intersector over a fine BVH (our builder, 4 triangles per leaf, traversed with `traversal.leaves_along_rays`)
only where embreex cannot be imported. Both backends return the same quantities:

* `first_hit`: distance t (inf on a miss), triangle id (-1 on a miss) and the unit geometric normal
  (v1 - v0) x (v2 - v0) of the hit triangle (not flipped toward the ray).
* `all_hits`: every intersection along each ray, sorted by t, as a flat list grouped by ray (CSR).

All inputs and outputs are in normalised mesh coordinates, float32; directions need not be unit length
(t is measured in units of |d|), but the samplers here always pass unit directions.
"""
from __future__ import annotations

import os
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from .embree_scene import open_scene
from .mesh import Mesh

#: Embree queries of at least this many rays are split over threads (embreex releases the GIL: 2 threads trace
#: 32k training rays in 3.7 instead of 7.5 ms on the 2-core CPU).
PARALLEL_MIN_RAYS = 4096
_pool: ThreadPoolExecutor | None = None


def _threads() -> int:
    return max(1, min(8, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1))


#: After a hit, the next all-hits query starts this far (normalised units) beyond it; closer hits merge.
ALL_HITS_EPS = 1e-5


class _EmbreexScene:
    """embreex's scene, where `embree_scene.open_scene` cannot build one (no kernel library)."""

    def __init__(self, scene):
        self.scene = scene

    def intersect(self, rays_o: np.ndarray, rays_d: np.ndarray, t_max: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        res = self.scene.run(rays_o, rays_d, dists=np.ascontiguousarray(t_max, np.float32), query="INTERSECT",
                             output=1)
        return res["tfar"], res["primID"]


@dataclass
class FirstHits:
    """t: (N,) float32, inf = miss; tri: (N,) int64, -1 = miss; normal: (N, 3) float32 (0 on a miss)."""

    t: np.ndarray
    tri: np.ndarray
    normal: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        return self.tri >= 0


@dataclass
class AllHits:
    """Every hit, grouped by ray and sorted by t. ray, tri: (H,) int64; t: (H,) float32; offsets: (N + 1,).
    `truncated`: number of rays that had more than `max_hits` hits (their list is cut)."""

    ray: np.ndarray
    t: np.ndarray
    tri: np.ndarray
    offsets: np.ndarray
    truncated: int = 0


class ExactTracer:
    """Exact first-hit and all-hits queries on one mesh; `backend` is 'embree' or 'numpy'."""

    def __init__(self, mesh: Mesh, backend: str = "auto"):
        self.mesh = mesh
        # held, not computed per hit: computing them when asked (12 B per triangle saved) made labelling ~20%
        # slower (a 32-step chunk on the bunny: 95-103 ms against 79-80 ms)
        self._normals = mesh.face_normals()
        if backend not in ("auto", "embree", "numpy"):
            raise ValueError(f"unknown backend {backend!r}")
        self._scene = None
        if backend in ("auto", "embree"):
            self._scene = open_scene(mesh.vertices, mesh.faces)  # shared buffers, compact (embree_scene.py)
        if backend in ("auto", "embree") and self._scene is None:
            try:
                from embreex import rtcore_scene
                from embreex.mesh_construction import TriangleMesh
            except ImportError as exc:
                if backend == "embree":
                    raise
                warnings.warn(f"embreex unavailable ({exc}); exact ray queries use the slower numpy fallback",
                              RuntimeWarning, stacklevel=2)
            else:
                self._scene = _EmbreexScene(rtcore_scene.EmbreeScene())
                # the mesh's own arrays (already float32 / int32): Embree copies them into its buffers
                TriangleMesh(scene=self._scene.scene, vertices=mesh.vertices.astype(np.float32, copy=False),
                             indices=mesh.faces.astype(np.int32, copy=False))
        if self._scene is None:
            self._init_fallback()
        self.backend = "embree" if self._scene is not None else "numpy"
        self._card = None  # the mesh's tracer on a card (`on_card`), made when first asked for

    def on_card(self, device: "torch.device | str", tree=None):
        """This mesh's `card_tracer.CardTracer` on `device`, made once (a run's trainings share it). tree: the run's
        full tree over this mesh (`bvh.full`), so that the card's tree costs no second build."""
        import torch

        from .card_tracer import CardTracer

        card = self._card
        if card is None or card.device != torch.device(device):
            fits = tree is not None and len(tree.tri_order) == self.mesh.n_triangles
            card = self._card = CardTracer(self.mesh, device, tree if fits else None)
        return card

    @property
    def scene_kind(self) -> str:
        """Which scene answers (for results): 'embree compact' / 'embree' (the kernel library's, on the mesh's
        arrays), 'embreex' (the fallback that copies them) or 'numpy'."""
        if isinstance(self._scene, _EmbreexScene):
            return "embreex"
        if self._scene is None:
            return "numpy"
        return "embree compact" if getattr(self._scene, "compact", False) else "embree"

    def normals(self, tri: np.ndarray) -> np.ndarray:
        """(K, 3) float32 unit normals of triangles `tri` (K,) int."""
        return np.take(self._normals, tri, axis=0)  # a third of fancy indexing's time for 60k rows

    def _intersect(self, rays_o: np.ndarray, rays_d: np.ndarray, t_max: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Embree nearest hits within t_max: (tfar (N,) float32, primID (N,) int32, -1 on a miss); split over
        threads for large batches (the same per-ray answers: rays are independent)."""
        global _pool
        if not isinstance(self._scene, _EmbreexScene):  # the kernel library spreads the rays itself
            return self._scene.intersect(rays_o, rays_d, t_max)
        n = rays_o.shape[0]
        parts = _threads() if n >= PARALLEL_MIN_RAYS else 1

        def run(a: int, b: int):
            return self._scene.intersect(rays_o[a:b], rays_d[a:b], t_max[a:b])

        if parts == 1:
            return run(0, n)
        if _pool is None:
            _pool = ThreadPoolExecutor(max_workers=_threads(), thread_name_prefix="nbvh-embree")
        cuts = [n * i // parts for i in range(parts + 1)]
        out = list(_pool.map(lambda i: run(cuts[i], cuts[i + 1]), range(parts)))
        return np.concatenate([t for t, _ in out]), np.concatenate([p for _, p in out])

    # -- first hit -----------------------------------------------------------------------------------------
    def first_hit(self, rays_o: np.ndarray, rays_d: np.ndarray, t_max: np.ndarray | float = np.inf) -> FirstHits:
        """Nearest hit with 0 <= t <= t_max. rays_o, rays_d: (N, 3) float32; t_max: scalar or (N,)."""
        rays_o = np.ascontiguousarray(rays_o, dtype=np.float32)
        rays_d = np.ascontiguousarray(rays_d, dtype=np.float32)
        n = rays_o.shape[0]
        t_max_arr = np.broadcast_to(np.asarray(t_max, np.float32), (n,)).copy()  # embreex needs writable
        if n == 0:
            return FirstHits(np.zeros(0, np.float32), np.zeros(0, np.int64), np.zeros((0, 3), np.float32))
        if self._scene is not None:
            # embreex takes tfar as `dists`; inf is accepted.
            tfar, prim = self._intersect(rays_o, rays_d, t_max_arr)
            tri = prim.astype(np.int64)
            t = np.where(tri >= 0, tfar, np.inf).astype(np.float32)
        else:
            t, tri = self._fallback_first(rays_o, rays_d, t_max_arr)
        normal = np.zeros((n, 3), np.float32)
        hit = tri >= 0
        normal[hit] = self.normals(tri[hit])
        return FirstHits(t=t, tri=tri, normal=normal)

    # -- all hits ------------------------------------------------------------------------------------------
    def all_hits(self, rays_o: np.ndarray, rays_d: np.ndarray, t_max: np.ndarray | float = np.inf,
                 max_hits: int = 256, first: FirstHits | None = None) -> AllHits:
        """All hits with 0 <= t <= t_max, sorted by t per ray (hits closer than ALL_HITS_EPS apart merge).

        first: these rays' `first_hit` results, when the caller has them: they are the first round of the search
        (the nearest hit within t_max is the nearest hit, if it lies within t_max), one Embree pass fewer."""
        rays_o = np.ascontiguousarray(rays_o, dtype=np.float32)
        rays_d = np.ascontiguousarray(rays_d, dtype=np.float32)
        n = rays_o.shape[0]
        t_max_arr = np.broadcast_to(np.asarray(t_max, np.float64), (n,)).copy()
        if self._scene is None:
            return self._fallback_all(rays_o, rays_d, t_max_arr, max_hits)
        rays_ = []
        ts = []
        tris = []
        live = np.arange(n)
        t_base = np.zeros(n, np.float64)  # distance already travelled by each live ray
        # Restarts go just beyond a hit: a step of ALL_HITS_EPS in space, scaled by |d| (per ray, once).
        restart = ALL_HITS_EPS / np.linalg.norm(rays_d, axis=1)
        truncated = 0
        if first is not None and max_hits > 0:
            live = live[(first.tri >= 0) & (first.t.astype(np.float64) <= t_max_arr)]
            t_hit = first.t[live].astype(np.float64)
            rays_.append(live)
            ts.append(t_hit)
            tris.append(first.tri[live])
            t_base[live] = t_hit + restart[live]
            max_hits -= 1
        for _ in range(max_hits):
            if live.size == 0:
                break
            o = (rays_o[live] + rays_d[live] * t_base[live, None]).astype(np.float32)
            tfar, prim = self._intersect(o, np.ascontiguousarray(rays_d[live]), t_max_arr[live] - t_base[live])
            hit = prim >= 0
            live = live[hit]
            t_hit = t_base[live] + tfar[hit]
            rays_.append(live)
            ts.append(t_hit)
            tris.append(prim[hit].astype(np.int64))
            t_base[live] = t_hit + restart[live]
        else:
            truncated = int(live.size)
        return _pack_rounds(n, rays_, ts, tris, truncated)

    # -- fallback ------------------------------------------------------------------------------------------
    def _init_fallback(self) -> None:
        from .bvh import build_full_tree, cut_tree
        from .traversal import TorchBVH

        tree = build_full_tree(self.mesh, max_leaf_size=4)
        self._fine = cut_tree(tree, tree.n_nodes, max_nodes=None)  # the whole tree, <= 4 triangles per leaf
        self._fine_torch = TorchBVH.from_bvh(self._fine)
        tri = self.mesh.triangles().astype(np.float64)
        self._v0 = tri[:, 0]
        self._e1 = tri[:, 1] - tri[:, 0]
        self._e2 = tri[:, 2] - tri[:, 0]

    def _candidates(self, rays_o, rays_d, t_max):
        """(ray, triangle, t) of every intersection within [0, t_max] (Moller-Trumbore, float64)."""
        import torch

        from .traversal import leaves_along_rays

        lh = leaves_along_rays(self._fine_torch, torch.from_numpy(rays_o), torch.from_numpy(rays_d),
                               torch.from_numpy(t_max.astype(np.float32)))
        ray = lh.ray.numpy()
        leaf = lh.leaf.numpy()
        starts, counts = self._fine.leaf_tri_start[leaf], self._fine.leaf_tri_count[leaf]
        rep_ray = np.repeat(ray, counts)
        offs = np.concatenate(([0], np.cumsum(counts)[:-1]))
        pos = np.repeat(starts - offs, counts) + np.arange(int(counts.sum()))
        tri = self._fine.tri_order[pos]
        o = rays_o[rep_ray].astype(np.float64)
        d = rays_d[rep_ray].astype(np.float64)
        e1, e2 = self._e1[tri], self._e2[tri]
        p = np.cross(d, e2)
        det = np.einsum("ij,ij->i", e1, p)
        ok = np.abs(det) > 1e-18
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        s = o - self._v0[tri]
        u = np.einsum("ij,ij->i", s, p) * inv
        q = np.cross(s, e1)
        v = np.einsum("ij,ij->i", d, q) * inv
        t = np.einsum("ij,ij->i", e2, q) * inv
        good = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0) & (t <= t_max[rep_ray])
        return rep_ray[good], tri[good], t[good]

    def _fallback_first(self, rays_o, rays_d, t_max):
        n = rays_o.shape[0]
        ray, tri, t = self._candidates(rays_o, rays_d, np.asarray(t_max, np.float64))
        best_t = np.full(n, np.inf)
        np.minimum.at(best_t, ray, t)
        best_tri = np.full(n, -1, np.int64)
        is_best = t == best_t[ray]
        best_tri[ray[is_best]] = tri[is_best]
        return best_t.astype(np.float32), best_tri

    def _fallback_all(self, rays_o, rays_d, t_max, max_hits):
        n = rays_o.shape[0]
        ray, tri, t = self._candidates(rays_o, rays_d, t_max)
        order = np.lexsort((t, ray))
        ray, tri, t = ray[order], tri[order], t[order]
        # Merge hits closer than ALL_HITS_EPS (shared edges report the same point twice), as Embree's restart does.
        dup = np.zeros(ray.size, bool)
        dup[1:] = (ray[1:] == ray[:-1]) & (t[1:] - t[:-1] < ALL_HITS_EPS)
        ray, tri, t = ray[~dup], tri[~dup], t[~dup]
        rank = np.arange(ray.size) - np.searchsorted(ray, ray)
        truncated = int(np.unique(ray[rank >= max_hits]).size)
        keep = rank < max_hits
        return _pack_hits(n, [ray[keep]], [t[keep]], [tri[keep]], truncated)


def _pack_rounds(n: int, rays: list, ts: list, tris: list, truncated: int) -> AllHits:
    """The hits of Embree's rounds (round k: each live ray's k-th hit, rays ascending) packed by ray, nearest first,
    without a sort: a ray live in round k was live in every round before it, so its k-th hit goes to offsets[ray] + k
    (a lexsort, as `_pack_hits` does for the fallback's unordered hits, costs a tenth of a chunk's labels on the
    bunny)."""
    counts = np.zeros(n, np.int64)
    for ray in rays:
        counts[ray] += 1  # a ray is live at most once per round: no repeated index
    offsets = np.zeros(n + 1, np.int64)
    np.cumsum(counts, out=offsets[1:])
    total = int(offsets[-1])
    ray_out, t_out, tri_out = np.empty(total, np.int64), np.empty(total, np.float32), np.empty(total, np.int64)
    for k, (ray, t, tri) in enumerate(zip(rays, ts, tris)):
        at = offsets[ray] + k
        ray_out[at], t_out[at], tri_out[at] = ray, t, tri
    return AllHits(ray=ray_out, t=t_out, tri=tri_out, offsets=offsets, truncated=truncated)


def _pack_hits(n: int, rays: list, ts: list, tris: list, truncated: int) -> AllHits:
    ray = np.concatenate(rays) if rays else np.zeros(0, np.int64)
    t = np.concatenate(ts).astype(np.float32) if ts else np.zeros(0, np.float32)
    tri = np.concatenate(tris) if tris else np.zeros(0, np.int64)
    order = np.lexsort((t, ray))
    ray, t, tri = ray[order], t[order], tri[order]
    offsets = np.zeros(n + 1, np.int64)
    offsets[1:] = np.cumsum(np.bincount(ray, minlength=n))
    return AllHits(ray=ray.astype(np.int64), t=t, tri=tri, offsets=offsets, truncated=truncated)
