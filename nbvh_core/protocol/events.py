"""The job protocol: progress events as JSON lines, shared by the CLI's progress bar and the Blender add-on.

Every event is a flat JSON object with an "event" key:
  {"event": "phase", "phase": "bvh" | "train" | "anneal" | "freeze" | "eval" | "save", "message": str}
  {"event": "progress", "phase": str, "step": int, "total": int | null, "fraction": float, "loss": float,
   "samples_per_s": float, "elapsed_s": float, "eta_s": float | null}
  {"event": "warning", "message": str}
  {"event": "result", "path": str, "bytes": int, ...}        (the job's outcome)
  {"event": "error", "kind": str, "message": str}            (the job failed; "cancelled" when cancelled)
A consumer ignores keys and events it does not know, so the protocol can grow.
"""
from __future__ import annotations

import json
import sys
import time
from typing import Callable, TextIO

EventSink = Callable[[dict], None]


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
