"""Crafted and fuzzed .nbvh files (shared by tests/test_safety.py and bench/fuzzing/fuzz_reader.py).

`craft` rebuilds a file around any header with a valid checksum, so damage reaches the header and structure checks
instead of stopping at the CRC; `fuzz_cases` yields truncations, bit flips (half of them with a recomputed
checksum) and mutations of one header field; `check_case` decodes and renders one case under a time limit.
"""
import json
import signal
import struct
import zlib

import numpy as np

from nbvh_core.storage.container import PREFIX, VERSION_MAJOR, VERSION_MINOR, header_bytes, header_json
from nbvh_core.storage.fileformat import NBVHFileError, decode_nbvh
from nbvh_core.rendering.render import orbit_cameras, render_neural


def split(data: bytes) -> tuple[dict, bytes]:
    """(header dict, payload bytes) of a file."""
    _, major, minor, hlen = PREFIX.unpack_from(data, 0)
    return (json.loads(header_json(data[PREFIX.size:PREFIX.size + hlen], (major, minor), "<split>")),
            data[PREFIX.size + hlen:-4])


def craft(header, payload: bytes, major: int = 2, minor: int | None = None) -> bytes:
    """A file with this header (any JSON value) and payload, and a valid checksum; version major.minor (minor: the
    writer's own for major 2, else 0 - the tensor layout the payload came with)."""
    minor = (VERSION_MINOR if major == VERSION_MAJOR else 0) if minor is None else minor
    hdr = header_bytes(header, (major, minor))
    body = PREFIX.pack(b"NBVH\x00\r\n\x1a", major, minor, len(hdr)) + hdr + payload
    return body + struct.pack("<I", zlib.crc32(body))


def _mutate_value(v, rng):
    choices = [None, -1, 0, 1, 2 ** 31, 2 ** 62, -2 ** 40, 1e308, "x", [], {}, [1, 2], True, 3.5]
    if isinstance(v, int) and not isinstance(v, bool) and rng.random() < 0.5:
        return int(v + rng.integers(-3, 4)) if rng.random() < 0.5 else int(v * rng.choice([2, 16, 1024]))
    return choices[rng.integers(len(choices))]


def _mutate_header(header, rng):
    """Change one random leaf value of the header tree."""
    node, path = header, []
    while isinstance(node, (dict, list)) and node:
        key = rng.choice(list(node)) if isinstance(node, dict) else int(rng.integers(len(node)))
        path.append((node, key))
        node = node[key]
        if rng.random() < 0.25:
            break
    if path:
        parent, key = path[-1]
        parent[key] = _mutate_value(node, rng)
    return header


def fuzz_cases(data: bytes, n: int, seed: int):
    """(kind, bytes) cases: truncations, bit flips (checksum recomputed half the time), header field mutations."""
    rng = np.random.default_rng(seed)
    for i in range(n):
        kind = ("truncate", "flip", "flip_rechecksum", "header")[i % 4]
        if kind == "truncate":
            yield kind, data[:int(rng.integers(0, len(data)))]
        elif kind.startswith("flip"):
            b = bytearray(data[:-4])
            for _ in range(int(rng.integers(1, 9))):
                pos = int(rng.integers(0, len(b)))
                b[pos] ^= 1 << int(rng.integers(8))
            crc = zlib.crc32(bytes(b)) if kind == "flip_rechecksum" else struct.unpack("<I", data[-4:])[0]
            yield kind, bytes(b) + struct.pack("<I", crc)
        else:
            header, payload = split(data)
            yield kind, craft(_mutate_header(header, rng), payload)


def check_case(blob: bytes, seconds: float = 10.0) -> str:
    """'model' or 'refused'; anything else (a crash, a hang past `seconds`, another exception) fails the test."""
    def alarm(*_):
        raise TimeoutError("hang")

    old = signal.signal(signal.SIGALRM, alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        model = decode_nbvh(blob)
        render_neural(model, orbit_cameras(2)[0], 12, 12)
        return "model"
    except NBVHFileError as exc:
        assert len(str(exc).splitlines()) == 1
        return "refused"
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


