#!/usr/bin/env bash
# A real screenshot of the add-on in Blender 3.4 with a window (Xvfb): the viewport in Rendered shading on the
# NBVH engine, the NBVH panel after a Compress job run in that session (blender_tests/screenshot.py).
#   bash scripts/screenshot.sh MODELS_DIR OUT.png [screenshot.py options]
# Needs Debian's blender, xvfb, imagemagick (apt-get install blender xvfb imagemagick python3-numpy).
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
MODELS="$(realpath "$1")"; OUT="$(realpath -m "$2")"; shift 2
USERDIR="$(mktemp -d)"
trap 'rm -rf "$USERDIR"' EXIT
export BLENDER_USER_SCRIPTS="$USERDIR/scripts" BLENDER_USER_CONFIG="$USERDIR/config"
export NBVH_PYTHON="${NBVH_PYTHON:-$ROOT/.venv/bin/python}"
ZIP="$("$ROOT/.venv/bin/python" -c "import sys; sys.path.insert(0, '$ROOT'); from pathlib import Path; from build_addon import build; print(build(Path('$USERDIR/dist')))")"
blender -b --factory-startup --python-expr "import bpy; bpy.ops.preferences.addon_install(filepath='$ZIP'); bpy.ops.preferences.addon_enable(module='nbvh'); bpy.context.preferences.view.show_splash = False; bpy.ops.wm.save_userpref()" >/dev/null
xvfb-run -a -s "-screen 0 1600x900x24" blender --enable-event-simulate --addons nbvh \
    --python "$ROOT/blender_tests/screenshot.py" -- "$OUT" --models "$MODELS" "$@" | grep "screenshot:"
