"""A real screenshot of Blender with a window (Debian's Blender 3.4 under Xvfb): the 3D viewport in Rendered
shading on the NBVH engine, the NBVH sidebar panel after a Compress job it ran in that session.

    xvfb-run -a -s "-screen 0 1600x900x24" blender SCENE.blend --addons nbvh \\
        --python blender_tests/screenshot.py -- OUT.png [--compress OBJECT] [--time-limit 15]

SCENE.blend: e.g. the engine test scene (engine_scene.py; make_engine_figure.py builds one). The script drives the
UI from a timer as a user would: Rendered shading through the scene camera, the sidebar on the NBVH tab, Compress
on OBJECT (preview preset), then waits for the job and the viewport's frames, takes the screenshot with
ImageMagick's `import -window root`, and quits; the last line says whether the job finished.
"""
import argparse
import subprocess
import sys
import time

import bpy

argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else []
ap = argparse.ArgumentParser()
ap.add_argument("out")
ap.add_argument("--compress", default="bunny")
ap.add_argument("--time-limit", type=int, default=15)
ap.add_argument("--timeout", type=float, default=300)
args = ap.parse_args(argv)
state = {"phase": "setup", "t0": time.monotonic(), "since": 0.0, "code": 0}


def view3d():
    window = bpy.context.window_manager.windows[0]
    area = max((a for a in window.screen.areas if a.type == "VIEW_3D"), key=lambda a: a.width * a.height)
    return window, area


def setup() -> None:
    window, area = view3d()
    space = area.spaces.active
    space.shading.type = "RENDERED"
    space.show_region_ui = True
    space.region_3d.view_perspective = "CAMERA"
    ui = next(r for r in area.regions if r.type == "UI")
    try:  # the sidebar's tab (writable in some versions; otherwise the tab the file remembers)
        ui.active_panel_category = "NBVH"
    except (AttributeError, TypeError):
        pass
    props = bpy.context.scene.nbvh_props
    props.preset, props.time_limit, props.force = "preview", args.time_limit, True
    props.show_image = False  # a second window would cover the one photographed
    obj = bpy.data.objects[args.compress]
    for o in bpy.context.scene.objects:
        o.select_set(o == obj)
    bpy.context.view_layer.objects.active = obj
    region = next(r for r in area.regions if r.type == "WINDOW")
    with bpy.context.temp_override(window=window, area=area, region=region):
        bpy.ops.nbvh.compress()


def tick():
    now = time.monotonic()
    props = bpy.context.scene.nbvh_props
    if state["phase"] == "setup":
        setup()
        state["phase"] = "compressing"
    elif state["phase"] == "compressing" and not props.running:
        print(f"screenshot: job ended: {props.phase} {props.last_error}")
        if props.phase != "done":
            state["code"] = 1
        state["phase"], state["since"] = "settle", now
    elif state["phase"] == "settle" and now - state["since"] > 10:  # the viewport's frames of the new model
        shoot()
        return None
    if now - state["t0"] > args.timeout:
        print("screenshot: timed out")
        state["code"] = 1
        shoot()
        return None
    return 0.5


def shoot() -> None:
    subprocess.run(["import", "-window", "root", args.out], check=False)
    print(f"screenshot: wrote {args.out} ({'ok' if state['code'] == 0 else 'with a failed job'})")
    bpy.ops.wm.quit_blender()


bpy.app.timers.register(tick, first_interval=3.0)
