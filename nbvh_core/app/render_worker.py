"""The render worker: a long-lived process that keeps a scene's models loaded and answers camera requests with
images (the NBVH render engine's back end; Blender's process never imports torch).

    python -m nbvh_core render-worker --frames DIR

Requests are JSON lines on stdin (the job protocol's style):
  {"op": "scene", "id": int, "scene": {...}}     the objects, lights and settings (`scene_render.SceneSpec`);
                                                  models and meshes are loaded once and kept while still used
  {"op": "render", "channel": str, "id": int, "camera": 4x4 rows (NDC -> world), "width": int, "height": int,
   "levels": [4, 2, 1], "samples": int, "bands": int}
                                                  progressive: one frame per level (1/level of the size, coarse
                                                  first); a newer request on the same channel (the view moved)
                                                  or a new scene abandons it between passes
  {"op": "cancel", "channel": str}               abandon that channel's request
  {"op": "quit"}                                 (end of input means the same)
Events are JSON lines on stdout:
  {"event": "ready", "pid": int}
  {"event": "scene", "id": int, "objects": int, "warnings": [str], "seconds": float}
  {"event": "frame", "channel", "id", "level", "width", "height", "path", "seconds", "last": bool}
       the image: `path` holds width * height * 4 float32 (linear RGBA, row 0 at the bottom), raw; written
       whole and renamed into place before the event, so a reader never sees part of it; the reader removes it
  {"event": "progress", "channel", "id", "fraction"}   (between bands of a level)
  {"event": "superseded", "channel", "id"}             (abandoned for a newer request or a cancel)
  {"event": "error", "channel", "id", "message"}       (that request failed; the worker goes on)
"""
from __future__ import annotations

import json
import os
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..protocol.events import json_lines
from ..protocol import events as wire
from ..protocol.process import Cancelled

#: Final renders first (F12 waits on them), then the viewports.
FINAL_CHANNEL = "final"


@dataclass
class Mailbox:
    """What the reader thread has received and the render loop has not handled yet: scenes in order, the newest
    render request per channel (older ones are dropped unseen), cancels, quit."""

    scenes: list = field(default_factory=list)
    renders: dict = field(default_factory=dict)  # channel -> request
    quit: bool = False
    generation: dict = field(default_factory=dict)  # channel -> count of requests and cancels received
    lock: threading.Condition = field(default_factory=threading.Condition)

    def put(self, msg: dict) -> None:
        with self.lock:
            op = msg.get("op")
            if op == "scene":
                self.scenes.append(msg)
            elif op == "render":
                channel = str(msg.get("channel", "default"))
                self.renders[channel] = msg
                self.generation[channel] = self.generation.get(channel, 0) + 1
            elif op == "cancel":
                channel = str(msg.get("channel", "default"))
                self.renders.pop(channel, None)
                self.generation[channel] = self.generation.get(channel, 0) + 1
            elif op == "quit":
                self.quit = True
            self.lock.notify_all()

    def take(self) -> tuple[str, dict | None, int]:
        """Block until there is work: ("quit", None, 0), ("scene", msg, 0) or ("render", msg, generation)."""
        with self.lock:
            while not (self.quit or self.scenes or self.renders):
                self.lock.wait()
            if self.quit:
                return "quit", None, 0
            if self.scenes:
                return "scene", self.scenes.pop(0), 0
            channel = FINAL_CHANNEL if FINAL_CHANNEL in self.renders else next(iter(self.renders))
            return "render", self.renders.pop(channel), self.generation.get(channel, 0)

    def requeue(self, channel: str, msg: dict, generation: int) -> None:
        """Put back a request abandoned only for a new scene (no newer request on its channel): it is redrawn
        with the new scene."""
        with self.lock:
            if not self.quit and self.generation.get(channel, 0) == generation and channel not in self.renders:
                self.renders[channel] = msg
                self.lock.notify_all()

    def stale(self, channel: str, generation: int) -> bool:
        """Has a newer request, a cancel, a new scene or quit arrived since `generation` of `channel`?"""
        with self.lock:
            return self.quit or bool(self.scenes) or self.generation.get(channel, 0) != generation


def read_requests(stream, mailbox: Mailbox, sink) -> None:
    """The reader thread: every JSON line into the mailbox; end of input is quit."""
    for line in stream:
        line = line.strip()
        if not line:
            continue
        try:
            msg = json.loads(line)
            if not isinstance(msg, dict):
                raise ValueError("not an object")
        except ValueError as exc:
            sink(wire.error(message=f"bad request line: {exc}"))
            continue
        mailbox.put(msg)
    mailbox.put(wire.quit_request())


def write_frame(path: Path, image: np.ndarray) -> None:
    """Write (H, W, 4) float32 raw and rename it into place (a reader never sees a partial frame)."""
    tmp = path.with_name(path.name + ".part")
    with open(tmp, "wb") as f:
        f.write(np.ascontiguousarray(image, np.float32).tobytes())
    os.replace(tmp, path)


def render_request(renderer, msg: dict, frames: Path, sink, stale) -> None:
    """All levels of one render request, a frame event after each; raises Cancelled when `stale()` turns true."""
    channel, rid = str(msg.get("channel", "default")), int(msg.get("id", 0))
    camera = np.asarray(msg["camera"], np.float64).reshape(4, 4)
    width, height = int(msg["width"]), int(msg["height"])
    if not (0 < width <= 16384 and 0 < height <= 16384):
        raise ValueError(f"image size {width} x {height} out of range")
    levels = [max(1, int(x)) for x in msg.get("levels", [1])] or [1]
    samples, bands = int(msg.get("samples", 1)), max(1, int(msg.get("bands", 1)))
    for i, level in enumerate(levels):
        if stale():
            raise Cancelled("superseded")
        t0 = time.monotonic()
        w, h = max(1, width // level), max(1, height // level)
        last = i == len(levels) - 1
        n_bands = bands if last else 1
        image = np.empty((h, w, 4), np.float32)
        for b in range(n_bands):
            y0, y1 = h * b // n_bands, h * (b + 1) // n_bands
            image[y0:y1] = renderer.render(camera, w, h, samples if last else 1, should_stop=stale, rows=(y0, y1))
            if n_bands > 1:
                sink(wire.progress(channel=channel, id=rid, fraction=(b + 1) / n_bands))
        path = frames / f"{_safe(channel)}-{rid}-{level}.rgba"
        write_frame(path, image)
        sink(wire.frame(channel=channel, id=rid, level=level, width=w, height=h, path=str(path),
                        seconds=round(time.monotonic() - t0, 4), last=last))


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in name)[:40] or "channel"


def serve(frames: Path, stdin=None, stdout=None) -> int:
    """Answer requests until quit or end of input. Returns the exit code (0)."""
    from ..rendering.scene_render import SceneRenderer
    from ..rendering.scene_spec import SceneSpec

    frames.mkdir(parents=True, exist_ok=True)
    sink = json_lines(stdout or sys.stdout)
    mailbox = Mailbox()
    threading.Thread(target=read_requests, args=(stdin or sys.stdin, mailbox, sink), daemon=True).start()
    renderer = SceneRenderer()
    sink(wire.ready(pid=os.getpid()))
    while True:
        kind, msg, generation = mailbox.take()
        if kind == "quit":
            return 0
        if kind == "scene":
            t0 = time.monotonic()
            try:
                warnings = renderer.set_scene(SceneSpec.from_dict(msg.get("scene")))
                sink(wire.scene(id=msg.get("id"), objects=len(renderer.placed), warnings=warnings,
                                seconds=round(time.monotonic() - t0, 3)))
            except (ValueError, TypeError, KeyError) as exc:
                sink(wire.error(id=msg.get("id"), message=f"bad scene: {exc}"))
            continue
        channel = str(msg.get("channel", "default"))
        try:
            render_request(renderer, msg, frames, sink, lambda: mailbox.stale(channel, generation))
        except Cancelled:
            mailbox.requeue(channel, msg, generation)  # a new scene: the same view again (a newer one replaces it)
            sink(wire.superseded(channel=channel, id=msg.get("id")))
        except (ValueError, TypeError, KeyError, OSError) as exc:
            sink(wire.error(channel=channel, id=msg.get("id"), message=str(exc)))


def main(argv: list[str] | None = None) -> int:
    import argparse

    ap = argparse.ArgumentParser(prog="nbvh render-worker", description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", required=True, help="folder for the frame files")
    args = ap.parse_args(argv)
    return serve(Path(args.frames))
