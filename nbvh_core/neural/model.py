"""NeuralBVH: BVH nodes + encoding + network = a ray-queryable neural representation of the mesh.

query(rays) -> hit, t, normal: front-to-back traversal with `traversal.LeafStream`; in every wave each live ray
gets its next leaf, all (ray, leaf) segments of the wave go through the network in batches, and a ray stops at
its first leaf whose prediction is a hit (the paper's inference). Rays and outputs are in normalised mesh
coordinates (the unit box); `Transform` maps them back.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn

from .. import kernels
from ..geometry.bvh import NODE_DTYPE
from ..geometry.mesh import Transform
from ..geometry.traversal import CompactBVH, LeafStream, TorchBVH
from . import fused_mlp as mlp
from .encodings import EncodingConfig, make_encoding
from .networks import NetworkConfig, make_network
from .quantize import StorageConfig, decode_nodes, encode_nodes, quantize_rows, shape_bits, stored_node_bytes


@dataclass
class ModelConfig:
    """Everything that defines a model's architecture (serialised into the .nbvh header)."""

    encoding: EncodingConfig = field(default_factory=EncodingConfig)
    network: NetworkConfig = field(default_factory=NetworkConfig)

    def to_dict(self) -> dict:
        return {"encoding": self.encoding.to_dict(), "network": self.network.to_dict()}

    @staticmethod
    def from_dict(d: dict) -> "ModelConfig":
        return ModelConfig(EncodingConfig(**d["encoding"]), NetworkConfig(**d["network"]))


@dataclass
class QueryResult:
    """hit: (N,) bool; t: (N,) float32 distance along the ray (inf on a miss); normal: (N, 3) float32 unit,
    facing the ray (n . d <= 0; 0 on a miss); leaves_evaluated: total (ray, leaf) segments the network evaluated."""

    hit: torch.Tensor
    t: torch.Tensor
    normal: torch.Tensor
    leaves_evaluated: int = 0


class NeuralBVH(nn.Module):
    """The neural model. nodes: (M,) NODE_DTYPE BVH array; cfg: ModelConfig; transform: to original units."""

    def __init__(self, nodes: np.ndarray, cfg: ModelConfig, transform: Transform | None = None,
                 inference: bool = False):
        """inference=True: built to be filled by the file reader (no trainable encoding state is allocated)."""
        super().__init__()
        self._nodes = nodes
        #: The stored 8-bit node format, held instead of the decoded nodes after `hold_nodes_compact`.
        self.compact_nodes: dict | None = None
        self.cfg = cfg
        self.transform = transform or Transform(1.0, np.zeros(3))
        self.encoding = make_encoding(cfg.encoding, inference)
        self.network = make_network(self.encoding.out_dim, cfg.network)
        self._tree: TorchBVH | None = None
        self.metadata: dict = {}  # what the file's header carried (training, quality, source)
        #: Why the card's ray query kernel could not answer (then the leaf stream does; `kernels.plan` says so).
        self.triton_query_failure: str | None = None
        #: The asset's materials, one per slot (`look.Material`; empty: a bare shape, shaded grey).
        self.materials: list = []
        #: The appearance head (`appearance.AppearanceHead`): slot and texture coordinates per hit point; None
        #: when the look needs none (one slot, no texture).
        self.appearance = None

    @property
    def half_tables(self) -> bool:
        """Query with float16 feature rows (fast path on the CPU, inference only); see bench/results/speed.md for
        what it changes in the metric."""
        return self.encoding.half_tables

    @half_tables.setter
    def half_tables(self, value: bool) -> None:
        self.encoding.half_tables = bool(value)

    @property
    def device(self) -> torch.device:
        return self.encoding.table.device

    @property
    def nodes(self) -> np.ndarray:
        """(M,) NODE_DTYPE decoded nodes (decoded on each access while the model holds the 8-bit format)."""
        if self._nodes is not None:
            return self._nodes
        c = self.compact_nodes
        return decode_nodes(c["root"], c["boxes"], c["left"], c["leaf"])

    @property
    def n_nodes(self) -> int:
        return len(self._nodes) if self._nodes is not None else len(self.compact_nodes["left"])

    def set_nodes(self, nodes: np.ndarray) -> None:
        """Replace the BVH nodes ((M,) NODE_DTYPE; e.g. a refined tree cut during training); the traversal tree is
        rebuilt on next use."""
        self._nodes, self.compact_nodes, self._tree = nodes, None, None

    def hold_nodes_compact(self, packed: dict | None = None) -> bool:
        """Hold the nodes in the file's 8-bit format (10 B per node; `packed` as `quantize.encode_nodes` returns
        it, default: encoded from the current nodes) instead of decoded 32-byte records; the fused traversal
        decodes boxes on the way down. Inference only. False (nothing changed) when the boxes cannot be encoded."""
        packed = packed if packed is not None else encode_nodes(self.nodes)
        if packed is None:
            return False
        self.compact_nodes, self._nodes, self._tree = packed, None, None
        return True

    def tree(self) -> TorchBVH | CompactBVH:
        """What the traversal reads: the 8-bit nodes as held (fused traversal on the CPU), else the decoded node
        records (a view of `nodes`; decoded from the 8-bit format for the reference path)."""
        if self.compact_nodes is not None and kernels.traversal_kernel(self.device) == "fused":
            if not isinstance(self._tree, CompactBVH):
                self._tree = CompactBVH(self.compact_nodes)
            return self._tree
        if self._tree is None or isinstance(self._tree, CompactBVH) or self._tree.device != self.device:
            self._tree = TorchBVH.from_nodes(self.nodes, self.device)
        return self._tree

    def segment_points(self, rays_o: torch.Tensor, rays_d: torch.Tensor, t_enter: torch.Tensor,
                       t_exit: torch.Tensor) -> torch.Tensor:
        """(B, k, 3) points t_i = t_enter + i / (k - 1) (t_exit - t_enter) of each segment (B rows)."""
        k = self.cfg.network.k
        frac = torch.linspace(0.0, 1.0, k, device=rays_o.device, dtype=rays_o.dtype)
        t = t_enter[:, None] + frac[None] * (t_exit - t_enter)[:, None]
        return rays_o[:, None, :] + t[..., None] * rays_d[:, None, :]

    def forward(self, rays_o: torch.Tensor, rays_d: torch.Tensor, t_enter: torch.Tensor,
                t_exit: torch.Tensor) -> torch.Tensor:
        """Raw network outputs for B segments (rays_o, rays_d: (B, 3); t_enter, t_exit: (B,))."""
        pts = self.segment_points(rays_o, rays_d, t_enter, t_exit)
        b, k, _ = pts.shape
        feats = self.encoding(pts.reshape(-1, 3)).reshape(b, k, -1)
        return self.network(feats)

    @torch.no_grad()
    def query(self, rays_o: torch.Tensor, rays_d: torch.Tensor, batch: int = 65536,
              ray_chunk: int = 1 << 17) -> QueryResult:
        """First predicted hit of every ray. rays_o, rays_d: (N, 3) float32 (unit directions), any device.

        Rays go through in chunks of `ray_chunk` (each with its own leaf stream: the per-ray traversal stacks of a
        1000x1000 image would otherwise take ~200 MB), the segments of a wave in batches of `batch`."""
        dev = self.device
        rays_o = rays_o.to(dev, torch.float32).contiguous()
        rays_d = rays_d.to(dev, torch.float32).contiguous()
        if kernels.query_kernel(self, dev) == "triton":
            try:
                return self._triton_query(rays_o, rays_d)
            except Exception as exc:  # a card or driver the kernel does not build for: the stream path answers
                self.triton_query_failure = (f"the Triton ray query failed ({type(exc).__name__}: "
                                             f"{str(exc).splitlines()[0][:160] if str(exc) else ''}); the leaf "
                                             "stream answers")
                warnings.warn(self.triton_query_failure, RuntimeWarning, stacklevel=2)
        n = rays_o.shape[0]
        hit = torch.zeros(n, dtype=torch.bool, device=dev)
        t_out = torch.full((n,), torch.inf, device=dev)
        normal = torch.zeros((n, 3), device=dev)
        evaluated = 0
        fused = self._fused_network()
        if self.compact_nodes is not None:  # stacks carry 6 floats more per entry: chunks 4x smaller, same memory
            ray_chunk = min(ray_chunk, 1 << 15)
        for c0 in range(0, n, ray_chunk):
            c1 = min(n, c0 + ray_chunk)
            evaluated += self._query_chunk(rays_o[c0:c1], rays_d[c0:c1], hit[c0:c1], t_out[c0:c1], normal[c0:c1],
                                           fused, batch)
        # Normals face the ray, whatever sign the network learnt (unoriented loss; rays that started inside).
        normal = torch.where(((normal * rays_d).sum(-1, keepdim=True) > 0), -normal, normal)
        return QueryResult(hit=hit, t=t_out, normal=normal, leaves_evaluated=evaluated)

    def _triton_query(self, rays_o: torch.Tensor, rays_d: torch.Tensor) -> QueryResult:
        """`query` as one Triton kernel on the card (`kernels.triton.ray_query`): every ray in one launch, no
        stacks in memory, no host sync until the result."""
        from ..kernels.triton.ray_query import first_hits
        from .networks import triton_packed

        tree = self.tree()
        if isinstance(tree, CompactBVH):  # the CPU's fused stream reads the 8-bit nodes (the interpreter's tests)
            tree = TorchBVH.from_nodes(self.nodes, self.device)
        k = self.cfg.network.k
        frac = torch.linspace(0.0, 1.0, k, device=rays_o.device, dtype=torch.float32)
        found = first_hits(rays_o, rays_d, tree.records, tree.max_depth, frac,
                           self.encoding.triton_rows(rays_o.device), triton_packed(self.network.net),
                           self.network.fused_kind)
        normal = torch.where(((found.normal * rays_d).sum(-1, keepdim=True) > 0), -found.normal, found.normal)
        return QueryResult(hit=found.hit, t=found.t, normal=normal, leaves_evaluated=int(found.segments.sum()))

    def _query_chunk(self, rays_o: torch.Tensor, rays_d: torch.Tensor, hit: torch.Tensor, t_out: torch.Tensor,
                     normal: torch.Tensor, fused: tuple | None, batch: int) -> int:
        """`query` for one chunk of rays, writing into the chunk's views of the outputs; returns segments."""
        evaluated = 0
        stream = LeafStream(self.tree(), rays_o, rays_d)
        while True:
            ray, _, te, tx = stream.next()
            if ray.numel() == 0:
                break
            evaluated += ray.numel()
            for s in range(0, ray.numel(), batch):
                r, a, b = ray[s:s + batch], te[s:s + batch], tx[s:s + batch]
                if fused is not None:
                    prob, local_t, nrm = self._fused_first_hits(fused, rays_o, rays_d, r, a, b)
                else:
                    prob, local_t, nrm = self.network.decode(self.forward(rays_o[r], rays_d[r], a, b))
                is_hit = prob > 0.5
                rh = r[is_hit]
                hit[rh] = True
                t_out[rh] = a[is_hit] + local_t[is_hit] * (b[is_hit] - a[is_hit])
                normal[rh] = nrm[is_hit]
                stream.stop(rh)
        return evaluated

    def _fused_network(self) -> tuple[torch.Tensor, torch.Tensor] | None:
        """The packed network for the fused inference kernel (`fused_mlp.pack`), or None where `kernels.plan`
        does not run it fused (reference path, CUDA)."""
        return mlp.pack(self) if mlp.applies(self) else None

    def _fused_raw(self, fused: tuple[torch.Tensor, torch.Tensor], rays_o: torch.Tensor, rays_d: torch.Tensor,
                   ray: torch.Tensor, t_enter: torch.Tensor, t_exit: torch.Tensor) -> torch.Tensor:
        """What `forward(rays_o[ray], rays_d[ray], t_enter, t_exit)` returns, from one fused kernel call."""
        return mlp.segments_raw(self, fused, rays_o, rays_d, ray, t_enter, t_exit)

    def _fused_first_hits(self, fused: tuple[torch.Tensor, torch.Tensor], rays_o: torch.Tensor, rays_d: torch.Tensor,
                          ray: torch.Tensor, t_enter: torch.Tensor, t_exit: torch.Tensor
                          ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """What `network.decode(forward(...))` returns (hit probability, local t, unit normal) from one fused
        kernel call (`fused_mlp.segments_first_hits`)."""
        return mlp.segments_first_hits(self, fused, rays_o, rays_d, ray, t_enter, t_exit)

    @torch.no_grad()
    def albedo_at(self, points: np.ndarray) -> np.ndarray | None:
        """(N, 3) float32 linear albedo of hit points (N, 3) normalised (the slot's base colour or its image at the
        predicted coordinates, `look.albedo`), or None for a bare shape (no materials)."""
        from ..geometry.look import albedo, srgb_to_linear

        if not self.materials:
            return None
        if self.appearance is None:
            return albedo(self.materials, np.zeros(len(points), np.int64), None)
        pts = torch.from_numpy(np.ascontiguousarray(points, np.float32))
        if self.appearance.cfg.target == "colour":
            return srgb_to_linear(self.appearance.colour(pts))
        slot, uv = self.appearance.predict(pts)
        return albedo(self.materials, slot, uv)

    def stored_bytes(self, storage: StorageConfig | None = None) -> dict[str, int]:
        """Bytes of the stored tensors by component (no header) at `storage` (default float32 everywhere): bvh,
        features, [index], network."""
        st = storage or StorageConfig.float32()
        out = {"bvh": stored_node_bytes(self.n_nodes, st.node_bits, self.shape_only())}
        out.update(self.encoding.stored_bytes(st.table_bits))
        out["network"] = network_stored_bytes(self.network, st.network_bits)
        return out

    def shape_only(self) -> bool:
        """Whether a file holds this tree's shape as one bit per node (`quantize.shape_bits`: the layout
        `bvh.layout_cut` makes) rather than links and leaf ordinals. Nodes not built yet (all zero: a shapes-only
        model sizing a file) count as laid out by `layout_cut`, which builds every trained tree."""
        c = self.compact_nodes
        left, leaf = (c["left"], c["leaf"]) if c is not None else (self._nodes["left"], self._nodes["leaf"])
        if len(left) > 1 and not np.asarray(left).any():
            return True
        return shape_bits(left, leaf) is not None

    def resident_bytes(self) -> dict[str, int]:
        """Bytes this model holds to answer rays, by component: the nodes as held (the 8-bit boxes with links and
        leaf ordinals, 10 B each, after `hold_nodes_compact`; else the decoded 32-byte records, which the fused
        traversal reads in place: `traversal.TorchBVH` is a view of them on the CPU), the
        feature rows as held (uint8 codes + affine, or floats), HashVQAD's codes (one byte each), the network's
        weights as held (float16 after `finalize_storage` at 16 bits, or when loaded from such a file; the fused
        kernels read them without a float32 copy), and for an asset with a look the appearance head as held and the
        decoded texture images."""
        enc = self.encoding
        rows = (enc.qcodes.numel() + 4 * (enc.qoffset.numel() + enc.qscale.numel()) if enc.quantized
                else enc.table.numel() * enc.table.element_size())
        bvh = (stored_node_bytes(self.n_nodes, 8, shape_only=False) if self.compact_nodes is not None
               else self.n_nodes * NODE_DTYPE.itemsize)
        out = {"bvh": bvh, "features": int(rows)}
        if enc.learned_index and enc.frozen:
            out["index"] = int(enc.codes.numel())
        out["network"] = sum(t.numel() * t.element_size()
                             for t in (*self.network.parameters(), *self.network.buffers()))
        if self.appearance is not None:  # the head's tables and layers as held
            out["appearance"] = sum(t.numel() * t.element_size()
                                    for t in (*self.appearance.parameters(), *self.appearance.buffers()))
        textures = sum(m.image.nbytes for m in self.materials if m.image is not None)
        if textures:  # the decoded images a hit samples
            out["textures"] = int(textures)
        return out

    @torch.no_grad()
    def finalize_storage(self, storage: StorageConfig) -> None:
        """Make this in-memory model exactly the one a file at `storage` loads back: the table as uint8 codes
        (8 bits) or rounded to float16, the network's weights held in float16 (16 bits), the nodes held in the
        8-bit format (8 bits; the pipeline trained on exactly these boxes: `quantize.snap_nodes`). Irreversible;
        inference only afterwards."""
        self.encoding.hold_as_stored(storage.table_bits)
        if storage.network_bits == 16:
            self.hold_network_half()
        elif storage.network_bits <= 8:
            self.hold_network_int8(bits=storage.network_bits)
        if storage.node_bits == 8:
            self.hold_nodes_compact()

    @torch.no_grad()
    def hold_network_int8(self, rows: dict | None = None, bits: int = 8) -> None:
        """Keep each Linear's weight as int8 rows with float16 scales (`quantize.quantize_rows` at `bits`, 8 or 4;
        `rows`: state_dict weight name -> (codes, scale) as a file stores them, default: quantized from the current
        weights) and the biases in float16, as a file with network_bits 8 or 4 stores them. Inference only."""
        for name, m in self.network.named_modules():
            if not isinstance(m, nn.Linear):
                continue
            key = f"{name}.weight"
            if rows is not None:
                codes, scale = rows[key]
            else:
                codes, scale = quantize_rows(m.weight.detach().float().cpu().numpy(), bits)
            m.weight.requires_grad_(False)
            m.weight.data = torch.from_numpy(np.ascontiguousarray(codes, np.int8)).to(m.weight.device)
            m.register_buffer("weight_scale", torch.from_numpy(np.ascontiguousarray(scale, np.float16)).to(m.weight.device))
            m.bias.requires_grad_(False)
            m.bias.data = m.bias.data.to(torch.float16)

    @torch.no_grad()
    def hold_network_half(self) -> None:
        """Keep the network's weights in float16 from now on, as the file stores them (half the resident bytes;
        the fused kernels read them as they are, the reference path casts per call). Inference only."""
        for p in self.network.parameters():
            p.data = p.data.to(torch.float16)

    def flops_per_segment(self) -> dict[str, int]:
        """Floating-point operations (a multiply-add = 2) to evaluate one (ray, leaf) segment, by part:
        'encoding' (k points x L levels x 8 corners x F weighted adds; the integer hash arithmetic is not
        counted) and 'network' (every Linear layer's multiply-adds and bias adds; KMLP runs k - 1 times)."""
        enc, net = self.cfg.encoding, self.cfg.network
        per_run = sum(2 * m.in_features * m.out_features + m.out_features
                      for m in self.network.modules() if isinstance(m, nn.Linear))
        runs = net.k - 1 if net.kind == "kmlp" else 1
        return {"encoding": 2 * net.k * enc.levels * 8 * enc.features, "network": runs * per_run}

    def describe(self) -> dict:
        return {"config": self.cfg.to_dict(), "nodes": int(self.n_nodes),
                "transform": self.transform.to_dict()}



def network_stored_bytes(network: nn.Module, bits: int) -> int:
    """Bytes of a network's stored tensors at `bits` per weight: 32/16: every parameter at that width; 8 or 4: each
    Linear's weight as codes (4-bit codes two to a byte) plus a float16 scale per row, biases float16."""
    if bits > 8:
        return sum(p.numel() for p in network.parameters()) * bits // 8
    total = 0
    for m in network.modules():
        if isinstance(m, nn.Linear):
            total += -(-m.in_features * m.out_features * bits // 8) + 2 * m.out_features + 2 * m.out_features
    return total
