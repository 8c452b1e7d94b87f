"""The README's render-engine figure: the engine test scene (three .nbvh models + a mesh ground, a sun, a point
light) rendered by `blender -b scene.blend --addons nbvh -E NBVH -f 1`, beside Blender's own Cycles render of the
original meshes, both by the same Blender (a .blend saved by Blender 5 does not open in 3.4).

    blender -b --factory-startup --python blender_tests/make_engine_figure.py -- MODELS_DIR docs/engine_render.png
    .venv/bin/python blender_tests/make_engine_figure.py MODELS_DIR OUT.png      (bpy 5.0: renders in-process)

MODELS_DIR: blob/bunny/studs .npz + .nbvh (see engine_scene.py). Prints both render times.
"""
import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import bpy
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "blender_tests"))

import addon  # noqa: E402
import engine_scene  # noqa: E402
from build_addon import build  # noqa: E402

ap = argparse.ArgumentParser()
ap.add_argument("models", type=Path)
ap.add_argument("out", type=Path)
ap.add_argument("--width", type=int, default=640)
ap.add_argument("--cycles-samples", type=int, default=64)
args = ap.parse_args(sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:])

work = Path(tempfile.mkdtemp(prefix="nbvh-figure-"))
addon.register()
scene, folder = engine_scene.build(args.models, work / "scene", width=args.width, height=args.width * 9 // 16)

# Blender's own render of the original meshes.
scene.render.engine = "CYCLES"
scene.cycles.samples = args.cycles_samples
scene.cycles.device = "CPU"
scene.cycles.use_denoising = False  # Debian's Blender has no OpenImageDenoise
scene.render.filepath = str(work / "cycles.png")
t0 = time.monotonic()
bpy.ops.render.render(write_still=True)
cycles_s = time.monotonic() - t0
scene.render.engine = "NBVH"
bpy.ops.wm.save_mainfile()

blender = bpy.app.binary_path if bpy.app.binary_path and Path(bpy.app.binary_path).name.startswith("blender") else ""
nbvh_png = work / "nbvh_0001.png"
t0 = time.monotonic()
if blender:
    user = work / "user"
    env = dict(os.environ, BLENDER_USER_SCRIPTS=str(user / "scripts"), BLENDER_USER_CONFIG=str(user / "config"))
    env.pop("PYTHONPATH", None)
    zip_path = build(work / "dist")
    subprocess.run([blender, "-b", "--factory-startup", "--python-expr",
                    f"import bpy; bpy.ops.preferences.addon_install(filepath={str(zip_path)!r}); "
                    "bpy.ops.preferences.addon_enable(module='nbvh'); bpy.ops.wm.save_userpref()"],
                   check=True, env=env, capture_output=True)
    t0 = time.monotonic()
    r = subprocess.run([blender, "-b", str(folder / "scene.blend"), "--addons", "nbvh", "-E", "NBVH", "-o",
                        str(work / "nbvh_####"), "-F", "PNG", "-f", "1"], env=env, capture_output=True, text=True)
    if not nbvh_png.exists():
        sys.exit(f"the NBVH render failed:\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}")
    how = f"blender {bpy.app.version_string} -b scene.blend -E NBVH -f 1"
else:
    scene.render.filepath = str(nbvh_png)
    bpy.ops.render.render(write_still=True)
    how = f"bpy {bpy.app.version_string} render, engine NBVH"
nbvh_s = time.monotonic() - t0



left, right = engine_scene.image_pixels(nbvh_png), engine_scene.image_pixels(work / "cycles.png")
gap = np.ones((left.shape[0], 8, 4), np.float32)
both = np.concatenate([left, gap, right], axis=1)
out = bpy.data.images.new("figure", both.shape[1], both.shape[0])
out.pixels.foreach_set(both.ravel())
args.out.parent.mkdir(parents=True, exist_ok=True)
out.filepath_raw = str(args.out.resolve())
out.file_format = "PNG"
out.save()
print(f"wrote {args.out}: left {how} in {nbvh_s:.1f} s (Blender start included), right Cycles "
      f"{args.cycles_samples} samples in {cycles_s:.1f} s, {left.shape[1]} x {left.shape[0]}")
shutil.rmtree(work, ignore_errors=True)
