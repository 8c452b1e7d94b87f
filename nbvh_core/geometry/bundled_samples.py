"""Where the bundled sample meshes live (the repository's `assets/` folder)."""
from __future__ import annotations

from pathlib import Path

ASSETS = Path(__file__).resolve().parents[2] / "assets"  # nbvh_core/geometry/ -> the repository

#: name -> what the sample is for (see assets/README.md)
SAMPLE_NAMES = {
    "blob": "smooth organic shape",
    "studs": "many small repeated details (211k triangles)",
    "gyroid": "thin walls and holes",
    "terrain": "open (non-watertight) surface",
    "bunny": "real scan with holes (Stanford bunny)",
}


def sample_path(name: str) -> Path:
    """Path of a bundled sample by name, e.g. 'bunny' -> assets/bunny.ply.gz."""
    if name not in SAMPLE_NAMES:
        raise KeyError(f"unknown sample {name!r}; bundled: {', '.join(SAMPLE_NAMES)}")
    return ASSETS / f"{name}.ply.gz"
