"""Mesh objects out of a .blend file, through a `blender` binary run headless (nbvh_core never imports bpy: the
add-on's `blend_export_script.py` runs in Blender's own process and writes one .npz per object).

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

#: The script Blender runs (Blender-side code lives with the add-on: in the repository addon/ sits beside
#: nbvh_core/, in the installed add-on nbvh_core/ sits inside it).
_SCRIPT_NAME = "blend_export_script.py"


def export_script() -> Path:
    """Where the Blender-side export script is; raises ValueError when this nbvh_core came without it."""
    beside_core = Path(__file__).resolve().parents[2]  # nbvh_core/app/ -> what holds nbvh_core/
    for candidate in (beside_core / _SCRIPT_NAME, beside_core / "addon" / _SCRIPT_NAME):
        if candidate.exists():
            return candidate
    raise ValueError(f"the Blender export script ({_SCRIPT_NAME}) is missing beside nbvh_core: reinstall the add-on "
                     "or use a checkout of the repository")


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
    # --disable-autoexec: a .blend's own scripts (registered text blocks, drivers) never run, whatever the user's
    # preferences say; the file is read as data and only our export script runs.
    cmd = [blender, "-b", "--factory-startup", "--disable-autoexec", str(blend), "--python", str(export_script()),
           "--", str(out_dir)]
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
