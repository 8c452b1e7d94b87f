"""Library and scene-wide runs from Blender: one background job running `nbvh_core.app.library_batch` (no torch here).

* `start_scene_report(context, ...)`: every mesh object of the open scene exported (evaluated, modifiers applied),
  then measured and given its verdict without training (the batch's first step): triangles, resident bytes,
  verdict, predicted savings; listed in the panel (sorted by savings) and written as report.html.
* `start_library(folder, ...)`: a folder of assets (mesh files, .blend files) compressed as a batch: progress in
  the panel, the library report at the end.
"""
from __future__ import annotations

import json
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import export
from .job import Job, JobQueue, default_python


@dataclass
class LibraryRun:
    """One library or scene-report job and where its report goes."""

    kind: str  # 'scene' | 'library'
    queue: JobQueue
    job: Job
    out_dir: str
    refusals: list = field(default_factory=list)  # objects that could not be exported (not meshes, empty)
    names: dict = field(default_factory=dict)  # asset name in the report -> Blender object name
    mesh_dir: str = ""  # the exported meshes of a scene report (removed when the run ends)


def _python(python: str | None) -> str:
    python = python or default_python()
    if not python:
        raise RuntimeError("no Python with PyTorch and nbvh_core found: set one in the add-on preferences or "
                           "press 'Install dependencies'")
    return python


def start_scene_report(context, out_dir: Path, settings: dict, python: str | None = None) -> LibraryRun:
    """Export every mesh object of the scene and queue one measure-only batch over them."""
    queue = JobQueue(_python(python))
    out_dir = Path(out_dir) / "scene_report"
    mesh_dir = Path(tempfile.mkdtemp(prefix="nbvh-scene-report-"))
    depsgraph = context.evaluated_depsgraph_get()
    lines, refusals, names = [], [], {}
    for obj in context.scene.objects:
        if obj.type != "MESH":
            continue
        try:
            verts, tris, _, look = export.evaluated_triangles(obj, depsgraph)
        except export.ExportError as exc:
            refusals.append(str(exc))
            continue
        stem = f"{len(lines):04d}_{''.join(c if c.isalnum() else '_' for c in obj.name)}"
        np.savez(mesh_dir / f"{stem}.npz", vertices=verts, faces=tris, **look)
        lines.append(str(mesh_dir / f"{stem}.npz"))
        names[stem] = obj.name
    if not lines:
        raise RuntimeError("the scene has no mesh objects with triangles")
    listing = mesh_dir / "objects.txt"
    listing.write_text("\n".join(lines) + "\n")
    job = queue.submit("scene-report", {"kind": "batch", "name": "scene-report", "library": str(listing),
                                        "out_dir": str(out_dir), "measure_only": True, "settings": settings})
    return LibraryRun("scene", queue, job, str(out_dir), refusals, names, str(mesh_dir))


def start_library(folder: str, out_dir: Path, settings: dict, python: str | None = None) -> LibraryRun:
    """Queue a batch over `folder` (searched recursively), results and report in out_dir/library."""
    if not folder or not Path(folder).is_dir():
        raise RuntimeError(f"not a folder: {folder!r}")
    queue = JobQueue(_python(python))
    out = Path(out_dir) / "library"
    job = queue.submit("library", {"kind": "batch", "name": "library", "library": str(Path(folder).resolve()),
                                   "out_dir": str(out), "settings": settings})
    return LibraryRun("library", queue, job, str(out))


def end_run(run: LibraryRun) -> None:
    """Remove what the run exported for its job (the scene's meshes); the report stays."""
    if run.mesh_dir:
        import shutil

        shutil.rmtree(run.mesh_dir, ignore_errors=True)


def read_rows(report_json: str | Path) -> tuple[list[dict], dict]:
    """The report's rows sorted by (measured or predicted) savings, largest first, and its totals."""
    data = json.loads(Path(report_json).read_text())
    rows = sorted(data["rows"], key=lambda r: -(r.get("saved_bytes") or r.get("predicted_savings") or 0))
    return rows, data["totals"]
