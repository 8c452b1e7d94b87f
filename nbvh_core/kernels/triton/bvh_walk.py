"""BVH traversal in Triton, shared by the card's kernels: the slab test of a block of rays against one node's box,
a register-tile stack per ray, and the pop-until-the-next-leaf step of the ray query. Node records are
`traversal.TorchBVH.records`' 32-byte rows: lo xyz, hi xyz as float32, then two int32 links read through an int32
view of the same memory (a model's tree: left child, 0 for a leaf, and the leaf ordinal, -1 for a padding leaf; the
mesh tracer's own tree, `mesh_trace.py`, its own two). The references: `traversal.ray_box` and `LeafStream`.
"""
from __future__ import annotations

import triton
import triton.language as tl


def stack_depth(max_depth: int) -> int:
    """Stack slots for a tree of `max_depth`: a pop pushes at most two, so depth + 2 (as `LeafStream`), rounded up to a
    power of two (a register tile's width)."""
    return triton.next_power_of_2(max_depth + 2)


@triton.jit
def _xyz(ptr, rows, live, other):
    """Rows `rows` of an (N, 3) float32 array: x, y, z as (BLOCK,) each, `other` where not `live`."""
    return (tl.load(ptr + rows * 3 + 0, mask=live, other=other), tl.load(ptr + rows * 3 + 1, mask=live, other=other),
            tl.load(ptr + rows * 3 + 2, mask=live, other=other))


@triton.jit
def _fmin(a, b):
    """C's fmin: a NaN operand yields the other."""
    return tl.where(a != a, b, tl.where(b != b, a, tl.minimum(a, b)))


@triton.jit
def _fmax(a, b):
    return tl.where(a != a, b, tl.where(b != b, a, tl.maximum(a, b)))


@triton.jit
def _slab(o, inv, lo, hi):
    """One axis of the slab test (`traversal.ray_box`): (near, far), a NaN (ray on the slab's plane) as -inf/+inf."""
    t0 = (lo - o) * inv
    t1 = (hi - o) * inv
    near = _fmin(t0, t1)
    far = _fmax(t0, t1)
    return tl.where(near != near, float("-inf"), near), tl.where(far != far, float("inf"), far)


@triton.jit
def _box(rec_f_ptr, node, live, ox, oy, oz, ix, iy, iz):
    """Slab test of each ray against node `node`'s box (record columns 0-5): entered, t_enter (>= 0), t_exit."""
    base = node.to(tl.int64) * 8
    nx, fx = _slab(ox, ix, tl.load(rec_f_ptr + base + 0, mask=live, other=0.0),
                   tl.load(rec_f_ptr + base + 3, mask=live, other=0.0))
    ny, fy = _slab(oy, iy, tl.load(rec_f_ptr + base + 1, mask=live, other=0.0),
                   tl.load(rec_f_ptr + base + 4, mask=live, other=0.0))
    nz, fz = _slab(oz, iz, tl.load(rec_f_ptr + base + 2, mask=live, other=0.0),
                   tl.load(rec_f_ptr + base + 5, mask=live, other=0.0))
    t_enter = tl.maximum(tl.maximum(tl.maximum(nx, ny), nz), 0.0)
    t_exit = tl.minimum(tl.minimum(fx, fy), fz)
    return t_enter <= t_exit, t_enter, t_exit


@triton.jit
def _push(stack, sp, slots, node, push):
    """Push `node` on the stacks of the rays where `push`: (stack, sp) after."""
    put = (slots[None, :] == sp[:, None]) & push[:, None]
    return tl.where(put, node[:, None], stack), sp + push.to(tl.int32)


@triton.jit
def _pop(stack, sp, slots, pop):
    """Pop the top of the stacks of the rays where `pop`: (node, sp) after (node 0 where nothing is popped)."""
    sp = sp - pop.to(tl.int32)
    return tl.sum(tl.where((slots[None, :] == sp[:, None]) & pop[:, None], stack, 0), axis=1), sp


@triton.jit
def _next_leaf(rec_f_ptr, rec_i_ptr, stack, sp, slots, ox, oy, oz, ix, iy, iz):
    """Every ray with nodes left pops until its next leaf (`traversal.LeafStream.next`'s order): (stack, sp, at_leaf,
    t_enter, t_exit) of the leaf's box for the rays `at_leaf`."""
    at_leaf = sp < 0
    seg_te = tl.zeros(sp.shape, tl.float32)
    seg_tx = tl.zeros(sp.shape, tl.float32)
    searching = sp > 0
    while tl.max(searching.to(tl.int32), axis=0) > 0:
        node, sp = _pop(stack, sp, slots, searching)
        left = tl.load(rec_i_ptr + node.to(tl.int64) * 8 + 6, mask=searching, other=0)
        ordinal = tl.load(rec_i_ptr + node.to(tl.int64) * 8 + 7, mask=searching, other=-1)
        found = searching & (left == 0) & (ordinal >= 0)  # a padding leaf (ordinal < 0) is skipped
        _, te, tx = _box(rec_f_ptr, node, found, ox, oy, oz, ix, iy, iz)
        seg_te = tl.where(found, te, seg_te)
        seg_tx = tl.where(found, tx, seg_tx)
        at_leaf = at_leaf | found
        inner = searching & (left != 0)
        hit_l, te_l, _ = _box(rec_f_ptr, left, inner, ox, oy, oz, ix, iy, iz)
        hit_r, te_r, _ = _box(rec_f_ptr, left + 1, inner, ox, oy, oz, ix, iy, iz)
        right_first = te_r < te_l
        near = tl.where(right_first, left + 1, left)
        far = tl.where(right_first, left, left + 1)
        stack, sp = _push(stack, sp, slots, far, inner & tl.where(right_first, hit_l, hit_r))
        stack, sp = _push(stack, sp, slots, near, inner & tl.where(right_first, hit_r, hit_l))
        searching = (sp > 0) & ~at_leaf
    return stack, sp, at_leaf, seg_te, seg_tx
