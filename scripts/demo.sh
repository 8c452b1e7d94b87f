#!/usr/bin/env bash
# The main job on a bundled sample: compress it into neural geometry and write the model, its report and a
# previews (the model and the mesh from the same view) to out/<name>/.
# Usage: scripts/demo.sh [SAMPLE or MESH FILE] [compress options, e.g. --preset preview]   (default: bunny)
#        (no options: --preset default --force, the model whatever the verdict, which its report and the last line
#        state; --need: the need-driven default, which may answer "keep as a mesh")
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/ensure_venv.sh"
cd "$NBVH_ROOT"
sample=${1:-bunny}
shift || true
name=$(basename "${sample%%.*}")
mkdir -p "out/$name"
if [ $# -eq 0 ]; then
  set -- --preset default --force
elif [ "$1" = "--need" ]; then
  shift
fi
# --overwrite: the demo owns out/NAME and replaces its own earlier result (only once the new one is complete)
rc=0
"$NBVH_PY" -m nbvh_core compress "$sample" -o "out/$name/$name.nbvh" --overwrite "$@" || rc=$?
if [ "$rc" -eq 4 ]; then  # kept as a mesh: the winning decimation or mesh is in out/NAME/
  echo "decided: kept as a mesh (it is smaller than the model at the same measured quality; see the lines above)"
  exit 0
elif [ "$rc" -ne 0 ]; then
  exit "$rc"
fi
"$NBVH_PY" -m nbvh_core info "out/$name/$name.nbvh" --mesh "$sample"
# one line: what was decided and why (the final verdict of a sized run, else the verdict before training)
"$NBVH_PY" -c 'import json, sys; r = json.load(open(sys.argv[1])); f = (r.get("decisions") or {}).get("final"); print("decided: " + (f["message"] if f else "the model (no alternative measured; before training: " + r["assessment"]["message"] + ")"))' "out/$name/$name.report.json"
