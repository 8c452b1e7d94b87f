#!/usr/bin/env bash
# Every test: the nbvh_core unit tests (pytest), then the add-on inside real Blender (bpy 5.0 module and
# Debian's blender 3.4 binary, installed here when missing). Extra arguments go to pytest.
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/ensure_venv.sh"
source "$(dirname "${BASH_SOURCE[0]}")/ensure_blender.sh"
cd "$NBVH_ROOT"
"$NBVH_PY" -m pytest tests --durations=15 "$@"  # the slowest 15 listed: where the suite's time goes
"$NBVH_PY" blender_tests/run.py
