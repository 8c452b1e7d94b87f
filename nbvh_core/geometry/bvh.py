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
from .tree_build import FullTree, TreeWatch, build_full_tree  # noqa: F401 - the full tree, as the cuts read it

#: One node, 32 bytes: AABB min (3 x float32), AABB max (3 x float32), left child (int32), leaf ordinal or -1.
NODE_DTYPE = np.dtype([("lo", "<f4", (3,)), ("hi", "<f4", (3,)), ("left", "<i4"), ("leaf", "<i4")])
assert NODE_DTYPE.itemsize == 32

MAX_NODES = 65535
DEFAULT_NODES = 4096


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


def shared_tree(mesh: Mesh, watch: TreeWatch | None = None) -> FullTree:
    """The full tree one run shares: the plan's resident-BVH count (nodes of more than 4 triangles) and compact mesh
    (clusters of at most 64), the training BVH's cut and its growth (at most MAX_NODES). One triangle per leaf below
    SHALLOW_TREE_TRIANGLES, else at most 4: the same nodes down to 4 triangles; only the order of the triangles
    inside a node of at most 4 differs (the 1M lattice's compact mesh: 4,015,493 B against 4,015,534 B)."""
    return build_full_tree(mesh, max_leaf_size=1 if mesh.n_triangles < SHALLOW_TREE_TRIANGLES else 4, watch=watch)


class SharedTree:
    """A run's one `shared_tree`, built when first asked for (`get`): the plan asks right after the decimation
    chain's top pass, so the tree (~40 B per triangle at 10M) and that pass's work (the plan's memory peak,
    bench/results/heavy.md) are never resident together."""

    def __init__(self, mesh: Mesh, watch: TreeWatch | None = None):
        self.mesh, self.watch = mesh, watch  # watch: the build's progress and Cancel
        self._tree: FullTree | None = None

    def get(self) -> FullTree:
        if self._tree is None:
            self._tree = shared_tree(self.mesh, self.watch)
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
