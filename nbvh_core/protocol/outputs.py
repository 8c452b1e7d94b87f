"""Writing a run's outputs safely (plain Python, no torch): checked before training, written as one unit.

* `resolve_output` - `-o DIR/` (or an existing folder) means DIR/<mesh name>.nbvh, never a file named DIR.
* `check_outputs` - before any training: no output may be an input (the source mesh is never written over), an
  existing output is replaced only when asked (`overwrite`), and the folder must be creatable and writable (a probe
  file is written and removed), so an unwritable location fails in a second, not after an hour of training.
* `OutputLock` - one run per output: a lock file created with O_EXCL beside the model; a second run writing the
  same output is refused while the first is alive (a stale lock of a dead process is taken over).
* `OutputSet` - every file of a result is staged beside its target (`.NAME.partial-PID`, fsynced), then all are
  renamed into place together; if a stage or a rename fails, what was already renamed is rolled back and the
  previous files are restored, so either the whole new result appears or the old one stays as it was.
"""
from __future__ import annotations

import os
from pathlib import Path


class OutputError(ValueError):
    """An output location that cannot or must not be written: the message says which and why."""


def resolve_output(arg: str | os.PathLike, default_stem: str, suffix: str = ".nbvh") -> Path:
    """The model path `arg` names: a folder (existing, or written with a trailing separator) gets
    `default_stem + suffix` inside it."""
    text = os.fspath(arg)
    path = Path(text)
    if text.endswith(("/", os.sep)) or path.is_dir():
        return path / f"{default_stem}{suffix}"
    return path


def checkpoint_for(model: str | os.PathLike) -> Path:
    """Where training toward `model` keeps its checkpoint by default: `.NAME.nbvh.checkpoint` beside it (the CLI,
    the job worker and the add-on's Resume button all look there)."""
    model = Path(model)
    return model.with_name(f".{model.name}.checkpoint")


def lock_for(model: str | os.PathLike) -> Path:
    """The lock file of a run writing `model` (see OutputLock)."""
    model = Path(model)
    return model.with_name(f".{model.name}.lock")


def _same_file(a: Path, b: Path) -> bool:
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
    except OSError:
        pass
    return a.resolve() == b.resolve()


def check_outputs(outputs: list[Path], inputs: list[Path], overwrite: bool = False) -> None:
    """Refuse (OutputError) before any work: an output that is an input, an existing output without `overwrite`,
    an output that is a folder, a folder that cannot be created or written."""
    for out in outputs:
        for src in inputs:
            if _same_file(out, src):
                raise OutputError(f"{out}: this is the input {src}; refusing to write over it (choose another -o)")
        if out.is_dir():
            raise OutputError(f"{out} is a folder; give the output file name, e.g. {out / 'model.nbvh'}")
    existing = [str(o) for o in outputs if o.exists()]
    if existing and not overwrite:
        raise OutputError(f"{existing[0]} exists (a finished result); pass --overwrite to replace it")
    for folder in {o.parent for o in outputs}:
        try:
            folder.mkdir(parents=True, exist_ok=True)
            probe = folder / f".nbvh-write-probe-{os.getpid()}"
            with open(probe, "wb") as f:
                f.write(b"probe")
            probe.unlink()
        except OSError as exc:
            raise OutputError(f"{folder}: cannot write there: {exc.strerror or exc}") from None


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


class OutputLock:
    """`with OutputLock(model_path):` - at most one run writes this output at a time (see module docstring)."""

    def __init__(self, target: Path):
        self.path = lock_for(target)
        self.held = False

    def acquire(self) -> None:
        for _ in range(2):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                try:
                    pid = int(self.path.read_text().strip() or "0")
                except (OSError, ValueError):
                    pid = 0
                if pid and _alive(pid):
                    raise OutputError(f"{self.path.with_name(self.path.name[1:-5])} is being written by another run "
                                      f"(process {pid}); wait for it or choose another output") from None
                self.path.unlink(missing_ok=True)  # a dead run's lock
                continue
            with os.fdopen(fd, "w") as f:
                f.write(str(os.getpid()))
            self.held = True
            return
        raise OutputError(f"cannot take the lock {self.path}")

    def release(self) -> None:
        if self.held:
            self.path.unlink(missing_ok=True)
            self.held = False

    def __enter__(self) -> "OutputLock":
        self.acquire()
        return self

    def __exit__(self, *exc) -> None:
        self.release()


def _write_synced(tmp: Path, data: bytes) -> None:
    """Write `data` to `tmp` and fsync it (removed again on any error)."""
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_atomic(path: str | os.PathLike, data: bytes) -> int:
    """Write `data` to a temporary file beside `path`, fsync, rename into place; returns len(data). On any error
    the temporary file is removed and an existing file at `path` is untouched."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.partial-{os.getpid()}")
    _write_synced(tmp, data)
    try:
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return len(data)


class OutputSet:
    """Stage files, then `commit()` them all (or none: see module docstring). `discard()` removes the stages."""

    def __init__(self):
        self._staged: list[tuple[Path, Path]] = []  # (stage, target)

    def stage(self, target: Path, data: bytes) -> None:
        target = Path(target)
        tmp = target.with_name(f".{target.name}.partial-{os.getpid()}")
        try:
            _write_synced(tmp, data)
        except BaseException:
            self.discard()
            raise
        self._staged.append((tmp, target))

    def commit(self) -> list[Path]:
        """Rename every staged file into place; on any failure restore the previous files. Returns the targets."""
        done: list[tuple[Path, Path | None]] = []  # (target, backup of the previous file or None)
        try:
            for tmp, target in self._staged:
                backup = None
                if target.exists():
                    backup = target.with_name(f".{target.name}.previous-{os.getpid()}")
                    os.replace(target, backup)
                done.append((target, backup))
                os.replace(tmp, target)
        except BaseException:
            for target, backup in reversed(done):
                if backup is not None:
                    os.replace(backup, target)
                else:
                    target.unlink(missing_ok=True)
            self.discard()
            raise
        for _, backup in done:
            if backup is not None:
                backup.unlink(missing_ok=True)
        targets = [t for _, t in self._staged]
        self._staged = []
        return targets

    def discard(self) -> None:
        for tmp, _ in self._staged:
            tmp.unlink(missing_ok=True)
        self._staged = []
