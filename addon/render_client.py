"""The Blender side of the render worker (`nbvh_core.app.render_worker`): starts it, sends scenes and camera requests,
collects its frames. No bpy and no torch here (tested outside Blender); a reader thread turns the worker's output
into events, so nothing here ever blocks Blender's UI except `wait`, which the final render calls on purpose.

One worker serves the whole Blender session (`shared_worker`): it keeps the models loaded between frames and
between renders. Viewports each use their own channel; the final render uses "final", which the worker serves
first.
"""
from __future__ import annotations

import json
import queue
import shutil
import subprocess
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .installer import stop_process
from .job import core_env, parse_event, wire

FINAL = "final"


class WorkerError(RuntimeError):
    """The worker could not start, died, or answered a request with an error."""


@dataclass
class Frame:
    """One image from the worker: pixels (H, W, 4) float32 linear RGBA, row 0 at the bottom."""

    channel: str
    id: int
    level: int
    pixels: np.ndarray
    seconds: float
    last: bool


@dataclass
class Channel:
    """What one viewport (or the final render) asked and got: the newest request id, its newest frame, whether
    a finer frame of it is still coming, and its errors."""

    requested: int = 0
    frame: Frame | None = None
    pending: bool = False
    progress: float = 0.0
    error: str | None = None


class RenderWorker:
    """A running `python -m nbvh_core render-worker` process."""

    def __init__(self, python: str, startup_timeout: float = 120.0):
        self.python = python
        self.frames_dir = Path(tempfile.mkdtemp(prefix="nbvh-frames-"))
        self._events: queue.Queue = queue.Queue()
        self._stderr: list[str] = []
        self._next_id = 0
        self.channels: dict[str, Channel] = {}
        self.scene_id = 0
        self.scene_done = 0
        self.warnings: list[str] = []
        try:
            self._proc = subprocess.Popen([python, "-m", "nbvh_core", "render-worker", "--frames", str(self.frames_dir)],
                                          stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                          text=True, env=core_env(), bufsize=1)
        except OSError as exc:
            shutil.rmtree(self.frames_dir, ignore_errors=True)
            raise WorkerError(f"cannot start the render worker with {python}: {exc}") from None
        threading.Thread(target=self._read_stdout, daemon=True).start()
        threading.Thread(target=self._read_stderr, daemon=True).start()
        self.pid = None
        deadline = time.monotonic() + startup_timeout
        while self.pid is None:
            self.poll()
            if not self.alive:
                raise WorkerError(f"the render worker exited at start: {self.last_error()}")
            if time.monotonic() > deadline:
                self.stop()
                raise WorkerError("the render worker did not start in time")
            time.sleep(0.02)

    # -- process ------------------------------------------------------------------------------------------
    def _read_stdout(self) -> None:
        for line in self._proc.stdout:
            event = parse_event(line)
            if event is not None:
                self._events.put(event)
        self._events.put(wire.process_exit())

    def _read_stderr(self) -> None:
        for line in self._proc.stderr:
            self._stderr.append(line)
            del self._stderr[:-200]

    @property
    def alive(self) -> bool:
        return self._proc.poll() is None

    def last_error(self) -> str:
        lines = [x.strip() for x in self._stderr if x.strip()]
        return lines[-1] if lines else f"exit code {self._proc.poll()}"

    def send(self, msg: dict) -> None:
        if not self.alive:
            raise WorkerError(f"the render worker is not running ({self.last_error()})")
        try:
            self._proc.stdin.write(json.dumps(msg, separators=(",", ":")) + "\n")
            self._proc.stdin.flush()
        except (BrokenPipeError, OSError) as exc:
            raise WorkerError(f"the render worker stopped: {exc}") from None

    def stop(self) -> None:
        """Ask the worker to quit, terminate it if it does not, remove its frames."""
        try:
            if self.alive:
                self._proc.stdin.write(json.dumps(wire.quit_request()) + "\n")
                self._proc.stdin.flush()
                self._proc.wait(timeout=3)
        except (OSError, ValueError, subprocess.TimeoutExpired):
            pass
        stop_process(self._proc)
        shutil.rmtree(self.frames_dir, ignore_errors=True)

    # -- requests -----------------------------------------------------------------------------------------
    def set_scene(self, scene: dict) -> int:
        """Send a scene (`nbvh_core.rendering.scene_render` JSON form); returns its id (`scene_done` reaches it)."""
        self.scene_id += 1
        self.send(wire.scene_request(id=self.scene_id, scene=scene))
        return self.scene_id

    def request(self, channel: str, camera, width: int, height: int, levels=(1,), samples: int = 1,
                bands: int = 1) -> int:
        """Ask for an image of the current scene; camera: (4, 4) NDC -> world. Returns the request id; an older
        request on the channel is abandoned by the worker."""
        self._next_id += 1
        ch = self.channels.setdefault(channel, Channel())
        ch.requested, ch.pending, ch.progress, ch.error = self._next_id, True, 0.0, None
        self.send(wire.render_request(channel=channel, id=self._next_id,
                                      camera=np.asarray(camera, np.float64).reshape(4, 4).tolist(), width=int(width),
                                      height=int(height), levels=[int(x) for x in levels], samples=int(samples),
                                      bands=int(bands)))
        return self._next_id

    def cancel(self, channel: str) -> None:
        ch = self.channels.get(channel)
        if ch is not None:
            ch.pending = False
        if self.alive:
            self.send(wire.cancel_request(channel=channel))

    # -- events -------------------------------------------------------------------------------------------
    def poll(self) -> bool:
        """Take every event that arrived (never blocks). Returns True when any channel got a new frame."""
        new_frame = False
        while True:
            try:
                event = self._events.get_nowait()
            except queue.Empty:
                return new_frame
            new_frame |= self._handle(event)

    def _handle(self, event: dict) -> bool:
        kind = event.get("event")
        if kind == "ready":
            self.pid = event.get("pid")
        elif kind == "scene":
            self.scene_done = max(self.scene_done, int(event.get("id") or 0))
            self.warnings = list(event.get("warnings") or [])
        elif kind == "exit":
            for ch in self.channels.values():
                if ch.pending:
                    ch.pending, ch.error = False, f"the render worker stopped: {self.last_error()}"
        elif kind in ("frame", "progress", "error") and event.get("channel") is not None:
            ch = self.channels.setdefault(str(event["channel"]), Channel())
            return self._channel_event(ch, event)
        elif kind == "error" and event.get("id") is not None:  # a bad scene
            self.scene_done = max(self.scene_done, int(event["id"]))
            self.warnings = [event.get("message", "bad scene")]
        return False

    def _channel_event(self, ch: Channel, event: dict) -> bool:
        kind, rid = event["event"], int(event.get("id") or 0)
        if kind == "progress" and rid == ch.requested:
            ch.progress = float(event.get("fraction", 0.0))
        elif kind == "error" and rid == ch.requested:
            ch.pending, ch.error = False, str(event.get("message"))
        elif kind == "frame":
            path = Path(event["path"])
            try:
                pixels = np.fromfile(path, np.float32).reshape(int(event["height"]), int(event["width"]), 4)
            except (OSError, ValueError):
                return False
            finally:
                path.unlink(missing_ok=True)
            if rid < (ch.frame.id if ch.frame else 0):
                return False  # an older request's late frame
            ch.frame = Frame(str(event["channel"]), rid, int(event["level"]), pixels, float(event.get("seconds", 0)),
                             bool(event.get("last")))
            if rid == ch.requested and ch.frame.last:
                ch.pending, ch.progress = False, 1.0
            return True
        return False

    def wait(self, done, timeout: float | None = None, should_stop=None, interval: float = 0.05) -> bool:
        """Poll until `done()` is true (True), `should_stop()` is true or the timeout passes (False). Raises
        WorkerError when the worker dies."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            self.poll()
            if done():
                return True
            if not self.alive:
                self.poll()
                if done():
                    return True
                raise WorkerError(f"the render worker stopped: {self.last_error()}")
            if (should_stop is not None and should_stop()) or (deadline is not None and time.monotonic() > deadline):
                return False
            time.sleep(interval)


_shared: dict = {"worker": None}


def shared_worker(python: str) -> RenderWorker:
    """The session's worker (started on first use, restarted when it died or the Python changed)."""
    w = _shared["worker"]
    if w is None or not w.alive or w.python != python:
        if w is not None:
            w.stop()
        _shared["worker"] = w = RenderWorker(python)
    return w


def current_worker() -> RenderWorker | None:
    return _shared["worker"]


def stop_shared() -> None:
    w = _shared["worker"]
    _shared["worker"] = None
    if w is not None:
        w.stop()
