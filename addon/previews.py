"""Load a finished job back into the scene, next to the original and never touching it.

* the neural rendering as a Blender image (packed, so it survives saving the .blend);
* a point-cloud proxy of the neural model's own ray hits, in a collection named after the object, with the
  original's world transform shifted beside it: Blender's point cloud object where Python can create one
  (`bpy.data.pointclouds.new`, Blender 4.x/5.x), otherwise a vertex-only mesh drawn as points by a Geometry
  Nodes "Mesh to Points" modifier (Blender 3.x).
"""
from __future__ import annotations

import os
from pathlib import Path

import bpy
import numpy as np
from mathutils import Matrix, Vector

PROXY_SUFFIX = "_nbvh_proxy"
COLLECTION_PREFIX = "NBVH "


def load_image(path: str, name: str):
    """A packed Blender image from a PNG file (replaces an earlier image of the same name)."""
    old = bpy.data.images.get(name)
    if old is not None:
        bpy.data.images.remove(old)
    img = bpy.data.images.load(str(path), check_existing=False)
    img.name = name
    img.pack()
    return img


def _collection_for(obj, scene):
    name = f"{COLLECTION_PREFIX}{obj.name}"
    coll = bpy.data.collections.get(name)
    if coll is None:
        coll = bpy.data.collections.new(name)
        scene.collection.children.link(coll)
    return coll


def beside_matrix(obj, gap: float = 0.1) -> Matrix:
    """World matrix of the original moved along world X by its bounding-box width (+ gap): side by side."""
    corners = [obj.matrix_world @ Vector(c) for c in obj.bound_box]
    width = max(c.x for c in corners) - min(c.x for c in corners)
    return Matrix.Translation(Vector((width * (1 + gap), 0, 0))) @ obj.matrix_world


def _mesh_to_points_group(radius: float):
    """A Geometry Nodes group: Mesh to Points with `radius`, for Blender without Python point clouds."""
    name = f"NBVH Mesh to Points {radius:.3g}"
    group = bpy.data.node_groups.get(name)
    if group is not None:
        return group
    group = bpy.data.node_groups.new(name, "GeometryNodeTree")
    if hasattr(group, "interface"):  # Blender 4.0+
        group.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
        group.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    else:  # Blender 3.x
        group.inputs.new("NodeSocketGeometry", "Geometry")
        group.outputs.new("NodeSocketGeometry", "Geometry")
    n_in = group.nodes.new("NodeGroupInput")
    n_out = group.nodes.new("NodeGroupOutput")
    to_points = group.nodes.new("GeometryNodeMeshToPoints")
    to_points.inputs["Radius"].default_value = radius
    group.links.new(n_in.outputs[0], to_points.inputs["Mesh"])
    group.links.new(to_points.outputs["Points"], n_out.inputs[0])
    return group


def make_proxy(obj, points: np.ndarray, scene, radius: float | None = None):
    """Point-cloud proxy from (P, 6) object-local points + normals, or (P, 9) with each point's linear colour (the
    model's look at the point: a colour attribute "nbvh_color" and a material that shows it); returns the new
    object. radius: point radius in object-local units (default 0.4% of the points' bounding-box diagonal)."""
    name = f"{obj.name}{PROXY_SUFFIX}"
    remove_proxy(obj)
    coll = _collection_for(obj, scene)
    pos = np.ascontiguousarray(points[:, :3], np.float32)
    if radius is None:
        diag = float(np.linalg.norm(pos.max(0) - pos.min(0))) if len(pos) else 1.0
        radius = 0.004 * diag
    data = None
    if hasattr(bpy.data, "pointclouds"):
        try:
            data = bpy.data.pointclouds.new(name, len(pos))
        except (TypeError, AttributeError, RuntimeError):
            data = None
    if data is not None:
        data.points.foreach_set("co", pos.ravel())
        if hasattr(data.points[0] if len(data.points) else None, "radius"):
            data.points.foreach_set("radius", np.full(len(pos), radius, np.float32))
        proxy = bpy.data.objects.new(name, data)
    else:
        mesh = bpy.data.meshes.new(name)
        mesh.vertices.add(len(pos))
        mesh.vertices.foreach_set("co", pos.ravel())
        mesh.update()
        proxy = bpy.data.objects.new(name, mesh)
        mod = proxy.modifiers.new("NBVH points", "NODES")
        mod.node_group = _mesh_to_points_group(radius)
    if points.ndim == 2 and points.shape[1] >= 9:
        _colour_points(proxy, np.ascontiguousarray(points[:, 6:9], np.float32))
    proxy.matrix_world = beside_matrix(obj)
    proxy["nbvh_source"] = obj.name
    coll.objects.link(proxy)
    return proxy


#: The point attribute that holds a proxy point's colour, and the material that shows it.
COLOR_ATTRIBUTE = "nbvh_color"


def _colour_points(proxy, colors: np.ndarray) -> None:
    """Store per-point linear colours on the proxy's points and give it a material reading them (Attribute node
    -> Base Color), so material preview, F12 and Cycles show the look the model learnt."""
    data = proxy.data
    attr = data.attributes.new(COLOR_ATTRIBUTE, "FLOAT_COLOR", "POINT")
    rgba = np.concatenate([colors, np.ones((len(colors), 1), np.float32)], axis=1)
    attr.data.foreach_set("color", rgba.ravel())
    mat = bpy.data.materials.get("NBVH proxy colour") or bpy.data.materials.new("NBVH proxy colour")
    mat.use_nodes = True
    nodes = mat.node_tree.nodes
    if not any(n.type == "ATTRIBUTE" for n in nodes):
        bsdf = next(n for n in nodes if n.type == "BSDF_PRINCIPLED")
        node = nodes.new("ShaderNodeAttribute")
        node.attribute_name = COLOR_ATTRIBUTE
        mat.node_tree.links.new(node.outputs["Color"], bsdf.inputs["Base Color"])
    data.materials.append(mat)


def find_proxy(obj):
    return bpy.data.objects.get(f"{obj.name}{PROXY_SUFFIX}") if obj is not None else None


def remove_proxy(obj) -> None:
    proxy = bpy.data.objects.get(f"{obj.name}{PROXY_SUFFIX}")
    if proxy is not None:
        data = proxy.data
        bpy.data.objects.remove(proxy)
        if data is not None and data.users == 0:
            (bpy.data.pointclouds if data.__class__.__name__ == "PointCloud" else bpy.data.meshes).remove(data)


def remove_all(obj_name: str) -> None:
    """Remove the previews of one object (its proxy, images, collection); never the original or its files."""
    obj = bpy.data.objects.get(obj_name)
    if obj is not None:
        remove_proxy(obj)
        if hasattr(obj, "nbvh_model"):
            obj.nbvh_model = ""  # the render engine draws the mesh again
    for key in (f"{obj_name} (neural)", f"{obj_name} (mesh)"):
        img = bpy.data.images.get(key)
        if img is not None:
            bpy.data.images.remove(img)
    coll = bpy.data.collections.get(f"{COLLECTION_PREFIX}{obj_name}")
    if coll is not None and len(coll.objects) == 0:
        bpy.data.collections.remove(coll)


def load_result(obj, result: dict, scene) -> dict:
    """Images + proxy of a finished job (`result` event of nbvh_core.app.job). Returns the names it created."""
    files = result["files"]
    neural = load_image(files["preview"], f"{obj.name} (neural)")
    reference = load_image(files["reference"], f"{obj.name} (mesh)")
    points = np.load(files["points"], allow_pickle=False)
    proxy = make_proxy(obj, points, scene)
    link_model(obj, result.get("path") or files.get("model"))
    return {"image": neural.name, "reference_image": reference.name, "proxy": proxy.name,
            "points": int(len(points))}


def show_image(image) -> bool:
    """Show `image` in an Image Editor: one already open in any window, else the one Blender's render view opens
    (the user's "Render Display" preference: a new window by default). False in background mode or without a
    window."""
    if bpy.app.background or image is None:
        return False
    wm = bpy.context.window_manager

    def editor():
        return next((a for w in wm.windows for a in w.screen.areas if a.type == "IMAGE_EDITOR"), None)

    area = editor()
    if area is None and wm.windows:
        window = wm.windows[0]
        view = next((a for a in window.screen.areas if a.type == "VIEW_3D"), window.screen.areas[0])
        try:
            with bpy.context.temp_override(window=window, area=view):
                bpy.ops.render.view_show("INVOKE_DEFAULT")
        except (RuntimeError, AttributeError, TypeError):
            return False
        area = editor()
    if area is None:
        return False
    area.spaces.active.image = image
    area.tag_redraw()
    return True


def _relative_link(path: Path, blend: str | Path | None) -> str:
    """`path` as a model link: "//" + relative to the folder of `blend` (a saved .blend), else absolute (no .blend,
    or another drive on Windows)."""
    if not blend:
        return str(path)
    try:
        return "//" + Path(os.path.relpath(path, Path(blend).resolve().parent)).as_posix()
    except ValueError:
        return str(path)


def link_model(obj, model: str | None) -> None:
    """Point the object at its model for the NBVH render engine: relative to the .blend when it is saved (so
    the link survives moving the project folder), else absolute."""
    if not model or not hasattr(obj, "nbvh_model"):
        return
    obj.nbvh_model = _relative_link(Path(model).resolve(), bpy.data.filepath)


def relink_models(target_blend: str | Path) -> int:
    """Rewrite every object's model link relative to `target_blend` (a .blend about to be saved elsewhere, whose
    folder "//" will then mean); a link whose file is missing is left as it is. Returns the links rewritten."""
    count = 0
    for obj in bpy.data.objects:
        link = getattr(obj, "nbvh_model", "")
        if not link:
            continue
        path = Path(bpy.path.abspath(link)).resolve()
        if not path.is_file():
            continue
        obj.nbvh_model = _relative_link(path, target_blend)
        count += 1
    return count


def camera_for(context, obj, width: int = 256, height: int = 256) -> dict | None:
    """The scene camera (or the viewport's view when there is none), in the object's local coordinates."""
    import math

    inv = obj.matrix_world.inverted()
    cam = context.scene.camera
    if cam is not None and cam.type == "CAMERA" and cam.data.type == "PERSP":
        m = inv @ cam.matrix_world
        r = context.scene.render
        aspect = (r.resolution_x * r.pixel_aspect_x) / max(r.resolution_y * r.pixel_aspect_y, 1e-9)
        height = max(1, round(width / aspect))
        # Blender's `angle` spans the sensor width, which (sensor fit AUTO/HORIZONTAL) maps to the larger image
        # side; our cameras take the vertical field of view.
        fit = cam.data.sensor_fit
        if fit == "VERTICAL":
            fov_v = cam.data.angle_y
        elif fit == "HORIZONTAL" or aspect >= 1:
            fov_v = 2 * math.atan(math.tan(cam.data.angle_x / 2) / aspect)
        else:
            fov_v = cam.data.angle_x
        return {"position": list(m.translation), "target": list(m @ Vector((0, 0, -1))),
                "up": list((m.to_3x3() @ Vector((0, 1, 0))).normalized()), "fov_deg": math.degrees(fov_v),
                "width": width, "height": height}
    area = next((a for a in (context.screen.areas if context.screen else []) if a.type == "VIEW_3D"), None)
    if area is None:
        return None
    r3d = area.spaces.active.region_3d
    view = inv @ r3d.view_matrix.inverted()
    return {"position": list(view.translation), "target": list(view @ Vector((0, 0, -1))),
            "up": list((view.to_3x3() @ Vector((0, 1, 0))).normalized()), "fov_deg": 50.0,
            "width": width, "height": height}


def delete_files(result: dict) -> None:
    """Remove a result's files (the user's own files are never in this list)."""
    for p in (result.get("files") or {}).values():
        Path(p).unlink(missing_ok=True)
