"""The network component: every parameter as float32 or float16 rows, or each Linear's weight as int8 codes (4
bits: the codes stored as nibbles c + 8, two to a byte, format 2.4) with float16 row scales and biases."""
from __future__ import annotations

import numpy as np
import torch

from ..container import pack_codes
from ..errors import NBVHFileError
from ..layout import float_dtype
from ...neural.quantize import StorageConfig, dequantize_rows, quantize_rows

#: A 4-bit network weight code c in [-7, 7] is stored as the unsigned nibble c + 8.
NETWORK_CODE_OFFSET4 = 8


def network_arrays(model, bits: int) -> list[tuple[str, np.ndarray]]:
    """The network's stored arrays in file order: every state_dict entry at `bits` (32/16), or at 8 or 4 bits each
    weight as int8 codes followed by its float16 row scales (held ones as they are, else quantized now)."""
    if bits > 8:
        fdt = float_dtype(bits)
        return [(n, p.detach().cpu().numpy().astype(fdt)) for n, p in model.network.state_dict().items()
                if not n.endswith(".weight_scale")]
    out = []
    for name, m in model.network.named_modules():
        if not isinstance(m, torch.nn.Linear):
            continue
        if m.weight.dtype == torch.int8:
            codes, scale = m.weight.cpu().numpy(), m.weight_scale.cpu().numpy()
        else:
            codes, scale = quantize_rows(m.weight.detach().float().cpu().numpy(), bits)
        out += [(f"{name}.weight", codes.astype(np.int8)), (f"{name}.weight_scale", scale.astype(np.float16)),
                (f"{name}.bias", m.bias.detach().cpu().numpy().astype(np.float16))]
    return out


def network_tensors(model, storage: StorageConfig) -> list[tuple[str, str, bytes, list[int]]]:
    """(name, component, bytes, shape) of the network's stored tensors at `storage.network_bits`."""
    out = []
    for name, arr in network_arrays(model, storage.network_bits):
        data = (pack_codes(arr.astype(np.int16) + NETWORK_CODE_OFFSET4, 4)
                if storage.network_bits == 4 and arr.dtype == np.int8 else arr.tobytes())
        out.append((f"network.{name}", "network", data, list(arr.shape)))
    return out


def load_network(model, bits: int, array, names: list[str]) -> None:
    """Fill the model's network from the file's arrays and hold it as stored (float16, or int8 rows + scales)."""
    if bits > 8:
        model.network.load_state_dict({n[len("network."):]: torch.from_numpy(array(n).astype(np.float32))
                                       for n in names})
        if bits == 16:
            model.hold_network_half()  # resident as stored
        return
    rows, state = {}, {}
    for n in names:
        key = n[len("network."):]
        if key.endswith(".weight_scale"):
            continue
        if f"{n}_scale" in names:
            codes, scale = array(n), array(f"{n}_scale")
            if bits == 4:  # stored offset by 8 (0..15); code -8 is never written, and reads as itself
                codes = (codes.astype(np.int16) - NETWORK_CODE_OFFSET4).astype(np.int8)
            if not np.isfinite(scale.astype(np.float32)).all():
                raise NBVHFileError(f"network scales must be finite ({n})")
            rows[key] = (codes, scale)
            state[key] = torch.from_numpy(dequantize_rows(codes, scale).astype(np.float32))
        else:
            state[key] = torch.from_numpy(array(n).astype(np.float32))
    model.network.load_state_dict(state)
    model.hold_network_int8(rows, bits)
