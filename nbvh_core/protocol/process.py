"""How a run ends, for every process that runs nbvh_core (the CLI, the add-on's job worker): the domain exceptions
that stop a run, their exit codes and event kinds, and the cancel signals. Plain Python (no torch), so the add-on
and the job protocol can share it.

Exit codes: 0 ok, 1 crash, 2 bad input (mesh, file, option, output location), 3 training diverged, 4 not worth
compressing (nothing trained), 130 cancelled (Ctrl-C / SIGTERM).
"""
from __future__ import annotations

import signal
import threading
from typing import Callable, NamedTuple


class Cancelled(Exception):
    """The job was cancelled; nothing was saved as a result."""


class TrainingDiverged(RuntimeError):
    """Loss or parameters became NaN/inf or exploded; the model is not usable and is never saved."""


class NotWorthCompressing(Exception):
    """The mesh is kept: the mesh (or a measured decimation) is smaller than the model would be (the verdict before
    training), or than the model is at its measured quality (a training check, the final verdict). No model file was
    written; `assessment` (decision.records.Assessment) has the sizes and the alternatives."""

    def __init__(self, assessment, decimator=None):
        super().__init__(assessment.message)
        self.assessment = assessment
        #: the run's decimation chain (`geometry.decimation.Decimator`), so the kept decimation is rebuilt from the
        #: levels it already holds (at 10M triangles the chain's first pass is ~15 s); None: rebuilt from the mesh
        self.decimator = decimator


class Outcome(NamedTuple):
    """How an exception ends a run: exit code, event kind (the `error` event's "kind"), one-line message."""

    code: int
    kind: str
    message: str


def outcome(exc: BaseException) -> Outcome:
    """The exit code, event kind and message for an exception that ended a run (the one mapping the CLI and the
    job worker share). Bad input is a ValueError (MeshError, NBVHFileError), an OSError or a KeyError (a request
    missing a field); anything else is a crash."""
    if isinstance(exc, (Cancelled, KeyboardInterrupt)):
        return Outcome(130, "cancelled", str(exc) or "interrupted")
    if isinstance(exc, TrainingDiverged):
        return Outcome(3, "diverged", f"training diverged: {exc}")
    if isinstance(exc, NotWorthCompressing):
        return Outcome(4, "not_worth", str(exc))
    if isinstance(exc, (ValueError, OSError, KeyError)):
        return Outcome(2, "input", str(exc))
    return Outcome(1, "crash", f"{type(exc).__name__}: {exc}")


def install_cancel_handlers() -> Callable[[], bool]:
    """SIGINT/SIGTERM set a flag the training loop polls (a clean cancel: nothing half-written). Returns the flag's
    reader, the `should_cancel` callback of `pipeline.compress_mesh` and `train.train`."""
    flag = threading.Event()

    def handler(signum, frame):
        flag.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            signal.signal(sig, handler)
        except ValueError:  # not the main thread
            pass
    return flag.is_set
