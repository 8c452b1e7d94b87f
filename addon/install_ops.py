"""Setting up the background jobs' Python: the dependency installer (a virtual environment with the CPU build of
PyTorch, in the background, progress and Cancel in the preferences) and the check of a configured Python."""
from __future__ import annotations

from pathlib import Path

import bpy

from .job import check_python, core_env
from .job_watcher import JobWatcher, addon_prefs, job_python


def _advance(inst) -> bool:
    """One tick of the installer: mirror it into the preferences; done -> the new Python. False once ended."""
    prefs = addon_prefs(bpy.context)
    state = inst.poll()
    if prefs is not None:
        prefs.install_progress = inst.fraction
        prefs.install_status = f"{inst.phase}: {inst.line}"[:200] if state == "running" else {
            "done": "installed: jobs run with the new environment", "cancelled": "install cancelled",
            "failed": (inst.error.splitlines() or ["failed"])[0][:200]}.get(state, state)
        if state == "done":
            prefs.python_path = inst.python
    return state == "running"


#: The running installer; its `python` is the environment's interpreter it sets up.
WATCHER = JobWatcher("dependency install", _advance, lambda inst: inst.cancel())


def installing() -> bool:
    """True while the dependency installer runs (the panel shows its progress instead of the buttons)."""
    return WATCHER.running


class NBVH_OT_install_dependencies(bpy.types.Operator):
    """Create a virtual environment with PyTorch (the CUDA build where an NVIDIA card is found, else the CPU build)
    and nbvh_core's dependencies for the background jobs, in a background process (progress and Cancel in these
    preferences)"""

    bl_idname = "nbvh.install_dependencies"
    bl_label = "Install Dependencies"

    @classmethod
    def poll(cls, context):
        return not WATCHER.running

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
        inst.python = str(venv_python(venv))
        inst.start()
        WATCHER.start(inst, first_interval=0.25)
        self.report({"INFO"}, f"installing into {venv} in the background")
        return {"FINISHED"}


class NBVH_OT_cancel_install(bpy.types.Operator):
    """Stop the dependency install (the half-made environment is continued by the next install)"""

    bl_idname = "nbvh.cancel_install"
    bl_label = "Cancel Install"

    def execute(self, context):
        inst = WATCHER.work
        if inst is not None:  # the installer ends itself; the watcher mirrors "install cancelled" on its last tick
            inst.cancel()
        return {"FINISHED"}


class NBVH_OT_check_python(bpy.types.Operator):
    """Check that the configured Python can run compression jobs"""

    bl_idname = "nbvh.check_python"
    bl_label = "Check Python"

    def execute(self, context):
        ok, msg = check_python(job_python(context))
        self.report({"INFO" if ok else "ERROR"}, msg)
        return {"FINISHED"} if ok else {"CANCELLED"}


CLASSES = (NBVH_OT_install_dependencies, NBVH_OT_cancel_install, NBVH_OT_check_python)
