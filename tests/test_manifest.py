"""Blender 5.0's own extension tool (shipped inside the bpy module, `bl_pkg/cli/blender_ext.py`) accepts the
add-on's manifest and the built zip (it refuses a `files` permission's text of 66 characters)."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _validator() -> Path | None:
    try:
        import importlib.util

        spec = importlib.util.find_spec("bpy")
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.submodule_search_locations:
        return None
    hits = sorted(Path(list(spec.submodule_search_locations)[0]).glob("*/scripts/addons_core/bl_pkg/cli/blender_ext.py"))
    return hits[0] if hits else None


@pytest.mark.parametrize("what", ["source", "zip"])
def test_blender_extension_validate_accepts_the_addon(what, tmp_path):
    tool = _validator()
    if tool is None:
        pytest.skip("no bpy module with Blender's extension tool")
    if what == "zip":
        sys.path.insert(0, str(ROOT))
        from build_addon import build

        target = build(tmp_path)
    else:
        target = ROOT / "addon"
    proc = subprocess.run([sys.executable, str(tool), "validate", str(target)], capture_output=True, text=True)
    assert proc.returncode == 0 and "Success" in proc.stdout + proc.stderr, proc.stdout + proc.stderr
