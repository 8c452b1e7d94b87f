"""The NBVH render engine (Render Properties > Render Engine > NBVH): the scene's compressed objects drawn from
their .nbvh models, each at its object's transform, the others from their meshes (exact, Embree), all in one
worker process (`render_client`, `nbvh_core.app.render_worker`), so a shot mixes neural and exact geometry correctly.

* Viewport (Rendered shading): `view_update` sends the scene when it changes (objects, transforms, lights,
  settings), `view_draw` asks for the current view and draws the newest frame it has; frames come coarse first
  (1/4, 1/2, then full of the viewport resolution scale) and a moved view abandons the frame in progress. Blender
  never waits: a timer polls the worker and redraws the viewports while frames are coming.
* Final render (F12, `blender -b scene.blend -E NBVH -f 1`): the scene camera at the output resolution, with
  `samples` per pixel, in bands (progress, Esc cancels), written into the render result like any engine's.

An object's model is `Object.nbvh_model` (a path, relative to the .blend when it was saved: a saved file renders
on any machine with the add-on and the files). A finished Compress sets it. Objects that are previews of a result
(the point-cloud proxies) are not scene geometry and are left out.
"""
from __future__ import annotations

import tempfile
from pathlib import Path

import bpy
import numpy as np

from . import export, render_client

ENGINE_ID = "NBVH"
VIEW_LEVELS = (4, 2, 1)


class NBVH_RenderSettings(bpy.types.PropertyGroup):
    shading: bpy.props.EnumProperty(name="Shading", items=[
        ("LAMBERT", "Scene lights", "Lambert shading with the scene's point, sun and spot lights, their colours and "
                                    "strengths, the world colour as ambient light, and shadows"),
        ("COSINE", "Paper (cosine)", "The N-BVH paper's shading: cosine to the first light (or a head light), "
                                     "white, no shadows; for comparing with the paper's numbers")], default="LAMBERT")
    shadows: bpy.props.BoolProperty(name="Shadows", default=True,
                                    description="Trace shadow rays through every object, neural or exact")
    geometry: bpy.props.EnumProperty(name="Geometry", items=[
        ("NEURAL", "Neural models", "Objects with an .nbvh model are drawn from it, the others from their meshes"),
        ("MESH", "Meshes (reference)", "Every object from its mesh, traced exactly: the reference to compare with")],
        default="NEURAL")
    samples: bpy.props.IntProperty(name="Samples", default=4, min=1, max=64,
                                   description="Rays per pixel in final renders (a square grid; antialiasing)")
    viewport_scale: bpy.props.FloatProperty(name="Viewport Resolution", default=0.5, min=0.1, max=1.0,
                                            subtype="FACTOR",
                                            description="Fraction of the viewport's pixels traced in Rendered shading")


def _worker() -> render_client.RenderWorker:
    """The running render worker, else a new one with the jobs' Python (found once: checking a Python starts a
    process, too slow for every viewport update). Raises ValueError when there is none, WorkerError when it
    cannot start."""
    worker = render_client.current_worker()
    if worker is not None and worker.alive:
        return worker
    from .job_watcher import job_python

    python = job_python(bpy.context)
    if not python:
        raise ValueError("no Python with PyTorch for the render worker: set one in the add-on preferences "
                         "(NBVH > Install Dependencies)")
    return render_client.shared_worker(python)


# ---------------------------------------------------------------------------------------------- scene
def model_path(obj) -> str | None:
    """The object's .nbvh model as an absolute path, or None when it has none or it is not one (`model_problem`)."""
    rel = getattr(obj, "nbvh_model", "") or ""
    return None if not rel or model_problem(rel) else str(Path(bpy.path.abspath(rel)).resolve())


def model_problem(rel: str) -> str | None:
    """Why a stored model path is not drawn from, or None. A .blend shared between studios carries these paths:
    only a regular file named .nbvh is handed to the worker, whose reader validates it as data (a pipe, a device
    or another kind of file never reaches it). Paths outside the project are allowed: models may live in a library
    folder, and reading one cannot run code."""
    path = Path(bpy.path.abspath(rel))
    if path.suffix.lower() != ".nbvh":
        return "Not an .nbvh file: the NBVH engine draws the mesh"
    if not path.is_file():
        return "The file is missing: the NBVH engine draws the mesh"
    return None


def object_color(obj) -> list[float]:
    """Linear albedo: the material's Principled/Diffuse base colour, else its viewport colour, else grey."""
    mat = obj.active_material
    if mat is not None:
        if mat.use_nodes and mat.node_tree is not None:
            for node in mat.node_tree.nodes:
                sock = node.inputs.get("Base Color") or node.inputs.get("Color") if node.type in (
                    "BSDF_PRINCIPLED", "BSDF_DIFFUSE") else None
                if sock is not None and not sock.is_linked:
                    return [float(c) for c in sock.default_value[:3]]
        return [float(c) for c in mat.diffuse_color[:3]]
    return [0.8, 0.8, 0.8]


def light_entry(light_obj, matrix) -> dict:
    """A Blender light -> the worker's light (area lights become point lights of the same power)."""
    data = light_obj.data
    m = np.array(matrix, np.float64)
    direction = m[:3, :3] @ np.array([0.0, 0.0, -1.0])
    kind = {"SUN": "sun", "SPOT": "spot"}.get(data.type, "point")
    entry = {"kind": kind, "color": [float(c) for c in data.color], "power": float(data.energy),
             "position": m[:3, 3].tolist(), "direction": (direction / max(np.linalg.norm(direction), 1e-12)).tolist()}
    if kind == "spot":
        entry["spot_size"], entry["spot_blend"] = float(data.spot_size), float(data.spot_blend)
    return entry


class MeshFiles:
    """Meshes of objects without a model, exported once per geometry change into a temporary folder."""

    def __init__(self):
        self.dir = Path(tempfile.mkdtemp(prefix="nbvh-engine-meshes-"))
        self.files: dict[str, str] = {}
        self.version = 0

    def invalidate(self, name: str | None = None) -> None:
        for key in ([name] if name else list(self.files)):
            path = self.files.pop(key, None)
            if path:
                Path(path).unlink(missing_ok=True)

    def close(self) -> None:
        """Remove the folder and every mesh in it."""
        import shutil

        self.files.clear()
        shutil.rmtree(self.dir, ignore_errors=True)

    def path_for(self, obj, depsgraph) -> str:
        """The object's evaluated mesh as .npz (object-local). Raises export.ExportError."""
        if obj.name not in self.files:
            verts, tris, _, look = export.evaluated_triangles(obj, depsgraph)
            self.version += 1
            path = self.dir / f"{self.version}.npz"
            np.savez(path, vertices=verts, faces=tris, **look)
            self.files[obj.name] = str(path)
        return self.files[obj.name]


def scene_description(depsgraph, meshes: MeshFiles) -> tuple[dict, list[str]]:
    """The worker's scene (`nbvh_core.rendering.scene_render` JSON) for what `depsgraph` shows, and notes about objects
    left out (no surface, no model and no mesh)."""
    scene = depsgraph.scene
    settings = scene.nbvh_render
    objects, lights, notes = [], [], []
    for inst in depsgraph.object_instances:
        ob = inst.object
        orig = ob.original
        matrix = [list(row) for row in inst.matrix_world]
        if ob.type == "LIGHT":
            lights.append(light_entry(ob, matrix))
            continue
        if ob.type not in export.CONVERTIBLE or orig.get("nbvh_source") is not None:
            continue  # cameras, empties; the previews of a result
        model = model_path(orig) if settings.geometry == "NEURAL" else None
        entry = {"name": orig.name, "matrix": matrix, "model": model, "color": object_color(orig)}
        if model is None:
            try:
                entry["mesh"] = meshes.path_for(orig, depsgraph)
            except export.ExportError as exc:
                notes.append(str(exc))
                continue
        objects.append(entry)
    world = scene.world
    return ({"objects": objects, "lights": lights,
             "world": [float(c) for c in world.color] if world is not None else [0.05, 0.05, 0.05],
             "transparent": bool(scene.render.film_transparent), "shading": settings.shading.lower(),
             "shadows": bool(settings.shadows), "geometry": settings.geometry.lower()}, notes)


def final_camera(depsgraph, width: int, height: int) -> np.ndarray:
    """NDC -> world (4, 4) of the scene camera for a width x height render (sensor fit, shift, ortho included)."""
    scene = depsgraph.scene
    cam = scene.camera
    if cam is None:
        raise ValueError("the scene has no camera")
    r = scene.render
    proj = cam.calc_matrix_camera(depsgraph, x=width, y=height, scale_x=r.pixel_aspect_x, scale_y=r.pixel_aspect_y)
    return np.linalg.inv(np.array(proj, np.float64) @ np.array(cam.matrix_world.inverted(), np.float64))


def to_display(pixels: np.ndarray, exposure: float = 0.0) -> np.ndarray:
    """Linear RGBA -> sRGB-encoded RGBA for the viewport texture (the standard view transform; the final render
    goes through Blender's own colour management)."""
    srgb = export.linear_to_srgb(pixels[..., :3] * (2.0 ** exposure))
    return np.concatenate([srgb, pixels[..., 3:4]], axis=-1).astype(np.float32)


# ---------------------------------------------------------------------------------------------- engine
class NBVHRenderEngine(bpy.types.RenderEngine):
    bl_idname = ENGINE_ID
    bl_label = "NBVH"
    bl_use_preview = False

    # -- final render ------------------------------------------------------------------------------------
    def render(self, depsgraph):
        scene = depsgraph.scene
        r = scene.render
        width = max(1, int(r.resolution_x * r.resolution_percentage / 100))
        height = max(1, int(r.resolution_y * r.resolution_percentage / 100))
        try:
            image = self._render_final(depsgraph, width, height)
        except (render_client.WorkerError, ValueError) as exc:
            self.report({"ERROR"}, f"NBVH: {exc}")
            print(f"NBVH render failed: {exc}")
            return
        if image is None:  # cancelled
            return
        result = self.begin_result(0, 0, width, height)
        result.layers[0].passes["Combined"].rect = image.reshape(-1, 4)
        self.end_result(result)

    def _render_final(self, depsgraph, width: int, height: int) -> np.ndarray | None:
        self.update_stats("", "NBVH: starting the render worker")
        worker = _worker()
        meshes = MeshFiles()
        try:
            desc, notes = scene_description(depsgraph, meshes)
            scene_id = worker.set_scene(desc)
            self.update_stats("", f"NBVH: loading {len(desc['objects'])} objects")
            if not worker.wait(lambda: worker.scene_done >= scene_id, should_stop=self.test_break):
                return None
            for note in notes + worker.warnings:
                self.report({"WARNING"}, f"NBVH: {note}")
            camera = final_camera(depsgraph, width, height)
            rid = worker.request(render_client.FINAL, camera, width, height, levels=(1,),
                                 samples=depsgraph.scene.nbvh_render.samples, bands=max(1, min(32, height // 64)))
            channel = worker.channels[render_client.FINAL]

            def done() -> bool:
                self.update_progress(channel.progress)
                return not channel.pending

            self.update_stats("", f"NBVH: tracing {width} x {height}")
            if not worker.wait(done, should_stop=self.test_break):
                worker.cancel(render_client.FINAL)
                return None
            if channel.error:
                raise render_client.WorkerError(channel.error)
            if channel.frame is None or channel.frame.id != rid:
                raise render_client.WorkerError("the render worker returned no image")
            return channel.frame.pixels
        finally:
            meshes.close()  # a final render's meshes are exported for it alone

    # -- viewport ----------------------------------------------------------------------------------------
    def _view(self) -> dict:
        state = getattr(self, "_nbvh_view", None)
        if state is None:
            state = {"meshes": MeshFiles(), "key": None, "texture": None, "frame": None, "error": None,
                     "channel": f"view-{id(self):x}", "scene_id": 0}
            self._nbvh_view = state
        return state

    def view_update(self, context, depsgraph):
        state = self._view()
        for update in depsgraph.updates:
            if isinstance(update.id, bpy.types.Object) and update.is_updated_geometry:
                state["meshes"].invalidate(update.id.original.name)
        try:
            worker = _worker()
            desc, notes = scene_description(depsgraph, state["meshes"])
            state["scene_id"] = worker.set_scene(desc)
            state["error"] = "; ".join(notes) or None
        except (render_client.WorkerError, ValueError) as exc:
            state["error"] = str(exc)
        _start_redraw_timer()

    def view_draw(self, context, depsgraph):
        state = self._view()
        worker = render_client.current_worker()
        region = context.region
        if worker is None or not worker.alive:
            self._draw_message(state.get("error") or "NBVH: the render worker is not running")
            return
        scale = depsgraph.scene.nbvh_render.viewport_scale
        width, height = max(1, int(region.width * scale)), max(1, int(region.height * scale))
        camera = np.linalg.inv(np.array(context.region_data.perspective_matrix, np.float64))
        key = (camera.round(9).tobytes(), width, height, state["scene_id"])
        if key != state["key"]:
            try:
                worker.request(state["channel"], camera, width, height, levels=VIEW_LEVELS)
            except render_client.WorkerError as exc:
                state["error"] = str(exc)
            state["key"] = key
            _start_redraw_timer()
        worker.poll()
        channel = worker.channels.get(state["channel"])
        if channel is not None and channel.frame is not None and channel.frame is not state["frame"]:
            state["frame"] = channel.frame
            state["texture"] = _texture(to_display(channel.frame.pixels, depsgraph.scene.view_settings.exposure))
        if state["texture"] is not None:
            import gpu
            from gpu_extras.presets import draw_texture_2d

            gpu.state.blend_set("ALPHA")
            draw_texture_2d(state["texture"], (0, 0), region.width, region.height)
            gpu.state.blend_set("NONE")

    def _draw_message(self, text: str) -> None:
        import blf

        blf.position(0, 20, 30, 0)
        blf.size(0, 14) if bpy.app.version >= (4, 0, 0) else blf.size(0, 14, 72)
        blf.draw(0, text[:200])


def _texture(pixels: np.ndarray):
    import gpu

    h, w = pixels.shape[:2]
    buf = gpu.types.Buffer("FLOAT", w * h * 4, np.ascontiguousarray(pixels, np.float32).ravel())
    return gpu.types.GPUTexture((w, h), format="RGBA16F", data=buf)


# ---------------------------------------------------------------------------------------------- redraws
_timer = {"on": False}


def _redraw_tick():
    """Poll the worker; redraw the viewports in Rendered shading while frames are coming (every 50 ms), stop when
    nothing is pending."""
    worker = render_client.current_worker()
    if worker is None:
        _timer["on"] = False
        return None
    new = worker.poll()
    pending = any(ch.pending for ch in worker.channels.values())
    if new or pending:
        for window in bpy.context.window_manager.windows:
            for area in window.screen.areas:
                if area.type == "VIEW_3D":
                    area.tag_redraw()
    if not pending and not new:
        _timer["on"] = False
        return None
    return 0.05


def _start_redraw_timer() -> None:
    if not _timer["on"] and not bpy.app.background:
        _timer["on"] = True
        bpy.app.timers.register(_redraw_tick, first_interval=0.05)


# ---------------------------------------------------------------------------------------------- UI
class RENDER_PT_nbvh(bpy.types.Panel):
    bl_label = "NBVH"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "render"
    COMPAT_ENGINES = {ENGINE_ID}

    @classmethod
    def poll(cls, context):
        return context.engine in cls.COMPAT_ENGINES

    def draw(self, context):
        s = context.scene.nbvh_render
        layout = self.layout
        layout.use_property_split = True
        layout.prop(s, "geometry")
        layout.prop(s, "shading")
        row = layout.row()
        row.enabled = s.shading == "LAMBERT"
        row.prop(s, "shadows")
        layout.prop(s, "samples")
        layout.prop(s, "viewport_scale")
        worker = render_client.current_worker()
        if worker is not None and worker.warnings:
            for w in worker.warnings[:5]:
                layout.label(text=w[:120], icon="ERROR")


class OBJECT_PT_nbvh_model(bpy.types.Panel):
    bl_label = "NBVH Model"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "object"

    @classmethod
    def poll(cls, context):
        return context.object is not None and context.object.type in export.CONVERTIBLE

    def draw(self, context):
        obj = context.object
        self.layout.prop(obj, "nbvh_model", text="Model")
        problem = model_problem(obj.nbvh_model) if obj.nbvh_model else None
        if problem:
            self.layout.label(text=problem, icon="ERROR")


def _model_property():
    """`Object.nbvh_model` (compress.py registers it too when the add-on is not enabled)."""
    kwargs = dict(name="NBVH model", subtype="FILE_PATH",
                  description="The .nbvh model the NBVH render engine draws this object from (set by Compress)")
    if bpy.app.version >= (5, 0, 0):  # Blender 5 asks paths to declare that they may be relative to the .blend
        return bpy.props.StringProperty(options={"PATH_SUPPORTS_BLEND_RELATIVE"}, **kwargs)
    return bpy.props.StringProperty(**kwargs)


def _compat_panels():
    """Blender's own panels that list the built-in render engine (resolution, output, lights, ...)."""
    exclude = {"VIEWLAYER_PT_filter", "VIEWLAYER_PT_layer_passes"}
    for panel in bpy.types.Panel.__subclasses__():
        compat = getattr(panel, "COMPAT_ENGINES", None)
        if isinstance(compat, set) and "BLENDER_RENDER" in compat and panel.__name__ not in exclude:
            yield panel


CLASSES = (NBVH_RenderSettings, NBVHRenderEngine, RENDER_PT_nbvh, OBJECT_PT_nbvh_model)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.nbvh_render = bpy.props.PointerProperty(type=NBVH_RenderSettings)
    bpy.types.Object.nbvh_model = _model_property()
    for panel in _compat_panels():
        panel.COMPAT_ENGINES.add(ENGINE_ID)


def unregister():
    render_client.stop_shared()
    for panel in _compat_panels():
        panel.COMPAT_ENGINES.discard(ENGINE_ID)
    del bpy.types.Object.nbvh_model
    del bpy.types.Scene.nbvh_render
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
