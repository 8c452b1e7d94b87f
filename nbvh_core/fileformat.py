"""The .nbvh file: a compact, versioned, checksummed container of one trained NeuralBVH.

Layout (little endian):

    offset  size  field
    0       8     magic b"NBVH\\x00\\r\\n\\x1a" (catches text-mode transfers and truncation at the first bytes)
    8       2     format major version (readers refuse other majors)
    10      2     format minor version (additions a reader may ignore)
    12      4     header length H (bytes of UTF-8 JSON)
    16      H     header JSON: model config, transform, float width, the tensor table (name, dtype, shape,
                  offset, nbytes) and free-form metadata (training, quality, source mesh)
    16+H    ...   payload: the tensors back to back in table order, each 8-byte aligned (zero padding)
    end-4   4     CRC-32 of every byte before it

Tensors: `bvh` (M x 32-byte nodes, the bytes `bvh.NODE_DTYPE` describes), `features` (L x T x F float32 or
float16), `index` (HashVQAD only: L x H codes of log2(t) bits, packed little-endian within each byte: code
2n in the low nibble at t = 16), then the network's parameters in `state_dict` order (float32 or float16).

`save_nbvh` writes to a temporary file beside the target and renames it into place only when complete, so a
crash or a full disk never leaves a partial file under the final name. `load_nbvh` checks magic, version,
length and checksum and raises `NBVHFileError` with a clear message for foreign, truncated or damaged files.
"""
from __future__ import annotations

import json
import os
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from .bvh import NODE_DTYPE
from .mesh import Transform
from .model import ModelConfig, NeuralBVH

MAGIC = b"NBVH\x00\r\n\x1a"
VERSION_MAJOR = 1
VERSION_MINOR = 0
_PREFIX = struct.Struct("<8sHHI")
_ALIGN = 8


class NBVHFileError(ValueError):
    """A file that is not a readable .nbvh model: the message says which file and why."""


def pack_codes(codes: np.ndarray, bits: int) -> bytes:
    """Pack unsigned integer codes (< 2^bits, bits in {1, 2, 4, 8}) densely, little-endian within each byte."""
    if bits not in (1, 2, 4, 8):
        raise ValueError(f"code width {bits} bits is not supported (1, 2, 4 or 8)")
    flat = np.asarray(codes, np.uint8).ravel()
    per_byte = 8 // bits
    pad = (-flat.size) % per_byte
    flat = np.concatenate((flat, np.zeros(pad, np.uint8))).reshape(-1, per_byte)
    shifts = (np.arange(per_byte) * bits).astype(np.uint8)
    return np.bitwise_or.reduce(flat << shifts, axis=1).astype(np.uint8).tobytes()


def unpack_codes(data: bytes, bits: int, count: int) -> np.ndarray:
    """Inverse of `pack_codes`: the first `count` codes as uint8."""
    per_byte = 8 // bits
    raw = np.frombuffer(data, np.uint8)
    shifts = (np.arange(per_byte) * bits).astype(np.uint8)
    out = (raw[:, None] >> shifts) & np.uint8((1 << bits) - 1)
    return out.ravel()[:count].astype(np.uint8)


@dataclass
class FileInfo:
    """What `read_info` tells without building the model: sizes by component (bytes), header, metadata."""

    path: str
    total_bytes: int
    components: dict
    header: dict

    @property
    def metadata(self) -> dict:
        return self.header.get("metadata", {})


def _tensors(model: NeuralBVH, float_bytes: int) -> list[tuple[str, str, bytes, list[int]]]:
    """(name, component, bytes, shape) of every stored tensor, in file order."""
    if float_bytes not in (2, 4):
        raise ValueError("float width must be 4 (float32) or 2 (float16) bytes")
    fdt = np.float16 if float_bytes == 2 else np.float32
    enc = model.encoding
    out = [("bvh", "bvh", np.ascontiguousarray(model.nodes, NODE_DTYPE).tobytes(), [len(model.nodes)])]
    table = enc.table.detach().cpu().numpy()
    out.append(("features", "features", table.astype(fdt).tobytes(), list(table.shape)))
    if model.cfg.encoding.kind == "hashvqad":
        if not enc.frozen:
            raise ValueError("HashVQAD must be frozen (argmax codes) before saving")
        codes = enc.codes.cpu().numpy()
        out.append(("index", "index", pack_codes(codes, enc.code_bits()), list(codes.shape)))
    for name, p in model.network.state_dict().items():
        arr = p.detach().cpu().numpy()
        out.append((f"network.{name}", "network", arr.astype(fdt).tobytes(), list(arr.shape)))
    return out


def encode_nbvh(model: NeuralBVH, metadata: dict | None = None, float_bytes: int = 4) -> bytes:
    """The complete file contents for `model` (see module docstring)."""
    tensors = _tensors(model, float_bytes)
    table, offset = [], 0
    for name, comp, data, shape in tensors:
        table.append({"name": name, "component": comp, "shape": shape, "offset": offset, "nbytes": len(data)})
        offset += len(data) + (-len(data)) % _ALIGN
    header = {"format": "nbvh", "config": model.cfg.to_dict(), "transform": model.transform.to_dict(),
              "float_bytes": float_bytes, "tensors": table, "metadata": metadata or {}}
    hdr = json.dumps(header, separators=(",", ":"), sort_keys=True).encode()
    hdr += b" " * ((-(_PREFIX.size + len(hdr))) % _ALIGN)  # align the payload
    parts = [_PREFIX.pack(MAGIC, VERSION_MAJOR, VERSION_MINOR, len(hdr)), hdr]
    for _, _, data, _ in tensors:
        parts += [data, b"\0" * ((-len(data)) % _ALIGN)]
    body = b"".join(parts)
    return body + struct.pack("<I", zlib.crc32(body))


def component_bytes(data: bytes) -> dict[str, int]:
    """Bytes of the file by component: header, bvh, features, [index], network, padding, checksum (sums to
    the file size)."""
    header = _parse(data, "<bytes>")
    comps: dict[str, int] = {"header": _PREFIX.size + header["_header_len"]}
    for t in header["tensors"]:
        comps[t["component"]] = comps.get(t["component"], 0) + t["nbytes"]
    comps["padding"] = len(data) - 4 - sum(comps.values())
    comps["checksum"] = 4
    return comps


def _parse(data: bytes, where: str) -> dict:
    if len(data) < _PREFIX.size + 4:
        raise NBVHFileError(f"{where}: too short to be an .nbvh file ({len(data)} bytes)")
    magic, major, minor, hlen = _PREFIX.unpack_from(data, 0)
    if magic != MAGIC:
        raise NBVHFileError(f"{where}: not an .nbvh file (wrong magic bytes {magic[:8]!r})")
    if major != VERSION_MAJOR:
        raise NBVHFileError(f"{where}: .nbvh format version {major}.{minor} is not supported "
                            f"(this reader reads {VERSION_MAJOR}.x)")
    stored_crc = struct.unpack_from("<I", data, len(data) - 4)[0]
    if zlib.crc32(data[:-4]) != stored_crc:
        raise NBVHFileError(f"{where}: damaged or truncated file (checksum mismatch)")
    try:
        header = json.loads(data[_PREFIX.size:_PREFIX.size + hlen])
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise NBVHFileError(f"{where}: unreadable header: {exc}") from None
    payload = len(data) - 4 - _PREFIX.size - hlen
    for t in header.get("tensors", []):
        if t["offset"] + t["nbytes"] > payload:
            raise NBVHFileError(f"{where}: tensor {t['name']} extends past the end of the file")
    header["_header_len"] = hlen
    header["_payload_start"] = _PREFIX.size + hlen
    return header


def decode_nbvh(data: bytes, where: str = "<bytes>", device: str | torch.device = "cpu") -> NeuralBVH:
    """Build the model stored in `data` (inference-ready: HashVQAD frozen)."""
    header = _parse(data, where)
    try:
        cfg = ModelConfig.from_dict(header["config"])
        transform = Transform.from_dict(header["transform"])
        fdt = np.float16 if header["float_bytes"] == 2 else np.float32
        start = header["_payload_start"]
        blobs = {t["name"]: (data[start + t["offset"]:start + t["offset"] + t["nbytes"]], t["shape"])
                 for t in header["tensors"]}
        nodes = np.frombuffer(blobs["bvh"][0], NODE_DTYPE).copy()
        model = NeuralBVH(nodes, cfg, transform)
        enc = model.encoding
        table = np.frombuffer(blobs["features"][0], fdt).reshape(blobs["features"][1]).astype(np.float32)
        with torch.no_grad():
            enc.table.copy_(torch.from_numpy(table))
            if cfg.encoding.kind == "hashvqad":
                shape = blobs["index"][1]
                codes = unpack_codes(blobs["index"][0], enc.code_bits(), int(np.prod(shape))).reshape(shape)
                enc.codes = torch.from_numpy(codes.copy())
                enc.logits = None
            state = {}
            for name, p in model.network.state_dict().items():
                raw, shape = blobs[f"network.{name}"]
                state[name] = torch.from_numpy(np.frombuffer(raw, fdt).reshape(shape).astype(np.float32))
            model.network.load_state_dict(state)
    except NBVHFileError:
        raise
    except (KeyError, ValueError, TypeError) as exc:
        raise NBVHFileError(f"{where}: inconsistent .nbvh contents: {type(exc).__name__}: {exc}") from None
    model.metadata = header.get("metadata", {})
    return model.to(device).eval()


def save_nbvh(model: NeuralBVH, path: str | os.PathLike, metadata: dict | None = None,
              float_bytes: int = 4) -> int:
    """Write `model` to `path` atomically (temporary file + rename); returns the file size in bytes.

    On any error (e.g. disk full) the temporary file is removed and an existing file at `path` is untouched.
    """
    return write_atomic(path, encode_nbvh(model, metadata, float_bytes))


def write_atomic(path: str | os.PathLike, data: bytes) -> int:
    """Write `data` to a temporary file beside `path`, fsync, rename into place; returns len(data).

    On any error the temporary file is removed and an existing file at `path` is untouched.
    """
    path = Path(path)
    tmp = path.with_name(f".{path.name}.partial-{os.getpid()}")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return len(data)


def load_nbvh(path: str | os.PathLike, device: str | torch.device = "cpu") -> NeuralBVH:
    """Read a .nbvh file (see `decode_nbvh`); raises `NBVHFileError` for anything that is not a valid model."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise NBVHFileError(f"{path}: cannot read: {exc.strerror or exc}") from None
    return decode_nbvh(data, str(path), device)


def read_info(path: str | os.PathLike) -> FileInfo:
    """Header, metadata and bytes by component of a .nbvh file, without building the model."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise NBVHFileError(f"{path}: cannot read: {exc.strerror or exc}") from None
    header = _parse(data, str(path))
    return FileInfo(path=str(path), total_bytes=len(data), components=component_bytes(data), header=header)
