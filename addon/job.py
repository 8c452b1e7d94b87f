"""Background jobs: one `python -m nbvh_core job REQUEST.json` process per object, run one at a time.

No bpy and no torch here: the add-on's operators and `compress.py` drive a `JobQueue` (from a Blender timer,
or by waiting on it under `blender -b`, where timers never fire while a script runs). Each job has an id,
its own temporary folder and its own cancel path (terminating its process), and its events are read from
the process's stdout by a reader thread into a queue, so polling never blocks.

A job is finished only when its process exited 0 *and* sent a `result` event; anything else (error event,
crash, non-zero exit, cancel) is a failure with a message, and its temporary folder is removed. The job process
writes its results as one unit at its very end, so a failed, cancelled or killed re-run never touches the object's
previous result: cleanup removes only that process's own partial files and lock, never a finished output. A job
that dies in training leaves its checkpoint (`checkpoint_for(model)`), which a new job can continue.
"""
from __future__ import annotations

import json
import os
import queue
import shutil
import subprocess
import tempfile
import threading
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path

# The add-on ships nbvh_core beside this file (build_addon.py copies it in); in the repository it is one up.
_HERE = Path(__file__).resolve().parent
CORE_PARENT = _HERE if (_HERE / "nbvh_core").is_dir() else _HERE.parent


try:  # the installed add-on carries nbvh_core inside it; in the repository it sits beside addon/
    from .nbvh_core.protocol import events as wire  # noqa: F401  (render_client.py builds its requests with it)
    from .nbvh_core.protocol.events import parse_line as parse_event  # no torch: these modules are plain Python
    from .nbvh_core.protocol.outputs import checkpoint_for, lock_for  # noqa: F401  (checkpoint_for: for compress_session.py)
    from .nbvh_core.protocol.quality_levels import (DEFAULT_LEVEL, QUALITY_LEVELS,  # noqa: F401  (compress_session.py, the panel)
                                                    TARGET_TRAININGS, most_trainings)
except ImportError:
    from nbvh_core.protocol import events as wire  # noqa: F401
    from nbvh_core.protocol.events import parse_line as parse_event
    from nbvh_core.protocol.outputs import checkpoint_for, lock_for  # noqa: F401
    from nbvh_core.protocol.quality_levels import (DEFAULT_LEVEL, QUALITY_LEVELS,  # noqa: F401
                                                   TARGET_TRAININGS, most_trainings)


def core_env() -> dict:
    """Environment for the job process: nbvh_core importable, unbuffered output, no user site confusion."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(CORE_PARENT) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env["PYTHONUNBUFFERED"] = "1"
    env.pop("PYTHONHOME", None)  # Blender sets it for its own Python; the job's Python needs its own
    return env


def check_python(python: str, timeout: float = 60.0) -> tuple[bool, str]:
    """Can `python` run the job (torch and nbvh_core importable)? Returns (ok, message)."""
    if not python:
        return False, "no Python interpreter configured"
    code = "import torch, numpy, nbvh_core; print(torch.__version__, numpy.__version__)"
    try:
        out = subprocess.run([python, "-c", code], capture_output=True, text=True, timeout=timeout, env=core_env())
    except (OSError, subprocess.TimeoutExpired) as exc:
        return False, f"cannot run {python}: {exc}"
    if out.returncode != 0:
        last = (out.stderr.strip().splitlines() or ["unknown error"])[-1]
        return False, f"{python} cannot run nbvh_core: {last}"
    return True, f"{python}: torch {out.stdout.split()[0]}"


def default_python(candidates: list[str] | None = None) -> str:
    """First interpreter that can run jobs: $NBVH_PYTHON, the add-on's own venv, the repository's .venv,
    then python3 on PATH. Returns '' when none works."""
    options = list(candidates or [])
    if os.environ.get("NBVH_PYTHON"):
        options.insert(0, os.environ["NBVH_PYTHON"])
    from .installer import venv_python

    options += [str(venv_python(CORE_PARENT / ".venv")), str(venv_python(CORE_PARENT.parent / ".venv")),
                shutil.which("python3") or ""]
    for p in options:
        if p and Path(p).exists() and check_python(p)[0]:
            return p
    return ""


@dataclass
class Job:
    """One object's compression. state: queued -> running -> done | skipped | failed | cancelled. `skipped`: the
    verdict before training said "not worth compressing" (`verdict` holds the message; nothing was written)."""

    name: str
    request: dict
    workdir: Path
    id: str = field(default_factory=lambda: uuid.uuid4().hex[:12])
    state: str = "queued"
    progress: dict = field(default_factory=dict)
    result: dict | None = None
    error: str | None = None
    verdict: str | None = None
    decimation: dict | None = None  # the verdict's winning decimation (triangles, mse, resident and compact bytes)
    kept_files: list = field(default_factory=list)  # what the job wrote in place of a model (NAME.glb, .compact.cmsh)
    scene_split: dict | None = None  # a scene budget's split as the job planned it (also when the mesh is kept)
    log: list = field(default_factory=list)
    started: float | None = None
    clock: "JobClock" = field(default_factory=lambda: JobClock())
    _proc: subprocess.Popen | None = None
    _events: queue.Queue = field(default_factory=queue.Queue)
    _stderr: list = field(default_factory=list)

    def start(self, python: str) -> None:
        req_path = self.workdir / "request.json"
        req_path.write_text(json.dumps(self.request))
        self._proc = subprocess.Popen([python, "-m", "nbvh_core", "job", str(req_path)], stdout=subprocess.PIPE,
                                      stderr=subprocess.PIPE, text=True, env=core_env(), cwd=str(self.workdir))
        self.state = "running"
        self.started = time.monotonic()
        threading.Thread(target=self._read, args=(self._proc.stdout, True), daemon=True).start()
        threading.Thread(target=self._read, args=(self._proc.stderr, False), daemon=True).start()

    def _read(self, stream, is_stdout: bool) -> None:
        for line in stream:
            if is_stdout:
                event = parse_event(line)
                if event is not None:
                    self._events.put(event)
            else:
                self._stderr.append(line)
                del self._stderr[:-200]

    def poll(self) -> list[dict]:
        """New events since the last poll; updates state when the process has ended."""
        new = []
        while True:
            try:
                new.append(self._events.get_nowait())
            except queue.Empty:
                break
        for ev in new:
            kind = ev.get("event")
            self.clock.see(ev)
            if kind in ("progress", "phase"):
                if ev.get("scene_split"):
                    self.scene_split = ev["scene_split"]
                self.progress.update({k: v for k, v in ev.items() if k not in ("event", "scene_split")})
            elif kind == "result":
                self.result = ev
            elif kind == "verdict":  # the decimation that meets the level, when it is what wins
                assessment = ev.get("assessment") or {}
                if assessment.get("recommendation") == "decimate":
                    self.decimation = (assessment.get("alternatives") or {}).get("decimation")
            elif kind == "written":  # the kept mesh's files, the CLI's own (nbvh_core.app.kept_mesh)
                self.kept_files = [str(f) for f in ev.get("files") or []]
            elif kind == "error" and ev.get("kind") == "not_worth":
                self.verdict = ev.get("message", "not worth compressing")
            elif kind == "error":
                self.error = ev.get("message", "unknown error")
            elif kind == "warning":
                self.log.append(ev.get("message", ""))
        if self.state == "running" and self._proc is not None and self._proc.poll() is not None:
            time.sleep(0.05)  # let the reader threads drain the pipes
            more = self.poll() if not self._events.empty() else []
            new += more
            if self.state != "running":
                return new
            code = self._proc.returncode
            if code == 0 and self.result is not None:
                self.state = "done"
            elif code == 4 and self.verdict is not None:
                self.state = "skipped"
            else:
                self.state = "failed"
                if not self.error:
                    tail = "".join(self._stderr[-15:]).strip()
                    self.error = f"job process exited with code {code}" + (f":\n{tail}" if tail else "")
        return new

    def cancel(self) -> None:
        """Stop the job now; its temporary folder goes; a finished job's outputs are kept."""
        from .installer import stop_process

        stop_process(self._proc)
        if self.state in ("queued", "running"):
            self.state = "cancelled"
            self.error = "cancelled"
            self.cleanup()

    def cleanup(self) -> None:
        """Remove the job's temporary folder and what its own process left half-written (staged files, its lock);
        finished outputs, earlier results and the training checkpoint are never removed."""
        shutil.rmtree(self.workdir, ignore_errors=True)
        if self._proc is None:
            return
        pid = self._proc.pid
        out_dir = Path(self.request.get("out_dir", ""))
        for p in out_dir.glob(f".{self.name}.*.partial-{pid}"):
            p.unlink(missing_ok=True)
        lock = lock_for(out_dir / f"{self.name}.nbvh")
        try:
            if lock.read_text().strip() == str(pid):
                lock.unlink()
        except OSError:
            pass

    def eta_s(self) -> float | None:
        """Seconds until this job ends (every phase, every training a target search may still run); None for a
        job that runs by steps and has not reported its speed yet."""
        if self.state == "queued":
            return self.clock.estimate(self.request)
        if self.state != "running":
            return 0.0
        return self.clock.remaining(self.request)

    @property
    def fraction(self) -> float:
        return float(self.progress.get("fraction", 0.0)) if self.state == "running" else (
            1.0 if self.state == "done" else 0.0)


#: Seconds the phases after a training take (evaluation; then the preview image, proxy points and files) until this
#: job has timed one: 4 s measured on this 2-core CPU for 16 views at 128 px, scaled to the default 256 px (4x the
#: pixels, the held-out and the check views), and a 256 px preview.
EVAL_GUESS_S, FINISH_GUESS_S = 12.0, 4.0
TRAINING_PHASES = ("train", "anneal", "freeze", "quantize")


@dataclass
class JobClock:
    """A whole-job ETA from the job's own events: the current training's remaining time (its `eta_s`), the
    trainings a target search may still run (each its time limit), the evaluation after each training (as long as
    this job's last one took) and the preview at the end."""

    trainings: int = 0  # trainings started
    in_training: bool = False
    training_eta: float | None = None
    training_seen_at: float = 0.0
    evals_done: int = 0
    eval_started: float | None = None
    eval_seconds: float | None = None
    finishing: bool = False  # the preview phase: no more training

    def see(self, event: dict) -> None:
        now = time.monotonic()
        kind, phase = event.get("event"), event.get("phase")
        if kind == "phase" and self.eval_started is not None and phase != "eval":
            self.eval_seconds, self.eval_started = now - self.eval_started, None
            self.evals_done += 1
        if kind == "phase" and phase == "train" and not str(event.get("message", "")).startswith("resumed"):
            self.trainings += 1
            self.in_training, self.training_eta = True, None
        elif kind == "phase" and phase == "eval":
            self.in_training, self.eval_started = False, now
        elif kind == "phase" and phase in ("preview", "save"):
            self.in_training, self.finishing = False, True
        elif kind == "progress" and phase in TRAINING_PHASES and event.get("eta_s") is not None:
            self.training_eta, self.training_seen_at = float(event["eta_s"]), now

    @staticmethod
    def _limits(request: dict) -> tuple[float | None, int]:
        settings = request.get("settings") or {}
        limit = settings.get("time_limit_s")
        most = most_trainings(settings) if not request.get("model") else 1
        return (float(limit) if limit else None), (0 if request.get("model") else most)

    def estimate(self, request: dict) -> float | None:
        """Before the job starts: every training at its full time limit, with its evaluation, and the preview."""
        limit, most = self._limits(request)
        if most and limit is None:
            return None
        return most * ((limit or 0.0) + EVAL_GUESS_S) + FINISH_GUESS_S

    def remaining(self, request: dict) -> float | None:
        limit, most = self._limits(request)
        eval_s = self.eval_seconds if self.eval_seconds is not None else EVAL_GUESS_S
        if self.finishing:
            return FINISH_GUESS_S
        if self.in_training:
            if self.training_eta is not None:
                current = max(0.0, self.training_eta - (time.monotonic() - self.training_seen_at))
            elif limit is not None:
                current = limit
            else:
                return None
            current += eval_s
        elif self.eval_started is not None:
            current = max(0.0, eval_s - (time.monotonic() - self.eval_started))
        else:
            current = (limit or 0.0) + eval_s if most else 0.0  # before the first training (plan, verdict, BVH)
        later = max(0, most - max(self.trainings, 1)) * ((limit or 0.0) + eval_s) if limit is not None else 0.0
        return current + later + FINISH_GUESS_S


class JobQueue:
    """Jobs run one after another (a 2-core machine cannot train two models at once usefully)."""

    def __init__(self, python: str):
        self.python = python
        self.jobs: list[Job] = []

    def submit(self, name: str, request: dict) -> Job:
        workdir = Path(tempfile.mkdtemp(prefix=f"nbvh-{name[:20]}-"))
        job = Job(name=name, request=request, workdir=workdir)
        self.jobs.append(job)
        return job

    def active(self) -> Job | None:
        return next((j for j in self.jobs if j.state == "running"), None)

    def finished(self, job: Job) -> bool:
        return job.state in ("done", "skipped", "failed", "cancelled")

    def pending(self) -> list[Job]:
        return [j for j in self.jobs if j.state in ("queued", "running")]

    def step(self) -> list[tuple[Job, dict]]:
        """Advance: poll the running job, start the next queued one. Returns (job, event) pairs."""
        out = []
        job = self.active()
        if job is not None:
            out += [(job, e) for e in job.poll()]
            if job.state != "running":
                job.cleanup()
        if self.active() is None:
            nxt = next((j for j in self.jobs if j.state == "queued"), None)
            if nxt is not None:
                nxt.start(self.python)
        return out

    def eta_s(self) -> float | None:
        """Seconds until every job of the queue has ended (None when one of them cannot say)."""
        parts = [j.eta_s() for j in self.pending()]
        return None if any(p is None for p in parts) else float(sum(parts))

    def cancel_all(self) -> None:
        for j in self.pending():
            j.cancel()

    def wait(self, on_event=None, poll_s: float = 0.2, timeout: float | None = None) -> None:
        """Block until every job has ended (the headless path); `on_event(job, event)` sees every event."""
        t0 = time.monotonic()
        while self.pending():
            for job, ev in self.step():
                if on_event:
                    on_event(job, ev)
            if timeout is not None and time.monotonic() - t0 > timeout:
                self.cancel_all()
                raise TimeoutError(f"jobs did not finish within {timeout} s")
            time.sleep(poll_s)
        for job, ev in self.step():
            if on_event:
                on_event(job, ev)
