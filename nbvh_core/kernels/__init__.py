"""The fast path: fused C++ CPU kernels, and the one switch between them and the reference torch code.

**The switch** (`set_path`, `current_path`, `using_path`, env `NBVH_PATH`): 'fast' (the default: kernels on the
CPU where they build, reference code otherwise and on CUDA), or 'reference' (pure torch everywhere). Every
caller asks `fast_enabled(device)`; results record `describe()` so a number says which path produced it.

**The kernels** (`nbvh_kernels.cpp`, plain C ABI through ctypes, OpenMP):
* `encode` - hash-grid / HashVQAD lookup fused per point: cell, hash, trilinear weights and the 8-row weighted sum
  of every level in one pass (the reference builds (N, L, 8) int64 index and weight tensors first); its backward
  recomputes the corners and scatters into the gradient table, one level per thread (no atomics, fixed order).
  Frozen HashVQAD codes are read inside the kernel (vertex -> code -> row).
* `stream_next` - `traversal.LeafStream.next` per ray with a real per-ray stack loop (the reference advances all
  rays one pop at a time with tensor ops).
* `leaves_traverse` / `leaves_collect` - the complete sorted leaf list per ray (training labels), one traversal.
* `net_segments` / `net_train` (used through `kernels.mlp`; MLP or KMLP) - inference / one training step of a whole MLP model
  per (ray, leaf) segment: points, encoding and every Linear layer (AVX2 6x16 register-blocked micro-kernel, bias
  and ReLU fused) on a tile of 48 segments that stays in the cache; the reference writes (B, k*L*F) features to
  memory and runs torch's layers over them.

Built at install (`python -m nbvh_core.kernels build`, run by scripts/ensure_venv.sh) or on first use, with
g++ -O3 -march=native -ffp-contract=off -fopenmp, into a cache folder keyed by the source, the compiler flags
and the CPU; no compiler (or a failed build) means the reference path, with the reason in `describe()`.
"""
from __future__ import annotations

import contextlib
import ctypes
import hashlib
import os
import platform
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import torch

SOURCE = Path(__file__).with_name("nbvh_kernels.cpp")
FLAGS = ["-O3", "-march=native", "-ffp-contract=off", "-fopenmp", "-shared", "-fPIC", "-std=c++17"]
ABI_VERSION = 12
PATHS = ("fast", "reference")

_path = os.environ.get("NBVH_PATH", "fast")
_lib: ctypes.CDLL | None = None
_load_error: str | None = None
_tried = False


def set_path(name: str) -> None:
    """Choose 'fast' or 'reference' for everything that follows (process-wide)."""
    global _path
    if name not in PATHS:
        raise ValueError(f"path must be one of {PATHS}, got {name!r}")
    _path = name


def current_path() -> str:
    return _path


@contextlib.contextmanager
def using_path(name: str):
    """Run a block with the given path, restoring the previous one after."""
    old = _path
    set_path(name)
    try:
        yield
    finally:
        set_path(old)


def fast_enabled(device: torch.device | str = "cpu") -> bool:
    """True when the fused kernels serve this device now (fast path chosen, CPU tensors, kernels built)."""
    return _path == "fast" and torch.device(device).type == "cpu" and load() is not None


def describe(device: torch.device | str = "cpu") -> str:
    """One line for results: which path ran and why."""
    if _path == "reference":
        return "reference (pure torch)"
    if torch.device(device).type != "cpu":
        return f"fast path on {torch.device(device).type}: torch kernels (the fused kernels are CPU-only)"
    if load() is None:
        return f"reference (pure torch): fused kernels unavailable ({_load_error})"
    return f"fast (fused C++ kernels, {threads()} threads)"


def threads() -> int:
    return max(1, torch.get_num_threads())


def _cpu_key() -> str:
    info = platform.machine() + platform.processor()
    try:
        text = Path("/proc/cpuinfo").read_text()
        for line in text.splitlines():
            if line.startswith(("model name", "flags")):
                info += line
                if line.startswith("flags"):
                    break
    except OSError:
        pass
    return info


def library_path() -> Path:
    """Where the built library lives: $NBVH_CACHE or ~/.cache/nbvh, keyed by source, flags, compiler, CPU."""
    key = hashlib.sha256(SOURCE.read_bytes() + " ".join(FLAGS).encode() + _cpu_key().encode()
                         + (shutil.which("g++") or "").encode()).hexdigest()[:16]
    root = Path(os.environ.get("NBVH_CACHE") or Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "nbvh")
    return root / f"nbvh_kernels-{key}.so"


def build(verbose: bool = False) -> Path:
    """Compile the kernels (atomically: a temp file renamed into place). Raises RuntimeError on failure."""
    target = library_path()
    if target.exists():
        return target
    compiler = shutil.which("g++") or shutil.which("c++")
    if compiler is None:
        raise RuntimeError("no C++ compiler (g++) found")
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=".so", dir=target.parent)
    os.close(fd)
    cmd = [compiler, *FLAGS, str(SOURCE), "-o", tmp]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        os.unlink(tmp)
        raise RuntimeError(f"compiling the kernels failed: {' '.join(cmd)}\n{proc.stderr[-2000:]}")
    if verbose:
        print(" ".join(cmd), file=sys.stderr)
    os.replace(tmp, target)
    return target


def load() -> ctypes.CDLL | None:
    """The kernel library, building it on first use; None (reason in `describe()`) when it cannot be built."""
    global _lib, _load_error, _tried
    if _tried:
        return _lib
    _tried = True
    if os.environ.get("NBVH_NO_KERNELS"):
        _load_error = "disabled by NBVH_NO_KERNELS"
        return None
    try:
        lib = ctypes.CDLL(str(build()))
        if lib.nbvh_abi_version() != ABI_VERSION:
            raise RuntimeError("stale kernel library (ABI version mismatch)")
    except (OSError, RuntimeError) as exc:
        _load_error = str(exc).splitlines()[0]
        return None
    P, I64, I32 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int
    enc = [P, I64, P, P, I32, I32, P, P, P, I64, I64, P, I64, I32]
    lib.nbvh_encode_forward.argtypes = enc
    lib.nbvh_encode_backward.argtypes = enc
    lib.nbvh_encode_forward_f16.argtypes = enc
    lib.nbvh_encode_forward_u8.argtypes = [P, I64, P, P, P, P, *enc[4:]]
    lib.nbvh_stream_next.argtypes = [P, P, I64, P, P, P, P, P, P, P, P, I32, P, P, P, I32]
    lib.nbvh_leaves_traverse.argtypes = [P, P, I64, P, P, P, P, P, I32, P, P, I32]
    lib.nbvh_leaves_traverse.restype = P
    lib.nbvh_leaves_collect.argtypes = [P, P, P, P]
    lib.nbvh_leaves_collect.restype = None
    lib.nbvh_net_segments.argtypes = [P, P, P, P, P, I64, I32, P, P, I32, P, P, *enc[4:13], I32, I32, P, P, P, I32]
    lib.nbvh_net_train.argtypes = [P, P, P, P, P, I64, I32, P, P, *enc[4:13], I32, I32, P, P, P, P, P, I64,
                                   ctypes.c_float, ctypes.c_float, P, P, P, P, P, P, I32]
    F32 = ctypes.c_float
    lib.nbvh_vqad_soft_forward.argtypes = [P, P, P, I32, I64, I64, I32, I32, F32, P, P, I32]
    lib.nbvh_vqad_soft_backward.argtypes = [P, P, P, P, I32, I64, I64, I32, I32, F32, P, P, I32]
    for fn in (lib.nbvh_encode_forward, lib.nbvh_encode_forward_f16, lib.nbvh_encode_forward_u8,
               lib.nbvh_encode_backward, lib.nbvh_stream_next,
               lib.nbvh_net_segments, lib.nbvh_net_train,
               lib.nbvh_vqad_soft_forward, lib.nbvh_vqad_soft_backward):
        fn.restype = None
    _lib = lib
    return lib


def keep_freed_memory() -> bool:
    """Ask glibc to serve blocks up to 32 MB from its heap and to keep freed memory (mallopt). By default every
    temporary array above 128 KB is a fresh mmap that the kernel zero-fills page by page and unmaps on free: on
    this 2-core VM that made a numpy temporary of 1 MB cost ~0.4 ms, and a training step's labels ~30% slower.
    Called once by the processes that train or render (CLI, job worker, benchmarks); returns False off glibc."""
    try:
        libc = ctypes.CDLL("libc.so.6")
        m_trim_threshold, m_mmap_threshold = -1, -3
        return bool(libc.mallopt(m_mmap_threshold, 32 << 20)) and bool(libc.mallopt(m_trim_threshold, 512 << 20))
    except (OSError, AttributeError):
        return False


def ptr(t: torch.Tensor | None) -> int | None:
    """Address of a contiguous CPU tensor's data (None for None)."""
    if t is None:
        return None
    assert t.is_contiguous() and t.device.type == "cpu", "kernels take contiguous CPU tensors"
    return t.data_ptr()

