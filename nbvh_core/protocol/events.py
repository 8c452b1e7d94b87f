"""The wire contract: every message that crosses a process boundary, as JSON lines, declared here (`EVENTS`,
`WORKER_REQUESTS`); tests/test_structure.py fails when code emits an event or a request not declared here.

Job and CLI events (`--events`, the add-on's background jobs, library batches) are flat JSON objects with an "event"
key; the render worker (`app/render_worker.py`) reads requests with an "op" key and answers with events. A consumer
ignores keys and events it does not know, so the protocol can grow.
"""
from __future__ import annotations

import json
import sys
import time
from typing import Callable, TextIO

EventSink = Callable[[dict], None]

#: event -> what it carries (the keys every emitter sets; more may come).
EVENTS = {
    # a compress run, a job, a library batch
    "phase": "phase ('plan', 'bvh', 'train', 'anneal', 'freeze', 'quantize', 'search', 'appearance', 'eval', "
             "'save', ...), message",
    "progress": "phase, fraction; a training: step, total, loss, samples_per_s, elapsed_s, eta_s; a batch: done, total",
    "warning": "message (one line)",
    "verdict": "worth_compressing (false), message, assessment (decision.records.Assessment: alternatives, recommendation, "
               "final: the decision.records.FinalVerdict that kept the mesh after training began, or null)",
    "written": "files (paths), kind ('decimation' | 'mesh' for a kept mesh), triangles",
    "asset": "a library row: name, phase ('measure' | 'train'), status, and its numbers",
    "result": "the run's outcome: path, bytes, quality, ... (a job: name, files, train_seconds, device)",
    "error": "kind (process.Outcome kind: 'bad_input', 'not_worth', 'cancelled', ...), message",
    # the render worker's answers
    "ready": "the worker started: pid",
    "scene": "id, objects, warnings (objects that could not be loaded), seconds",
    "frame": "channel, id, level, width, height, path (the pixels: raw float32 RGBA), seconds, last",
    "superseded": "channel, id: a newer request replaced this one",
    # the add-on's render client, when the worker process ends
    "exit": "code (or null)",
}
#: The render worker's requests ("op") -> what they carry.
WORKER_REQUESTS = {
    "scene": "id, scene (scene_render.SceneSpec as a dict)",
    "render": "channel, id, camera (4x4 rows, NDC -> world), width, height, samples, levels",
    "cancel": "channel",
    "quit": "nothing (end of input means the same)",
}


def event(kind: str, /, **fields) -> dict:
    """One declared event (`EVENTS`); raises ValueError for an undeclared kind. The constructors below are the
    way code builds events; this one serves a kind chosen at run time."""
    if kind not in EVENTS:
        raise ValueError(f"undeclared event {kind!r}; declared: {', '.join(EVENTS)}")
    return {"event": kind, **fields}


# ---------------------------------------------------------------- one constructor per event (EVENTS)
def phase(phase: str, message: str, **more) -> dict:
    """A run entering `phase` (or saying something within it): message, one line."""
    return event("phase", phase=phase, message=message, **more)


def progress(fraction: float, **detail) -> dict:
    """How far a phase is, `fraction` in [0, 1]; detail: a training's phase, step, total, loss, samples_per_s,
    elapsed_s, eta_s; the plan's phase, message (what it measures now), step, total, elapsed_s, eta_s; a batch's
    phase, done, total; a render's channel, id."""
    return event("progress", fraction=fraction, **detail)


def warning(message: str, **more) -> dict:
    """Something the user should know that does not stop the run (one line)."""
    return event("warning", message=message, **more)


def verdict(message: str, assessment: dict | None, worth_compressing: bool = False) -> dict:
    """The run keeps the mesh: why (message) and the measured alternatives (`Assessment.to_dict()`)."""
    return event("verdict", worth_compressing=worth_compressing, message=message, assessment=assessment)


def written(files: list[str], **more) -> dict:
    """Files written in place of a model: kind ('decimation' | 'mesh'), triangles."""
    return event("written", files=files, **more)


def asset(phase: str, **row) -> dict:
    """A library batch's row for one asset in `phase` ('measure' | 'train'): name, status and its numbers."""
    return event("asset", phase=phase, **row)


def result(**fields) -> dict:
    """A run's or a job's outcome: path, bytes, quality, ... (a job: name, files, train_seconds, device)."""
    return event("result", **fields)


def error(message: str, **more) -> dict:
    """A failure, one line: kind (`process.Outcome` kind) for a run; channel, id for a render request."""
    return event("error", message=message, **more)


def ready(pid: int) -> dict:
    """The render worker started (its process id)."""
    return event("ready", pid=pid)


def scene(id: int | None, objects: int, warnings: list[str], seconds: float) -> dict:
    """The render worker loaded a scene: objects placed, warnings (objects it could not load), seconds."""
    return event("scene", id=id, objects=objects, warnings=warnings, seconds=seconds)


def frame(channel: str, id: int, level: int, width: int, height: int, path: str, seconds: float,
          last: bool) -> dict:
    """A rendered frame of a request (level: coarse to fine; last: the final level), its pixels at `path`."""
    return event("frame", channel=channel, id=id, level=level, width=width, height=height, path=path,
                 seconds=seconds, last=last)


def superseded(channel: str, id: int | None) -> dict:
    """A render request abandoned for a newer one or a cancel."""
    return event("superseded", channel=channel, id=id)


def process_exit(code: int | None = None) -> dict:
    """The render worker's process ended (the client's own event, `code` when known)."""
    return event("exit", code=code)


#: kind -> its constructor (a test checks that every declared event has exactly one).
CONSTRUCTORS = {"phase": phase, "progress": progress, "warning": warning, "verdict": verdict, "written": written,
                "asset": asset, "result": result, "error": error, "ready": ready, "scene": scene, "frame": frame,
                "superseded": superseded, "exit": process_exit}


# ---------------------------------------------------------------- one constructor per worker request
def request(op: str, /, **fields) -> dict:
    """One declared render-worker request (`WORKER_REQUESTS`); raises ValueError for an undeclared op."""
    if op not in WORKER_REQUESTS:
        raise ValueError(f"undeclared request {op!r}; declared: {', '.join(WORKER_REQUESTS)}")
    return {"op": op, **fields}


def scene_request(id: int, scene: dict) -> dict:
    """Load a scene (`scene_render.SceneSpec` as a dict) under `id`."""
    return request("scene", id=id, scene=scene)


def render_request(channel: str, id: int, camera: list, width: int, height: int, **more) -> dict:
    """Render `channel` (viewport / final) from camera (4x4 rows, NDC -> world) at width x height; more: samples,
    levels, shadows, ..."""
    return request("render", channel=channel, id=id, camera=camera, width=width, height=height, **more)


def cancel_request(channel: str) -> dict:
    """Abandon that channel's request."""
    return request("cancel", channel=channel)


def quit_request() -> dict:
    """End the worker (end of input means the same)."""
    return request("quit")


REQUEST_CONSTRUCTORS = {"scene": scene_request, "render": render_request, "cancel": cancel_request,
                        "quit": quit_request}


def null_sink(event: dict) -> None:
    """Discard events."""


def json_lines(stream: TextIO = sys.stdout) -> EventSink:
    """Write each event as one JSON line and flush (a reader in another process sees it at once)."""
    def sink(event: dict) -> None:
        stream.write(json.dumps(event, separators=(",", ":")) + "\n")
        stream.flush()
    return sink


def parse_line(line: str) -> dict | None:
    """The event on one line of a job's output, or None for anything that is not an event."""
    line = line.strip()
    if not line.startswith("{"):
        return None
    try:
        event = json.loads(line)
    except json.JSONDecodeError:
        return None
    return event if isinstance(event, dict) and "event" in event else None


def _fmt_seconds(s: float | None) -> str:
    if s is None or s != s or s == float("inf"):
        return "?"
    s = int(round(s))
    return f"{s // 60}m{s % 60:02d}s" if s >= 60 else f"{s}s"


def progress_bar(stream: TextIO = sys.stderr, width: int = 28, min_interval: float = 0.2) -> EventSink:
    """A one-line terminal progress bar driven by the same events."""
    last = [0.0]

    def sink(event: dict) -> None:
        kind = event.get("event")
        if kind == "progress":
            now = time.monotonic()
            if now - last[0] < min_interval and event.get("fraction", 0) < 1:
                return
            last[0] = now
            frac = max(0.0, min(1.0, float(event.get("fraction", 0.0))))
            bar = "#" * int(frac * width) + "-" * (width - int(frac * width))
            if "done" in event:  # a library batch: assets, not steps
                what = f"{event.get('phase', '')} {event['done']}/{event.get('total')} assets"
            elif "message" in event:  # the plan: what it measures now
                what = f"{event.get('phase', '')}: {event['message']}"
            else:
                what = (f"{event.get('phase', '')} step {event.get('step')} loss {event.get('loss', float('nan')):.4f} "
                        f"{event.get('samples_per_s', 0):,.0f} samples/s")
            stream.write(f"\r[{bar}] {frac * 100:5.1f}% {what} ETA {_fmt_seconds(event.get('eta_s'))}   ")
            stream.flush()
        elif kind == "phase":
            stream.write(f"\n{event.get('phase')}: {event.get('message', '')}\n")
            stream.flush()
        elif kind in ("warning", "error"):
            stream.write(f"\n{kind}: {event.get('message')}\n")
            stream.flush()
        elif kind == "asset" and event.get("status") == "failed":
            stream.write(f"\n{event.get('name')}: failed: {event.get('error')}\n")
            stream.flush()
    return sink
