"""NBVH: compress meshes into neural BVH geometry and preview them (3D viewport > sidebar > NBVH).

Blender 4.2+ installs it as an extension (blender_manifest.toml); older Blender (3.4+) as a legacy add-on
through `bl_info`. Training runs in a separate Python process with PyTorch (see job.py); this package never
imports torch.
"""
bl_info = {
    "name": "NBVH Neural Geometry",
    "author": "NBVH team",
    "version": (0, 1, 0),
    "blender": (3, 4, 0),
    "location": "3D Viewport > Sidebar > NBVH",
    "description": "Compress meshes into neural BVH geometry and preview them",
    "category": "Mesh",
}


def register():
    from . import panel, render_engine

    panel.register()
    render_engine.register()


def unregister():
    from . import panel, render_engine

    render_engine.unregister()
    panel.unregister()
