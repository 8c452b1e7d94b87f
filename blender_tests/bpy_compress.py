"""Run compress.py with the bpy module as `blender -b FILE.blend -P compress.py -- ARGS` would:
    python bpy_compress.py compress.py [--blend FILE.blend] ARGS
"""
import runpy
import sys

script = sys.argv[1]
rest = sys.argv[2:]
if rest[:1] == ["--blend"]:
    import bpy

    bpy.ops.wm.open_mainfile(filepath=rest[1])
    rest = rest[2:]
sys.argv = [script, "--", *rest]
runpy.run_path(script, run_name="__main__")
