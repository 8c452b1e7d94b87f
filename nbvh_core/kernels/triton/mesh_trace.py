"""Exact ray-triangle queries on the card as one Triton kernel: per ray, the nearest triangle hit with
t_min <= t <= t_max, through the mesh's own BVH (front to back with a register-tile stack, boxes beyond the best hit
culled) and Moller-Trumbore in float32. The card's training labels use it (first hits, then each segment's nearest
hit); the reference is `exact.ExactTracer` (Embree, watertight), which it matches to float32 rounding: a ray that
grazes an edge or a vertex may hit the neighbour triangle or, rarely, slip through the seam (tests measure how often).

The tree (`geometry.card_tracer.mesh_records`): 32-byte rows as the model's (lo xyz, hi xyz float32) whose two int32
links read: an inner node's left child (> 0; the right is left + 1) and 0; a leaf's -count (<= 0) and its first row in
the leaf-ordered triangle table. Triangles: (T, 9) float32 rows v0, e1 = v1 - v0, e2 = v2 - v0, and their ids.

    t, tri = nearest_hits(rays_o, rays_d, t_min, t_max, records, max_depth, triangles, tri_ids)
"""
from __future__ import annotations

import torch
import triton
import triton.language as tl

from . import rows_per_program
from .bvh_walk import _box, _pop, _push, _xyz, stack_depth

#: Rays per program on a card (`rows_per_program`), warps per program. Not yet timed on a card.
BLOCK_R, WARPS = 32, 4


@triton.jit
def _dot(ax, ay, az, bx, by, bz):
    return ax * bx + ay * by + az * bz


@triton.jit
def _leaf_hits(tri_ptr, id_ptr, start, count, leaf, ox, oy, oz, dx, dy, dz, t_min, best, best_tri):
    """Moller-Trumbore against each leaf's triangles: the nearer hits within [t_min, best] replace (best, best_tri)
    (ties keep the first found, and a hit at t_max itself counts)."""
    for j in range(0, tl.max(tl.where(leaf, count, 0), axis=0)):
        m = leaf & (j < count)
        row = (start + j).to(tl.int64) * 9
        v0x = tl.load(tri_ptr + row + 0, mask=m, other=0.0)
        v0y = tl.load(tri_ptr + row + 1, mask=m, other=0.0)
        v0z = tl.load(tri_ptr + row + 2, mask=m, other=0.0)
        e1x = tl.load(tri_ptr + row + 3, mask=m, other=0.0)
        e1y = tl.load(tri_ptr + row + 4, mask=m, other=0.0)
        e1z = tl.load(tri_ptr + row + 5, mask=m, other=0.0)
        e2x = tl.load(tri_ptr + row + 6, mask=m, other=0.0)
        e2y = tl.load(tri_ptr + row + 7, mask=m, other=0.0)
        e2z = tl.load(tri_ptr + row + 8, mask=m, other=0.0)
        px, py, pz = dy * e2z - dz * e2y, dz * e2x - dx * e2z, dx * e2y - dy * e2x  # d x e2
        det = _dot(e1x, e1y, e1z, px, py, pz)
        inv = 1.0 / tl.where(det != 0.0, det, 1.0)
        sx, sy, sz = ox - v0x, oy - v0y, oz - v0z
        u = _dot(sx, sy, sz, px, py, pz) * inv
        qx, qy, qz = sy * e1z - sz * e1y, sz * e1x - sx * e1z, sx * e1y - sy * e1x  # s x e1
        v = _dot(dx, dy, dz, qx, qy, qz) * inv
        t = _dot(e2x, e2y, e2z, qx, qy, qz) * inv
        ok = m & (det != 0.0) & (u >= 0.0) & (v >= 0.0) & (u + v <= 1.0) & (t >= t_min)
        ok = ok & ((t < best) | ((t == best) & (best_tri < 0)))
        best = tl.where(ok, t, best)
        best_tri = tl.where(ok, tl.load(id_ptr + start + j, mask=m, other=-1), best_tri)
    return best, best_tri


@triton.jit
def _nearest_hits(o_ptr, d_ptr, inv_ptr, tmin_ptr, tmax_ptr, n, rec_f_ptr, rec_i_ptr, tri_ptr, id_ptr, t_ptr, out_ptr,
                  DEPTH: tl.constexpr, BR: tl.constexpr):
    rows = tl.program_id(0) * BR + tl.arange(0, BR)
    live = rows < n
    ox, oy, oz = _xyz(o_ptr, rows, live, 0.0)
    dx, dy, dz = _xyz(d_ptr, rows, live, 0.0)
    ix, iy, iz = _xyz(inv_ptr, rows, live, 1.0)
    t_min = tl.load(tmin_ptr + rows, mask=live, other=0.0)
    best = tl.load(tmax_ptr + rows, mask=live, other=0.0)
    best_tri = tl.full((BR,), -1, tl.int32)
    slots = tl.arange(0, DEPTH)
    stack = tl.zeros((BR, DEPTH), tl.int32)  # slot 0: the root, node 0
    sp = live.to(tl.int32)
    while tl.max(sp, axis=0) > 0:
        active = sp > 0
        node, sp = _pop(stack, sp, slots, active)
        entered, te, tx = _box(rec_f_ptr, node, active, ox, oy, oz, ix, iy, iz)
        # the box again at the pop: a hit found since the push may cull it now
        visit = active & entered & (te <= best) & (tx >= t_min)
        link = tl.load(rec_i_ptr + node.to(tl.int64) * 8 + 6, mask=visit, other=0)
        start = tl.load(rec_i_ptr + node.to(tl.int64) * 8 + 7, mask=visit, other=0)
        leaf = visit & (link <= 0)
        best, best_tri = _leaf_hits(tri_ptr, id_ptr, start, -link, leaf, ox, oy, oz, dx, dy, dz, t_min, best,
                                    best_tri)
        inner = visit & (link > 0)
        hit_l, te_l, tx_l = _box(rec_f_ptr, link, inner, ox, oy, oz, ix, iy, iz)
        hit_r, te_r, tx_r = _box(rec_f_ptr, link + 1, inner, ox, oy, oz, ix, iy, iz)
        hit_l = inner & hit_l & (te_l <= best) & (tx_l >= t_min)
        hit_r = inner & hit_r & (te_r <= best) & (tx_r >= t_min)
        right_first = te_r < te_l
        near = tl.where(right_first, link + 1, link)
        far = tl.where(right_first, link, link + 1)
        stack, sp = _push(stack, sp, slots, far, tl.where(right_first, hit_l, hit_r))
        stack, sp = _push(stack, sp, slots, near, tl.where(right_first, hit_r, hit_l))
    tl.store(t_ptr + rows, tl.where(best_tri >= 0, best, float("inf")), mask=live)
    tl.store(out_ptr + rows, best_tri, mask=live)


def nearest_hits(rays_o: torch.Tensor, rays_d: torch.Tensor, t_min: torch.Tensor, t_max: torch.Tensor,
                 records: torch.Tensor, max_depth: int, triangles: torch.Tensor,
                 tri_ids: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The nearest hit of every ray with t_min <= t <= t_max, in one launch.

    rays_o, rays_d: (N, 3) float32 (t in units of |rays_d|); t_min, t_max: (N,) float32 (t_min >= 0); records: (M, 8)
    float32 tree rows (module docstring), max_depth: the tree's depth; triangles: (T, 9) float32 in leaf order;
    tri_ids: (T,) int32 each row's triangle id. Returns t (N,) float32, inf on a miss, and tri (N,) int32, -1."""
    n = rays_o.shape[0]
    dev = rays_o.device
    t = torch.empty(n, dtype=torch.float32, device=dev)
    tri = torch.empty(n, dtype=torch.int32, device=dev)
    if n == 0:
        return t, tri
    rays_o = rays_o.contiguous().float()
    rays_d = rays_d.contiguous().float()
    inv_d = (1.0 / rays_d).contiguous()  # 1/0 = inf: the slab test takes it, as `traversal.ray_box`
    records = records.contiguous()
    rows = rows_per_program(BLOCK_R)
    _nearest_hits[(triton.cdiv(n, rows),)](
        rays_o, rays_d, inv_d, t_min.contiguous().float(), t_max.contiguous().float(), n, records,
        records.view(torch.int32), triangles.contiguous(), tri_ids.contiguous(), t, tri,
        DEPTH=stack_depth(max_depth), BR=rows, num_warps=WARPS)
    return t, tri
