"""Batched BVH traversal in torch (CPU or CUDA, same code): which leaves does each ray enter, and where.

Two forms:

* `leaves_along_rays` - the complete list (training): for every ray, every leaf whose box it enters, sorted
  front to back by `t_enter`, packed as one flat list grouped by ray (CSR, `LeafHits.offsets`). The traversal
  walks the tree level by level over all (ray, node) pairs at once; the Python loop is over tree depth only.
* `LeafStream` - streaming front to back (rendering): every call to `next()` gives each live ray its next leaf
  from a per-ray stack (nearer child popped first, as in N-BVH's inference). A renderer that finds a hit calls
  `shorten()` (the ray's max t becomes the hit: boxes entered beyond it are skipped) or `stop()`, so work ends at
  the first hit instead of visiting every leaf.

Slab test: t0 = (lo - o) / d, t1 = (hi - o) / d per axis; t_enter = max(0, max_axis min(t0, t1)),
t_exit = min_axis max(t0, t1); the ray enters the box when t_enter <= t_exit (touching counts) and
t_enter <= t_max. Rays that start inside a box get t_enter = 0. Division by a zero direction component gives
+-inf; NaN (0 * inf, ray on a slab plane) is ignored by fmin/fmax, so axis-parallel rays work.
"""
from __future__ import annotations


from dataclasses import dataclass

import numpy as np
import torch

from .. import kernels
from ..kernels import bindings
from .bvh import BVH


class TorchBVH:
    """BVH node records as tensors on one device, without copies beyond the one (M, 8) record table: `records`
    holds each 32-byte node (lo xyz, hi xyz as float32; left, leaf as int32) and lo, hi: (M, 3) float32 are views
    of it; left, leaf: (M,) int64 (0 = leaf; -1 for internal and padding nodes) are made on first use (the
    reference traversal and training's labels ask for them; the fused inference kernel reads the records in place,
    so a model answering rays holds its nodes once: `NeuralBVH.resident_bytes`)."""

    def __init__(self, records: torch.Tensor, max_depth: int):
        self.records = records
        self.lo, self.hi = records[:, 0:3], records[:, 3:6]
        self.max_depth = max_depth
        self._links: tuple | None = None
        self._int32: tuple | None = None

    def _int64_links(self) -> tuple[torch.Tensor, torch.Tensor]:
        if self._links is None:
            links = self.records.view(torch.int32)[:, 6:8]
            self._links = (links[:, 0].to(torch.int64), links[:, 1].to(torch.int64))
        return self._links

    @property
    def left(self) -> torch.Tensor:
        return self._int64_links()[0]

    @property
    def leaf(self) -> torch.Tensor:
        return self._int64_links()[1]

    def int32_arrays(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(left, leaf) as contiguous int32 (what the label kernels read); cached."""
        if self._int32 is None:
            links = self.records.view(torch.int32)[:, 6:8]
            self._int32 = (links[:, 0].contiguous(), links[:, 1].contiguous())
        return self._int32

    @staticmethod
    def from_nodes(nodes: np.ndarray, device: str | torch.device = "cpu") -> "TorchBVH":
        """From a (M,) NODE_DTYPE array (a BVH's nodes or the ones read from a file); on the CPU the records are a
        view of `nodes` itself (the array must stay alive and unchanged: NeuralBVH.set_nodes replaces it whole)."""
        arr = np.ascontiguousarray(nodes)
        records = torch.from_numpy(arr.view(np.float32).reshape(len(arr), 8))
        if torch.device(device).type != "cpu":
            records = records.to(device)
        depth = np.zeros(len(arr), np.int64)
        internal = np.flatnonzero(arr["left"] > 0)  # BFS layout: parents come before children
        for i in internal:
            depth[arr["left"][i]:arr["left"][i] + 2] = depth[i] + 1
        tree = TorchBVH(records, int(depth.max()) if len(arr) else 0)
        tree._source = arr  # keeps the viewed array alive
        return tree

    @staticmethod
    def from_bvh(bvh: BVH, device: str | torch.device = "cpu") -> "TorchBVH":
        return TorchBVH.from_nodes(bvh.nodes, device)

    @property
    def device(self) -> torch.device:
        return self.records.device


class CompactBVH:
    """The stored 8-bit node format held as it is (`quantize.encode_nodes`: root box (6,) float32, boxes (M, 6)
    uint8 codes relative to the parent, left and leaf (M,) uint16 with 65535 for none): 10 bytes per node. Only the
    fused traversal reads it (`LeafStream` decodes the boxes on the way down, bit-identical to the decoded nodes
    training used); lo/hi: the root box (1, 3), for the first push."""

    def __init__(self, packed: dict):
        self.packed = {k: np.ascontiguousarray(v) for k, v in packed.items()}
        root = torch.from_numpy(self.packed["root"].astype(np.float32))
        self.lo, self.hi = root[:3].view(1, 3), root[3:].view(1, 3)
        left = self.packed["left"].astype(np.int64)
        depth = np.zeros(len(left), np.int64)
        for i in np.flatnonzero(left > 0):  # BFS layout: parents come before children
            depth[left[i]:left[i] + 2] = depth[i] + 1
        self.max_depth = int(depth.max()) if len(left) else 0

    @property
    def device(self) -> torch.device:
        return torch.device("cpu")


def ray_box(rays_o: torch.Tensor, inv_d: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor,
            t_max: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Slab test of rays against boxes, element-wise over the leading dimension.

    rays_o, inv_d (= 1 / direction), lo, hi: (N, 3) float32; t_max: (N,) or None (unbounded).
    Returns entered (N,) bool, t_enter (N,) float32 (>= 0), t_exit (N,) float32.
    """
    t0 = (lo - rays_o) * inv_d
    t1 = (hi - rays_o) * inv_d
    t_near = torch.fmin(t0, t1).nan_to_num(nan=-torch.inf)
    t_far = torch.fmax(t0, t1).nan_to_num(nan=torch.inf)
    t_enter = t_near.amax(dim=-1).clamp_min(0.0)
    t_exit = t_far.amin(dim=-1)
    entered = t_enter <= t_exit
    if t_max is not None:
        entered &= t_enter <= t_max
    return entered, t_enter, t_exit


def _inverse(rays_d: torch.Tensor) -> torch.Tensor:
    return 1.0 / rays_d  # 1/0 = inf, 1/-0 = -inf: the slab test handles both


@dataclass
class LeafHits:
    """Every (ray, leaf) pair where the ray enters the leaf's box, grouped by ray, front to back.

    ray: (K,) int64; leaf: (K,) int64 leaf ordinal; node: (K,) int64; t_enter, t_exit: (K,) float32 (ray units);
    offsets: (N + 1,) int64, the pairs of ray r are [offsets[r], offsets[r + 1]).
    """

    ray: torch.Tensor
    leaf: torch.Tensor
    node: torch.Tensor
    t_enter: torch.Tensor
    t_exit: torch.Tensor
    offsets: torch.Tensor

    def __len__(self) -> int:
        return int(self.ray.shape[0])

    def counts(self) -> torch.Tensor:
        """(N,) number of leaves entered by each ray."""
        return self.offsets[1:] - self.offsets[:-1]

    def rank(self) -> torch.Tensor:
        """(K,) position of each pair in its ray's front-to-back order (0 = first leaf entered)."""
        return torch.arange(len(self), device=self.ray.device) - self.offsets[self.ray]


def leaves_along_rays(tree: TorchBVH, rays_o: torch.Tensor, rays_d: torch.Tensor,
                      t_max: torch.Tensor | None = None) -> LeafHits:
    """Complete front-to-back leaf list of every ray (see module docstring).

    rays_o, rays_d: (N, 3) float32 on tree.device (directions need not be unit length; t is in units of
    |rays_d|); t_max: (N,) float32 or None. Leaves with t_enter > t_max are left out.
    """
    kind = kernels.leaf_list_kernel(rays_o.device)
    if kind == "fused":
        return _leaves_along_rays_fast(tree, rays_o, rays_d, t_max)
    if kind == "triton":
        return _leaves_along_rays_triton(tree, rays_o, rays_d, t_max)
    n = rays_o.shape[0]
    dev = rays_o.device
    inv_d = _inverse(rays_d)
    ray_idx = torch.arange(n, device=dev)
    node = torch.zeros(n, dtype=torch.int64, device=dev)
    out_ray, out_node, out_te, out_tx = [], [], [], []
    while ray_idx.numel():
        entered, te, tx = ray_box(rays_o[ray_idx], inv_d[ray_idx], tree.lo[node], tree.hi[node],
                                  None if t_max is None else t_max[ray_idx])
        ray_idx, node, te, tx = ray_idx[entered], node[entered], te[entered], tx[entered]
        left = tree.left[node]
        is_leaf = left == 0
        out_ray.append(ray_idx[is_leaf])
        out_node.append(node[is_leaf])
        out_te.append(te[is_leaf])
        out_tx.append(tx[is_leaf])
        inner = ~is_leaf
        ray_idx = ray_idx[inner].repeat_interleave(2)
        node = torch.stack((left[inner], left[inner] + 1), dim=1).reshape(-1)
    ray = torch.cat(out_ray)
    node = torch.cat(out_node)
    t_enter = torch.cat(out_te)
    t_exit = torch.cat(out_tx)
    # Keep padding/empty boxes out (they are never entered, but a degenerate input could touch one).
    keep = tree.leaf[node] >= 0
    ray, node, t_enter, t_exit = ray[keep], node[keep], t_enter[keep], t_exit[keep]
    # Sort by (ray, t_enter, t_exit, node): two stable sorts, the secondary key first.
    o = torch.argsort(t_exit, stable=True)
    o = o[torch.argsort(t_enter[o], stable=True)]
    o = o[torch.argsort(ray[o], stable=True)]
    ray, node, t_enter, t_exit = ray[o], node[o], t_enter[o], t_exit[o]
    counts = torch.bincount(ray, minlength=n)
    offsets = torch.zeros(n + 1, dtype=torch.int64, device=dev)
    offsets[1:] = torch.cumsum(counts, 0)
    return LeafHits(ray=ray, leaf=tree.leaf[node], node=node, t_enter=t_enter, t_exit=t_exit, offsets=offsets)


def _leaves_along_rays_fast(tree: TorchBVH, rays_o: torch.Tensor, rays_d: torch.Tensor,
                            t_max: torch.Tensor | None) -> LeafHits:
    """`leaves_along_rays` by the C++ kernel: one per-ray stack loop into per-thread lists, then copied out."""
    n = rays_o.shape[0]
    o = rays_o.to(torch.float32).contiguous()
    inv = _inverse(rays_d.to(torch.float32)).contiguous()
    tm = None if t_max is None else t_max.to(torch.float32).contiguous()
    left, leaf = tree.int32_arrays()
    lo, hi = tree.lo.contiguous(), tree.hi.contiguous()
    counts = torch.empty(n, dtype=torch.int64)
    total = torch.zeros(1, dtype=torch.int64)
    handle = bindings.leaves_traverse(rays_o=o, inv_d=inv, n=n, t_max_arr=tm, node_lo=lo, node_hi=hi, node_left=left,
                                      node_leaf=leaf, depth=tree.max_depth + 2, counts=counts, total=total)
    k = int(total)
    node = torch.empty(k, dtype=torch.int64)
    t_enter = torch.empty(k, dtype=torch.float32)
    t_exit = torch.empty(k, dtype=torch.float32)
    bindings.leaves_collect(handle=handle, out_node=node, out_te=t_enter, out_tx=t_exit)
    offsets = torch.zeros(n + 1, dtype=torch.int64)
    offsets[1:] = torch.cumsum(counts, 0)
    ray = torch.repeat_interleave(torch.arange(n), counts)
    return LeafHits(ray=ray, leaf=tree.leaf[node], node=node, t_enter=t_enter, t_exit=t_exit, offsets=offsets)


def _leaves_along_rays_triton(tree: TorchBVH, rays_o: torch.Tensor, rays_d: torch.Tensor,
                              t_max: torch.Tensor | None) -> LeafHits:
    """`leaves_along_rays` on a card: the Triton walk counts, then writes each ray's leaves; sorted front to back
    by (ray, t_enter, t_exit, node) as the reference (stable sorts, the last key first)."""
    from ..kernels.triton.leaf_lists import leaf_counts, leaf_lists

    n = rays_o.shape[0]
    o = rays_o.to(torch.float32).contiguous()
    inv = _inverse(rays_d.to(torch.float32)).contiguous()
    tm = (torch.full((n,), torch.inf, device=o.device) if t_max is None else t_max.to(torch.float32).contiguous())
    records = tree.records.contiguous()
    counts = leaf_counts(o, inv, tm, records, tree.max_depth)
    offsets = torch.zeros(n + 1, dtype=torch.int64, device=o.device)
    offsets[1:] = torch.cumsum(counts, 0)
    node, t_enter, t_exit = leaf_lists(o, inv, tm, records, tree.max_depth, offsets)
    ray = torch.repeat_interleave(torch.arange(n, device=o.device), counts, output_size=node.shape[0])
    order = torch.argsort(node, stable=True)
    for key in (t_exit, t_enter, ray):
        order = order[torch.argsort(key[order], stable=True)]
    node, t_enter, t_exit = node[order], t_enter[order], t_exit[order]
    return LeafHits(ray=ray, leaf=tree.leaf[node], node=node, t_enter=t_enter, t_exit=t_exit, offsets=offsets)


class LeafStream:
    """Front-to-back leaf stream for a batch of rays, with early termination (see module docstring).

    rays_o, rays_d: (N, 3) float32 on tree.device; t_max: (N,) float32 or None (unbounded).
    Order: at every internal node the child entered first is visited first (ties: the left child). When sibling
    boxes overlap, a leaf can come before another leaf with a smaller t_enter; a caller that needs the nearest
    hit therefore `shorten()`s on a hit and keeps streaming until the ray is `done`.
    """

    def __init__(self, tree: TorchBVH, rays_o: torch.Tensor, rays_d: torch.Tensor,
                 t_max: torch.Tensor | None = None):
        n = rays_o.shape[0]
        dev = rays_o.device
        self.tree = tree
        self.rays_o = rays_o
        self.inv_d = _inverse(rays_d)
        self.t_max = (torch.full((n,), torch.inf, device=dev) if t_max is None
                      else t_max.to(torch.float32).clone())
        depth = tree.max_depth + 2
        self.fast = kernels.traversal_kernel(dev) == "fused"
        # The C++ stepper keeps int32 stacks (contiguous, one row per ray; it reads only entries below sp, so they
        # are left uninitialised); the reference int64.
        alloc = torch.empty if self.fast else torch.zeros
        self.stack_node = alloc((n, depth), dtype=torch.int32 if self.fast else torch.int64, device=dev)
        self.stack_t = alloc((n, depth), dtype=torch.float32, device=dev)
        self.sp = torch.zeros(n, dtype=torch.int32 if self.fast else torch.int64, device=dev)
        self.compact = isinstance(tree, CompactBVH)
        if self.compact:  # each stack entry carries its node's decoded box
            assert self.fast, "8-bit nodes are read by the fused traversal only"
            self.stack_box = torch.empty((n, depth, 6), dtype=torch.float32)
            self.stack_box[:, 0, :3], self.stack_box[:, 0, 3:] = tree.lo, tree.hi
        if self.fast:  # what the kernel reads and writes, allocated once per stream
            self._o = rays_o.to(torch.float32).contiguous()
            self._inv = self.inv_d.to(torch.float32).contiguous()
            self._out_leaf = torch.empty(n, dtype=torch.int32)
            self._out_te = torch.empty(n, dtype=torch.float32)
            self._out_tx = torch.empty(n, dtype=torch.float32)
        # Push the root for rays that enter it.
        entered, te, _ = ray_box(rays_o, self.inv_d, tree.lo[:1].expand(n, 3), tree.hi[:1].expand(n, 3),
                                 self.t_max)
        self.stack_node[:, 0] = 0
        self.stack_t[:, 0] = te
        self.sp[entered] = 1

    @property
    def done(self) -> torch.Tensor:
        """(N,) bool: no leaves left for the ray."""
        return self.sp == 0

    def shorten(self, ray: torch.Tensor, t: torch.Tensor) -> None:
        """Lower t_max of rays `ray` (R,) int64 to `t` (R,) where smaller: boxes entered beyond it are skipped."""
        self.t_max[ray] = torch.minimum(self.t_max[ray], t)

    def stop(self, ray: torch.Tensor) -> None:
        """End rays `ray` (R,) int64: no further leaves."""
        self.sp[ray] = 0

    def next(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The next leaf of every live ray: ray (R,) int64, leaf (R,) int64, t_enter (R,), t_exit (R,).

        Rays whose stacks run empty without finding another leaf are absent (and `done`).
        """
        if self.fast:
            return self._next_fast()
        tree = self.tree
        dev = self.sp.device
        out_ray, out_leaf, out_te, out_tx = [], [], [], []
        ray = torch.nonzero(self.sp > 0).squeeze(1)
        while ray.numel():
            self.sp[ray] -= 1
            sp = self.sp[ray]
            node = self.stack_node[ray, sp]
            t_in = self.stack_t[ray, sp]
            alive = t_in <= self.t_max[ray]
            pruned = ray[~alive]  # entered beyond a shortened t_max: skip the node, keep popping
            pruned = pruned[self.sp[pruned] > 0]
            ray, node = ray[alive], node[alive]
            left = tree.left[node]
            is_leaf = left == 0
            if is_leaf.any():
                r, nd = ray[is_leaf], node[is_leaf]
                _, te, tx = ray_box(self.rays_o[r], self.inv_d[r], tree.lo[nd], tree.hi[nd])
                real = tree.leaf[nd] >= 0
                out_ray.append(r[real])
                out_leaf.append(tree.leaf[nd][real])
                out_te.append(te[real])
                out_tx.append(tx[real])
            ray, left = ray[~is_leaf], left[~is_leaf]
            if ray.numel() == 0:
                ray = pruned
                continue
            o, inv, tm = self.rays_o[ray], self.inv_d[ray], self.t_max[ray]
            hit_l, te_l, _ = ray_box(o, inv, tree.lo[left], tree.hi[left], tm)
            hit_r, te_r, _ = ray_box(o, inv, tree.lo[left + 1], tree.hi[left + 1], tm)
            right_first = te_r < te_l
            near = torch.where(right_first, left + 1, left)
            far = torch.where(right_first, left, left + 1)
            near_hit = torch.where(right_first, hit_r, hit_l)
            far_hit = torch.where(right_first, hit_l, hit_r)
            near_t = torch.where(right_first, te_r, te_l)
            far_t = torch.where(right_first, te_l, te_r)
            # Push far first so near is popped first.
            for child, hit, t in ((far, far_hit, far_t), (near, near_hit, near_t)):
                r = ray[hit]
                sp = self.sp[r]
                self.stack_node[r, sp] = child[hit]
                self.stack_t[r, sp] = t[hit]
                self.sp[r] = sp + 1
            # Rays that pushed nothing and have an empty stack drop out; the rest pop again.
            ray = torch.cat((ray[self.sp[ray] > 0], pruned))
        if not out_ray:
            empty = torch.empty(0, dtype=torch.int64, device=dev)
            return empty, empty, torch.empty(0, device=dev), torch.empty(0, device=dev)
        ray = torch.cat(out_ray)
        return ray, torch.cat(out_leaf), torch.cat(out_te), torch.cat(out_tx)

    def _next_fast(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """`next()` by the C++ kernel: each live ray pops its own stack until its next leaf (same order)."""
        tree = self.tree
        n = self.sp.shape[0]
        self.t_max = self.t_max.contiguous()
        if self.compact:
            bindings.stream_next_q(rays_o=self._o, inv_d=self._inv, n=n, codes=tree.packed["boxes"],
                                   node_left=tree.packed["left"], node_leaf=tree.packed["leaf"],
                                   stack_node=self.stack_node, stack_t=self.stack_t, stack_box=self.stack_box,
                                   sp_arr=self.sp, t_max_arr=self.t_max, depth=self.stack_node.shape[1],
                                   out_leaf=self._out_leaf, out_te=self._out_te, out_tx=self._out_tx)
            ray = torch.nonzero(self._out_leaf >= 0).squeeze(1)
            return ray, self._out_leaf[ray].to(torch.int64), self._out_te[ray], self._out_tx[ray]
        bindings.stream_next(rays_o=self._o, inv_d=self._inv, n=n, records=tree.records,  # read in place
                             stack_node=self.stack_node, stack_t=self.stack_t, sp_arr=self.sp, t_max_arr=self.t_max,
                             depth=self.stack_node.shape[1], out_leaf=self._out_leaf, out_te=self._out_te,
                             out_tx=self._out_tx)
        ray = torch.nonzero(self._out_leaf >= 0).squeeze(1)
        return ray, self._out_leaf[ray].to(torch.int64), self._out_te[ray], self._out_tx[ray]
