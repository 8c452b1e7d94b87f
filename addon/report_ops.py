"""Opening a report the add-on wrote (the objects' memory report or the library's): in the web browser, or, where
there is none, its JSON in Blender's Text Editor."""
from __future__ import annotations

import webbrowser
from pathlib import Path

import bpy


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


CLASSES = (NBVH_OT_open_report,)
