#!/usr/bin/env bash
# The main job on a bundled sample: writes out/<sample>/report.json and preview images.
# Usage: scripts/demo.sh [SAMPLE or MESH FILE] (default: bunny)
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/ensure_venv.sh"
cd "$NBVH_ROOT"
sample=${1:-bunny}
"$NBVH_PY" -m nbvh_core inspect "$sample" --out "out/$(basename "${sample%%.*}")"
