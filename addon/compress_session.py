"""The compress session: the add-on's one code path from a selection to its results, shared by the panel's
Compress (`compress_ops`) and the headless compress.py: selected objects -> exported arrays -> queued background
jobs -> results loaded back -> report.

bpy is used here (export, load back) but torch never is: the jobs run nbvh_core in another process.
"""
from __future__ import annotations

import json
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import bpy
import numpy as np

from . import export, previews, report
from .job import DEFAULT_LEVEL, QUALITY_LEVELS, TARGET_TRAININGS, JobQueue, checkpoint_for, default_python  # noqa: F401  (for callers)


@dataclass
class Request:
    """What the user asked for. preset: nbvh_core preset name (None with no size in `overrides`: sized to the
    default quality level, `settings.settings_from_request`); overrides: nbvh_core Settings fields."""

    preset: str | None = None
    overrides: dict = field(default_factory=dict)
    out_dir: str = ""
    proxy_points: int = 20000
    image_size: int = 256
    load_model: str | None = None  # an existing .nbvh to load back instead of training (one object)
    resume: bool = False  # continue each object's checkpoint (left by a job that died) instead of starting anew


@dataclass
class Session:
    """Jobs of one Compress click (or one compress.py run) and what they produced."""

    queue: JobQueue
    objects: dict = field(default_factory=dict)  # job id -> object name
    blender_bytes: dict = field(default_factory=dict)  # object name -> export.mesh_data_bytes
    loaded: dict = field(default_factory=dict)  # object name -> load_result dict
    failures: dict = field(default_factory=dict)  # object name -> message
    kept_as_mesh: dict = field(default_factory=dict)  # object name -> the "not worth compressing" verdict
    scene_split: dict | None = None  # a scene budget's split, from a job that kept its mesh (trained ones report it)
    decimations: dict = field(default_factory=dict)  # object name -> the decimation that wins (`decimation_offer`)
    triangles: dict = field(default_factory=dict)  # object name -> exported triangles
    textures: dict = field(default_factory=dict)  # object name -> export.asset_textures (images, material slots)
    out_dir: str = ""
    scene_dir: str = ""  # shared meshes of a scene budget (every job reads all of them); removed by end_session


def output_dir(requested: str) -> Path:
    """The folder for results: the requested one, else beside the .blend (`//nbvh`), else a temp folder."""
    # Absolute: the job process runs in its own temporary folder, where a relative path would point elsewhere.
    if requested:
        return Path(bpy.path.abspath(requested)).resolve()
    if bpy.data.filepath:
        return Path(bpy.path.abspath("//nbvh")).resolve()
    return Path(tempfile.gettempdir()) / "nbvh"


def safe_name(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name) or "object"


def checkpoint_path(out_dir: str | Path, obj_name: str) -> Path | None:
    """The checkpoint a job that died while training `obj_name` left in out_dir, or None."""
    p = checkpoint_for(Path(out_dir) / f"{safe_name(obj_name)}.nbvh")
    return p if p.exists() else None


def start(context, objects, req: Request, python: str | None = None) -> tuple[Session, list[str]]:
    """Export `objects` and queue one job each. Returns the session and the refusals (messages naming the
    objects that cannot be compressed). Raises RuntimeError when no Python can run the jobs."""
    python = python or default_python()
    if not python:
        raise RuntimeError("no Python with PyTorch and nbvh_core found: set one in the add-on preferences or "
                           "press 'Install dependencies'")
    out_dir = output_dir(req.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    session = Session(queue=JobQueue(python), out_dir=str(out_dir))
    refusals = []
    depsgraph = context.evaluated_depsgraph_get()
    for obj in objects:
        try:
            # Bytes of the mesh as Blender stores it: the evaluated one, so modifiers count.
            verts, tris, session.blender_bytes[obj.name], look = export.evaluated_triangles(obj, depsgraph)
            session.triangles[obj.name] = len(tris)
            session.textures[obj.name] = export.asset_textures(obj)
        except export.ExportError as exc:
            refusals.append(str(exc))
            continue
        name = safe_name(obj.name)
        job_request = {"name": name, "out_dir": str(out_dir), "proxy_points": req.proxy_points,
                       "settings": {"preset": req.preset, **req.overrides},
                       "camera": previews.camera_for(context, obj, req.image_size, req.image_size)}
        if req.load_model:
            job_request["model"] = str(Path(bpy.path.abspath(req.load_model)).resolve())
        if req.resume:
            checkpoint = checkpoint_path(out_dir, obj.name)
            if checkpoint is None:
                refusals.append(f"{obj.name!r} has no training to resume in {out_dir}")
                continue
            job_request["resume"] = str(checkpoint)
        job = session.queue.submit(name, job_request)
        mesh_path = job.workdir / "mesh.npz"
        np.savez(mesh_path, vertices=verts, faces=tris, **look)
        job.request["mesh"] = str(mesh_path)
        session.objects[job.id] = obj.name
    scene_jobs = [j for j in session.queue.jobs if j.id in session.objects]
    if "budget_kb" in req.overrides and len(scene_jobs) > 1 and not req.load_model:
        # One budget for the whole selection, shared by need (detail, size on screen) inside every job
        # (nbvh_core.decision.scene_budget, deterministic): the jobs have not started yet, so their requests can
        # still carry the full list of exported meshes.
        # A job's own folder goes when it finishes, so the shared copies live in a session folder.
        objs = [bpy.data.objects[session.objects[j.id]] for j in scene_jobs]
        weights = screen_weights(context, objs)
        session.scene_dir = tempfile.mkdtemp(prefix="nbvh-scene-")
        shared = []
        for i, j in enumerate(scene_jobs):
            dst = Path(session.scene_dir) / f"{i}.npz"
            shutil.copyfile(j.request["mesh"], dst)
            shared.append(str(dst))
        for i, j in enumerate(scene_jobs):
            j.request["settings"].pop("budget_kb", None)
            j.request["scene"] = {"budget_kb": req.overrides["budget_kb"], "meshes": shared,
                                  "names": [session.objects[x.id] for x in scene_jobs], "weights": weights, "index": i}
    return session, refusals


def end_session(session: Session) -> None:
    """Remove what the session kept for all its jobs (the scene's shared meshes); results stay."""
    if session.scene_dir:
        shutil.rmtree(session.scene_dir, ignore_errors=True)


def screen_weights(context, objects) -> list[float]:
    """Relative size on screen of each object: (world bounding-box diagonal / distance to the scene camera)^2,
    normalised to mean 1 (without a camera: the diagonal squared)."""
    from mathutils import Vector

    cam = context.scene.camera
    raw = []
    for obj in objects:
        corners = [obj.matrix_world @ Vector(c) for c in obj.bound_box]
        lo = Vector([min(c[a] for c in corners) for a in range(3)])
        hi = Vector([max(c[a] for c in corners) for a in range(3)])
        diag = (hi - lo).length
        dist = ((lo + hi) / 2 - cam.matrix_world.translation).length if cam else 1.0
        raw.append((diag / max(dist, 1e-6)) ** 2)
    mean = sum(raw) / len(raw) if raw and sum(raw) > 0 else 1.0
    return [max(r / mean, 1e-3) for r in raw]


def finish_done(session: Session, scene) -> None:
    """Load previews of jobs that finished since the last call; record failures."""
    for job in session.queue.jobs:
        obj_name = session.objects.get(job.id)
        if obj_name is None or obj_name in session.loaded or obj_name in session.failures \
                or obj_name in session.kept_as_mesh:
            continue
        if job.state == "done":
            obj = bpy.data.objects.get(obj_name)
            if obj is None:
                session.failures[obj_name] = "the object was deleted while it was being compressed"
                continue
            session.loaded[obj_name] = previews.load_result(obj, job.result, scene)
            session.loaded[obj_name]["result"] = job.result
        elif job.state == "skipped":
            session.kept_as_mesh[obj_name] = job.verdict
            session.scene_split = session.scene_split or job.scene_split
            if job.decimation:
                glb = next((f for f in job.kept_files if f.endswith(".glb")), None)
                session.decimations[obj_name] = decimation_offer(job.decimation, session.triangles.get(obj_name, 0),
                                                                 glb)
        elif job.state in ("failed", "cancelled"):
            session.failures[obj_name] = job.error or job.state


def decimation_offer(decimation: dict, source_triangles: int, glb: str | None = None) -> dict:
    """What the panel offers for an object kept as a mesh: the measured decimation itself (`glb`: the NAME.glb the
    job wrote, added as a copy of the object), with its triangles, image MSE and bytes (plain and as a compact
    mesh); ratio: its share of the object's triangles (a Decimate modifier's, where no file was written)."""
    ratio = min(1.0, decimation["triangles"] / max(source_triangles, 1))
    return {"ratio": ratio, "glb": glb or "", "triangles": int(decimation["triangles"]), "mse": float(decimation["mse"]),
            "resident_bytes": int(decimation["resident_bytes"]),
            "compact_bytes": int(decimation.get("compact_bytes") or 0)}


def write_scene_report(session: Session) -> tuple[Path, Path] | None:
    entries = []
    for obj_name, loaded in session.loaded.items():
        job_report = json.loads(Path(loaded["result"]["files"]["report"]).read_text())
        images, slots = session.textures.get(obj_name, ({}, 0))
        entries.append(report.object_entry(obj_name, session.blender_bytes[obj_name], job_report, images, slots))
    if not entries and not session.kept_as_mesh:
        return None
    kept = [{"name": n, "blender_mesh_bytes": session.blender_bytes[n], "verdict": v,
             "decimation": session.decimations.get(n), "textures": session.textures.get(n, ({}, 0))[0]}
            for n, v in session.kept_as_mesh.items()]
    return report.write_report(report.build_report(entries, kept, session.scene_split), session.out_dir)
