"""The process's memory as a heavy run sees it: its peak (the run's report) and memory freed but still held."""
from __future__ import annotations

import ctypes
import ctypes.util
import platform
from functools import lru_cache


def peak_resident_bytes() -> int | None:
    """The process's peak resident memory in bytes (its whole life: in a batch, the largest asset's so far), or
    None where the platform does not say (Windows). On Linux its own address space's high-water mark (VmHWM):
    getrusage's ru_maxrss also counts the parent's when the process was spawned by vfork and exec (Python's
    subprocess does): a benchmark that had generated a 20M-triangle mesh before starting the run read 17.8 GB
    where the run itself peaked 5.1 GB."""
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        import resource
    except ImportError:
        return None
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(peak if platform.system() == "Darwin" else peak * 1024)  # macOS says bytes, Linux kilobytes


@lru_cache(maxsize=1)
def _glibc_trim():
    """glibc's malloc_trim, or None (another C library, another platform)."""
    if platform.system() != "Linux":
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        return libc.malloc_trim
    except (OSError, AttributeError):
        return None


def return_free_memory() -> None:
    """Hand the memory freed inside the C heap back to the system (glibc's malloc_trim; elsewhere nothing). Between
    the plan's measurements of a heavy mesh, what they freed stayed resident: the 10M-triangle lattice's full tree
    was built on top of ~0.23 GiB freed and held (bench/results/heavy.md)."""
    trim = _glibc_trim()
    if trim is not None:
        trim(0)
