#!/usr/bin/env bash
# Source me after ensure_venv.sh. Makes both Blender flavours the add-on is tested on available:
#   * Blender 5.0 as a Python module: pip install bpy==5.0.1 into .venv (needs numpy < 2, which we pin);
#   * Blender 3.4: Debian's `blender` package (+ python3-numpy for its system Python).
set -euo pipefail
if ! "$NBVH_PY" -c "import bpy" >/dev/null 2>&1; then
  echo "installing bpy==5.0.1 (Blender 5.0 as a Python module) into .venv" >&2
  "$NBVH_PY" -m pip install -q "bpy==5.0.1"
fi
if ! command -v blender >/dev/null 2>&1; then
  echo "installing Debian's blender and python3-numpy (apt-get)" >&2
  SUDO=""
  [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq blender python3-numpy >/dev/null
fi
# Both must start now, or the tests would silently run on one.
"$NBVH_PY" -c "import bpy" || { echo "bpy==5.0.1 was installed but does not import" >&2; exit 1; }
blender -b --factory-startup --python-expr "import bpy" >/dev/null 2>&1 \
  || { echo "Debian's blender was installed but does not start headless" >&2; exit 1; }
