"""Properties, preferences and the N-panel (3D viewport sidebar, tab "NBVH")."""
from __future__ import annotations

import bpy

from . import compress_ops, compress_session, install_ops, library_ops, report_ops, settings_fields

PRESET_ITEMS = [("preview", "Preview", "Small and quick (about a minute)"),
                ("default", "Default", "Balanced size and quality (a few minutes)"),
                ("high", "High", "Larger model, longer training")]


class NBVH_Result(bpy.types.PropertyGroup):
    object_name: bpy.props.StringProperty()
    model_path: bpy.props.StringProperty(subtype="FILE_PATH")
    report_path: bpy.props.StringProperty(subtype="FILE_PATH")
    image_name: bpy.props.StringProperty()
    proxy_name: bpy.props.StringProperty()
    nbvh_bytes: bpy.props.IntProperty(name=".nbvh bytes", description=(
        "Size of the model file. A neural model is ray-traced as it is stored, so this is also what it holds in "
        "memory (resident bytes); a mesh must hold vertices, indices, normals and a BVH to be traced"))
    blender_bytes: bpy.props.IntProperty(name="Mesh bytes", description="What the mesh holds as Blender stores it "
                                         "(positions, corners, faces, normals)")
    mse: bpy.props.FloatProperty(name="MSE", precision=5, description=(
        "Image mean squared error of the neural rendering against the exact one of the mesh, over 16 held-out orbit "
        "views at 256 px "
        f"(0 = identical; {compress_session.QUALITY_LEVELS['standard']:g} is the 'standard' quality level)"))
    iou: bpy.props.FloatProperty(name="IoU", precision=4, description=(
        "Silhouette intersection over union: the share of pixels covered by both renderings among those covered "
        "by either (1 = the same outline)"))
    flip: bpy.props.FloatProperty(name="FLIP", precision=4, description=(
        "NVIDIA's FLIP of the file as shipped, its look included (colours, textures), against the exact coloured "
        "render of the mesh on the same held-out views (0 = identical; shown for assets with materials)"))
    train_seconds: bpy.props.FloatProperty()
    verdict: bpy.props.StringProperty(description="What the user could ship instead: the mesh as a ray tracer "
                                      "holds it, a decimation of equal quality, Draco for storage")


class NBVH_LibraryRow(bpy.types.PropertyGroup):
    """One object (scene report) or asset (library) of the last library run."""

    name: bpy.props.StringProperty()
    status: bpy.props.StringProperty()
    triangles: bpy.props.IntProperty()
    resident_bytes: bpy.props.IntProperty()
    model_bytes: bpy.props.IntProperty()
    savings: bpy.props.IntProperty()
    verdict: bpy.props.StringProperty()


class NBVH_Props(bpy.types.PropertyGroup):
    mode: bpy.props.EnumProperty(name="Size by", items=[
        ("PRESET", "Preset", "A named quality preset"),
        ("TARGET", "Target quality", "The smallest model that reaches a quality level"),
        ("BUDGET", "Byte budget", "The best model that fits a size")], default="TARGET")
    preset: bpy.props.EnumProperty(name="Preset", items=PRESET_ITEMS, default="default")
    target: bpy.props.EnumProperty(name="Quality", items=[
        (name.upper(), name.title(), f"image MSE <= {mse:g}") for name, mse in compress_session.QUALITY_LEVELS.items()],
        default=compress_session.DEFAULT_LEVEL.upper())
    budget_kb: bpy.props.IntProperty(name="Budget (KB)", default=400, min=16, max=100000)
    output_dir: bpy.props.StringProperty(name="Folder", subtype="DIR_PATH",
                                         description="Where .nbvh files go (empty: //nbvh beside the .blend)")
    show_image: bpy.props.BoolProperty(name="Show result in Image Editor", default=True,
                                       description="When a compression finishes, show its neural rendering in an "
                                                   "Image Editor (a new window when none is open)")
    running: bpy.props.BoolProperty()
    progress: bpy.props.FloatProperty(min=0.0, max=1.0, subtype="FACTOR")
    phase: bpy.props.StringProperty()
    eta: bpy.props.StringProperty()
    last_error: bpy.props.StringProperty()
    last_note: bpy.props.StringProperty()  # verdicts: objects kept as meshes (not worth compressing)
    decimations: bpy.props.StringProperty()  # JSON {object name: compress_session.decimation_offer}: one click each
    warnings: bpy.props.StringProperty()  # the jobs' warning events (a target missed, a restart after divergence)
    message_selection: bpy.props.StringProperty()  # the selection last_error / last_note are about
    report_html: bpy.props.StringProperty(subtype="FILE_PATH")
    library_folder: bpy.props.StringProperty(name="Library", subtype="DIR_PATH")
    library_running: bpy.props.BoolProperty()
    library_progress: bpy.props.FloatProperty(min=0.0, max=1.0, subtype="FACTOR")
    library_phase: bpy.props.StringProperty()
    library_summary: bpy.props.StringProperty()
    library_report_html: bpy.props.StringProperty(subtype="FILE_PATH")
    library_rows: bpy.props.CollectionProperty(type=NBVH_LibraryRow)


# The settings the core declares for the panel (`settings_fields`: time limit, device, mesh layout, look, force...),
# each a property named as the request's field, added before the class is registered.
for _name, _kind, _kwargs in settings_fields.property_specs():
    NBVH_Props.__annotations__[_name] = getattr(bpy.props, _kind)(**_kwargs)


class NBVH_Preferences(bpy.types.AddonPreferences):
    bl_idname = __package__

    python_path: bpy.props.StringProperty(
        name="Python for jobs", subtype="FILE_PATH",
        description="A Python with PyTorch that runs nbvh_core (empty: found automatically)")

    install_progress: bpy.props.FloatProperty(min=0.0, max=1.0, subtype="FACTOR")
    install_status: bpy.props.StringProperty()

    def draw(self, context):
        col = self.layout.column()
        col.prop(self, "python_path")
        row = col.row()
        row.operator("nbvh.check_python")
        row.operator("nbvh.install_dependencies")
        if self.install_status:
            col.label(text=self.install_status)
            if install_ops.installing():
                col.prop(self, "install_progress", text="", slider=True)
                col.operator("nbvh.cancel_install", icon="CANCEL")


class NBVH_PT_panel(bpy.types.Panel):
    bl_label = "Compress to NBVH"
    bl_idname = "NBVH_PT_panel"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "NBVH"

    def draw(self, context):
        layout = self.layout
        props = context.scene.nbvh_props
        col = layout.column()
        col.prop(props, "mode")
        if props.mode == "PRESET":
            col.prop(props, "preset")
        elif props.mode == "TARGET":
            col.prop(props, "target")
            col.label(text="one training: its table grows until the level is met", icon="INFO")
        else:
            col.prop(props, "budget_kb")
        for name in settings_fields.panel_names():
            col.prop(props, name)
        col.prop(props, "output_dir")
        col.prop(props, "show_image")
        if props.running:
            box = layout.box()
            box.label(text=props.phase or "working")
            if hasattr(box, "progress"):  # Blender 4.0+
                box.progress(factor=props.progress, text=f"{props.progress * 100:.0f}%  ETA {props.eta or '?'}")
            else:
                box.prop(props, "progress", text=f"ETA {props.eta or '?'}", slider=True)
            box.operator("nbvh.cancel", icon="CANCEL")
        if props.warnings and (props.running or props.message_selection in ("", compress_ops.selection_key(context))):
            _wrapped(layout, props.warnings, "ERROR", context)
        else:
            n = len(context.selected_objects)
            layout.operator("nbvh.compress", text=f"Compress {n} object{'s' if n != 1 else ''} to NBVH",
                            icon="MOD_REMESH")
            resumable = [o.name for o in context.selected_objects
                         if compress_session.checkpoint_path(compress_session.output_dir(props.output_dir), o.name) is not None]
            if resumable:  # a job died in training: continue it instead of starting over
                op = layout.operator("nbvh.compress", text=f"Resume training ({', '.join(resumable)[:40]})",
                                     icon="RECOVER_LAST")
                op.resume = True
        why = compress_ops.compress_disabled_reason(context)
        if why and not props.running:
            _wrapped(layout, why, "INFO", context)
        current = props.running or props.message_selection in ("", compress_ops.selection_key(context))
        if props.last_error and current:  # a message about another selection is stale: not shown
            _wrapped(layout, props.last_error, "ERROR", context, lines=6)
        if props.last_note and current:
            _wrapped(layout, props.last_note, "INFO", context, lines=6)
        for name, offer in compress_ops.decimation_offers(context).items():
            op = layout.operator("nbvh.apply_decimation", icon="MOD_DECIM",
                                 text=f"Decimate {name[:24]} to {offer['triangles']:,} triangles")
            op.object_name, op.ratio, op.glb = name, offer["ratio"], offer.get("glb", "")
        out = compress_session.output_dir(props.output_dir)
        row = layout.row()
        row.label(text=f"Output: {_short_path(out, context)}", icon="FILE_FOLDER")
        row.operator("nbvh.open_folder", text="", icon="FOLDER_REDIRECT")
        for r in context.scene.nbvh_results:
            box = layout.box()
            box.label(text=r.object_name, icon="OBJECT_DATA")
            col = box.column(align=True)
            # props, not text: hovering explains what each size counts
            col.prop(r, "nbvh_bytes", text=".nbvh bytes", emboss=False)
            col.prop(r, "blender_bytes", text="mesh bytes", emboss=False)
            col.label(text=f"{r.blender_bytes / max(r.nbvh_bytes, 1):.1f}x smaller than the mesh")
            col.prop(r, "mse", text="MSE", emboss=False)
            col.prop(r, "iou", text="IoU", emboss=False)
            if r.flip > 0:  # an asset with a look: what people see, scored on the written file
                col.prop(r, "flip", text="FLIP, as shipped", emboss=False)
            col.label(text=f"trained {r.train_seconds:.0f} s")
            if r.verdict:
                _wrapped(box, r.verdict, "NONE", context, lines=6)
            row = box.row()
            op = row.operator("nbvh.toggle_preview", text="Proxy", icon="HIDE_OFF")
            op.object_name = r.object_name
            row.operator("nbvh.open_report", text="Report", icon="TEXT")
            op = row.operator("nbvh.remove_result", text="", icon="TRASH")
            op.object_name = r.object_name


def _chars(context) -> int:
    """About how many characters of a label fit across the region (the sidebar is narrow by default)."""
    scale = context.preferences.system.ui_scale
    return max(18, int((context.region.width if context.region else 300) / (7.5 * scale)) - 6)


def _wrapped(layout, text: str, icon: str = "NONE", context=None, lines: int = 4) -> None:
    """A long message as several labels, wrapped to the region's width (one long label would be cut off)."""
    import textwrap

    col = layout.column(align=True)
    width = _chars(context or bpy.context)
    for i, line in enumerate(textwrap.wrap(text, width)[:lines]):
        col.label(text=line, icon=icon if i == 0 else "BLANK1")


def _short_path(path, context) -> str:
    """A folder path that fits: its end, with "..." for what is left out."""
    text, width = str(path), _chars(context) - 8
    return text if len(text) <= width else "..." + text[-max(8, width - 3):]


class NBVH_PT_library(bpy.types.Panel):
    """Scene memory report and library batches (below the main panel)."""

    bl_label = "Scene & Library Memory"
    bl_idname = "NBVH_PT_library"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "NBVH"
    bl_parent_id = "NBVH_PT_panel"

    def draw(self, context):
        layout = self.layout
        props = context.scene.nbvh_props
        row = layout.row()
        row.operator("nbvh.scene_report", icon="SPREADSHEET")
        row.operator("nbvh.compress_library", icon="FILE_FOLDER")
        if props.library_running:
            box = layout.box()
            box.label(text=props.library_phase or "working")
            box.prop(props, "library_progress", text="", slider=True)
            box.operator("nbvh.cancel_library", icon="CANCEL")
        elif props.library_phase:
            layout.label(text=props.library_phase)
        if props.library_summary:
            layout.label(text=props.library_summary, icon="INFO")
            layout.operator("nbvh.open_report", text="Open Library Report", icon="TEXT").which = "library_report_html"
        for r in list(props.library_rows)[:30]:
            box = layout.box()
            box.label(text=f"{r.name}: {r.status}", icon="MESH_DATA")
            box.label(text=f"{r.triangles:,} tris, resident {r.resident_bytes / 1024:,.0f} KB, "
                           f"savings {r.savings / 1024:,.0f} KB")
            if r.verdict:
                box.label(text=r.verdict[:90])


CLASSES = (NBVH_Result, NBVH_LibraryRow, NBVH_Props, NBVH_Preferences, NBVH_PT_panel, NBVH_PT_library)
#: The operators, by feature.
OPERATORS = compress_ops.CLASSES + library_ops.CLASSES + install_ops.CLASSES + report_ops.CLASSES


def register():
    for cls in CLASSES + OPERATORS:
        bpy.utils.register_class(cls)
    bpy.types.Scene.nbvh_props = bpy.props.PointerProperty(type=NBVH_Props)
    bpy.types.Scene.nbvh_results = bpy.props.CollectionProperty(type=NBVH_Result)


def unregister():
    del bpy.types.Scene.nbvh_results
    del bpy.types.Scene.nbvh_props
    for cls in reversed(CLASSES + OPERATORS):
        bpy.utils.unregister_class(cls)
