"""The render engine's test scene, shared by the Blender tests, the README figure and the screenshot script:
three objects with models (rotated, scaled, moved), a ground plane without one (drawn from its mesh), a sun and a
warm point light, a camera. The models are copied beside the saved .blend and linked relative to it.

MODELS holds NAME.npz (object-local `vertices`, `faces`: the coordinates each model was trained in) and
NAME.nbvh for NAME in `PLACED`.
"""
from __future__ import annotations

import math
from pathlib import Path

import bpy
import numpy as np
from mathutils import Vector

#: name -> (centre location, rotation (XYZ Euler, radians), base colour)
PLACED = {"blob": ((-1.4, 0.0, 0.0), (0.0, 0.0, 0.4), (0.8, 0.3, 0.2)),
          "bunny": ((0.0, 0.2, 0.0), (0.3, 0.0, -0.6), (0.85, 0.85, 0.85)),
          "studs": ((1.4, 0.0, 0.0), (0.0, 0.2, 0.9), (0.2, 0.55, 0.8))}


def mesh_object(name: str, verts: np.ndarray, faces: np.ndarray):
    me = bpy.data.meshes.new(name)
    me.from_pydata(np.asarray(verts, float).tolist(), [], np.asarray(faces, int).tolist())
    me.update()
    obj = bpy.data.objects.new(name, me)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def set_base_color(obj, rgb) -> None:
    """A material whose Principled base colour (and viewport colour) is `rgb`."""
    mat = bpy.data.materials.new(f"{obj.name} paint")
    mat.diffuse_color = (*rgb, 1.0)
    if bpy.app.version < (5, 0, 0):
        mat.use_nodes = True
    bsdf = next((n for n in mat.node_tree.nodes if n.type == "BSDF_PRINCIPLED"), None) if mat.node_tree else None
    if bsdf is not None:
        bsdf.inputs["Base Color"].default_value = (*rgb, 1.0)
    obj.data.materials.append(mat)


def build(models: Path, folder: Path, make_object=None, width: int = 320, height: int = 180):
    """Empty the current scene, build the test scene, save it as folder/scene.blend with the models in
    folder/models (linked relative to it). Returns (scene, folder)."""
    make_object = make_object or (lambda name, v, f: mesh_object(name, v, f))
    scene = bpy.context.scene
    for obj in list(scene.objects):
        bpy.data.objects.remove(obj)
    (folder / "models").mkdir(parents=True, exist_ok=True)
    for name, (loc, rot, rgb) in PLACED.items():
        data = np.load(models / f"{name}.npz")
        v = data["vertices"]  # the coordinates the model was trained in: they must stay the object's own
        obj = make_object(name, v, data["faces"])
        obj.rotation_euler = rot
        obj.scale = (1.1 / float(np.ptp(v, axis=0).max()),) * 3
        bpy.context.view_layer.update()
        centre = obj.matrix_world @ Vector(((v.max(0) + v.min(0)) / 2).tolist())
        obj.location = Vector(loc) - (centre - obj.location)
        set_base_color(obj, rgb)
        (folder / "models" / f"{name}.nbvh").write_bytes((models / f"{name}.nbvh").read_bytes())
    ground = make_object("Ground", np.array([[-4, -4, -0.6], [4, -4, -0.6], [4, 4, -0.6], [-4, 4, -0.6]], float),
                         np.array([[0, 1, 2], [0, 2, 3]]))
    set_base_color(ground, (0.5, 0.5, 0.5))
    sun = bpy.data.objects.new("Sun", bpy.data.lights.new("Sun", "SUN"))
    sun.data.energy = 2.5
    sun.rotation_euler = (0.6, 0.2, 0.4)
    lamp = bpy.data.objects.new("Lamp", bpy.data.lights.new("Lamp", "POINT"))
    lamp.data.energy = 400.0
    lamp.data.color = (1.0, 0.85, 0.7)
    lamp.location = (2.0, -3.0, 3.0)
    cam = bpy.data.objects.new("Cam", bpy.data.cameras.new("Cam"))
    cam.location = (0.0, -5.2, 2.2)
    cam.rotation_euler = (math.radians(68), 0.0, 0.0)
    for obj in (sun, lamp, cam):
        scene.collection.objects.link(obj)
    scene.camera = cam
    scene.render.engine = "NBVH"
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = width, height, 100
    scene.render.image_settings.file_format = "PNG"
    scene.nbvh_render.samples = 4
    bpy.ops.wm.save_as_mainfile(filepath=str(folder / "scene.blend"))
    for name in PLACED:
        bpy.data.objects[name].nbvh_model = bpy.path.relpath(str(folder / "models" / f"{name}.nbvh"))
    bpy.ops.wm.save_mainfile()
    return scene, folder


def image_pixels(path) -> np.ndarray:
    """(H, W, 4) float32 pixels of an image file as Blender reads it (row 0 at the bottom); the image is not kept."""
    img = bpy.data.images.load(str(path))
    w, h = img.size
    px = np.empty(w * h * 4, np.float32)
    img.pixels.foreach_get(px)
    bpy.data.images.remove(img)
    return px.reshape(h, w, 4)
