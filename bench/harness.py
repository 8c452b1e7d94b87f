"""What every benchmark's rows share: the stamp (commit, machine, command) and appending a row to a CSV as it lands
(a rerun resumes; a CSV learns new columns without shifting old rows)."""
from __future__ import annotations

import csv
import os
import platform
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def stamp() -> dict:
    """commit (short hash), machine (host, architecture, CPUs) and the command that made the row."""
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True)
    return {"commit": commit.stdout.strip() or "unknown",
            "machine": f"{platform.node()} {platform.machine()} cpus={os.cpu_count()}",
            "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]])}


def append_rows(path: str | os.PathLike, rows: list[dict]) -> None:
    """Append `rows` to the CSV at `path`; columns new to it are added (older rows get them empty)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    old = list(csv.DictReader(open(path))) if path.exists() else []
    fields = list(dict.fromkeys([*(old[0].keys() if old else []), *(k for r in rows for k in r)]))
    if old and list(old[0].keys()) == fields:
        with open(path, "a", newline="") as f:
            csv.DictWriter(f, fieldnames=fields).writerows(rows)
        return
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields)
        w.writeheader()
        w.writerows([*old, *rows])


def read_rows(path: str | os.PathLike) -> list[dict]:
    return list(csv.DictReader(open(path))) if Path(path).exists() else []
