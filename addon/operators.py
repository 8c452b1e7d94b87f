"""Operators: Compress (starts jobs, watched by a timer so the UI never blocks), Cancel, previews, report,
remove results, install dependencies."""
from __future__ import annotations

import json
import webbrowser
from dataclasses import dataclass
from pathlib import Path

import bpy

from . import engine, library, previews
from .job import check_python, core_env, default_python, most_trainings

@dataclass
class AddonState:
    """What the add-on holds between timer ticks (one Blender instance, one of each at a time)."""

    session: object = None           # engine.Session of the current Compress click
    library: object = None           # library.LibraryRun of the library batch or scene report
    installer: object = None         # installer.Installer while dependencies install
    installer_python: str = ""       # the Python the installer sets up


STATE = AddonState()


def installing() -> bool:
    """True while the dependency installer runs (the panel shows its progress instead of the buttons)."""
    return STATE.installer is not None


def addon_prefs(context):
    addon = context.preferences.addons.get(__package__)
    return addon.preferences if addon else None


def _python(context) -> str:
    prefs = addon_prefs(context)
    return (prefs.python_path if prefs and prefs.python_path else "") or default_python()


def request_from_props(props) -> engine.Request:
    """Panel settings -> engine.Request (preset, or target quality, or byte budget; time limit; device)."""
    overrides = {"time_limit_s": float(props.time_limit), "device": props.device.lower(), "steps": None,
                 "appearance_target": props.look.lower(), "mesh_layout": props.compare_with.lower()}
    if props.force:
        overrides["force"] = True
    preset = props.preset
    if props.mode == "TARGET":
        overrides["target_mse"] = engine.QUALITY_LEVELS[props.target.lower()]
    elif props.mode == "BUDGET":
        overrides["budget_kb"] = float(props.budget_kb)
    return engine.Request(preset=preset, overrides=overrides, out_dir=props.output_dir)


def _verdict(report_path: str) -> str:
    """The job's comparison with what the user could ship instead: the final verdict (the model as shipped against
    the compact decimation at the same measured MSE) when there is one, else the verdict before training."""
    try:
        report = json.loads(Path(report_path).read_text())
    except (OSError, ValueError):
        return ""
    final = (report.get("decisions") or {}).get("final") or {}
    return str(final.get("message") or (report.get("assessment") or {}).get("message") or "")


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
        item.verdict = _verdict(res["files"]["report"])
    paths = engine.write_scene_report(session)
    if paths:
        scene.nbvh_props.report_html = str(paths[1])


def _tick():
    """Timer: advance the job queue, mirror progress into the panel, load finished results."""
    session = STATE.session
    if session is None:
        return None
    scene = bpy.context.scene
    session.queue.step()
    props = scene.nbvh_props
    job = session.queue.active()
    if job is not None:
        props.progress = job.fraction
        props.phase = f"{job.name}: {job.progress.get('phase', 'starting')}"
        props.eta = format_eta(job.eta_s(), session.queue.eta_s(), job.clock.trainings, job.request)
    warnings = [f"{session.objects.get(j.id, j.name)}: {w}" for j in session.queue.jobs for w in j.log]
    props.warnings = "; ".join(warnings[-3:])[:400]
    engine.finish_done(session, scene)
    if not session.queue.pending():
        _store_results(scene, session)
        engine.end_session(session)
        props.running = False
        props.progress = 1.0
        props.phase = "done" if not session.failures else "finished with errors"
        props.last_error = "; ".join(f"{k}: {v}" for k, v in session.failures.items())
        props.last_note = "; ".join(f"{k} kept as a mesh: {v}" for k, v in session.kept_as_mesh.items())
        props.decimations = json.dumps(session.decimations)
        STATE.session = None
        if props.show_image and session.loaded:
            previews.show_image(bpy.data.images.get(next(iter(session.loaded.values()))["image"]))
        done = [f"{name}: {loaded['result']['bytes'] / 1024:,.1f} KB" for name, loaded in session.loaded.items()]
        notify(f"NBVH: {props.phase}", done + [f"{k}: {v}" for k, v in session.failures.items()]
               + [f"{k}: kept as a mesh" for k in session.kept_as_mesh] + [f"results in {session.out_dir}"],
               "ERROR" if session.failures else "INFO")
        for area in (bpy.context.screen.areas if bpy.context.screen else []):
            area.tag_redraw()
        return None
    for area in (bpy.context.screen.areas if bpy.context.screen else []):
        if area.type == "VIEW_3D":
            area.tag_redraw()
    return 0.25


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


def notify(title: str, lines: list[str], icon: str = "INFO") -> None:
    """Say that a background run ended (a popup at the mouse; nothing in background mode, where the events are
    printed). Timers have no operator to `report` through."""
    if bpy.app.background:
        return

    def draw(menu, context):
        for line in lines[:8]:
            menu.layout.label(text=line[:120])

    try:
        bpy.context.window_manager.popup_menu(draw, title=title, icon=icon)
    except (RuntimeError, AttributeError):  # no window to show it in (a timer between redraws)
        pass


def compress_disabled_reason(context) -> str:
    """Why Compress cannot run now ('' when it can): shown on the greyed-out button and in the panel."""
    if STATE.session is not None:
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
            session, refusals = engine.start(context, list(context.selected_objects), req, _python(context))
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
        STATE.session = session
        bpy.app.timers.register(_tick, first_interval=0.1)
        return {"FINISHED"}


class NBVH_OT_cancel(bpy.types.Operator):
    """Stop the running and queued compression jobs; their temporary files are removed"""

    bl_idname = "nbvh.cancel"
    bl_label = "Cancel"

    def execute(self, context):
        session = STATE.session
        if session is not None:
            session.queue.cancel_all()
            engine.end_session(session)
        props = context.scene.nbvh_props
        props.running, props.phase = False, "cancelled"
        STATE.session = None
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


class NBVH_OT_open_report(bpy.types.Operator):
    """Open the asset memory report (HTML) in the web browser"""

    bl_idname = "nbvh.open_report"
    bl_label = "Open Report"
    #: Which report: the property of nbvh_props that holds its path (the objects' or the library's).
    which: bpy.props.StringProperty(default="report_html", options={"HIDDEN"})

    def execute(self, context):
        if self.which not in ("report_html", "library_report_html"):
            return {"CANCELLED"}
        path = getattr(context.scene.nbvh_props, self.which)
        if not path or not Path(path).exists():
            self.report({"WARNING"}, "no report yet")
            return {"CANCELLED"}
        if not _open_in_browser(Path(path)):  # no browser registered (a server, a bare desktop): read it here
            text = open_report_text(Path(path))
            self.report({"INFO"}, f"no web browser found: the report is in the Text Editor as '{text.name}' ({path})")
        return {"FINISHED"}


def _open_in_browser(path: Path) -> bool:
    try:
        return bool(webbrowser.open(path.as_uri()))
    except webbrowser.Error:
        return False


def open_report_text(path: Path):
    """Load the report's JSON (beside the HTML) as a Blender text block and show it in a Text Editor if one is
    open; returns the text block."""
    src = path.with_suffix(".json") if path.with_suffix(".json").exists() else path
    name = f"NBVH {src.name}"
    old = bpy.data.texts.get(name)
    if old is not None:
        bpy.data.texts.remove(old)
    text = bpy.data.texts.load(str(src))
    text.name = name
    for area in (bpy.context.screen.areas if bpy.context.screen else []):
        if area.type == "TEXT_EDITOR":
            area.spaces.active.text = text
    return text


class NBVH_OT_open_folder(bpy.types.Operator):
    """Open the folder the results are written to in the system's file browser"""

    bl_idname = "nbvh.open_folder"
    bl_label = "Open Output Folder"

    def execute(self, context):
        folder = engine.output_dir(context.scene.nbvh_props.output_dir)
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


def _install_tick():
    """Timer: advance the dependency installer and mirror it into the preferences; done -> the new Python."""
    inst = STATE.installer
    if inst is None:
        return None
    prefs = addon_prefs(bpy.context)
    state = inst.poll()
    if prefs is not None:
        prefs.install_progress = inst.fraction
        prefs.install_status = f"{inst.phase}: {inst.line}"[:200] if state == "running" else {
            "done": "installed: jobs run with the new environment", "cancelled": "install cancelled",
            "failed": (inst.error.splitlines() or ["failed"])[0][:200]}.get(state, state)
        if state == "done":
            prefs.python_path = STATE.installer_python
    for window in bpy.context.window_manager.windows:
        for area in window.screen.areas:
            area.tag_redraw()
    if state == "running":
        return 0.25
    STATE.installer = None
    return None


class NBVH_OT_install_dependencies(bpy.types.Operator):
    """Create a virtual environment with PyTorch (CPU build) and nbvh_core's dependencies for the background jobs,
    in a background process (progress and Cancel in these preferences)"""

    bl_idname = "nbvh.install_dependencies"
    bl_label = "Install Dependencies"

    @classmethod
    def poll(cls, context):
        return STATE.installer is None

    def execute(self, context):
        from .installer import Installer, default_base_python, install_steps, venv_python

        if not getattr(bpy.app, "online_access", True):  # Blender 4.2+: Preferences > System > Allow Online Access
            self.report({"ERROR"}, "online access is off (Preferences > System > Network > Allow Online Access): "
                                   "pip cannot download PyTorch")
            return {"CANCELLED"}
        venv = Path(bpy.utils.user_resource("SCRIPTS", path="nbvh_venv", create=True))
        req = Path(__file__).resolve().parent / "nbvh_core" / "requirements.txt"
        if not req.exists():  # the repository layout: nbvh_core beside addon/
            req = Path(__file__).resolve().parent.parent / "nbvh_core" / "requirements.txt"
        env = core_env()
        inst = Installer(install_steps(venv, default_base_python(), req), env=env)
        STATE.installer, STATE.installer_python = inst, str(venv_python(venv))
        inst.start()
        bpy.app.timers.register(_install_tick, first_interval=0.25)
        self.report({"INFO"}, f"installing into {venv} in the background")
        return {"FINISHED"}


class NBVH_OT_cancel_install(bpy.types.Operator):
    """Stop the dependency install (the half-made environment is continued by the next install)"""

    bl_idname = "nbvh.cancel_install"
    bl_label = "Cancel Install"

    def execute(self, context):
        inst = STATE.installer
        if inst is not None:
            inst.cancel()
        return {"FINISHED"}


class NBVH_OT_check_python(bpy.types.Operator):
    """Check that the configured Python can run compression jobs"""

    bl_idname = "nbvh.check_python"
    bl_label = "Check Python"

    def execute(self, context):
        ok, msg = check_python(_python(context))
        self.report({"INFO" if ok else "ERROR"}, msg)
        return {"FINISHED"} if ok else {"CANCELLED"}


def _library_settings(props) -> dict:
    """The batch's settings from the panel: the preset or target (a byte budget applies per asset), time limit,
    and *Train even if not worth it*."""
    spec = {"preset": props.preset, "time_limit_s": float(props.time_limit), "device": props.device.lower(),
            "mesh_layout": props.compare_with.lower()}
    if props.force:
        spec["force"] = True
    if props.mode == "TARGET":
        spec["target_mse"] = engine.QUALITY_LEVELS[props.target.lower()]
    elif props.mode == "BUDGET":
        spec["budget_kb"] = float(props.budget_kb)
    return spec


def store_library_rows(props, run) -> None:
    """The finished run's report -> the panel's rows (largest savings first) and totals line."""
    rows, totals = library.read_rows(Path(run.out_dir) / "report.json")
    props.library_rows.clear()
    for r in rows:
        item = props.library_rows.add()
        item.name = run.names.get(r["name"], r["name"])
        item.status = r.get("status") or ""
        item.triangles = int(r.get("triangles") or 0)
        item.resident_bytes = int(r.get("mesh_resident_bytes") or 0)
        item.model_bytes = int(r.get("model_bytes") or r.get("predicted_model_bytes") or 0)
        item.savings = int(r.get("saved_bytes") or r.get("predicted_savings") or 0)
        item.verdict = (r.get("error") or r.get("verdict") or "")[:200]
    saved = totals["saved_bytes"] or totals["predicted_savings_bytes"]
    what = "saved" if totals["saved_bytes"] else "predicted savings"
    props.library_summary = (f"{totals['assets']} objects, resident {totals['resident_before_bytes'] / 1024:,.0f} KB; "
                             f"{what} {saved / 1024:,.0f} KB")
    props.library_report_html = str(Path(run.out_dir) / "report.html")


def _library_tick():
    """Timer: advance the library job, mirror its progress, list its rows when it ends."""
    run = STATE.library
    if run is None:
        return None
    props = bpy.context.scene.nbvh_props
    run.queue.step()
    job = run.job
    props.library_progress = job.fraction
    done, total = job.progress.get("done"), job.progress.get("total")
    props.library_phase = f"{job.progress.get('phase', 'starting')}" + (f" {done}/{total}" if total else "")
    if run.queue.finished(job):
        props.library_running = False
        if job.state == "done":
            store_library_rows(props, run)
            props.library_phase = "finished"
            notify("NBVH: library report ready", [props.library_summary, props.library_report_html])
        else:
            props.library_phase = f"{job.state}: {job.error or ''}"[:300]
            notify(f"NBVH: library run {job.state}", [props.library_phase], "ERROR")
        library.end_run(run)
        STATE.library = None
    for area in (bpy.context.screen.areas if bpy.context.screen else []):
        area.tag_redraw()
    return None if STATE.library is None else 0.25


def start_library_run(props, run) -> None:
    props.library_running, props.library_progress, props.library_phase = True, 0.0, "starting"
    props.library_rows.clear()
    props.library_summary = ""
    STATE.library = run
    run.queue.step()  # starts the job now
    bpy.app.timers.register(_library_tick, first_interval=0.25)


class NBVH_OT_scene_report(bpy.types.Operator):
    """Measure every mesh object of the scene and say which are worth compressing (no training): triangles,
    resident bytes, verdict, predicted savings"""

    bl_idname = "nbvh.scene_report"
    bl_label = "Scene Memory Report"

    @classmethod
    def poll(cls, context):
        return STATE.library is None

    def execute(self, context):
        props = context.scene.nbvh_props
        try:
            run = library.start_scene_report(context, engine.output_dir(props.output_dir), _library_settings(props),
                                             _python(context))
        except RuntimeError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        for msg in run.refusals:
            self.report({"WARNING"}, msg)
        start_library_run(props, run)
        return {"FINISHED"}


class NBVH_OT_compress_library(bpy.types.Operator):
    """Compress a folder of assets (mesh files and .blend files) as a batch in the background, with a library
    memory report"""

    bl_idname = "nbvh.compress_library"
    bl_label = "Compress Library..."

    directory: bpy.props.StringProperty(subtype="DIR_PATH")

    @classmethod
    def poll(cls, context):
        return STATE.library is None

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        props = context.scene.nbvh_props
        folder = bpy.path.abspath(self.directory or props.library_folder)
        try:
            run = library.start_library(folder, engine.output_dir(props.output_dir), _library_settings(props),
                                        _python(context))
        except RuntimeError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        props.library_folder = folder
        start_library_run(props, run)
        return {"FINISHED"}


class NBVH_OT_cancel_library(bpy.types.Operator):
    """Stop the library run; what finished stays in its report"""

    bl_idname = "nbvh.cancel_library"
    bl_label = "Cancel"

    def execute(self, context):
        run = STATE.library
        if run is not None:
            run.queue.cancel_all()
            library.end_run(run)
        props = context.scene.nbvh_props
        props.library_running, props.library_phase = False, "cancelled"
        STATE.library = None
        self.report({"INFO"}, "NBVH: library run cancelled; what finished stays in its report")
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
    """Add a Decimate modifier that gives the decimation the verdict found (it meets the quality level with fewer
    bytes than a model): non-destructive, undoable, the mesh data untouched"""

    bl_idname = "nbvh.apply_decimation"
    bl_label = "Use the decimation"
    bl_options = {"REGISTER", "UNDO"}

    object_name: bpy.props.StringProperty()
    ratio: bpy.props.FloatProperty(min=0.0, max=1.0)

    def execute(self, context):
        obj = bpy.data.objects.get(self.object_name)
        if obj is None or obj.type != "MESH":
            self.report({"ERROR"}, f"{self.object_name!r} is not a mesh object")
            return {"CANCELLED"}
        mod = obj.modifiers.get("NBVH decimation") or obj.modifiers.new("NBVH decimation", "DECIMATE")
        mod.decimate_type, mod.ratio = "COLLAPSE", self.ratio
        self.report({"INFO"}, f"{obj.name}: Decimate modifier, ratio {self.ratio:.4f}")
        return {"FINISHED"}


CLASSES = (NBVH_OT_compress, NBVH_OT_apply_decimation, NBVH_OT_cancel, NBVH_OT_toggle_preview, NBVH_OT_open_report, NBVH_OT_open_folder,
           NBVH_OT_remove_result,
           NBVH_OT_install_dependencies, NBVH_OT_cancel_install, NBVH_OT_check_python, NBVH_OT_scene_report, NBVH_OT_compress_library,
           NBVH_OT_cancel_library)
