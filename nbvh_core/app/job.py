"""A background compression job: the process the Blender add-on (or compress.py) starts and watches.

    python -m nbvh_core job REQUEST.json

REQUEST.json (written by the add-on):
  {"name": str, "mesh": "mesh.npz" (arrays `vertices` (V, 3) float32 and `faces` (F, 3) int32, object-local
   coordinates), "out_dir": str, "settings": {preset: str, overrides...},
   "camera": {"position": [3], "target": [3], "up": [3], "fov_deg": float, "width": int, "height": int}
             (object-local coordinates; optional), "proxy_points": int}

Outputs: the result bundle (`result_bundle`: NAME.nbvh, NAME.report.json, NAME.preview.png from the request's
camera (or an orbit view), NAME.reference.png, NAME.points.npy object-local proxy points) in out_dir, renamed into
place together at the very end (a failed, cancelled or killed re-run leaves the previous result of the object
exactly as it was), and named in the final `result` event (the only marker of a finished job).
Training writes `.NAME.nbvh.checkpoint` in out_dir every 60 s (`outputs.checkpoint_for`); a request with "resume": PATH continues it (the
add-on offers this after a crash). "force": true trains even when the verdict is "not worth compressing"
(otherwise the job ends in seconds with a `verdict` event and an `error` event of kind "not_worth", exit 4).
Events are JSON lines on stdout (see `events.py`); errors end with an `error` event and exit code != 0.
A request with "kind": "batch" runs a library (`run_batch_job`: the add-on's scene memory report and "Compress
library...").
"""
from __future__ import annotations

import json
import sys
import time
import traceback
from pathlib import Path

import numpy as np

from ..protocol.events import json_lines
from ..protocol import events as wire


#: The request's fields and their JSON types (the request file is data: anything else is refused in one line).
REQUEST_FIELDS = {"kind": str, "name": str, "mesh": str, "out_dir": str, "settings": dict, "camera": dict,
                  "proxy_points": int, "resume": str, "force": bool, "model": str, "scene": dict, "library": str,
                  "measure_only": bool, "address": str}
MAX_REQUEST_BYTES = 1 << 20


def check_request(request, where: str = "request") -> dict:
    """Refuse (ValueError, one line) a request that is not an object of REQUEST_FIELDS with their types, whose name
    is not a plain object name, or whose settings are not valid settings (`settings.settings_from_dict`)."""
    from ..planning.settings import preset, settings_from_dict

    if not isinstance(request, dict):
        raise ValueError(f"{where}: a job request must be a JSON object")
    for key, value in request.items():
        want = REQUEST_FIELDS.get(key)
        if want is None:
            raise ValueError(f"{where}: unknown request field {str(key)[:40]!r}")
        if value is not None and (not isinstance(value, want) or (want is int and isinstance(value, bool))):
            raise ValueError(f"{where}: request field {key!r} must be a {want.__name__}")
    missing = [k for k in (("name", "library", "out_dir") if request.get("kind") == "batch"
                           else ("name", "mesh", "out_dir")) if not request.get(k)]
    if missing or request.get("kind") not in (None, "batch"):
        raise ValueError(f"{where}: the request needs {', '.join(missing) or 'a known kind'}")
    name = request["name"]
    if len(name) > 255 or any(c in name for c in "/\\\0") or name in (".", ".."):
        raise ValueError(f"{where}: {name[:40]!r} is not a plain object name")
    if not 0 <= int(request.get("proxy_points") or 0) <= 10_000_000:
        raise ValueError(f"{where}: proxy_points must be in [0, 10000000]")
    spec = dict(request.get("settings") or {})
    base = preset(str(spec.pop("preset", None) or "default"))
    settings_from_dict({**base.to_dict(), **spec}, f"{where}: settings")
    return request


def run_batch_job(request: dict, events, should_cancel) -> dict:
    """A library request ({"kind": "batch", "name", "library": folder or list file, "out_dir", "settings",
    "measure_only": bool, "address": optional}): `batch.run_batch`, whose events (progress with the fraction of
    assets done, one `asset` event per row) reach the add-on; the `result` event names the report."""
    from .library_batch import run_batch

    summary = run_batch(request["library"], request["out_dir"], dict(request.get("settings") or {}), events,
                        should_cancel, address=request.get("address"), measure_only=bool(request.get("measure_only")))
    event = wire.result(name=request["name"], path=summary["html"], report=summary["html"], json=summary["json"],
                        totals=summary["totals"])
    events(event)
    return event


def run_job(request: dict, events, should_cancel) -> dict:
    """Run one request (see module docstring); returns the `result` event it emits."""
    if request.get("kind") == "batch":
        return run_batch_job(request, events, should_cancel)
    started_at = time.perf_counter()  # the run's wall counts the mesh's loading (run_wall)
    from ..geometry.mesh_arrays import mesh_from_npz
    from ..protocol.outputs import OutputLock, check_outputs
    from .pipeline import resume_settings
    from .result_bundle import bundle_paths
    from ..planning.settings import settings_from_request

    name = request["name"]
    out_dir = Path(request["out_dir"])
    out_dir.mkdir(parents=True, exist_ok=True)
    mesh = mesh_from_npz(request["mesh"], name)  # data only: pickled or oversized arrays are refused
    for msg in mesh.repairs:
        events(wire.warning(message=msg))
    settings = settings_from_request(request.get("settings") or {})
    scene_split = None
    if request.get("scene"):
        settings, scene_split = _scene_share(request["scene"], settings, events)
    if request.get("resume"):
        settings = resume_settings(request["resume"], mesh)
    if request.get("force"):
        settings = settings.with_overrides(force=True)
    model_path = out_dir / f"{name}.nbvh"
    files = {role: str(path) for role, path in bundle_paths(model_path).items()}
    if request.get("model"):
        files["model"] = str(request["model"])  # loaded, never rewritten
    # A re-run replaces the object's previous result (only once the new one is complete); an input never.
    inputs = [Path(request["mesh"])] + ([Path(request["model"])] if request.get("model") else [])
    check_outputs([Path(p) for k, p in files.items() if not (k == "model" and request.get("model"))], inputs,
                  overwrite=True)
    with OutputLock(model_path):
        return _run_locked(request, events, should_cancel, mesh, settings, scene_split, files, name, started_at)


def _write_kept_mesh(mesh, assessment, model_path: Path, events, decimator=None) -> None:
    """The kept mesh's files (`kept_mesh.kept_mesh_files`: NAME.glb, NAME.compact.cmsh) beside where the model would
    have gone, each written atomically, announced in one `written` event (files, kind, triangles, bytes each)."""
    from .alternatives import winning_decimation
    from ..protocol.outputs import write_atomic
    from .kept_mesh import kept_mesh_files

    files = kept_mesh_files(mesh, assessment, winning_decimation(mesh, assessment, decimator))
    paths = []
    for suffix, data in files.items():
        path = model_path.with_name(model_path.stem + suffix)
        write_atomic(path, data)
        paths.append(str(path))
    if paths:
        dec = assessment.alternatives.decimation if assessment.recommendation == "decimate" else None
        events(wire.written(files=paths, kind="decimation" if dec else "mesh",
                            triangles=int(dec.triangles) if dec else mesh.n_triangles,
                            bytes={Path(p).name: len(d) for p, d in zip(paths, files.values())}))


def _run_locked(request, events, should_cancel, mesh, settings, scene_split, files, name,
                started_at: float | None = None) -> dict:
    from ..protocol.outputs import checkpoint_for
    from ..protocol.process import NotWorthCompressing
    from .pipeline import compress_mesh
    from .result_bundle import ROLES, LoadedResult, View, make_bundle, write_bundle
    from ..rendering.render import Camera, orbit_cameras

    model_path = Path(files["model"])
    if request.get("model"):
        # Load an existing model instead of training (a damaged file fails here with NBVHFileError).
        from ..storage.fileformat import load_nbvh, read_info

        events(wire.phase(phase="load", message=request["model"]))
        model = load_nbvh(request["model"])
        info = read_info(request["model"])
        result = LoadedResult(model, info, str(request["model"]))
    else:
        try:
            result = compress_mesh(mesh, settings, None, events=events, should_cancel=should_cancel,
                                   checkpoint_path=checkpoint_for(model_path), resume_from=request.get("resume"),
                                   started_at=started_at)
        except NotWorthCompressing as exc:  # the mesh wins: the same files as the CLI's, then the verdict ends it
            _write_kept_mesh(mesh, exc.assessment, model_path, events, exc.decimator)
            raise
    cam_spec = request.get("camera")
    view = View(orbit_cameras(1)[0])
    if cam_spec:
        tf = mesh.transform
        pos = tf.to_normalised(np.asarray([cam_spec["position"]], float))[0]
        tgt = tf.to_normalised(np.asarray([cam_spec["target"]], float))[0]
        view = View(Camera(position=pos, target=tgt, up=np.asarray(cam_spec.get("up", [0, 0, 1]), float),
                           fov_deg=float(cam_spec.get("fov_deg", 40.0))),
                    int(cam_spec.get("width", 256)), int(cam_spec.get("height", 256)))
    events(wire.phase(phase="preview", message=f"{view.width}x{view.height} image, proxy points"))
    extra = {"name": name, "files": files, **({"scene_split": scene_split} if scene_split is not None else {})}
    roles = tuple(r for r in ROLES if not (r == "model" and request.get("model")))
    bundle = make_bundle(result, mesh, view, roles, proxy_points=int(request.get("proxy_points", 20000)),
                         seed=settings.seed, extra=extra)
    write_bundle({role: Path(p) for role, p in files.items()}, bundle, should_cancel=should_cancel)
    if not request.get("model"):
        checkpoint_for(model_path).unlink(missing_ok=True)
    report = bundle.report
    event = wire.result(name=name, path=str(model_path), bytes=result.file_bytes, files=files,
                        quality=report["quality"], train_seconds=round(float(result.training.seconds), 2),
                        device=result.training.device)
    events(event)
    return event


def _scene_share(scene: dict, settings, events):
    """This object's share of a scene budget: {"budget_kb", "meshes": [npz paths, all objects, in order], "names",
    "weights", "index"}. Every job computes the same plan (sizing.plan_scene, deterministic) and takes entry
    `index`; returns (settings with that size, the split for the report). An object the split excludes (its mesh no
    larger than the model its share buys) is sized at the share it turned down: its verdict then ends its job
    before training."""
    import dataclasses

    from ..geometry.mesh_arrays import read_mesh_arrays
    from ..geometry.mesh import mesh_from_arrays
    from ..planning.sizing import plan_scene

    meshes = []
    for path in scene["meshes"]:
        arrays = read_mesh_arrays(path)
        meshes.append(mesh_from_arrays(arrays["vertices"], arrays["faces"]))
    names = scene.get("names") or [str(k) for k in range(len(meshes))]
    plan = plan_scene(meshes, float(scene["budget_kb"]) * 1024, settings, scene.get("weights"), names)
    i = int(scene["index"])
    split = {"budget_kb": scene["budget_kb"], "level_mse": plan["level"], "total_bytes": plan["total"],
             "objects": plan["objects"]}
    base = plan["base"]
    if i in plan["excluded"]:
        events(wire.phase(phase="plan", message="scene budget: this object gets nothing (its mesh is no larger than "
                                                "its model)", scene_split=split))
        return dataclasses.replace(base, log2_table=plan["declined_log2"][i]), split
    shared = len(meshes) - len(plan["excluded"])
    kb = plan["bytes"][i] / 1024
    events(wire.phase(phase="plan", message=f"scene budget {scene['budget_kb']:g} KB shared by need over {shared} "
                                            f"objects: this one gets T=2^{plan['log2'][i]} (~{kb:.0f} KB, predicted "
                                            f"MSE {plan['predicted_mse'][i]:.4g})", scene_split=split))
    return dataclasses.replace(base, log2_table=plan["log2"][i]), split


def main(argv: list[str]) -> int:
    """Entry of `python -m nbvh_core job REQUEST.json`: the exit code and the final `error` event's kind come from
    `process.outcome`, as the CLI's do; a crash's event carries its traceback."""
    from ..protocol.process import install_cancel_handlers, outcome

    events = json_lines(sys.stdout)
    should_cancel = install_cancel_handlers()
    try:
        path = Path(argv[0])
        if path.stat().st_size > MAX_REQUEST_BYTES:
            raise ValueError(f"{path}: a job request is at most {MAX_REQUEST_BYTES} bytes")
        run_job(check_request(json.loads(path.read_text()), str(path)), events, should_cancel)
        return 0
    except (Exception, KeyboardInterrupt) as exc:
        end = outcome(exc)
        event = wire.error(kind=end.kind,
                           message=f"{type(exc).__name__}: {exc}" if end.kind == "input" else end.message)
        if end.kind == "crash":
            event["traceback"] = traceback.format_exc()
        events(event)
        return end.code
    finally:
        sys.stdout.flush()
