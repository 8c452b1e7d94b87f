"""The library feature: a folder of assets compressed as a batch, or the open scene measured without training
(*Scene Memory Report*), as one background job with its report; the panel lists its rows when it ends."""
from __future__ import annotations

from pathlib import Path

import bpy

from . import compress_session, library, settings_fields
from .job_watcher import JobWatcher, job_python, notify


def _library_settings(props) -> dict:
    """The batch's settings from the panel: the preset or target (a byte budget applies per asset) and the core's
    declared panel settings (time limit, device, mesh layout, look, *Train even if not worth it*)."""
    spec = {"preset": props.preset, **settings_fields.request_fields(props)}
    if props.mode == "TARGET":
        spec["target_mse"] = compress_session.QUALITY_LEVELS[props.target.lower()]
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


def _advance(run) -> bool:
    """One tick of the library job: step it, mirror its progress; at the end list its rows. False once ended."""
    props = bpy.context.scene.nbvh_props
    run.queue.step()
    job = run.job
    props.library_progress = job.fraction
    done, total = job.progress.get("done"), job.progress.get("total")
    props.library_phase = f"{job.progress.get('phase', 'starting')}" + (f" {done}/{total}" if total else "")
    if not run.queue.finished(job):
        return True
    props.library_running = False
    if job.state == "done":
        store_library_rows(props, run)
        props.library_phase = "finished"
        notify("NBVH: library report ready", [props.library_summary, props.library_report_html])
    else:
        props.library_phase = f"{job.state}: {job.error or ''}"[:300]
        notify(f"NBVH: library run {job.state}", [props.library_phase], "ERROR")
    library.end_run(run)
    return False


def _stop(run) -> None:
    run.queue.cancel_all()
    library.end_run(run)


#: The running library batch or scene report (one at a time).
WATCHER = JobWatcher("library run", _advance, _stop)


def start_library_run(props, run) -> None:
    props.library_running, props.library_progress, props.library_phase = True, 0.0, "starting"
    props.library_rows.clear()
    props.library_summary = ""
    run.queue.step()  # starts the job now
    WATCHER.start(run, first_interval=0.25)


class NBVH_OT_scene_report(bpy.types.Operator):
    """Measure every mesh object of the scene and say which are worth compressing (no training): triangles,
    resident bytes, verdict, predicted savings"""

    bl_idname = "nbvh.scene_report"
    bl_label = "Scene Memory Report"

    @classmethod
    def poll(cls, context):
        return not WATCHER.running

    def execute(self, context):
        props = context.scene.nbvh_props
        try:
            run = library.start_scene_report(context, compress_session.output_dir(props.output_dir), _library_settings(props),
                                             job_python(context))
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
        return not WATCHER.running

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        props = context.scene.nbvh_props
        folder = bpy.path.abspath(self.directory or props.library_folder)
        try:
            run = library.start_library(folder, compress_session.output_dir(props.output_dir), _library_settings(props),
                                        job_python(context))
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
        WATCHER.cancel()
        props = context.scene.nbvh_props
        props.library_running, props.library_phase = False, "cancelled"
        self.report({"INFO"}, "NBVH: library run cancelled; what finished stays in its report")
        return {"FINISHED"}


CLASSES = (NBVH_OT_scene_report, NBVH_OT_compress_library, NBVH_OT_cancel_library)
