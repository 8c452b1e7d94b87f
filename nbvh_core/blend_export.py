"""Mesh objects out of a .blend file, through a `blender` binary run headless (nbvh_core never imports bpy: the
script below runs in Blender's own process and writes one .npz per object).

    export_blend(Path("props.blend"), Path("cache/props"), blender="blender") -> [(object name, npz path), ...]

Each object is exported as Blender evaluates it (modifiers applied), triangulated, in object-local coordinates;
objects without triangles are left out. Plain Python, no torch.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

#: Runs inside Blender (2.8+ API, tested on 3.4 and 5.0): argv after "--" is the output folder.
EXPORT_SCRIPT = r'''
import json, os, re, sys
import bpy
import numpy as np

out = sys.argv[sys.argv.index("--") + 1]
os.makedirs(out, exist_ok=True)
deps = bpy.context.evaluated_depsgraph_get()
done = []
for obj in bpy.data.objects:
    if obj.type != "MESH":
        continue
    ev = obj.evaluated_get(deps)
    mesh = ev.to_mesh()
    try:
        mesh.calc_loop_triangles()
        nv, nt = len(mesh.vertices), len(mesh.loop_triangles)
        if nt == 0:
            continue
        v = np.empty(nv * 3, np.float32)
        mesh.vertices.foreach_get("co", v)
        f = np.empty(nt * 3, np.int32)
        mesh.loop_triangles.foreach_get("vertices", f)
    finally:
        ev.to_mesh_clear()
    safe = re.sub(r"[^A-Za-z0-9_.-]+", "_", obj.name)
    path = os.path.join(out, safe + ".npz")
    np.savez(path, vertices=v.reshape(-1, 3), faces=f.reshape(-1, 3))
    done.append([obj.name, path])
print("NBVH_EXPORT " + json.dumps(done))
'''


def find_blender() -> str | None:
    """The `blender` binary: $NBVH_BLENDER, else `blender` on PATH; None when there is none."""
    return os.environ.get("NBVH_BLENDER") or shutil.which("blender")


def export_blend(blend: Path, out_dir: Path, blender: str | None = None, timeout_s: float = 600.0) -> list[tuple[str, Path]]:
    """Export every mesh object of `blend` to `out_dir/<object>.npz` (arrays `vertices` (V, 3) float32 and `faces`
    (F, 3) int32); returns [(object name, path)]. Raises ValueError (no Blender, a damaged file, a timeout)."""
    blender = blender or find_blender()
    if blender is None:
        raise ValueError(f"{blend}: a .blend needs a `blender` binary (none on PATH; set NBVH_BLENDER)")
    out_dir.mkdir(parents=True, exist_ok=True)
    cmd = [blender, "-b", "--factory-startup", str(blend), "--python-expr", EXPORT_SCRIPT, "--", str(out_dir)]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        raise ValueError(f"{blend}: Blender took more than {timeout_s:.0f} s to export it") from None
    except OSError as exc:
        raise ValueError(f"{blend}: could not run Blender ({blender}): {exc}") from None
    line = next((ln for ln in proc.stdout.splitlines() if ln.startswith("NBVH_EXPORT ")), None)
    if proc.returncode != 0 or line is None:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
        raise ValueError(f"{blend}: Blender could not export it (exit {proc.returncode}): {' | '.join(tail)}")
    return [(name, Path(path)) for name, path in json.loads(line[len("NBVH_EXPORT "):])]
