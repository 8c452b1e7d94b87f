"""The GPU twin of the fused kernels: Triton, one file per component, each beside its reference (the torch code in
`nbvh_core.neural`, the oracle) and tested against it on the CPU by Triton's interpreter (`TRITON_INTERPRET=1`,
tests/test_triton_kernels.py). `kernels.plan` decides when they run (CUDA tensors, Triton importable) and records
it; anything they do not cover runs the torch path, and the plan's note says which and why.

* `hashgrid` - the multiresolution hash-grid lookup fused per point (cell, hash or dense index, trilinear weights,
  the 8-row weighted sum of every level) and its backward (atomic adds into the table's gradient): a HashGrid's
  rows, a HashVQAD's soft row table, or its rows through the frozen index's packed codes.
* `bvh_walk` - the slab test, the register-tile stacks and the ray query's pop-to-the-next-leaf step.
* `leaf_lists` - every leaf of the model's tree a ray enters (the training labels' segments), counted, then written.
* `mesh_trace` - the nearest triangle hit in a t range through the mesh's own tree (the labels' exact hits).
* `mlp` - a whole MLP (Linear + ReLU layers, the last without) over rows of inputs through `tl.dot`, K-blocked,
  the activations kept on chip between layers; in training the same kernel stores them, and a backward kernel takes
  the gradient back through every layer (the weights' gradients one matmul per layer).
"""
from __future__ import annotations

import os

import torch


def triton_missing() -> str | None:
    """None when Triton can run kernels here, else one line saying why not."""
    try:
        import triton  # noqa: F401
    except ImportError:
        return "Triton is not installed (it comes with torch's CUDA builds on Linux)"
    return None


def interpreted() -> bool:
    """True when Triton runs its kernels in its CPU interpreter (tests), where they take CPU tensors."""
    return os.environ.get("TRITON_INTERPRET") == "1"


#: Rays per program under the interpreter: it runs programs one after another and pays per operation, not per row
#: (the mesh tracer on 512 rays: 18 s at 32 rows per program, 2 s at 512 on the 2-core CPU).
INTERPRETED_ROWS = 256


def rows_per_program(card: int) -> int:
    """A kernel's rows per program: `card` on a card, INTERPRETED_ROWS under the interpreter (the same answers)."""
    return INTERPRETED_ROWS if interpreted() else card


def serves(device: torch.device | str) -> bool:
    """True when the Triton kernels serve tensors on `device`: CUDA with Triton importable, or the CPU under the
    interpreter (tests only: the C++ kernels are the CPU's fast path)."""
    kind = torch.device(device).type
    return triton_missing() is None and (kind == "cuda" or (kind == "cpu" and interpreted()))
