"""One level of the binned-SAH build (`bvh.build_full_tree`), for all of its nodes at once: the centroids binned per
node and axis (`level_bins`), the cheapest split plane by the surface area heuristic (`sah_planes`), a median split
where no plane separates (`median_split`), and the children's boxes (`child_bounds`). Pure numpy, no loop over
triangles or nodes."""
from __future__ import annotations

import numpy as np

def segment_reduce(values: np.ndarray, starts: np.ndarray, op) -> np.ndarray:
    """op.reduceat over contiguous, non-empty segments beginning at `starts` (sorted)."""
    return op.reduceat(values, starts, axis=0)


def level_bins(order: np.ndarray, active_start: np.ndarray, active_count: np.ndarray, centroid: np.ndarray,
                n_bins: int) -> tuple:
    """The triangles of all active nodes of one level, node-major: (seg_node (n,) node of each, local (n,) its
    position in the node, pos (n,) its slot in `order`, tids (n,) triangle ids, c (n, 3) centroids, extent
    (n_act, 3) each node's centroid extent, b (n, 3) int64 bin per axis in [0, n_bins))."""
    n_act = active_count.size
    seg_node = np.repeat(np.arange(n_act), active_count)
    offs = np.concatenate(([0], np.cumsum(active_count)[:-1]))
    local = np.arange(active_count.sum()) - np.repeat(offs, active_count)
    pos = np.repeat(active_start, active_count) + local
    tids = order[pos]
    c = centroid[tids]
    c_lo = segment_reduce(c, offs, np.minimum)
    extent = segment_reduce(c, offs, np.maximum) - c_lo
    scale = np.where(extent > 0, n_bins / np.where(extent > 0, extent, 1), 0.0)
    b = ((c - c_lo[seg_node]) * scale[seg_node]).astype(np.int64)
    np.clip(b, 0, n_bins - 1, out=b)
    return seg_node, local, pos, tids, c, extent, b


def sah_planes(b: np.ndarray, seg_node: np.ndarray, t_lo: np.ndarray, t_hi: np.ndarray, active_count: np.ndarray,
                median_below: int, n_bins: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The cheapest SAH plane of every active node above `median_below` triangles (one level of
    `build_full_tree`). b: (n, 3) bin of each triangle per axis; seg_node: (n,) its node; t_lo/t_hi: (n, 3) its
    bounds. Returns (cost, axis, plane) per node (n_act,): triangles with bin <= plane go left; cost inf = none
    (a small node, or all centroids in one bin: the median split takes it)."""
    n_act = active_count.size
    best_cost = np.full(n_act, np.inf)
    best_axis = np.zeros(n_act, np.int64)
    best_plane = np.zeros(n_act, np.int64)
    big = np.flatnonzero(active_count > median_below)
    if not big.size:
        return best_cost, best_axis, best_plane
    big_of = np.full(n_act, -1, np.int64)
    big_of[big] = np.arange(big.size)
    tri_big = big_of[seg_node] >= 0
    bnode = big_of[seg_node[tri_big]]
    bb = b[tri_big]
    blo_t, bhi_t = t_lo[tri_big].ravel(), t_hi[tri_big].ravel()
    n_big = big.size
    nb = n_big * n_bins
    for axis in range(3):
        key = bnode * n_bins + bb[:, axis]
        cnt = np.bincount(key, minlength=nb).reshape(n_big, n_bins).astype(np.float64)
        key3 = (key[:, None] * 3 + np.arange(3)).ravel()  # 1-D ufunc.at is ~3x faster than 2-D
        blo = np.full(nb * 3, np.inf, np.float32)
        bhi = np.full(nb * 3, -np.inf, np.float32)
        np.minimum.at(blo, key3, blo_t)
        np.maximum.at(bhi, key3, bhi_t)
        blo = blo.reshape(n_big, n_bins, 3)
        bhi = bhi.reshape(n_big, n_bins, 3)
        # Sweep from the left and from the right: bounds and counts of bins [0..i] and [i+1..].
        l_lo = np.minimum.accumulate(blo, axis=1)[:, :-1]
        l_hi = np.maximum.accumulate(bhi, axis=1)[:, :-1]
        r_lo = np.minimum.accumulate(blo[:, ::-1], axis=1)[:, ::-1][:, 1:]
        r_hi = np.maximum.accumulate(bhi[:, ::-1], axis=1)[:, ::-1][:, 1:]
        l_cnt = np.cumsum(cnt, axis=1)[:, :-1]
        r_cnt = cnt.sum(axis=1, keepdims=True) - l_cnt
        cost = half_area(l_lo, l_hi) * l_cnt + half_area(r_lo, r_hi) * r_cnt
        cost = np.where((l_cnt > 0) & (r_cnt > 0), cost, np.inf)
        plane = cost.argmin(axis=1)
        pc = cost[np.arange(n_big), plane]
        better = pc < best_cost[big]
        best_cost[big] = np.where(better, pc, best_cost[big])
        best_axis[big] = np.where(better, axis, best_axis[big])
        best_plane[big] = np.where(better, plane, best_plane[big])
    return best_cost, best_axis, best_plane


def median_split(go_right: np.ndarray, stuck: np.ndarray, c: np.ndarray, extent: np.ndarray, seg_node: np.ndarray,
                  local: np.ndarray, active_count: np.ndarray) -> None:
    """Set go_right (n,) of the triangles of `stuck` nodes (n_act,) bool: the upper half of each node's triangles
    along its longest centroid axis (c: (n, 3) centroids, extent: (n_act, 3), local: (n,) position in the node)."""
    if not stuck.any():
        return
    tri_stuck = stuck[seg_node]
    ax = extent.argmax(axis=1)
    key_val = c[np.arange(c.shape[0]), ax[seg_node]]
    # Rank within the node along the axis (stable lexsort: node, then coordinate, then position).
    idx = np.flatnonzero(tri_stuck)
    ordr = idx[np.lexsort((local[idx], key_val[idx], seg_node[idx]))]
    node_of = seg_node[ordr]
    first = np.concatenate(([0], np.flatnonzero(np.diff(node_of)) + 1))
    grp_start = np.repeat(first, np.diff(np.concatenate((first, [ordr.size]))))
    rank = np.arange(ordr.size) - grp_start
    go_right[ordr] = rank >= (active_count[node_of] // 2)


def child_bounds(seg_node: np.ndarray, go_right: np.ndarray, perm: np.ndarray, t_lo: np.ndarray, t_hi: np.ndarray,
                  n_act: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Bounds (n_act, 3) float32 of the left and right children (lo_l, hi_l, lo_r, hi_r) after the partition
    `perm` (children's triangles are contiguous then: a segmented reduction)."""
    child_lo_l = np.full((n_act, 3), np.inf, np.float32)
    child_hi_l = np.full((n_act, 3), -np.inf, np.float32)
    child_lo_r = child_lo_l.copy()
    child_hi_r = child_hi_l.copy()
    child_key = seg_node[perm] * 2 + go_right[perm]
    seg_starts = np.concatenate(([0], np.flatnonzero(np.diff(child_key)) + 1))
    keys = child_key[seg_starts]
    red_lo = np.minimum.reduceat(t_lo[perm], seg_starts, axis=0)
    red_hi = np.maximum.reduceat(t_hi[perm], seg_starts, axis=0)
    is_r = keys % 2 == 1
    child_lo_l[keys[~is_r] // 2], child_hi_l[keys[~is_r] // 2] = red_lo[~is_r], red_hi[~is_r]
    child_lo_r[keys[is_r] // 2], child_hi_r[keys[is_r] // 2] = red_lo[is_r], red_hi[is_r]
    return child_lo_l, child_hi_l, child_lo_r, child_hi_r


def half_area(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Half the surface area of boxes (..., 3); empty boxes (inf bounds) give 0."""
    d = np.maximum(hi.astype(np.float64) - lo, 0)
    d = np.where(np.isfinite(d), d, 0)
    return d[..., 0] * d[..., 1] + d[..., 1] * d[..., 2] + d[..., 2] * d[..., 0]
