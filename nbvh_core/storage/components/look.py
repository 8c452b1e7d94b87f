"""The asset's look (format 2.3): the appearance head's table, network, patch maps and slots, and every slot image
as PNG or JPEG bytes (`Material.stored_image`; a reader that knows PNG only refuses a JPEG texture in one line)."""
from __future__ import annotations

import numpy as np
import torch

from ..errors import NBVHFileError
from .table import load_table, table_tensors
from ...geometry.look import LookError, Material, decode_texture
from ...neural.appearance import AppearanceHead, head_table_bits
from ...neural.quantize import StorageConfig


def look_tensors(model, storage: StorageConfig) -> list[tuple[str, str, bytes, list[int]]]:
    """The appearance head's table and network, then every slot image as stored (`Material.stored_image`)."""
    out = []
    head = model.appearance
    if head is not None:
        out += table_tensors(head.encoding, "appearance.features", "appearance", head_table_bits(storage.table_bits),
                              "appearance.finalize_head")
        fdt = np.float32 if storage.network_bits == 32 else np.float16
        for name, p in head.network.state_dict().items():
            arr = p.detach().cpu().numpy().astype(fdt)
            out.append((f"appearance.network.{name}", "appearance", arr.tobytes(), list(arr.shape)))
        affine = head.affine.cpu().numpy().astype(np.float32)[:head.cfg.stored_maps]
        patch_slot = head.patch_slot.cpu().numpy().astype(np.uint16)
        if len(affine):
            out.append(("appearance.affine", "appearance", affine.tobytes(), list(affine.shape)))
        out.append(("appearance.patch_slot", "appearance", patch_slot.tobytes(), list(patch_slot.shape)))
    for i, m in enumerate(model.materials):
        if m.image is not None:
            data = m.stored_image()
            out.append((f"texture.{i}", "textures", data, [len(data)]))
    return out


def look_header(model) -> dict | None:
    """The header's `appearance` field: the head's config and the materials (None without materials)."""
    if not model.materials:
        return None
    return {"config": None if model.appearance is None else model.appearance.cfg.to_dict(),
            "materials": [m.to_dict() for m in model.materials]}


def load_look(model, look: tuple, table_bits: int, array, where: str) -> None:
    """The materials (textures decoded from their PNG or JPEG bytes) and the appearance head, held as stored."""
    cfg, mats = look
    materials = []
    for i, m in enumerate(mats):
        image = None
        if m["image"] is not None:
            try:
                image = decode_texture(array(f"texture.{i}").tobytes(), tuple(m["image"]), where)
            except LookError as exc:
                raise NBVHFileError(str(exc)) from None
        materials.append(Material(m["name"], np.asarray(m["base_color"], np.float32), image))
    model.materials = materials
    if cfg is None:
        return
    head = AppearanceHead(cfg, inference=True)
    load_table(head.encoding, "appearance.features", head_table_bits(table_bits), array,
                f"{where}: appearance feature scales must be > 0")
    state = {n: torch.from_numpy(array(f"appearance.network.{n}").astype(np.float32))
             for n in head.network.state_dict()}
    head.network.load_state_dict(state)
    patch_slot = array("appearance.patch_slot").astype(np.int64)
    if (patch_slot >= len(materials)).any():
        raise NBVHFileError(f"{where}: appearance patches name slots beyond the {len(materials)} materials")
    if cfg.stored_maps:
        head.affine[:cfg.stored_maps] = torch.from_numpy(array("appearance.affine"))
    head.patch_slot.copy_(torch.from_numpy(patch_slot))
    head.requires_grad_(False)
    model.appearance = head.eval()
