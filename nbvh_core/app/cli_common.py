"""What the command line's commands share: a mesh argument resolved (a file or a bundled sample's name) and loaded
with its warnings printed, and byte counts as people read them."""
from __future__ import annotations

import sys
import warnings
from pathlib import Path

def resolve_mesh(arg: str) -> Path:
    """A mesh argument as a path: a bundled sample's name, else the file named."""
    from ..geometry.bundled_samples import SAMPLE_NAMES, sample_path

    if arg in SAMPLE_NAMES:
        return sample_path(arg)
    return Path(arg)


def load_mesh_reporting(arg: str):
    """The mesh of a mesh argument (`resolve_mesh`), each warning of its loading printed on stderr."""
    from ..geometry.mesh import load_mesh

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        mesh = load_mesh(resolve_mesh(arg))
    for w in caught:
        print(f"warning: {w.message}", file=sys.stderr)
    return mesh


def fmt_bytes(n: int) -> str:
    """Bytes in KB below 1 MB, else MB."""
    return f"{n / 1024:,.1f} KB" if n < 1024 ** 2 else f"{n / 1024 ** 2:,.2f} MB"
