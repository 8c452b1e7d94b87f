"""A real screenshot of Blender with a window (Debian's Blender 3.4 under Xvfb): the 3D viewport in Rendered
shading on the NBVH engine, the NBVH sidebar panel after a Compress job it ran in that session.

    xvfb-run -a -s "-screen 0 1600x900x24" blender --enable-event-simulate --addons nbvh \\
        --python blender_tests/screenshot.py -- OUT.png --models MODELS_DIR [--compress OBJECT] [--time-limit 15]

With --models it first builds the engine test scene (engine_scene.py) in a temporary folder; without, it works on
the .blend given to Blender. It drives the UI from a timer as a user would: Rendered shading through the scene camera, the sidebar on the NBVH tab, Compress
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
ap.add_argument("--preset", default="default")
ap.add_argument("--time-limit", type=int, default=60)
ap.add_argument("--timeout", type=float, default=300)
ap.add_argument("--models", help="build the engine test scene from these models first")
ap.add_argument("--show-image", action="store_true", help="leave 'Show result in Image Editor' on")
args = ap.parse_args(argv)
state = {"phase": "setup", "t0": time.monotonic(), "since": 0.0, "code": 0}


def view3d():
    window = bpy.context.window_manager.windows[0]
    area = max((a for a in window.screen.areas if a.type == "VIEW_3D"), key=lambda a: a.width * a.height)
    return window, area


def setup() -> None:
    window, area = view3d()
    if args.models:
        import tempfile
        from pathlib import Path

        sys.path.insert(0, str(Path(__file__).resolve().parent))
        import engine_scene

        with bpy.context.temp_override(window=window, area=area):
            engine_scene.build(Path(args.models), Path(tempfile.mkdtemp(prefix="nbvh-shot-")), width=640, height=360)
    space = area.spaces.active
    space.shading.type = "RENDERED"
    space.show_region_ui = True
    space.region_3d.view_perspective = "CAMERA"
    bpy.context.preferences.view.show_splash = False
    props = bpy.context.scene.nbvh_props
    props.preset, props.time_limit_s, props.force = args.preset, args.time_limit, True
    props.show_image = args.show_image  # off by default: a second window would cover the one photographed
    obj = bpy.data.objects[args.compress]
    for o in bpy.context.scene.objects:
        o.select_set(o == obj)
    bpy.context.view_layer.objects.active = obj
    region = next(r for r in area.regions if r.type == "WINDOW")
    with bpy.context.temp_override(window=window, area=area, region=region):
        bpy.ops.nbvh.compress()


def click_sidebar_tab(name: str) -> None:
    """Click the sidebar's tab as a user would (Blender 3.4's Python cannot select a tab): a simulated mouse click
    (Blender started with --enable-event-simulate) on the tab column, at the height of the tab's label (tabs are
    stacked from the top in registration order)."""
    window, area = view3d()
    ui = next(r for r in area.regions if r.type == "UI")
    tabs = ["Item", "Tool", "View", name]  # the default startup's sidebar tabs, then the add-on's
    scale = bpy.context.preferences.system.ui_scale
    x = ui.x + ui.width - int(10 * scale)
    y = ui.y + ui.height - int((14 + sum(len(t) * 7 + 18 for t in tabs[:-1]) + len(name) * 3.5) * scale)
    window.event_simulate(type="MOUSEMOVE", value="NOTHING", x=x, y=y)
    window.event_simulate(type="LEFTMOUSE", value="PRESS", x=x, y=y)
    window.event_simulate(type="LEFTMOUSE", value="RELEASE", x=x, y=y)
    window.event_simulate(type="MOUSEMOVE", value="NOTHING", x=200, y=120)
    print(f"screenshot: clicked the {name} tab at {x}, {y} (window coordinates)")


def tick():
    now = time.monotonic()
    props = bpy.context.scene.nbvh_props
    if state["phase"] == "setup":
        setup()
        state["phase"] = "compressing"
    elif state["phase"] == "compressing" and now - state["t0"] > 8 and not state.get("tab"):
        click_sidebar_tab("NBVH")
        state["tab"] = True
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
