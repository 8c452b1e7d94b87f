"""The .nbvh container: prefix, header bytes, payload alignment and checksum; what every component is stored in.

Layout (little endian):

    offset  size  field
    0       8     magic b"NBVH\\x00\\r\\n\\x1a" (catches text-mode transfers and truncation at the first bytes)
    8       2     format major version (this reader reads 1 and 2; writes 2)
    10      2     format minor version (additions a reader may ignore)
    12      4     header length H (bytes of UTF-8 JSON)
    16      H     header: JSON (format 2.4: zlib-compressed JSON, zero-padded), holding the model config, transform,
                  storage (bits per component), the tensor table (name, component, shape, offset, nbytes) and
                  free-form metadata (training, quality, source mesh)
    16+H    ...   payload: the tensors back to back in table order, each 8-byte aligned (zero padding)
    end-4   4     CRC-32 of every byte before it

What the header must say is `header.py`'s; which tensors a config stores and their sizes, `layout.py`'s; how each
component is written and read back, `components/`'s.
"""
from __future__ import annotations

import json
import struct
import zlib

import numpy as np

from .errors import NBVHFileError

MAGIC = b"NBVH\x00\r\n\x1a"
VERSION_MAJOR = 2
VERSION_MINOR = 5  # 2.1: network_bits 8 (a 2.0 reader refuses such a file by its storage field); 2.2: HashVQAD's
#                    index holds its reachable entries only (a 2.1 reader refuses such a file by the index's shape);
#                    2.3: the asset's look (header `appearance`, tensors appearance.* and texture.*; a 2.2 reader
#                    refuses such a file by its tensors); 2.4: the header zlib-compressed (4.8 KB of JSON in 1.7 KB
#                    on the bunny's default model) and 4-bit network rows (a 2.3 reader refuses such a file: its
#                    header is not JSON); 2.5: the BVH's shape as one bit per node (`bvh.shape`; a 2.4 reader
#                    refuses such a file by its tensors)
REACHABLE_INDEX_SINCE = (2, 2)
APPEARANCE_SINCE = (2, 3)
COMPRESSED_HEADER_SINCE = (2, 4)
SHAPE_BITS_SINCE = (2, 5)
READABLE_MAJORS = (1, 2)
PREFIX = struct.Struct("<8sHHI")
ALIGN = 8
MAX_HEADER_BYTES = 1 << 20


def writer_version() -> tuple[int, int]:
    """(major, minor) of the files this writer writes (read at call time: a test writes as an older writer did)."""
    return VERSION_MAJOR, VERSION_MINOR


def pack_codes(codes: np.ndarray, bits: int) -> bytes:
    """Pack unsigned integer codes (< 2^bits, bits in 1..8) densely as one little-endian bit stream: code i holds
    stream bits [i * bits, (i + 1) * bits), byte k stream bits [8k, 8k + 8) from its least significant bit (so at 1,
    2, 4 bits each byte holds whole codes; at 6 bits four codes fill three bytes)."""
    if not 1 <= bits <= 8:
        raise ValueError(f"code width {bits} bits is not supported (1 to 8)")
    flat = np.asarray(codes, np.uint8).ravel()
    if bits == 8:
        return flat.tobytes()
    stream = np.unpackbits(flat[:, None], axis=1, count=bits, bitorder="little")
    return np.packbits(stream.ravel(), bitorder="little").tobytes()


def unpack_codes(data: bytes, bits: int, count: int) -> np.ndarray:
    """Inverse of `pack_codes`: the first `count` codes as uint8 (ValueError when `data` holds fewer)."""
    if not 1 <= bits <= 8:
        raise ValueError(f"code width {bits} bits is not supported (1 to 8)")
    raw = np.frombuffer(data, np.uint8)
    if raw.size * 8 < count * bits:
        raise ValueError(f"{raw.size} bytes hold fewer than {count} codes of {bits} bits")
    if bits == 8:
        return raw[:count].copy()
    stream = np.unpackbits(raw, count=count * bits, bitorder="little").reshape(count, bits)
    return np.packbits(stream, axis=1, bitorder="little").ravel()


def header_bytes(header: dict, version: tuple[int, int] | None = None) -> bytes:
    """A header as a file of `version` (default: the writer's) stores it: JSON, zlib-compressed from 2.4 on, padded
    so the payload that follows starts 8-byte aligned (zeros after compressed bytes, spaces after plain JSON)."""
    version = version or writer_version()
    text = json.dumps(header, separators=(",", ":"), sort_keys=True, allow_nan=False).encode()
    if version >= COMPRESSED_HEADER_SINCE:
        text = zlib.compress(text, 9)
        return text + b"\0" * ((-(PREFIX.size + len(text))) % ALIGN)
    return text + b" " * ((-(PREFIX.size + len(text))) % ALIGN)


def header_json(raw: bytes, version: tuple[int, int], where: str) -> bytes:
    """The JSON text of a stored header (inverse of `header_bytes`): a compressed one is inflated to at most
    MAX_HEADER_BYTES, and nothing but its alignment padding may follow it. Raises NBVHFileError (one line)."""
    if version < COMPRESSED_HEADER_SINCE:
        return raw
    inflate = zlib.decompressobj()
    try:
        text = inflate.decompress(raw, MAX_HEADER_BYTES)
    except zlib.error as exc:
        raise NBVHFileError(f"{where}: unreadable header (not zlib data: {str(exc)[:60]})") from None
    if not inflate.eof:
        raise NBVHFileError(f"{where}: header does not inflate within {MAX_HEADER_BYTES} bytes (truncated or too "
                            "large)")
    if len(inflate.unused_data) >= ALIGN or inflate.unused_data.strip(b"\0"):
        raise NBVHFileError(f"{where}: bytes after the compressed header")
    return text


def assemble(header: dict, blobs: list[bytes]) -> bytes:
    """The file: prefix, `header` as `header_bytes` stores it, the blobs in table order (each padded to ALIGN), the
    checksum."""
    hdr = header_bytes(header)
    major, minor = writer_version()
    parts = [PREFIX.pack(MAGIC, major, minor, len(hdr)), hdr]
    for data in blobs:
        parts += [data, b"\0" * ((-len(data)) % ALIGN)]
    body = b"".join(parts)
    return body + struct.pack("<I", zlib.crc32(body))


def tensor_table(tensors: list[tuple[str, str, bytes, list[int]]]) -> list[dict]:
    """The header's tensor table for (name, component, bytes, shape) in file order: each one's offset, 8-byte
    aligned, and size."""
    table, offset = [], 0
    for name, comp, data, shape in tensors:
        table.append({"name": name, "component": comp, "shape": shape, "offset": offset, "nbytes": len(data)})
        offset += len(data) + (-len(data)) % ALIGN
    return table


def read_prefix(data: bytes, where: str) -> tuple[dict, tuple[int, int], int]:
    """The stored header as JSON, the file's (major, minor) version and the header's stored length, after checking
    the magic, the version and the checksum. Raises NBVHFileError (one line)."""
    if len(data) < PREFIX.size + 4:
        raise NBVHFileError(f"{where}: too short to be an .nbvh file ({len(data)} bytes)")
    magic, major, minor, hlen = PREFIX.unpack_from(data, 0)
    if magic != MAGIC:
        raise NBVHFileError(f"{where}: not an .nbvh file (wrong magic bytes {magic[:8]!r})")
    if major not in READABLE_MAJORS:
        raise NBVHFileError(f"{where}: .nbvh format version {major}.{minor} is not supported "
                            f"(this reader reads {', '.join(f'{m}.x' for m in READABLE_MAJORS)})")
    stored_crc = struct.unpack_from("<I", data, len(data) - 4)[0]
    if zlib.crc32(memoryview(data)[:-4]) != stored_crc:
        raise NBVHFileError(f"{where}: damaged or truncated file (checksum mismatch)")
    if hlen > min(MAX_HEADER_BYTES, len(data) - PREFIX.size - 4):
        raise NBVHFileError(f"{where}: header length {hlen} does not fit the file ({len(data)} bytes)")
    try:
        fields = json.loads(header_json(bytes(data[PREFIX.size:PREFIX.size + hlen]), (major, minor), where))
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise NBVHFileError(f"{where}: unreadable header: {str(exc)[:80]}") from None
    if not isinstance(fields, dict):
        raise NBVHFileError(f"{where}: the header must be a JSON object, not {type(fields).__name__}")
    return fields, (major, minor), hlen
