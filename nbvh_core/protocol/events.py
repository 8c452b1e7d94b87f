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
    "ready": "the worker started: path (the compute path it runs)",
    "scene": "id, problems (objects that could not be loaded)",
    "frame": "channel, id, level, width, height, seconds (the pixels follow as raw float32 RGBA)",
    "superseded": "channel, id: a newer request replaced this one",
    # the add-on's render client, when the worker process ends
    "exit": "code",
}
#: The render worker's requests ("op") -> what they carry.
WORKER_REQUESTS = {
    "scene": "id, scene (scene_render.SceneSpec as a dict)",
    "render": "channel, id, camera (4x4 rows, NDC -> world), width, height, samples, levels",
    "cancel": "channel",
    "quit": "nothing (end of input means the same)",
}


def event(kind: str, **fields) -> dict:
    """One declared event (`EVENTS`); raises ValueError for an undeclared kind."""
    if kind not in EVENTS:
        raise ValueError(f"undeclared event {kind!r}; declared: {', '.join(EVENTS)}")
    return {"event": kind, **fields}


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
