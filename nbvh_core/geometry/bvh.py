"""BVH over a mesh's triangles, built to an exact node budget.

Two stages, both vectorised with numpy (no Python loop over triangles):

1. `build_full_tree`: a binned-SAH BVH down to `max_leaf_size` triangles per leaf, built level by level (all
   nodes of one depth are split together). This is the tree a conventional ray tracer would hold resident.
2. `cut_tree`: a cut through the full tree with exactly the requested number of nodes. Starting from the root,
   the cut repeatedly expands the leaf with the highest SAH cost (box surface area x triangle count: the work a
   ray tracer expects to spend there), so nodes go where the geometry is dense and large.

The result, `BVH`, stores its nodes as one flat array of 32-byte records (`NODE_DTYPE`), the exact bytes the
.nbvh file stores. Layout: the root is node 0, the two children of an internal node are `left` and `left + 1`;
`left == 0` marks a leaf (the root is never a child). The 4 spare bytes of a leaf hold its leaf ordinal, of an
internal node -1. For an even budget, node 1 is an unused padding node (empty box) so that the node count is
exactly the budget and every sibling pair starts at an even index (one 64-byte cache line per pair).
Leaf triangle ranges (`leaf_tri_start`, `leaf_tri_count` into `tri_order`) are for training only; they are
never stored in the file.
"""
from __future__ import annotations

import heapq
import warnings
from dataclasses import dataclass

import numpy as np

from .mesh import Mesh
from .sah_bins import child_bounds, level_bins, median_split, sah_planes

#: One node, 32 bytes: AABB min (3 x float32), AABB max (3 x float32), left child (int32), leaf ordinal or -1.
NODE_DTYPE = np.dtype([("lo", "<f4", (3,)), ("hi", "<f4", (3,)), ("left", "<i4"), ("leaf", "<i4")])
assert NODE_DTYPE.itemsize == 32

MAX_NODES = 65535
DEFAULT_NODES = 4096


@dataclass
class FullTree:
    """Binned-SAH tree over all triangles (arrays indexed by node id; root = 0).

    lo, hi: (M, 3) float32 node AABBs; left: (M,) int64 first child or -1 for leaves (right = left + 1);
    start, count: (M,) int64 range of the node's triangles in `tri_order`; depth: (M,) int32.
    tri_order: (F,) int64 permutation of triangle ids grouped by node.
    """

    lo: np.ndarray
    hi: np.ndarray
    left: np.ndarray
    start: np.ndarray
    count: np.ndarray
    depth: np.ndarray
    tri_order: np.ndarray

    @property
    def n_nodes(self) -> int:
        return int(self.left.shape[0])

    @property
    def n_leaves(self) -> int:
        return int((self.left < 0).sum())


@dataclass
class BVH:
    """The BVH cut to a node budget (see module docstring for the layout).

    nodes: (M,) NODE_DTYPE, M = `n_nodes` (== the budget whenever the mesh has enough triangles).
    leaf_node: (L,) int64 node index of each leaf ordinal; leaf_tri_start, leaf_tri_count: (L,) int64 ranges in
    `tri_order` (F,) int64; tri_leaf: (F,) int32 the leaf that owns each triangle. `max_depth`: root depth 0.
    """

    nodes: np.ndarray
    leaf_node: np.ndarray
    leaf_tri_start: np.ndarray
    leaf_tri_count: np.ndarray
    tri_order: np.ndarray
    tri_leaf: np.ndarray
    max_depth: int
    budget: int
    #: The full tree this BVH was cut from and the full-tree node of each leaf (for refining the cut; not stored).
    full: "FullTree | None" = None
    leaf_full: np.ndarray | None = None

    @property
    def n_nodes(self) -> int:
        return int(self.nodes.shape[0])

    @property
    def n_leaves(self) -> int:
        return int(self.leaf_node.shape[0])

    @property
    def nbytes(self) -> int:
        """Stored size: 32 bytes per node."""
        return self.n_nodes * NODE_DTYPE.itemsize

    def to_bytes(self) -> bytes:
        return self.nodes.tobytes()

    @staticmethod
    def nodes_from_bytes(data: bytes) -> np.ndarray:
        """Node array from stored bytes (length must be a multiple of 32)."""
        if len(data) % NODE_DTYPE.itemsize:
            raise ValueError(f"BVH node data is {len(data)} bytes, not a multiple of {NODE_DTYPE.itemsize}")
        return np.frombuffer(data, dtype=NODE_DTYPE).copy()

    def leaf_boxes(self) -> tuple[np.ndarray, np.ndarray]:
        """(L, 3), (L, 3) float32 AABB min and max of every leaf, indexed by leaf ordinal."""
        n = self.nodes[self.leaf_node]
        return n["lo"].copy(), n["hi"].copy()

    def leaf_triangles(self, leaf: int) -> np.ndarray:
        """Triangle ids owned by one leaf."""
        s = int(self.leaf_tri_start[leaf])
        return self.tri_order[s:s + int(self.leaf_tri_count[leaf])]


def _ranges(starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Concatenation of arange(s, s + c) for every (s, c), vectorised."""
    offs = np.concatenate(([0], np.cumsum(counts)[:-1]))
    return np.repeat(starts - offs, counts) + np.arange(int(counts.sum()))


def build_full_tree(mesh: Mesh, max_leaf_size: int = 1, n_bins: int = 16, median_below: int = 16) -> FullTree:
    """Binned-SAH BVH over `mesh` down to at most `max_leaf_size` triangles per leaf.

    All nodes of one depth are split at once: per node and axis, triangle centroids are binned into `n_bins`
    bins, the SAH cost of the n_bins - 1 candidate planes is swept from both sides, the cheapest plane wins.
    Nodes of at most `median_below` triangles, and nodes SAH cannot separate (all centroids in one bin), are
    split at the median of their longest centroid axis."""
    from ..kernels import library

    tri_lo, tri_hi = triangle_boxes(mesh)
    n_tri = tri_lo.shape[0]
    if library.fast_enabled() and n_tri:  # kernels/native/tree_build.cpp: node for node the numpy build below
        return _build_full_tree_native(tri_lo, tri_hi, max_leaf_size, n_bins, median_below)
    centroid = ((tri_lo.astype(np.float64) + tri_hi) * 0.5)

    lo_list = [tri_lo.min(axis=0, keepdims=True)]
    hi_list = [tri_hi.max(axis=0, keepdims=True)]
    left_list = [np.full(1, -1, np.int64)]
    start_list = [np.zeros(1, np.int64)]
    count_list = [np.full(1, n_tri, np.int64)]
    depth_list = [np.zeros(1, np.int32)]
    order = np.arange(n_tri, dtype=np.int64)

    # Active nodes of the current level, as (global id, start, count); their triangles are contiguous in `order`.
    active_id = np.zeros(1, np.int64)
    active_start = np.zeros(1, np.int64)
    active_count = np.full(1, n_tri, np.int64)
    n_total = 1
    depth = 0
    while True:
        split = active_count > max_leaf_size
        active_id, active_start, active_count = active_id[split], active_start[split], active_count[split]
        if active_id.size == 0:
            break
        depth += 1
        n_act = active_id.size
        seg_node, local, pos, tids, c, extent, b = level_bins(order, active_start, active_count, centroid, n_bins)
        t_lo, t_hi = tri_lo[tids], tri_hi[tids]
        # SAH binning for nodes above `median_below` triangles; smaller nodes take the median split below
        # (binning 16 bins for a handful of triangles costs more than it gains).
        best_cost, best_axis, best_plane = sah_planes(b, seg_node, t_lo, t_hi, active_count, median_below, n_bins)
        go_right = b[np.arange(b.shape[0]), best_axis[seg_node]] > best_plane[seg_node]
        # Small nodes, and nodes SAH cannot split (coincident centroids): median split along the longest axis.
        median_split(go_right, ~np.isfinite(best_cost), c, extent, seg_node, local, active_count)

        # Stable partition inside every node: left triangles first.
        perm = np.lexsort((go_right, seg_node))
        order[pos] = tids[perm]
        n_right = np.bincount(seg_node, weights=go_right, minlength=n_act).astype(np.int64)
        n_left = active_count - n_right

        child_lo_l, child_hi_l, child_lo_r, child_hi_r = child_bounds(seg_node, go_right, perm, t_lo, t_hi, n_act)

        child_ids = n_total + 2 * np.arange(n_act)
        left_arr = np.concatenate(left_list)
        left_list = [left_arr]
        left_arr[active_id] = child_ids
        c_lo = np.empty((2 * n_act, 3), np.float32)
        c_hi = np.empty((2 * n_act, 3), np.float32)
        c_lo[0::2], c_lo[1::2] = child_lo_l, child_lo_r
        c_hi[0::2], c_hi[1::2] = child_hi_l, child_hi_r
        c_start = np.empty(2 * n_act, np.int64)
        c_count = np.empty(2 * n_act, np.int64)
        c_start[0::2], c_start[1::2] = active_start, active_start + n_left
        c_count[0::2], c_count[1::2] = n_left, n_right
        lo_list.append(c_lo)
        hi_list.append(c_hi)
        left_list.append(np.full(2 * n_act, -1, np.int64))
        start_list.append(c_start)
        count_list.append(c_count)
        depth_list.append(np.full(2 * n_act, depth, np.int32))
        active_id = np.arange(n_total, n_total + 2 * n_act, dtype=np.int64)
        active_start, active_count = c_start, c_count
        n_total += 2 * n_act

    return FullTree(lo=np.concatenate(lo_list), hi=np.concatenate(hi_list), left=np.concatenate(left_list),
                    start=np.concatenate(start_list), count=np.concatenate(count_list),
                    depth=np.concatenate(depth_list), tri_order=order)


def triangle_boxes(mesh: Mesh, chunk: int = 1 << 20) -> tuple[np.ndarray, np.ndarray]:
    """Each triangle's box: (lo, hi), each (F, 3) float32, a chunk of triangles at a time (the (F, 3, 3) corners of
    a 10M-triangle mesh at once are 360 MB)."""
    n = mesh.n_triangles
    lo, hi = np.empty((n, 3), np.float32), np.empty((n, 3), np.float32)
    for a in range(0, n, chunk):
        tri = mesh.vertices[mesh.faces[a:a + chunk]]
        lo[a:a + chunk], hi[a:a + chunk] = tri.min(axis=1), tri.max(axis=1)
    return lo, hi


def _build_full_tree_native(tri_lo: np.ndarray, tri_hi: np.ndarray, max_leaf_size: int, n_bins: int,
                            median_below: int) -> FullTree:
    """build_full_tree by the compiled builder (the same tree; ~20x faster than the level-wise numpy sorts). tri_lo,
    tri_hi: (F, 3) float32 triangle boxes, used as the builder's scratch (left permuted with the triangle order)."""
    from ..kernels import bindings

    n = len(tri_lo)
    cap = 2 * n - 1  # a binary tree over n triangles has at most 2n - 1 nodes
    lo, hi = np.empty((cap, 3), np.float32), np.empty((cap, 3), np.float32)
    left, start, count = np.empty(cap, np.int64), np.empty(cap, np.int64), np.empty(cap, np.int64)
    depth, order, used = np.empty(cap, np.int32), np.empty(n, np.int64), np.zeros(1, np.int64)
    bindings.build_full_tree(tri_lo=np.ascontiguousarray(tri_lo, np.float32),
                             tri_hi=np.ascontiguousarray(tri_hi, np.float32), n=n, max_leaf_size=max_leaf_size,
                             n_bins=n_bins, median_below=median_below, capacity=cap, node_lo=lo, node_hi=hi,
                             left=left, start=start, count=count, depth=depth, order=order, n_nodes=used)
    m = int(used[0])
    # Leaves of several triangles use fewer rows than reserved: the rows used are kept as views. The pages past them
    # were never written, so they take no memory; copying them out held both (~0.6 GB at 10M triangles).
    return FullTree(lo=lo[:m], hi=hi[:m], left=left[:m], start=start[:m], count=count[:m], depth=depth[:m],
                    tri_order=order)


def _sah_priority(tree: FullTree, node: int) -> float:
    d = np.maximum(tree.hi[node].astype(np.float64) - tree.lo[node], 0)
    return float((d[0] * d[1] + d[1] * d[2] + d[2] * d[0]) * tree.count[node])


def cut_tree(tree: FullTree, budget: int = DEFAULT_NODES, priority=None, max_nodes: int | None = MAX_NODES) -> BVH:
    """Cut `tree` to exactly `budget` nodes (1..max_nodes), or fewer when the full tree has fewer leaves to offer.

    max_nodes=None lifts the file format's 65535 limit (for in-memory trees such as the exact fallback's).

    priority(tree, node) -> float chooses which leaf of the cut to expand next (default: SAH cost, box surface
    area x triangle count). The expansion is greedy, highest priority first.
    """
    if budget < 1 or (max_nodes is not None and budget > max_nodes):
        raise ValueError(f"node budget must be in [1, {max_nodes}], got {budget}")
    # A binary tree has an odd node count; an even budget keeps one padding node (see module docstring).
    return layout_cut(tree, _greedy_cut(tree, (budget + 1) // 2, priority or _sah_priority), budget, max_nodes)


def _greedy_cut(tree: FullTree, target_leaves: int, priority) -> set:
    """Full-tree nodes of the cut with `target_leaves` leaves (fewer when the tree runs out): from the root, the
    leaf of highest priority is expanded first."""
    cut_leaves = {0}
    heap: list[tuple[float, int]] = []
    if tree.left[0] >= 0:
        heap.append((-priority(tree, 0), 0))
    while len(cut_leaves) < target_leaves and heap:
        _, node = heapq.heappop(heap)
        cut_leaves.remove(node)
        for child in (int(tree.left[node]), int(tree.left[node]) + 1):
            cut_leaves.add(child)
            if tree.left[child] >= 0:
                heapq.heappush(heap, (-priority(tree, child), child))
    return cut_leaves


def refine_cut(bvh: BVH, leaf_scores: np.ndarray, new_leaves: int) -> tuple[BVH, np.ndarray]:
    """N-BVH's tree-cut splitting: replace the `new_leaves` highest-scoring splittable leaves of `bvh` by their two
    children in the full tree (each split adds one leaf, two nodes), never beyond bvh.budget.

    leaf_scores: (L,) per leaf ordinal (e.g. the running error). Returns (the refined BVH, parent (L',) int64: the
    old leaf ordinal each new leaf comes from), so per-leaf statistics can follow the split.
    """
    tree, leaf_full = bvh.full, bvh.leaf_full
    if tree is None or leaf_full is None:
        raise ValueError("this BVH does not carry its full tree; build it with build_bvh")
    room = (bvh.budget + 1) // 2 - len(leaf_full)
    order = np.argsort(-np.asarray(leaf_scores, np.float64), kind="stable")
    split = [int(i) for i in order if tree.left[leaf_full[i]] >= 0][:max(0, min(new_leaves, room))]
    cut = {int(n) for n in leaf_full}
    origin = {int(n): i for i, n in enumerate(leaf_full)}
    for i in split:
        node = int(leaf_full[i])
        cut.remove(node)
        for child in (int(tree.left[node]), int(tree.left[node]) + 1):
            cut.add(child)
            origin[child] = i
    out = layout_cut(tree, cut, bvh.budget, final=False)
    return out, np.array([origin[int(n)] for n in out.leaf_full], np.int64)


def coarse_cut(bvh: BVH, leaves: int) -> BVH:
    """The SAH cut of bvh's full tree with `leaves` leaves, to be refined up to bvh.budget (`refine_cut`)."""
    return layout_cut(bvh.full, _greedy_cut(bvh.full, leaves, _sah_priority), bvh.budget, final=False)


def layout_cut(tree: FullTree, cut_leaves: set, budget: int, max_nodes: int | None = MAX_NODES,
               final: bool = True) -> BVH:
    """The BVH whose leaves are the full-tree nodes `cut_leaves` (a valid cut), laid out in BFS order; `budget` is
    what the cut may grow to (final=False: a cut still being refined, smaller by design, no warning)."""
    n_leaves = len(cut_leaves)
    n_tree_nodes = 2 * n_leaves - 1
    padded = budget % 2 == 0 and n_tree_nodes == budget - 1
    if final and n_tree_nodes + padded < budget and max_nodes is not None:
        warnings.warn(f"the mesh has too few triangles for {budget} BVH nodes; using {n_tree_nodes}", stacklevel=2)

    # Lay out the cut in BFS order: root 0, (padding 1), then sibling pairs.
    n_nodes = n_tree_nodes + int(padded)
    nodes = np.zeros(n_nodes, dtype=NODE_DTYPE)
    full_of = np.zeros(n_nodes, np.int64)  # full-tree node of every output node
    depth_of = np.zeros(n_nodes, np.int32)
    nodes["leaf"] = -1
    next_free = 2 if padded else 1
    queue = [0]
    head = 0
    leaf_node, leaf_full = [], []
    while head < len(queue):
        out = queue[head]
        head += 1
        src = int(full_of[out])
        nodes["lo"][out] = tree.lo[src]
        nodes["hi"][out] = tree.hi[src]
        if src in cut_leaves:
            nodes["left"][out] = 0
            nodes["leaf"][out] = len(leaf_node)
            leaf_node.append(out)
            leaf_full.append(src)
        else:
            nodes["left"][out] = next_free
            for k in range(2):
                full_of[next_free + k] = tree.left[src] + k
                depth_of[next_free + k] = depth_of[out] + 1
                queue.append(next_free + k)
            next_free += 2
    if padded:  # empty, inverted box: no ray ever enters it
        nodes["lo"][1] = np.inf
        nodes["hi"][1] = -np.inf
        nodes["left"][1] = 0
        nodes["leaf"][1] = -1
    leaf_full_arr = np.asarray(leaf_full, np.int64)
    leaf_start = tree.start[leaf_full_arr]
    leaf_count = tree.count[leaf_full_arr]
    tri_leaf = np.empty(tree.tri_order.shape[0], np.int32)
    tri_leaf[tree.tri_order[_ranges(leaf_start, leaf_count)]] = np.repeat(np.arange(n_leaves, dtype=np.int32),
                                                                         leaf_count)
    return BVH(nodes=nodes, leaf_node=np.asarray(leaf_node, np.int64), leaf_tri_start=leaf_start,
               leaf_tri_count=leaf_count, tri_order=tree.tri_order, tri_leaf=tri_leaf,
               max_depth=int(depth_of.max()), budget=budget, full=tree, leaf_full=leaf_full_arr)


#: From this many triangles the tree a run shares stops at 4 triangles per leaf (`shared_tree`): its cuts still find
#: MAX_NODES leaves, and the 10M-triangle lattice's tree holds ~0.6n nodes instead of 2n - 1 (52 B each: 1.05 GiB
#: at one triangle per leaf, held from the plan to the end of training).
SHALLOW_TREE_TRIANGLES = 4 * MAX_NODES


def shared_tree(mesh: Mesh) -> FullTree:
    """The full tree one run shares: the plan's resident-BVH count (nodes of more than 4 triangles) and compact mesh
    (clusters of at most 64), the training BVH's cut and its growth (at most MAX_NODES). One triangle per leaf below
    SHALLOW_TREE_TRIANGLES, else at most 4: the same nodes down to 4 triangles; only the order of the triangles
    inside a node of at most 4 differs (the 1M lattice's compact mesh: 4,015,493 B against 4,015,534 B)."""
    return build_full_tree(mesh, max_leaf_size=1 if mesh.n_triangles < SHALLOW_TREE_TRIANGLES else 4)


class SharedTree:
    """A run's one `shared_tree`, built when first asked for (`get`): the plan measures its decimations and scores the
    whole mesh before it exists, so the tree (~40 B per triangle at 10M) is not resident during the decimation
    chain's top pass, which sets the plan's memory peak (bench/results/heavy.md)."""

    def __init__(self, mesh: Mesh):
        self.mesh = mesh
        self._tree: FullTree | None = None

    def get(self) -> FullTree:
        if self._tree is None:
            self._tree = shared_tree(self.mesh)
        return self._tree


def tree_of(mesh: Mesh, tree: "FullTree | SharedTree | None") -> FullTree:
    """`tree` as a FullTree: itself, a SharedTree's (built now when not yet), or for None a new `build_full_tree`."""
    if isinstance(tree, SharedTree):
        return tree.get()
    return tree if tree is not None else build_full_tree(mesh)


def build_bvh(mesh: Mesh, budget: int = DEFAULT_NODES, n_bins: int = 16) -> BVH:
    """Binned-SAH BVH over `mesh` with exactly `budget` nodes (32 B each); see `build_full_tree`, `cut_tree`."""
    return cut_tree(build_full_tree(mesh, max_leaf_size=1, n_bins=n_bins), budget)


def resident_bvh_nodes(tree: FullTree, max_leaf_size: int = 4) -> int:
    """Node count of a conventional ray-tracing BVH with at most `max_leaf_size` triangles per leaf.

    Taken from the full tree: every node with more than `max_leaf_size` triangles is internal.
    """
    internal = tree.count > max_leaf_size
    # A node is in the tree if its parent is internal; count = internal nodes * 2 + 1 (root).
    return int(2 * (internal & (tree.left >= 0)).sum() + 1)
