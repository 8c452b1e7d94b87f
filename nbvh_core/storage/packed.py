"""The storage variant of an .nbvh file: the traceable file entropy-coded (xz, LZMA2) for disk and transfer, decoded
at load back to the exact bytes a tracer holds. The traceable file stays the format (read in place, every tensor
at its offset); this wrapper only trades load time for bytes, like Draco does for meshes.

Layout: PACKED_MAGIC (8 bytes), the traceable file's length (uint64 little-endian), the xz stream. A reader
checks the declared length against MAX_UNPACKED_BYTES and MAX_RATIO x the packed size before decoding anything
and stops the decoder at that length, so a crafted file cannot make it allocate more."""
from __future__ import annotations

import lzma
import struct

from .errors import NBVHFileError

PACKED_MAGIC = b"NBVHXZ\x00\x01"
#: Largest traceable file a packed one may declare (the high preset's model is under 1 MB; 4k textures are tens).
MAX_UNPACKED_BYTES = 1 << 28
#: Largest declared length per packed byte: quantized tables pack ~1.5x, all-zero padding ~100x; a bomb far more.
MAX_RATIO = 1000
_HEAD = struct.Struct("<8sQ")


def is_packed(data: bytes) -> bool:
    """True when `data` starts as a packed .nbvh does."""
    return data[:len(PACKED_MAGIC)] == PACKED_MAGIC


def pack(data: bytes) -> bytes:
    """The storage variant of a traceable .nbvh file's bytes (xz at its strongest preset)."""
    return _HEAD.pack(PACKED_MAGIC, len(data)) + lzma.compress(data, format=lzma.FORMAT_XZ,
                                                                preset=9 | lzma.PRESET_EXTREME)


def unpack(data: bytes, where: str = "<bytes>") -> bytes:
    """The traceable file a packed one holds, exactly; NBVHFileError (one line) for anything else."""
    if len(data) < _HEAD.size or not is_packed(data):
        raise NBVHFileError(f"{where}: not a packed .nbvh file")
    _, length = _HEAD.unpack_from(data)
    stream = data[_HEAD.size:]
    if length > min(MAX_UNPACKED_BYTES, MAX_RATIO * max(len(stream), 1)):
        raise NBVHFileError(f"{where}: declares {length:,} bytes unpacked from {len(stream):,}: refused unread")
    decoder = lzma.LZMADecompressor(format=lzma.FORMAT_XZ)
    try:
        out = decoder.decompress(stream, max_length=length + 1)
    except lzma.LZMAError as exc:
        raise NBVHFileError(f"{where}: the packed stream is damaged ({exc})") from None
    if len(out) != length or not decoder.eof:
        raise NBVHFileError(f"{where}: the packed stream holds {'more' if len(out) > length else 'fewer'} bytes "
                            f"than the {length:,} it declares (truncated or damaged)")
    return out
