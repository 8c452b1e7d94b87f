"""The Compress feature: the panel's settings -> a compress session (`compress_session`) watched in the
background; its results loaded as previews and listed in the panel; Cancel, the proxy's toggle, removing a result,
the output folder, and the one-click decimation a verdict offers."""
from __future__ import annotations

import json
from pathlib import Path

import bpy
import numpy as np

from . import compress_session, previews, settings_fields
from .job import most_trainings
from .job_watcher import JobWatcher, job_python, notify


def request_from_props(props) -> compress_session.Request:
    """Panel settings -> compress_session.Request (preset, or target quality, or byte budget; time limit; device)."""
    overrides = {**settings_fields.request_fields(props), "steps": None}  # the core's declared settings
    preset = props.preset
    if props.mode == "TARGET":
        overrides["target_mse"] = compress_session.QUALITY_LEVELS[props.target.lower()]
    elif props.mode == "BUDGET":
        overrides["budget_kb"] = float(props.budget_kb)
    return compress_session.Request(preset=preset, overrides=overrides, out_dir=props.output_dir)


def _read_report(report_path: str) -> dict:
    """The job's report ({} when it cannot be read: the row then shows what the job's result event said)."""
    try:
        report = json.loads(Path(report_path).read_text())
    except (OSError, ValueError):
        return {}
    return report if isinstance(report, dict) else {}


def _verdict(report: dict) -> str:
    """The job's comparison with what the user could ship instead: the final verdict (the model as shipped against
    the compact decimation at the same measured MSE) when there is one, else the verdict before training."""
    final = (report.get("decisions") or {}).get("final") or {}
    return str(final.get("message") or (report.get("assessment") or {}).get("message") or "")


def _shipped_flip(report: dict) -> float:
    """FLIP of the file as shipped, its look included, on the held-out views (0: a bare shape, or not scored)."""
    flip = (report.get("quality_as_shipped") or {}).get("flip")
    return float(flip) if isinstance(flip, (int, float)) else 0.0


def _store_results(scene, session) -> None:
    for obj_name, loaded in session.loaded.items():
        res = loaded["result"]
        item = next((r for r in scene.nbvh_results if r.object_name == obj_name), None) or scene.nbvh_results.add()
        item.object_name = obj_name
        item.model_path = res["path"]
        item.report_path = res["files"]["report"]
        item.image_name = loaded["image"]
        item.proxy_name = loaded["proxy"]
        item.nbvh_bytes = res["bytes"]
        q = res.get("quality") or {}
        item.mse = q.get("mse") or 0.0
        item.iou = q.get("silhouette_iou") or 0.0
        item.train_seconds = res.get("train_seconds") or 0.0
        item.blender_bytes = session.blender_bytes[obj_name]["total"]
        report = _read_report(res["files"]["report"])
        item.verdict = _verdict(report)
        item.flip = _shipped_flip(report)
    paths = compress_session.write_scene_report(session)
    if paths:
        scene.nbvh_props.report_html = str(paths[1])


def _advance(session) -> bool:
    """One tick of the compress session: step its job queue, mirror progress into the panel, load finished
    results; at the end, store the results and say how it went. False once it has ended."""
    scene = bpy.context.scene
    session.queue.step()
    props = scene.nbvh_props
    job = session.queue.active()
    if job is not None:
        props.progress = job.fraction
        phase = job.progress.get("phase", "starting")
        doing = job.progress.get("message", "") if phase == "plan" else ""  # the plan: what it measures now
        props.phase = f"{job.name}: {phase}" + (f" ({doing[:60]})" if doing else "")
        props.eta = format_eta(job.eta_s(), session.queue.eta_s(), job.clock.trainings, job.request)
    warnings = [f"{session.objects.get(j.id, j.name)}: {w}" for j in session.queue.jobs for w in j.log]
    props.warnings = "; ".join(warnings[-3:])[:400]
    compress_session.finish_done(session, scene)
    if session.queue.pending():
        return True
    _store_results(scene, session)
    compress_session.end_session(session)
    props.running = False
    props.progress = 1.0
    props.phase = "done" if not session.failures else "finished with errors"
    props.last_error = "; ".join(f"{k}: {v}" for k, v in session.failures.items())
    props.last_note = "; ".join(f"{k} kept as a mesh: {v}" for k, v in session.kept_as_mesh.items())
    props.decimations = json.dumps(session.decimations)
    if props.show_image and session.loaded:
        previews.show_image(bpy.data.images.get(next(iter(session.loaded.values()))["image"]))
    done = [f"{name}: {loaded['result']['bytes'] / 1024:,.1f} KB" for name, loaded in session.loaded.items()]
    notify(f"NBVH: {props.phase}", done + [f"{k}: {v}" for k, v in session.failures.items()]
           + [f"{k}: kept as a mesh" for k in session.kept_as_mesh] + [f"results in {session.out_dir}"],
           "ERROR" if session.failures else "INFO")
    return False


def _stop(session) -> None:
    session.queue.cancel_all()
    compress_session.end_session(session)


#: The running compress session (one at a time).
WATCHER = JobWatcher("compression", _advance, _stop)


def format_eta(this_s: float | None, all_s: float | None, trainings: int, request: dict) -> str:
    """'35 s', '35 s, all 2 min' (more objects queued), '+ up to 2 more trainings' for a target search."""
    def fmt(x: float) -> str:
        return f"{x:.0f} s" if x < 90 else f"{x / 60:.0f} min"

    if this_s is None:
        return ""
    text = fmt(this_s)
    if all_s is not None and all_s > this_s + 1:
        text += f", all {fmt(all_s)}"
    settings = request.get("settings") or {}
    if trainings < most_trainings(settings):
        text += f" (at most; a target search trains up to {most_trainings(settings)} times)"
    return text


def compress_disabled_reason(context) -> str:
    """Why Compress cannot run now ('' when it can): shown on the greyed-out button and in the panel."""
    if WATCHER.running:
        return "a compression is running (Cancel it, or wait for it to finish)"
    if not context.selected_objects:
        return "select one or more mesh objects to compress"
    return ""


def selection_key(context) -> str:
    """The selection a message was about: a message about other objects is not shown (it is stale)."""
    return "|".join(sorted(o.name for o in context.selected_objects))


class NBVH_OT_compress(bpy.types.Operator):
    """Compress the selected objects into neural geometry (.nbvh) in a background process"""

    bl_idname = "nbvh.compress"
    bl_label = "Compress to NBVH"
    bl_options = {"REGISTER"}

    @classmethod
    def poll(cls, context):
        why = compress_disabled_reason(context)
        if why and hasattr(cls, "poll_message_set"):  # Blender 3.0+: the greyed-out button's tooltip says why
            cls.poll_message_set(why)
        return not why

    resume: bpy.props.BoolProperty(default=False, options={"HIDDEN"})

    def execute(self, context):
        props = context.scene.nbvh_props
        req = request_from_props(props)
        req.resume = self.resume
        try:
            session, refusals = compress_session.start(context, list(context.selected_objects), req,
                                                       job_python(context))
        except RuntimeError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        for msg in refusals:
            self.report({"WARNING"}, msg)
        if not session.objects:
            props.last_error = "; ".join(refusals) or "nothing to compress"
            props.message_selection = selection_key(context)
            self.report({"ERROR"}, "nothing to compress: " + props.last_error)
            return {"CANCELLED"}
        props.running, props.progress, props.phase, props.last_error = True, 0.0, "starting", ""
        props.last_note = props.warnings = ""
        props.message_selection = selection_key(context)
        WATCHER.start(session)
        return {"FINISHED"}


class NBVH_OT_cancel(bpy.types.Operator):
    """Stop the running and queued compression jobs; their temporary files are removed"""

    bl_idname = "nbvh.cancel"
    bl_label = "Cancel"

    def execute(self, context):
        WATCHER.cancel()
        props = context.scene.nbvh_props
        props.running, props.phase = False, "cancelled"
        self.report({"INFO"}, "NBVH: compression cancelled; earlier results are kept")
        return {"FINISHED"}


class NBVH_OT_toggle_preview(bpy.types.Operator):
    """Show or hide the neural point-cloud proxy of this result"""

    bl_idname = "nbvh.toggle_preview"
    bl_label = "Show/Hide Proxy"
    object_name: bpy.props.StringProperty()

    def execute(self, context):
        proxy = previews.find_proxy(bpy.data.objects.get(self.object_name))
        if proxy is None:
            self.report({"WARNING"}, f"no proxy for '{self.object_name}'")
            return {"CANCELLED"}
        proxy.hide_viewport = not proxy.hide_viewport
        proxy.hide_render = proxy.hide_viewport
        return {"FINISHED"}


class NBVH_OT_open_folder(bpy.types.Operator):
    """Open the folder the results are written to in the system's file browser"""

    bl_idname = "nbvh.open_folder"
    bl_label = "Open Output Folder"

    def execute(self, context):
        folder = compress_session.output_dir(context.scene.nbvh_props.output_dir)
        folder.mkdir(parents=True, exist_ok=True)
        bpy.ops.wm.path_open(filepath=str(folder))
        return {"FINISHED"}


class NBVH_OT_remove_result(bpy.types.Operator):
    """Remove this result's previews and files (the original object is not touched)"""

    bl_idname = "nbvh.remove_result"
    bl_label = "Remove Result"
    object_name: bpy.props.StringProperty()

    def execute(self, context):
        scene = context.scene
        idx = next((i for i, r in enumerate(scene.nbvh_results) if r.object_name == self.object_name), None)
        if idx is None:
            return {"CANCELLED"}
        item = scene.nbvh_results[idx]
        previews.remove_all(self.object_name)
        try:
            files = json.loads(Path(item.report_path).read_text()).get("files", {})
        except (OSError, ValueError):
            files = {}
        previews.delete_files({"files": files})
        scene.nbvh_results.remove(idx)
        return {"FINISHED"}


def decimation_offers(context) -> dict:
    """{object name: offer} of the selected objects the last verdicts kept as meshes with a winning decimation."""
    try:
        offers = json.loads(context.scene.nbvh_props.decimations or "{}")
    except ValueError:
        return {}
    selected = {o.name for o in context.selected_objects}
    return {n: o for n, o in offers.items() if n in selected and isinstance(o, dict) and "ratio" in o}


class NBVH_OT_apply_decimation(bpy.types.Operator):
    """Add the decimation the verdict measured (it meets the quality level with fewer bytes than a model) as a copy of
    the object: new mesh data from the job's NAME.glb, the object's own materials, UVs and transform. Undoable;
    the original object is not touched"""

    bl_idname = "nbvh.apply_decimation"
    bl_label = "Use the decimation"
    bl_options = {"REGISTER", "UNDO"}

    object_name: bpy.props.StringProperty()
    ratio: bpy.props.FloatProperty(min=0.0, max=1.0)
    glb: bpy.props.StringProperty(description="The measured decimation the job wrote (NAME.glb)")

    def execute(self, context):
        obj = bpy.data.objects.get(self.object_name)
        if obj is None or obj.type != "MESH":
            self.report({"ERROR"}, f"{self.object_name!r} is not a mesh object")
            return {"CANCELLED"}
        if not self.glb:  # no file from the job (an older result): Blender's own decimation at the same share
            mod = obj.modifiers.get("NBVH decimation") or obj.modifiers.new("NBVH decimation", "DECIMATE")
            mod.decimate_type, mod.ratio = "COLLAPSE", self.ratio
            self.report({"INFO"}, f"{obj.name}: Decimate modifier, ratio {self.ratio:.4f}")
            return {"FINISHED"}
        try:
            copy = decimated_copy(obj, Path(self.glb))
        except (OSError, ValueError) as exc:
            self.report({"ERROR"}, f"{obj.name}: the decimation could not be read: {exc}")
            return {"CANCELLED"}
        for o in context.selected_objects:
            o.select_set(False)
        copy.select_set(True)
        context.view_layer.objects.active = copy
        self.report({"INFO"}, f"{copy.name}: {len(copy.data.polygons):,} triangles, the measured decimation")
        return {"FINISHED"}


def decimated_copy(obj, glb: Path):
    """A new object beside `obj` (its collections, transform and material slots) whose mesh data is the decimation
    in `glb` (object-local coordinates, as the job was sent them); `obj` and its data are not modified."""
    try:
        from .nbvh_core.protocol.glb_reader import read_glb
    except ImportError:
        from nbvh_core.protocol.glb_reader import read_glb
    arrays = read_glb(glb.read_bytes(), glb.name)
    faces = arrays["faces"]
    mesh = bpy.data.meshes.new(f"{obj.data.name} NBVH decimation")
    mesh.from_pydata(arrays["positions"].astype(float).tolist(), [], faces.tolist())
    n_slots = len(obj.material_slots)
    for slot in obj.material_slots:
        mesh.materials.append(slot.material)
    if n_slots:
        mesh.polygons.foreach_set("material_index", np.clip(arrays["face_material"], 0, n_slots - 1).astype(np.int32))
    if arrays["uvs"] is not None:
        layer = mesh.uv_layers.new(name="UVMap")
        layer.data.foreach_set("uv", arrays["uvs"][faces.reshape(-1)].astype(np.float32).reshape(-1))
    if arrays["normals"] is not None:
        mesh.polygons.foreach_set("use_smooth", np.ones(len(faces), bool))
    mesh.update()
    copy = bpy.data.objects.new(f"{obj.name} decimated", mesh)
    copy.matrix_world = obj.matrix_world.copy()
    for collection in obj.users_collection:
        collection.objects.link(copy)
    return copy


CLASSES = (NBVH_OT_compress, NBVH_OT_cancel, NBVH_OT_apply_decimation, NBVH_OT_toggle_preview, NBVH_OT_open_folder,
           NBVH_OT_remove_result)
