"""Exact ray queries against the mesh on the card: `CardTracer` holds the mesh's own BVH (at most `LEAF_TRIANGLES`
triangles per leaf), its triangles and their normals on the device, and answers nearest hits within a t range with
one Triton kernel (`kernels/triton/mesh_trace.py`). It is `exact.ExactTracer`'s twin for the card's training labels:
the same quantities (t, triangle id, the unit geometric normal (v1 - v0) x (v2 - v0)), as torch tensors on the card;
Embree's watertight answers and these agree to float32 rounding (tests/test_card_labels.py measures it).

    tracer = CardTracer(mesh, "cuda")              # or CardTracer(mesh, device, tree=bvh.full): no second build
    t, tri = tracer.nearest(rays_o, rays_d, t_min, t_max)
"""
from __future__ import annotations

import numpy as np
import torch

from .mesh import Mesh
from .tree_build import FullTree, build_full_tree

#: Triangles per leaf of the card's mesh tree: a conventional tracer's (the numpy fallback's too).
LEAF_TRIANGLES = 4
#: Triangles whose corners are gathered at once when the table is made.
TABLE_CHUNK = 1 << 20


def mesh_records(mesh: Mesh, tree: FullTree | None = None,
                 leaf_triangles: int = LEAF_TRIANGLES) -> tuple[np.ndarray, int, np.ndarray, np.ndarray]:
    """The mesh tracer's tree from `tree` (default: a new binned-SAH build), every node of at most `leaf_triangles`
    a leaf: records (M, 8) float32 (lo, hi; then int32 links: an inner node's left child and 0, a leaf's -count and
    its first row), max_depth, triangles (T, 9) float32 (v0, v1 - v0, v2 - v0 in leaf order), tri_ids (T,) int32.
    Nodes are laid out level by level, siblings side by side (right = left + 1), the root first."""
    if tree is None:
        tree = build_full_tree(mesh, max_leaf_size=leaf_triangles)
    lo_rows, hi_rows, links, starts = [], [], [], []
    level, base, depth = np.zeros(1, np.int64), 0, 0
    while True:
        inner = (tree.left[level] >= 0) & (tree.count[level] > leaf_triangles)
        next_base = base + level.size
        rank = np.cumsum(inner) - inner
        links.append(np.where(inner, next_base + 2 * rank, -tree.count[level]))
        starts.append(np.where(inner, 0, tree.start[level]))
        lo_rows.append(tree.lo[level])
        hi_rows.append(tree.hi[level])
        if not inner.any():
            break
        kids = tree.left[level[inner]]
        level, base, depth = np.stack((kids, kids + 1), axis=1).reshape(-1), next_base, depth + 1
    records = np.zeros((next_base, 8), np.float32)
    records[:, 0:3] = np.concatenate(lo_rows)
    records[:, 3:6] = np.concatenate(hi_rows)
    ints = records.view(np.int32)
    ints[:, 6] = np.concatenate(links)
    ints[:, 7] = np.concatenate(starts)
    order = tree.tri_order
    triangles = np.empty((len(order), 9), np.float32)
    for a in range(0, len(order), TABLE_CHUNK):  # in parts: a 10M mesh's corners in float64 would be 720 MB at once
        corners = mesh.vertices[mesh.faces[order[a:a + TABLE_CHUNK]]].astype(np.float64)  # (chunk, 3, 3)
        triangles[a:a + TABLE_CHUNK, 0:3] = corners[:, 0]
        triangles[a:a + TABLE_CHUNK, 3:6] = corners[:, 1] - corners[:, 0]
        triangles[a:a + TABLE_CHUNK, 6:9] = corners[:, 2] - corners[:, 0]
    return records, depth, triangles, order.astype(np.int32)


class CardTracer:
    """Nearest hits on `device` (a card, or the CPU under Triton's interpreter in tests). tree: the run's full tree
    (`bvh.full`, `bvh.shared_tree`) when there is one, else one is built here."""

    def __init__(self, mesh: Mesh, device: torch.device | str, tree: FullTree | None = None):
        records, self.max_depth, triangles, tri_ids = mesh_records(mesh, tree)
        self.device = torch.device(device)
        self.records = torch.from_numpy(records).to(self.device)
        self.triangles = torch.from_numpy(triangles).to(self.device)
        self.tri_ids = torch.from_numpy(tri_ids).to(self.device)
        self.normals = torch.from_numpy(mesh.face_normals().astype(np.float32)).to(self.device)

    @property
    def resident_bytes(self) -> int:
        """Bytes this tracer holds on its device (the tree, the triangles, their ids and normals)."""
        return sum(t.numel() * t.element_size() for t in (self.records, self.triangles, self.tri_ids, self.normals))

    def nearest(self, rays_o: torch.Tensor, rays_d: torch.Tensor, t_min: torch.Tensor | None = None,
                t_max: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Nearest hit with max(t_min, 0) <= t <= t_max (None: 0 and inf, the whole ray). rays_o, rays_d: (N, 3)
        float32 on the tracer's device; t_min, t_max: (N,) float32. Returns t (N,) float32 (inf on a miss) and tri
        (N,) int64 (-1 on a miss)."""
        from ..kernels.triton.mesh_trace import nearest_hits

        zeros = torch.zeros(rays_o.shape[0], dtype=torch.float32, device=rays_o.device)
        t_min = zeros if t_min is None else t_min.clamp_min(0.0)
        t_max = zeros + float("inf") if t_max is None else t_max
        t, tri = nearest_hits(rays_o, rays_d, t_min, t_max, self.records, self.max_depth, self.triangles,
                              self.tri_ids)
        return t, tri.long()

    def first_hit(self, rays_o: torch.Tensor, rays_d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Nearest hit along the whole ray: t (N,) float32 (inf on a miss), tri (N,) int64 (-1), normal (N, 3)
        float32 (0 on a miss), as `ExactTracer.first_hit`'s fields."""
        t, tri = self.nearest(rays_o, rays_d)
        return t, tri, self.normals_of(tri)

    def normals_of(self, tri: torch.Tensor) -> torch.Tensor:
        """(N, 3) float32 unit normals of triangles `tri` (N,) int64, 0 where tri < 0."""
        normal = self.normals[tri.clamp_min(0)]
        return torch.where((tri >= 0)[:, None], normal, torch.zeros_like(normal))
