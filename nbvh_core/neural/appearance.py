"""The appearance head: what a hit looks like - its material slot and texture coordinates - from its position.

The geometry network answers hit, distance and normal per (ray, leaf) segment; the look of a hit depends only on
where on the surface it is, so it is a field over points, queried once per hit pixel after the geometry query:

    point (N, 3) in [0, 1]^3 -> HashGrid features (L * F) ++ point -> MLP -> patch logits (P), residual (2)
    slot = patch_slot[patch];  uv = affine[patch] @ (point, 1) + tanh(residual) * fit_error[patch]

Seams are handled by classification, not regression: the surface is cut into patches (`uv_patches.uv_patches`: one
per UV island and slot, curved islands cut further until an affine map of position fits their coordinates) and
the head names the patch a hit lies on. A regression across a seam would blur two islands' coordinates into
texels of neither; a wrong class lands on the neighbouring patch, whose map is continuous with this one unless a
seam runs between them. Planar-projected islands (Blender's Smart UV Project, box and cube maps) are exactly
affine, so there the coordinates are exact wherever the patch is right; curved maps (a sphere's
equirectangular, a torus) leave a residual the network regresses (L1), bounded by the patch's fit error (so an
exact patch stays exact whatever the network outputs) and far smaller than the coordinates.
Measured on the generated assets (bench/look/bench_look.py): the full-coordinate regression this replaces held
18-34% of hits within half a 512 px texel after 20-30 s; see docs/results.md for the patch head.
Its training, on exact labels at traced hits, is `training/appearance_training.py`.

A look with one slot and no texture needs no head (`Look.plain`); the model then carries the material only.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ..geometry.mesh import Mesh
from .encodings import EncodingConfig, make_encoding
from .networks import run_layers


@dataclass
class AppearanceConfig:
    """The head's architecture. slots: the asset's material slots; patches: the classes it tells apart
    (`uv_patches.uv_patches`; at most max_patches unless the islands alone are more); uv: whether it regresses
    coordinates; levels x 2^log2_table rows of `features` floats at resolutions n_min..n_max; `hidden` layers of
    `width`. patch_tolerance: the affine fit a curved island is cut to (normalised UV units; 1/2048 = a quarter
    texel at 512 px). target: "coordinates" (slot and texture coordinates; the images stay in the file) or
    "colour" (the textured colour itself, sRGB, regressed per point: no images stored, no patches)."""

    target: str = "coordinates"
    slots: int = 1
    patches: int = 1
    uv: bool = True
    max_patches: int = 64
    patch_tolerance: float = 1.0 / 2048
    #: 1: each patch's coordinates are an affine map of position (exact for planar projections); 2: quadratic; 3:
    #: cubic (168 B a patch). Within half a 512 px texel, away from seams, maps alone at 64 patches (faces sampled
    #: uniformly): globe 86% quadratic / 97% cubic, ring (torus) 44% / 99%.
    patch_degree: int = 3
    levels: int = 8
    n_min: int = 16
    n_max: int = 1024
    features: int = 2
    log2_table: int = 9
    hidden: int = 2
    width: int = 32
    uv_weight: float = 10.0
    #: Patches whose maps a file stores: the first ones, those of slots that sample an image (a plain slot's patch
    #: needs no coordinates: 100 plain slots would otherwise store 16.8 KB of zero cubic maps). None: all.
    mapped_patches: int | None = None

    def encoding(self) -> EncodingConfig:
        return EncodingConfig(kind="hashgrid", levels=self.levels, n_min=self.n_min, n_max=self.n_max,
                              features=self.features, log2_table=self.log2_table)

    @property
    def classes(self) -> int:
        """Logits the head outputs (0 with a single patch)."""
        return self.patches if self.patches > 1 and self.target == "coordinates" else 0

    @property
    def outputs(self) -> int:
        return 3 if self.target == "colour" else self.classes + (2 if self.uv else 0)

    @property
    def stored_maps(self) -> int:
        """How many patch maps a file holds (the first `mapped_patches`, or all)."""
        return self.patches if self.mapped_patches is None else self.mapped_patches

    def to_dict(self) -> dict:
        return asdict(self)


class AppearanceHead(nn.Module):
    """points (N, 3) normalised -> patch logits (N, P) and coordinate residuals (N, 2); `predict` turns them into
    slots and coordinates with the buffers `affine` (P, 2, 5) and `patch_slot` (P,) (`uv_patches.uv_patches`)."""

    def __init__(self, cfg: AppearanceConfig, inference: bool = False):
        super().__init__()
        if cfg.outputs == 0:
            raise ValueError("an appearance head needs more than one patch or texture coordinates")
        self.cfg = cfg
        self.register_buffer("affine", torch.zeros(cfg.patches, 2, map_width(cfg.patch_degree)))
        self.register_buffer("patch_slot", torch.zeros(cfg.patches, dtype=torch.int64))
        self.encoding = make_encoding(cfg.encoding(), inference)
        layers: list[nn.Module] = []
        d = self.encoding.out_dim + 3
        for _ in range(cfg.hidden):
            layers += [nn.Linear(d, cfg.width), nn.ReLU()]
            d = cfg.width
        layers.append(nn.Linear(d, cfg.outputs))
        self.network = nn.Sequential(*layers)

    def forward(self, points: torch.Tensor) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        """points (N, 3) float32 -> patch logits (N, P) or None (one patch), and residual (N, 2) or None; for
        the colour target (None, sRGB colour (N, 3) in [0, 1])."""
        feats = self.encoding(points)
        x = torch.cat([feats, points * 2 - 1], dim=1)
        out = run_layers(self.network, x.to(self.network[0].weight.dtype)).float()  # on a card: one Triton kernel
        if self.cfg.target == "colour":
            return None, torch.sigmoid(out)
        c = self.cfg.classes
        return (out[:, :c] if c else None), (out[:, c:c + 2] if self.cfg.uv else None)

    @torch.no_grad()
    def colour(self, points: torch.Tensor, batch: int = 1 << 16) -> np.ndarray:
        """points (N, 3) normalised -> (N, 3) float32 sRGB colour (the colour target)."""
        return np.concatenate([self(points[a:a + batch].to(self.affine.device, torch.float32))[1].cpu().numpy()
                               for a in range(0, points.shape[0], batch)] or [np.zeros((0, 3), np.float32)])

    def patch_map(self, points: torch.Tensor, patch: torch.Tensor, residual: torch.Tensor | None = None
                  ) -> torch.Tensor:
        """(N, 2) coordinates of each patch's affine map at points (N, 3), plus the raw residual (N, 2) squashed
        to the patch's fit error when given."""
        from ..geometry.uv_patches import patch_basis

        a = self.affine[patch]
        uv = torch.einsum("nij,nj->ni", a[:, :, :-1], patch_basis(points, self.cfg.patch_degree))
        return uv if residual is None else uv + torch.tanh(residual) * a[:, :, -1]

    @torch.no_grad()
    def predict(self, points: torch.Tensor, batch: int = 1 << 16) -> tuple[np.ndarray, np.ndarray | None]:
        """points (N, 3) normalised -> slot (N,) int32, uv (N, 2) float32 (None without coordinates)."""
        dev = self.affine.device
        n = points.shape[0]
        slot = np.zeros(n, np.int32)
        uv = np.zeros((n, 2), np.float32) if self.cfg.uv else None
        for a in range(0, n, batch):
            p = points[a:a + batch].to(dev, torch.float32)
            logits, residual = self(p)
            patch = logits.argmax(1) if logits is not None else torch.zeros(len(p), dtype=torch.int64, device=dev)
            slot[a:a + batch] = self.patch_slot[patch].cpu().numpy()
            if residual is not None:
                uv[a:a + batch] = self.patch_map(p, patch, residual).cpu().numpy()
        return slot, uv

    def loss(self, points: torch.Tensor, patch: torch.Tensor, uv: torch.Tensor | None) -> torch.Tensor:
        """Cross-entropy of the patch + uv_weight x L1 of the coordinates on the true patch, averaged (the L1 is
        scaled by 1 / the mean fit error, so a curved map's small residual still steers the network). The colour
        target: L1 of the sRGB colour (`uv` holds the target colours (N, 3))."""
        logits, residual = self(points)
        if self.cfg.target == "colour":
            return (residual - uv).abs().sum(1).mean()
        total = points.new_zeros(())
        if logits is not None:
            total = total + F.cross_entropy(logits, patch)
        if residual is not None and uv is not None:
            scale = self.affine[:, :, -1].mean().clamp_min(1e-6)
            error = (self.patch_map(points, patch, residual) - uv).abs().sum(1).mean() / scale
            total = total + self.cfg.uv_weight * 1e-2 * error
        return total


def make_head(mesh: Mesh, base: AppearanceConfig | None = None) -> tuple[AppearanceHead, np.ndarray] | None:
    """The untrained head a mesh's look needs and its faces' patches (F,), or None (a plain look needs none):
    `base`'s sizes with the look's slots, patches (`uv_patches.uv_patches`, their maps in the head's buffers) and uv."""
    from ..geometry.uv_patches import uv_patches

    look = mesh.look
    if look is None or look.plain:
        return None
    cfg = AppearanceConfig(**(base.to_dict() if base is not None else {}))
    if cfg.target not in TARGETS:
        raise ValueError(f"unknown appearance target {cfg.target!r}; choose from {', '.join(TARGETS)}")
    if cfg.target == "colour":  # one patch: the network answers the colour itself
        face_patch = np.zeros(len(mesh.faces), np.int32)
        affine, patch_slot = np.zeros((1, 2, map_width(cfg.patch_degree)), np.float32), np.zeros(1, np.int32)
    else:
        face_patch, affine, patch_slot = uv_patches(mesh.vertices, mesh.faces, look, cfg.patch_tolerance,
                                                    cfg.max_patches, cfg.patch_degree)
    cfg.slots, cfg.patches, cfg.uv = look.n_slots, len(affine), look.textured and cfg.target == "coordinates"
    sampled = look.image_slots[patch_slot]
    cfg.mapped_patches = int(sampled.sum()) if cfg.uv else 0
    assert sampled[:cfg.mapped_patches].all() or not cfg.uv, "uv_patches puts image slots' patches first"
    head = AppearanceHead(cfg)
    with torch.no_grad():
        head.affine.copy_(torch.from_numpy(affine))
        head.patch_slot.copy_(torch.from_numpy(patch_slot.astype(np.int64)))
    return head, face_patch


#: What an appearance head answers (AppearanceConfig.target).
TARGETS = ("coordinates", "colour")


def head_table_bits(table_bits: int) -> int:
    """Bits per feature of the head's table in a file whose geometry table has `table_bits`: never below 8 (the head
    trains no quantization-aware phase, and rounding a table to 4 bits afterwards read 4.9x the MSE on the geometry)."""
    return max(table_bits, 8)


@torch.no_grad()
def finalize_head(head: AppearanceHead, table_bits: int, network_bits: int) -> None:
    """Hold the head as a file with these geometry widths stores it: table as uint8 codes (8, also for a 4-bit
    geometry table: `head_table_bits`) or float16-rounded (16); network weights rounded to float16 (16 or 8: the head
    is small, so it is never stored below 16 bits)."""
    head.encoding.hold_as_stored(head_table_bits(table_bits))
    if network_bits < 32:
        for p in head.network.parameters():
            p.copy_(p.half().float())
    head.eval()


def map_width(degree: int) -> int:
    """Numbers per coordinate of a patch map: the basis (4, 10 or 20) and the fit error."""
    from ..geometry.uv_patches import PATCH_BASIS_SIZE

    return PATCH_BASIS_SIZE[degree] + 1
