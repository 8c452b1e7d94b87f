"""The fast path: fused C++ CPU kernels (`native/`: one source per component, their C ABI declared once in
`nbvh_kernels.h`; OpenMP), built and switched against the reference torch code by `library.py`, called only
through `bindings.py` (keyword arguments checked against the header), and the plan of which path runs each stage
(`plan.py`).

The kernels:
* `encode` - hash-grid / HashVQAD lookup fused per point: cell, hash, trilinear weights and the 8-row weighted sum
  of every level in one pass (the reference builds (N, L, 8) int64 index and weight tensors first); its backward
  recomputes the corners and scatters into the gradient table, one level per thread (no atomics, fixed order).
  Frozen HashVQAD codes are read inside the kernel (vertex -> code -> row); rows as float32, float16 or uint8.
* `stream_next` - `traversal.LeafStream.next` per ray with a real per-ray stack loop (the reference advances all
  rays one pop at a time with tensor ops).
* `leaves_traverse` / `leaves_collect` - the complete sorted leaf list per ray (training labels), one traversal.
* `net_segments` / `net_train` (used through `neural.fused_mlp`; MLP or KMLP) - inference / one training step of a whole
  model per (ray, leaf) segment: points, encoding and every Linear layer (AVX2 6x16 register-blocked micro-kernel,
  bias and ReLU fused) on a tile of 48 segments that stays in the cache; the reference writes (B, k*L*F) features to
  memory and runs torch's layers over them.
* `vqad_soft_forward` / `vqad_soft_backward` - HashVQAD's soft row table (softmax over t candidates) and its
  backward into the rows and the logits.

The card's twins are Triton kernels (`triton/`: a model's whole ray query in one kernel, the hash-grid lookup and
its backward, a whole MLP per kernel and its training's forward and backward, the training labels' leaf lists and
exact mesh hits), tested on the CPU by Triton's interpreter; `plan.py` picks them for CUDA tensors.
"""
from .library import (HEADER, PATHS, abi_hash, build, current_path, describe, fast_enabled, keep_freed_memory,
                      library_path, load, set_path, threads, using_path)
from .plan import (KernelPlan, encoding_kernel, label_kernel, leaf_list_kernel, mlp_kernel, network_kernel,
                   optimizer_kernel, plan, query_kernel, soft_table_kernel, train_step_kernel, training_layers_kernel,
                   traversal_kernel, triton_serves)

__all__ = ["HEADER", "PATHS", "abi_hash", "build", "current_path", "describe", "fast_enabled",
           "keep_freed_memory", "library_path", "load", "set_path", "threads", "using_path", "KernelPlan",
           "encoding_kernel", "network_kernel", "optimizer_kernel", "plan", "query_kernel", "soft_table_kernel", "train_step_kernel",
           "traversal_kernel", "label_kernel", "leaf_list_kernel", "mlp_kernel", "training_layers_kernel", "triton_serves"]
