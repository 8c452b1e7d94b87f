"""The kernel library and the one switch between it and the reference torch code.

**The switch** (`set_path`, `current_path`, `using_path`, env `NBVH_PATH`): 'fast' (the default: kernels on the
CPU where they build, reference code otherwise and on CUDA), or 'reference' (pure torch everywhere).
`fast_enabled(device)` is read only by `kernels.plan`, which decides each stage.

**The library**: built at install (`python -m nbvh_core.kernels build`, run by scripts/ensure_venv.sh) or on
first use, with g++ -O3 -march=native -ffp-contract=off -fopenmp, into a cache folder keyed by the source, the
compiler flags and the CPU; no compiler (or a failed build) means the reference path, with the reason in
`describe()`. Every C signature is declared once, in the C++ source's `extern "C"` block; `c_signatures` reads
the ctypes argument types from it.
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
        lib.nbvh_abi_version.restype = ctypes.c_int
        if lib.nbvh_abi_version() != abi_version():
            raise RuntimeError("stale kernel library (ABI version mismatch)")
    except (OSError, RuntimeError) as exc:
        _load_error = str(exc).splitlines()[0]
        return None
    for name, (restype, argtypes, _) in c_signatures().items():
        fn = getattr(lib, name)
        fn.restype, fn.argtypes = restype, argtypes
    _lib = lib
    return lib


_C_TYPES = {"int": ctypes.c_int, "int32_t": ctypes.c_int32, "int64_t": ctypes.c_int64, "float": ctypes.c_float,
            "double": ctypes.c_double, "void": None}


def c_signatures(source: str | None = None) -> dict[str, tuple]:
    """{name: (restype, argtypes, argument names)} of every function in the source's `extern "C"` block, read from
    the C++ definitions themselves: the one place a signature is declared (a pointer of any type is a c_void_p;
    ctypes then checks every call's argument count and kinds)."""
    import re

    text = source if source is not None else SOURCE.read_text()
    block = text[text.index('extern "C" {'):]
    out = {}
    for m in re.finditer(r"^(void\s*\*|int|void)\s+(nbvh_\w+)\(([^)]*)\)\s*\{", block, re.M):
        ret, name, params = m.group(1).replace(" ", ""), m.group(2), m.group(3)
        argtypes, names = [], []
        for param in filter(None, (p.strip() for p in params.replace("\n", " ").split(","))):
            ctype, arg = param.rsplit(None, 1) if "*" not in param else (param[:param.rindex("*") + 1], param[param.rindex("*") + 1:])
            names.append(arg.strip())
            argtypes.append(ctypes.c_void_p if "*" in ctype else _C_TYPES[ctype.replace("const", "").strip()])
        out[name] = (ctypes.c_void_p if ret == "void*" else _C_TYPES[ret], argtypes, names)
    return out


def abi_version(source: str | None = None) -> int:
    """The ABI version the source declares (`nbvh_abi_version`); a library built from other source is refused."""
    import re

    text = source if source is not None else SOURCE.read_text()
    return int(re.search(r"int nbvh_abi_version\(\)\s*\{\s*return (\d+);", text).group(1))


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

