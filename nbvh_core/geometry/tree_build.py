"""The full binned-SAH tree over a mesh's triangles (`build_full_tree`): built level by level, by the compiled
builder (kernels/native/tree_build.cpp) or its numpy reference, with its progress and Cancel (`TreeWatch`). The
cuts a run trains on and the layouts it stores are made from it (`bvh`)."""
from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from .mesh import Mesh
from .sah_bins import child_bounds, level_bins, median_split, sah_planes


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


#: A tree build's progress: watch(fraction done in [0, 1)) is called about every WATCH_EVERY_S seconds of the build
#: (from the thread that asked for it); an exception it raises (a Cancel) stops the build and is raised on.
TreeWatch = Callable[[float], None]
WATCH_EVERY_S = 0.5


def expected_split_work(n_triangles: int, max_leaf_size: int) -> float:
    """The triangles a build splits in all, about (each level splits every triangle above leaf size once): n x
    (log2(n / leaf) + 2); the SAH tree of the 10M lattice at 4 per leaf had 26 levels against log2's 21.3."""
    return max(n_triangles * (math.log2(max(n_triangles / max(max_leaf_size, 1), 2.0)) + 2.0), 1.0)


def build_full_tree(mesh: Mesh, max_leaf_size: int = 1, n_bins: int = 16, median_below: int = 16,
                    watch: TreeWatch | None = None) -> FullTree:
    """Binned-SAH BVH over `mesh` down to at most `max_leaf_size` triangles per leaf. watch: the build's progress
    and Cancel (`TreeWatch`).

    All nodes of one depth are split at once: per node and axis, triangle centroids are binned into `n_bins`
    bins, the SAH cost of the n_bins - 1 candidate planes is swept from both sides, the cheapest plane wins.
    Nodes of at most `median_below` triangles, and nodes SAH cannot separate (all centroids in one bin), are
    split at the median of their longest centroid axis."""
    from ..kernels import library

    tri_lo, tri_hi = triangle_boxes(mesh)
    n_tri = tri_lo.shape[0]
    if library.fast_enabled() and n_tri:  # kernels/native/tree_build.cpp: node for node the numpy build below
        return _build_full_tree_native(tri_lo, tri_hi, max_leaf_size, n_bins, median_below, watch)
    return _build_full_tree_numpy(tri_lo, tri_hi, max_leaf_size, n_bins, median_below, watch)


def _build_full_tree_numpy(tri_lo: np.ndarray, tri_hi: np.ndarray, max_leaf_size: int, n_bins: int,
                           median_below: int, watch: TreeWatch | None = None) -> FullTree:
    """build_full_tree level by level in numpy (the reference the compiled builder matches node for node)."""
    n_tri = tri_lo.shape[0]
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
    work, done, last_watch = expected_split_work(n_tri, max_leaf_size), 0, time.perf_counter()
    while True:
        split = active_count > max_leaf_size
        active_id, active_start, active_count = active_id[split], active_start[split], active_count[split]
        if active_id.size == 0:
            break
        if watch is not None and time.perf_counter() - last_watch >= WATCH_EVERY_S:
            watch(min(done / work, 0.99))
            last_watch = time.perf_counter()
        done += int(active_count.sum())
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
                            median_below: int, watch: TreeWatch | None = None) -> FullTree:
    """build_full_tree by the compiled builder (the same tree; ~20x faster than the level-wise numpy sorts). tri_lo,
    tri_hi: (F, 3) float32 triangle boxes, used as the builder's scratch (left permuted with the triangle order)."""
    from ..kernels import bindings

    n = len(tri_lo)
    cap = 2 * n - 1  # a binary tree over n triangles has at most 2n - 1 nodes
    lo, hi = np.empty((cap, 3), np.float32), np.empty((cap, 3), np.float32)
    left, start, count = np.empty(cap, np.int64), np.empty(cap, np.int64), np.empty(cap, np.int64)
    depth, order, used = np.empty(cap, np.int32), np.empty(n, np.int64), np.zeros(1, np.int64)
    control = np.zeros(2, np.int64)  # [0] triangles split so far (the builder's), [1] stop (ours)
    _watched(lambda: bindings.build_full_tree(
        tri_lo=np.ascontiguousarray(tri_lo, np.float32), tri_hi=np.ascontiguousarray(tri_hi, np.float32), n=n,
        max_leaf_size=max_leaf_size, n_bins=n_bins, median_below=median_below, capacity=cap, node_lo=lo, node_hi=hi,
        left=left, start=start, count=count, depth=depth, order=order, n_nodes=used, control=control),
        control, expected_split_work(n, max_leaf_size), watch)
    m = int(used[0])
    # Leaves of several triangles use fewer rows than reserved: the rows used are kept as views. The pages past them
    # were never written, so they take no memory; copying them out held both (~0.6 GB at 10M triangles).
    return FullTree(lo=lo[:m], hi=hi[:m], left=left[:m], start=start[:m], count=count[:m], depth=depth[:m],
                    tri_order=order)


def _watched(build: Callable[[], None], control: np.ndarray, work: float, watch: TreeWatch | None) -> None:
    """Run the compiled `build` (which releases the GIL) in a thread while this one reports its progress
    (control[0] of `work`) to `watch`; whatever `watch` raises sets the stop flag control[1], waits for the
    builder to stop at its next level (under a second at 10M triangles) and is raised on."""
    if watch is None:
        build()
        return
    failed: list[BaseException] = []

    def run() -> None:
        try:
            build()
        except BaseException as exc:  # raised in this thread below
            failed.append(exc)

    builder = threading.Thread(target=run, name="nbvh-tree-build", daemon=True)
    builder.start()
    try:
        while builder.is_alive():
            builder.join(WATCH_EVERY_S)
            if builder.is_alive():
                watch(min(float(control[0]) / work, 0.99))
    except BaseException:
        control[1] = 1
        builder.join()
        raise
    if failed:
        raise failed[0]
