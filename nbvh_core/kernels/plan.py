"""Which kernel runs each stage: decided here and nowhere else, and recorded in every result.

Every decision reads the one switch (`kernels.fast_enabled`: the fast path chosen, CPU tensors, the library built)
and the model's declared capabilities (`Encoding.grid_lookup` / `learned_index`, `Network.fused_kind`), never
probes for methods. The call sites ask the stage functions below; `plan(model, device)` gathers them into the
`KernelPlan` a result records (`TrainResult.compute_path`, `kernel_plan`), so a number says exactly which code
produced it.

Stages: query (a model's first hits: one Triton kernel on a card, else the leaf stream and the network stage),
traversal (leaf streams), leaf lists and labels (a training's rays: on the card or the host), encoding (grid lookups
outside the fused network), soft_table (HashVQAD's softmax row table while its index is soft), network (inference
per segment), train_step (forward, loss and backward of one step), optimizer (Adam's update), appearance (the
appearance head's query).
"""
from __future__ import annotations

import os
from dataclasses import asdict, dataclass

import torch

from .library import current_path, describe, fast_enabled, threads
from .triton import triton_missing

TORCH = "torch"


def triton_serves(device: torch.device | str) -> bool:
    """True when the Triton kernels serve `device`: CUDA tensors, the fast path chosen, Triton importable."""
    return current_path() == "fast" and torch.device(device).type == "cuda" and triton_missing() is None


def triton_encoding_gap(encoding) -> str | None:
    """Why the Triton lookup does not cover `encoding` (None when it does): it reads float32 rows or uint8 codes
    of a power-of-two width, a HashGrid's or a HashVQAD's (its soft row table, or its rows through the frozen
    index), hashed into powers of two."""
    if not encoding.grid_lookup:
        return "not a grid lookup"
    features = encoding.cfg.features
    if features & (features - 1) or (not encoding.quantized and encoding.table.dtype != torch.float32):
        return f"rows of {features} {str(encoding.table.dtype).replace('torch.', '')} features"
    vertex_table = encoding.vertex_table_size()
    if vertex_table & (vertex_table - 1):
        return f"an index of {vertex_table} entries (a power of two is covered)"
    return None


def triton_network_gap(net) -> str | None:
    """Why the Triton MLP does not cover `net` (an nn.Sequential of Linear/ReLU; None when it does)."""
    widths = [m.out_features for m in net if isinstance(m, torch.nn.Linear)][:-1]
    if not widths or widths[0] < 16 or widths[0] & (widths[0] - 1) or len(set(widths)) != 1:
        return f"hidden widths {widths} (one power of two >= 16 is covered)"
    return None


def mlp_kernel(net, device: torch.device | str) -> str:
    """A network's layers at inference (no autograd) on `device`: 'triton' or 'torch'."""
    return "triton" if triton_serves(device) and triton_network_gap(net) is None else TORCH


#: $NBVH_CARD_TRAINING_LAYERS=torch trains a card's layers with torch's autograd (cuBLAS per layer) instead of the
#: Triton MLP's forward and backward: the device check measures both.
TRAINING_LAYERS_ENV = "NBVH_CARD_TRAINING_LAYERS"


def training_layers_kernel(net, device: torch.device | str) -> str:
    """A network's layers in training (autograd) on `device`: 'triton' (`kernels.triton.mlp.mlp_train_forward`, where
    the inference kernel serves, its weights float32) or 'torch'."""
    trainable = all(p.dtype == torch.float32 for p in net.parameters())
    wanted = os.environ.get(TRAINING_LAYERS_ENV, "triton") != TORCH
    return "triton" if wanted and trainable and mlp_kernel(net, device) == "triton" else TORCH


def query_kernel(model, device: torch.device | str | None = None) -> str:
    """A model's ray query (first hits) on `device` (default: the model's): 'triton' (traversal, points, lookup,
    network and decode in one kernel, `triton/ray_query.py`) where the card's kernels cover the encoding and the
    network, else 'stream' (the leaf stream's traversal, then the network stage per wave of segments)."""
    device = model.device if device is None else device
    if not triton_serves(device) or model.network.fused_kind is None or getattr(model, "triton_query_failure", None):
        return "stream"
    gaps = triton_encoding_gap(model.encoding) or triton_network_gap(model.network.net)
    return "stream" if gaps else "triton"


def traversal_kernel(device: torch.device | str) -> str:
    """'fused' (per-ray stack loops in C++) or 'torch' (all rays one pop at a time with tensor ops)."""
    return "fused" if fast_enabled(device) else TORCH


def leaf_list_kernel(device: torch.device | str) -> str:
    """Every leaf each ray enters (`traversal.leaves_along_rays`: training labels' segments): 'fused' (C++ on the CPU),
    'triton' (`triton/leaf_lists.py` on a card) or 'torch'."""
    if triton_serves(device):
        return "triton"
    return traversal_kernel(device)


#: $NBVH_CARD_LABELS=host labels a card's training rays on the host (Embree and the fused C++ kernels) instead of on
#: the card: the device check measures both.
CARD_LABELS_ENV = "NBVH_CARD_LABELS"


def label_kernel(device: torch.device | str) -> str:
    """Where a training on `device` labels its rays: 'card' (the leaves entered and the mesh's exact hits by Triton
    kernels on the card, `training/card_labels.py`) or 'host' (Embree and the fused kernels, `training/rays.py`)."""
    wanted = os.environ.get(CARD_LABELS_ENV, "card") != "host"
    return "card" if wanted and triton_serves(device) else "host"


def encoding_kernel(encoding, device: torch.device | str) -> str:
    """'fused f32' | 'fused f16' | 'fused u8' (the C++ kernel on the CPU, by the row type it reads), 'triton f32' |
    'triton u8' (the Triton kernel on a card) or 'torch'."""
    if triton_serves(device):
        if triton_encoding_gap(encoding) is not None:
            return TORCH
        return "triton u8" if encoding.quantized else "triton f32"
    if not (encoding.grid_lookup and fast_enabled(device)):
        return TORCH
    if encoding.quantized:
        return "fused u8"
    if encoding.table.dtype != torch.float32:
        return TORCH
    return "fused f16" if encoding.uses_half_rows() else "fused f32"


def soft_table_kernel(encoding, device: torch.device | str) -> str | None:
    """HashVQAD's soft row table: 'fused' or 'torch'; None when the encoding has no soft index (now)."""
    if not encoding.learned_index or encoding.frozen:
        return None
    fused = (fast_enabled(device) and encoding.cfg.candidates <= 256
             and encoding.table.dtype == encoding.logits.dtype == torch.float32)  # the kernel computes in float32
    return "fused" if fused else TORCH


def network_kernel(model, device: torch.device | str | None = None) -> str:
    """Inference per (ray, leaf) segment on `device` (default: the model's): 'fused mlp' | 'fused kmlp' (points,
    lookup and every layer in one call) or 'torch' (the encoding's stage, then torch's layers)."""
    net, enc = model.network, model.encoding
    device = model.device if device is None else device
    if triton_serves(device):  # the layers fused on the card; points and lookup are the encoding's stage
        return f"triton {net.fused_kind or 'layers'}" if mlp_kernel(net.net, device) != TORCH else TORCH
    if (net.fused_kind is None or not enc.grid_lookup or not fast_enabled(device)
            or enc.table.dtype != torch.float32):
        return TORCH
    dtype = next(net.parameters()).dtype
    held = {torch.float16: " f16 weights", torch.int8: " int8 weights"}.get(dtype, "")
    return f"fused {net.fused_kind}{held}"


def train_step_kernel(model, device: torch.device | str | None = None) -> str:
    """One training step: 'fused mlp' | 'fused kmlp' (forward, loss and backward in one kernel call), 'autograd,
    triton layers' (on a card: torch's autograd over the stages, the layers' forward and backward Triton's) or
    'autograd' (torch autograd over the encoding's and the soft table's stages)."""
    fused = network_kernel(model, device)
    trainable = not model.encoding.quantized and next(model.network.parameters()).dtype == torch.float32
    if fused.startswith("fused") and trainable:
        return fused.replace(" f16 weights", "")
    device = model.device if device is None else device
    return ("autograd, triton layers" if trainable and training_layers_kernel(model.network.net, device) == "triton"
            else "autograd")


def appearance_kernel(model, device: torch.device | str | None = None) -> str | None:
    """The appearance head's query (hit points -> patch and coordinates, or colour) on `device`: its grid lookup's
    kernel (`encoding_kernel`) and its layers' (`mlp_kernel`), e.g. 'triton u8 lookup, triton layers' on a card;
    None without a head."""
    head = getattr(model, "appearance", None)
    if head is None:
        return None
    device = model.device if device is None else device
    return f"{encoding_kernel(head.encoding, device)} lookup, {mlp_kernel(head.network, device)} layers"


def optimizer_kernel() -> str:
    """'fused Adam' (torch's one-kernel Adam over all parameters: 8 vs 84 ms per step for HashVQAD's 8.4M index
    logits on the 2-core CPU) on the fast path, 'Adam' (the default implementation) on the reference path."""
    return "fused Adam" if current_path() == "fast" else "Adam"


@dataclass(frozen=True)
class KernelPlan:
    """What runs each stage for one model on one device (see the module docstring)."""

    path: str  # 'fast' | 'reference': the switch
    device: str
    traversal: str
    query: str
    encoding: str
    soft_table: str | None
    network: str
    train_step: str
    optimizer: str
    threads: int
    note: str = ""  # why the fused kernels do not serve this device, if they do not
    appearance: str | None = None  # the appearance head's query, when the model has a head
    labels: str = "host"  # where training rays are labelled: 'host' | 'card'

    def describe(self) -> str:
        """One line for results, e.g. 'fast on cpu (2 threads): traversal fused, train step fused kmlp, ...'."""
        stages = [f"query {self.query}", f"traversal {self.traversal}", f"labels on the {self.labels}",
                  f"train step {self.train_step}",
                  f"network {self.network}", f"encoding {self.encoding}"]
        if self.soft_table is not None:
            stages.append(f"soft table {self.soft_table}")
        if self.appearance is not None:
            stages.append(f"appearance {self.appearance}")
        stages.append(self.optimizer)
        head = f"{self.path} on {self.device} ({self.threads} threads)"
        return f"{head}: {', '.join(stages)}" + (f" [{self.note}]" if self.note else "")

    def to_dict(self) -> dict:
        return asdict(self)


def plan(model, device: torch.device | str | None = None) -> KernelPlan:
    """The plan for `model` (NeuralBVH) on `device` (default: where the model is), as it is now (a HashVQAD's soft
    table stage disappears once it is frozen; a quantized table is read as u8)."""
    device = torch.device(device if device is not None else model.device)
    enc = model.encoding
    note = "" if fast_enabled(device) or current_path() == "reference" else describe(device)
    if triton_serves(device):
        gaps = [f"encoding: {g}" for g in [triton_encoding_gap(enc)] if g]
        gaps += [f"network: {g}" for g in [triton_network_gap(model.network.net)] if g]
        gaps += [f"ray query: {g}" for g in [getattr(model, "triton_query_failure", None)] if g]
        layers = training_layers_kernel(model.network.net, device)
        labeller = ("Triton kernels label training rays on the card" if label_kernel(device) == "card"
                    else "the host's fused kernels label training rays")
        note = ("Triton kernels on the card (the ray query one kernel); " + labeller +
                f"; the training step's layers {'Triton' if layers == 'triton' else 'torch'}'s under autograd"
                + (f"; torch where not covered ({'; '.join(gaps)})" if gaps else ""))
    traversal = traversal_kernel(device)
    if traversal == "fused" and model.compact_nodes is not None:
        traversal = "fused 8-bit nodes"
    return KernelPlan(path=current_path(), device=device.type, traversal=traversal,
                      query=query_kernel(model, device),
                      encoding=encoding_kernel(enc, device), soft_table=soft_table_kernel(enc, device),
                      network=network_kernel(model, device), train_step=train_step_kernel(model, device),
                      optimizer=optimizer_kernel(), threads=threads(), note=note,
                      appearance=appearance_kernel(model, device), labels=label_kernel(device))
