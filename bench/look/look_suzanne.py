"""A textured, two-material asset through the whole product, against Cycles.

Suzanne, subdivided twice (applied), Smart UV Project; slot 0 an image texture (512 px), slot 1 plain blue; the
add-on's export; `preview` preset (60 s); the model linked to the object; a sun and a point light, black world.
Renders the saved scene with the NBVH engine (final render, bpy in-process: a Blender 5 .blend does not open in
Debian's 3.4 binary) and with Cycles direct light only (0 bounces, no denoising), then scores the NBVH image
against Cycles: FLIP (NVIDIA, `flip-evaluator`), MSE, and each material's mean colour over its pixels.

    .venv/bin/python -m bench.look.look_suzanne bench/results/look_suzanne [--seconds 60] [--size 512]

Writes OUT/figure.png (NBVH | Cycles) and one row in bench/results/look_suzanne.csv; OUT/scene.blend,
OUT/suzanne.{nbvh,npz} (the add-on's export, for `bench_look.py --npz`), OUT/{nbvh,cycles,masks}.png stay
uncommitted (.gitignore).
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]

import bpy

from bench.harness import RESULTS, append_rows, save_image


def build_scene(size: int):
    """The asset, its materials, lights and camera in an empty scene; returns (scene, object)."""
    from nbvh_core.geometry.demo_assets import pattern

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    bpy.ops.mesh.primitive_monkey_add(size=2.0)
    obj = bpy.context.active_object
    obj.name = "Suzanne"
    sub = obj.modifiers.new("subdivide", "SUBSURF")
    sub.levels = sub.render_levels = 2
    bpy.ops.object.modifier_apply(modifier=sub.name)
    bpy.ops.object.mode_set(mode="EDIT")
    bpy.ops.mesh.select_all(action="SELECT")
    bpy.ops.uv.smart_project()
    bpy.ops.object.mode_set(mode="OBJECT")
    img = bpy.data.images.new("pattern", 512, 512)
    px = np.concatenate([pattern(512)[::-1].astype(np.float32) / 255, np.ones((512, 512, 1), np.float32)], 2)
    img.pixels.foreach_set(px.ravel())
    img.pack()
    textured = _material("painted", (0.8, 0.8, 0.8, 1.0), img)
    blue = _material("blue", (0.05, 0.15, 0.7, 1.0), None)
    obj.data.materials.append(textured)
    obj.data.materials.append(blue)
    centres = np.empty(len(obj.data.polygons) * 3, np.float32)
    obj.data.polygons.foreach_get("center", centres)
    obj.data.polygons.foreach_set("material_index", (centres.reshape(-1, 3)[:, 0] > 0.25).astype(np.int32))
    obj.data.update()
    sun = bpy.data.objects.new("Sun", bpy.data.lights.new("Sun", "SUN"))
    sun.data.energy = 3.0
    sun.rotation_euler = (0.7, 0.3, 0.6)
    lamp = bpy.data.objects.new("Lamp", bpy.data.lights.new("Lamp", "POINT"))
    lamp.data.energy = 300.0
    lamp.location = (-3.0, -4.0, 3.0)
    cam = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    cam.location = (0.0, -6.5, 0.6)
    cam.rotation_euler = (1.48, 0.0, 0.0)
    for o in (sun, lamp, cam):
        scene.collection.objects.link(o)
    scene.camera = cam
    world = bpy.data.worlds.new("black")
    world.color = (0.0, 0.0, 0.0)
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (0, 0, 0, 1)
    scene.world = world
    scene.render.resolution_x = scene.render.resolution_y = size
    scene.render.resolution_percentage = 100
    scene.view_settings.view_transform = "Standard"
    return scene, obj


def _material(name: str, color, image):
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    mat.diffuse_color = color
    bsdf = next(n for n in mat.node_tree.nodes if n.type == "BSDF_PRINCIPLED")
    bsdf.inputs["Base Color"].default_value = color
    for key in ("Specular IOR Level", "Specular"):  # diffuse only: the NBVH engine shades Lambert
        if key in bsdf.inputs:
            bsdf.inputs[key].default_value = 0.0
    if "Roughness" in bsdf.inputs:
        bsdf.inputs["Roughness"].default_value = 1.0
    if image is not None:
        tex = mat.node_tree.nodes.new("ShaderNodeTexImage")
        tex.image = image
        tex.interpolation = "Linear"
        mat.node_tree.links.new(tex.outputs["Color"], bsdf.inputs["Base Color"])
    return mat


def compress(obj, out: Path, seconds: float) -> tuple[Path, dict]:
    """The add-on's export of `obj`, compressed with the preview preset in `seconds`; the model path and facts."""
    from addon import export
    from nbvh_core.geometry.look import look_from_arrays
    from nbvh_core.geometry.mesh import mesh_from_arrays
    from nbvh_core.app.pipeline import compress_mesh, preset

    verts, tris, _, look = export.evaluated_triangles(obj, bpy.context.evaluated_depsgraph_get())
    np.savez(out / "suzanne.npz", vertices=verts, faces=tris, **look)  # for bench_look.py --npz
    mesh = mesh_from_arrays(verts, tris, "suzanne", look_from_arrays(look, "suzanne"))
    path = out / "suzanne.nbvh"
    t = time.perf_counter()
    r = compress_mesh(mesh, preset("preview").with_overrides(time_limit_s=seconds, force=True), path)
    meta = r.model.metadata if r.model.metadata else {}
    head = r.model.appearance.cfg if r.model.appearance is not None else None
    return path, {"triangles": mesh.n_triangles, "file_bytes": r.file_bytes, "wall_s": round(time.perf_counter() - t, 1),
                  "appearance_bytes": r.components.get("appearance", 0), "texture_bytes": r.components.get("textures", 0),
                  "patches": head.patches if head else 0, "mse": r.quality.mse if r.quality else None, **meta}


def render(scene, engine: str, path: Path) -> np.ndarray:
    """(H, W, 3) sRGB-encoded float of a final render with `engine`."""
    scene.render.engine = engine
    scene.render.filepath = str(path)
    scene.render.image_settings.file_format = "PNG"
    bpy.ops.render.render(write_still=True)
    from PIL import Image

    return np.asarray(Image.open(path).convert("RGB"), np.float32) / 255


def material_masks(scene, obj, path: Path) -> list[np.ndarray]:
    """(H, W) bool per material slot: its pixels, from a flat Workbench render with one colour per slot."""
    saved = [tuple(m.diffuse_color) for m in obj.data.materials]
    for m, c in zip(obj.data.materials, ((1, 0, 0, 1), (0, 1, 0, 1))):
        m.diffuse_color = c
    shading = scene.display.shading
    shading.light, shading.color_type = "FLAT", "MATERIAL"
    scene.render.engine = "BLENDER_WORKBENCH"
    img = render(scene, "BLENDER_WORKBENCH", path)
    for m, c in zip(obj.data.materials, saved):
        m.diffuse_color = c
    return [(img[..., 0] > 0.5) & (img[..., 1] < 0.5), (img[..., 1] > 0.5) & (img[..., 0] < 0.5)]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("out", type=Path)
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--cycles-samples", type=int, default=64)
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    import addon

    addon.register()
    scene, obj = build_scene(args.size)
    model, facts = compress(obj, args.out, args.seconds)
    obj.nbvh_model = str(model)
    bpy.ops.wm.save_as_mainfile(filepath=str(args.out / "scene.blend"))
    scene.cycles.samples = args.cycles_samples
    scene.cycles.max_bounces = 0
    scene.cycles.use_denoising = False
    scene.cycles.device = "CPU"
    t = time.perf_counter()
    cycles = render(scene, "CYCLES", args.out / "cycles.png")
    cycles_s = time.perf_counter() - t
    t = time.perf_counter()
    nbvh = render(scene, "NBVH", args.out / "nbvh.png")
    nbvh_s = time.perf_counter() - t
    masks = material_masks(scene, obj, args.out / "masks.png")
    import flip_evaluator

    flip = float(flip_evaluator.evaluate(cycles, nbvh, "LDR", applyMagma=False)[1])
    means = [(float(np.abs(nbvh[m].mean(0) - cycles[m].mean(0)).max()) if m.any() else float("nan")) for m in masks]
    from PIL import Image

    gap = np.ones((args.size, 8, 3), np.float32)
    save_image(Image.fromarray((np.concatenate([nbvh, gap, cycles], 1) * 255 + 0.5).astype(np.uint8)), args.out / "figure.png")
    row = {"size": args.size,
           "seconds": args.seconds, "triangles": facts["triangles"], "file_bytes": facts["file_bytes"],
           "appearance_bytes": facts["appearance_bytes"], "texture_bytes": facts["texture_bytes"],
           "patches": facts["patches"], "geometry_mse": facts["mse"], "compress_wall_s": facts["wall_s"],
           "flip": round(flip, 4), "mse": round(float(((nbvh - cycles) ** 2).mean()), 5),
           "mean_colour_error_textured": round(means[0], 4), "mean_colour_error_blue": round(means[1], 4),
           "nbvh_render_s": round(nbvh_s, 1), "cycles_render_s": round(cycles_s, 1)}
    append_rows(RESULTS / "look_suzanne.csv", [row])
    print(row)


if __name__ == "__main__":
    main()
