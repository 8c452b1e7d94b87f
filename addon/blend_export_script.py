"""Run by nbvh_core/app/blend_export.py inside Blender (`blender -b FILE.blend --python THIS -- OUT_DIR`; 2.8+ API,
tested on 3.4 and 5.0): every mesh object, evaluated (modifiers applied) and triangulated, in object-local
coordinates, to OUT_DIR/<object>.npz (`vertices` (V, 3) float32, `faces` (F, 3) int32); the last line printed is
"NBVH_EXPORT " + JSON [[object name, path], ...]. Blender-side code, so it lives with the add-on, not in nbvh_core.
"""
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
