"""The kernel library and the one switch between it and the reference torch code.

**The switch** (`set_path`, `current_path`, `using_path`, env `NBVH_PATH`): 'fast' (the default: kernels on the
CPU where they build, reference code otherwise and on CUDA), or 'reference' (pure torch everywhere).
`fast_enabled(device)` is read only by `kernels.plan`, which decides each stage.

**The library**: built at install (`python -m nbvh_core.kernels build`, run by scripts/ensure_venv.sh) or on
first use, with g++ -O3 -march=native -ffp-contract=off -fopenmp, into a cache folder keyed by the source, the
compiler flags and the CPU; no compiler (or a failed build) means the reference path, with the reason in
`describe()`. The C entry points are declared once, in `native/nbvh_kernels.h`, and called only through
`bindings.py`; the ABI version is that header's hash (`abi_hash`).
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

NATIVE = Path(__file__).with_name("native")
HEADER = NATIVE / "nbvh_kernels.h"
FLAGS = ["-O3", "-march=native", "-ffp-contract=off", "-fopenmp", "-fPIC", "-std=c++17"]
PATHS = ("fast", "reference")

_path = os.environ.get("NBVH_PATH", "fast")
_lib: ctypes.CDLL | None = None
_load_error: str | None = None
_tried = False


def sources() -> list[Path]:
    """The C++ translation units, one per component (encode, networks, vqad, traversal, mesh_codec, tree_build, abi)."""
    return sorted(NATIVE.glob("*.cpp"))


def abi_hash(header: bytes | None = None) -> int:
    """The ABI version: the first 64 bits of the header's SHA-256. Built into the library (`nbvh_abi_hash`), so a
    library built against another header is refused, and nobody edits a version number by hand."""
    data = header if header is not None else HEADER.read_bytes()
    return int.from_bytes(hashlib.sha256(data).digest()[:8], "little")


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
        from .triton import triton_missing

        kind = torch.device(device).type
        missing = triton_missing() if kind == "cuda" else "the C++ kernels are CPU-only, the Triton ones CUDA-only"
        return (f"fast path on {kind}: Triton kernels (encoding, network) and torch" if missing is None
                else f"fast path on {kind}: torch kernels ({missing})")
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
    """Where the built library lives: $NBVH_CACHE or ~/.cache/nbvh, keyed by sources, flags, compiler, CPU."""
    digest = hashlib.sha256(" ".join(FLAGS).encode() + _cpu_key().encode() + (shutil.which("g++") or "").encode())
    for path in sorted(NATIVE.glob("*.[ch]*")):
        digest.update(path.name.encode() + path.read_bytes())
    root = Path(os.environ.get("NBVH_CACHE") or Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "nbvh")
    return root / f"nbvh_kernels-{digest.hexdigest()[:16]}.so"


def build(verbose: bool = False) -> Path:
    """Compile the kernels: the translation units in parallel, then one link; the library appears atomically (a temp
    file renamed into place). Raises RuntimeError on failure."""
    target = library_path()
    if target.exists():
        return target
    compiler = shutil.which("g++") or shutil.which("c++")
    if compiler is None:
        raise RuntimeError("no C++ compiler (g++) found")
    target.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=target.parent) as tmp:
        flags = [*FLAGS, f"-DNBVH_ABI_HASH={abi_hash()}ULL"]
        objects = [Path(tmp) / f"{src.stem}.o" for src in sources()]
        cmds = [[compiler, *flags, "-c", str(src), "-o", str(obj)] for src, obj in zip(sources(), objects)]
        cmds.append([compiler, *FLAGS, "-shared", *map(str, objects), "-o", str(Path(tmp) / "lib.so")])
        for group in (cmds[:-1], cmds[-1:]):
            procs = [(cmd, subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
                     for cmd in group]
            for cmd, proc in procs:
                _, err = proc.communicate()
                if proc.returncode != 0:
                    raise RuntimeError(f"compiling the kernels failed: {' '.join(cmd)}\n{err[-2000:]}")
                if verbose:
                    print(" ".join(cmd), file=sys.stderr)
        os.replace(Path(tmp) / "lib.so", target)
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
        lib.nbvh_abi_hash.restype = ctypes.c_uint64
        if lib.nbvh_abi_hash() != abi_hash():
            raise RuntimeError("stale kernel library (built against another nbvh_kernels.h)")
    except (OSError, RuntimeError, AttributeError) as exc:
        _load_error = str(exc).splitlines()[0]
        return None
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
