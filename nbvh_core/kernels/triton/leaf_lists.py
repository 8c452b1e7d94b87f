"""Every leaf a ray enters, on the card: the training labels' segment lists (`traversal.leaves_along_rays`, the
reference, and its C++ kernel on the CPU) as two launches of one Triton kernel. Per ray, a stack walk of the model's
tree; a node is entered when the slab test passes and t_enter <= the ray's t_max. The first launch counts each ray's
leaves, a prefix sum places them, the second writes (node, t_enter, t_exit) in walk order; the caller sorts each
ray's leaves front to back as the reference does. No atomics: the same rays give the same lists, bit for bit.

    counts = leaf_counts(rays_o, inv_d, t_max, records, max_depth)
    node, t_enter, t_exit = leaf_lists(rays_o, inv_d, t_max, records, max_depth, offsets)
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
def _leaf_walk(o_ptr, inv_ptr, tmax_ptr, n, rec_f_ptr, rec_i_ptr, count_ptr, offset_ptr, node_ptr, te_ptr, tx_ptr,
               WRITE: tl.constexpr, DEPTH: tl.constexpr, BR: tl.constexpr):
    rows = tl.program_id(0) * BR + tl.arange(0, BR)
    live = rows < n
    ox, oy, oz = _xyz(o_ptr, rows, live, 0.0)
    ix, iy, iz = _xyz(inv_ptr, rows, live, 1.0)
    t_max = tl.load(tmax_ptr + rows, mask=live, other=0.0)
    at = tl.zeros((BR,), tl.int64)
    room = tl.zeros((BR,), tl.int64)
    if WRITE:
        at = tl.load(offset_ptr + rows, mask=live, other=0)
        room = tl.load(offset_ptr + rows + 1, mask=live, other=0) - at
    slots = tl.arange(0, DEPTH)
    stack = tl.zeros((BR, DEPTH), tl.int32)  # slot 0: the root, node 0
    sp = live.to(tl.int32)
    found = tl.zeros((BR,), tl.int32)
    while tl.max(sp, axis=0) > 0:
        active = sp > 0
        node, sp = _pop(stack, sp, slots, active)
        entered, te, tx = _box(rec_f_ptr, node, active, ox, oy, oz, ix, iy, iz)
        visit = active & entered & (te <= t_max)
        left = tl.load(rec_i_ptr + node.to(tl.int64) * 8 + 6, mask=visit, other=0)
        ordinal = tl.load(rec_i_ptr + node.to(tl.int64) * 8 + 7, mask=visit, other=-1)
        leaf = visit & (left == 0) & (ordinal >= 0)  # a padding leaf (ordinal < 0) is never listed
        if WRITE:  # never past the ray's counted room, whatever the second walk finds
            put = leaf & (found < room)
            tl.store(node_ptr + at + found, node.to(tl.int64), mask=put)
            tl.store(te_ptr + at + found, te, mask=put)
            tl.store(tx_ptr + at + found, tx, mask=put)
        found += leaf.to(tl.int32)
        inner = visit & (left != 0)
        stack, sp = _push(stack, sp, slots, left + 1, inner)
        stack, sp = _push(stack, sp, slots, left, inner)
    if not WRITE:
        tl.store(count_ptr + rows, found.to(tl.int64), mask=live)


def leaf_counts(rays_o: torch.Tensor, inv_d: torch.Tensor, t_max: torch.Tensor, records: torch.Tensor,
                max_depth: int) -> torch.Tensor:
    """(N,) int64: how many leaves each ray enters with t_enter <= t_max.

    rays_o, inv_d (1 / direction): (N, 3) float32; t_max: (N,) float32; records: (M, 8) float32 node rows
    (`traversal.TorchBVH.records`), max_depth: the tree's depth."""
    n = rays_o.shape[0]
    counts = torch.zeros(n, dtype=torch.int64, device=rays_o.device)
    if n:
        rows = rows_per_program(BLOCK_R)
        _leaf_walk[(triton.cdiv(n, rows),)](
            rays_o, inv_d, t_max, n, records, records.view(torch.int32), counts, counts, counts, t_max, t_max,
            WRITE=False, DEPTH=stack_depth(max_depth), BR=rows, num_warps=WARPS)
    return counts


def leaf_lists(rays_o: torch.Tensor, inv_d: torch.Tensor, t_max: torch.Tensor, records: torch.Tensor, max_depth: int,
               offsets: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Each ray's leaves in walk order at [offsets[r], offsets[r + 1]): node (K,) int64, t_enter, t_exit (K,) float32.

    offsets: (N + 1,) int64, the prefix sum of `leaf_counts` for the same arguments."""
    n = rays_o.shape[0]
    k = int(offsets[-1]) if n else 0
    dev = rays_o.device
    node = torch.empty(k, dtype=torch.int64, device=dev)
    t_enter = torch.empty(k, dtype=torch.float32, device=dev)
    t_exit = torch.empty(k, dtype=torch.float32, device=dev)
    if n and k:
        rows = rows_per_program(BLOCK_R)
        _leaf_walk[(triton.cdiv(n, rows),)](
            rays_o, inv_d, t_max, n, records, records.view(torch.int32), offsets, offsets, node, t_enter, t_exit,
            WRITE=True, DEPTH=stack_depth(max_depth), BR=rows, num_warps=WARPS)
    return node, t_enter, t_exit
