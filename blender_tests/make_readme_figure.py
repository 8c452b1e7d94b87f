"""The README's picture: top, Blender (bpy 5.0, Workbench, headless) rendering an original object next to the
point-cloud proxy the add-on loaded back from its .nbvh; bottom, the add-on's neural image from the same scene
camera (rendered by the model, not by Blender).

    .venv/bin/python blender_tests/make_readme_figure.py MODEL.nbvh SAMPLE_NAME docs/addon_preview.png

Runs the add-on's real code path (compress_session.start with load_model -> job -> previews.load_result).
"""
import sys
from pathlib import Path

import bpy
from mathutils import Vector

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from addon import compress_session  # noqa: E402
from addon.job import default_python  # noqa: E402
from nbvh_core.geometry.mesh import load_mesh  # noqa: E402
from nbvh_core.geometry.bundled_samples import sample_path  # noqa: E402

model_path, sample, out_png = sys.argv[1], sys.argv[2], Path(sys.argv[3])
for o in list(bpy.data.objects):
    bpy.data.objects.remove(o)
mesh = load_mesh(sample_path(sample))
verts = mesh.transform.to_original(mesh.vertices)  # the coordinates the model was trained in
me = bpy.data.meshes.new(sample)
me.from_pydata(verts.tolist(), [], mesh.faces.tolist())
me.update()
obj = bpy.data.objects.new(sample.capitalize(), me)
bpy.context.scene.collection.objects.link(obj)
# Object transform brings it to about unit size at the origin (the mesh data keeps the model's coordinates).
centre = (verts.max(0) + verts.min(0)) / 2
scale = 1.6 / float((verts.max(0) - verts.min(0)).max())
obj.scale = (scale,) * 3
obj.location = tuple(-centre * scale)
cam = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
bpy.context.scene.collection.objects.link(cam)
bpy.context.scene.camera = cam
scene0 = bpy.context.scene
scene0.render.resolution_x, scene0.render.resolution_y = 640, 320
cam.location = (0.95, -6.2, 1.7)
direction = Vector((0.95, 0, 0.05)) - cam.location
cam.rotation_euler = direction.to_track_quat("-Z", "Y").to_euler()
bpy.context.view_layer.update()

req = compress_session.Request(preset="default", out_dir=str(out_png.parent / "figure_out"), load_model=model_path,
                     proxy_points=60000, image_size=640)
session, refusals = compress_session.start(bpy.context, [obj], req, default_python())
assert not refusals, refusals
session.queue.wait()
compress_session.finish_done(session, bpy.context.scene)
assert obj.name in session.loaded, session.failures

scene = bpy.context.scene
scene.render.engine = "BLENDER_WORKBENCH"
scene.display.shading.light = "STUDIO"
scene.display.shading.color_type = "SINGLE"
scene.render.filepath = str(out_png.with_suffix(".blender.png"))
bpy.ops.render.render(write_still=True)

from PIL import Image  # noqa: E402

render = Image.open(scene.render.filepath).convert("RGB")
neural = Image.open(session.loaded[obj.name]["result"]["files"]["preview"]).convert("RGB")
canvas = Image.new("RGB", (640, 640))
canvas.paste(render, (0, 0))
canvas.paste(neural, (0, 320))
canvas.save(out_png)
print(f"wrote {out_png}")
