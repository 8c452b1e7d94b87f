"""Build the installable add-on zip: dist/nbvh-VERSION.zip with one top folder `nbvh/` holding the add-on
(addon/*) and the core (nbvh_core/) inside it, so installing needs no manual copying.

    python build_addon.py [--out dist]

The same zip installs as a Blender 4.2+ extension (blender_manifest.toml; extensions may keep their files in
one top folder) and as a legacy add-on on Blender 3.4+ (bl_info in __init__.py).
"""
from __future__ import annotations

import argparse
import re
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent
PACKAGE = "nbvh"


def version() -> str:
    text = (ROOT / "addon" / "blender_manifest.toml").read_text()
    return re.search(r'^version\s*=\s*"([^"]+)"', text, re.M).group(1)


def build(out_dir: Path) -> Path:
    out_dir.mkdir(parents=True, exist_ok=True)
    target = out_dir / f"{PACKAGE}-{version()}.zip"
    tmp = target.with_suffix(".zip.partial")
    skip = re.compile(r"(__pycache__|\.pyc$|\.partial)")
    with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as zf:
        for src_root, prefix in ((ROOT / "addon", PACKAGE), (ROOT / "nbvh_core", f"{PACKAGE}/nbvh_core")):
            for path in sorted(src_root.rglob("*")):
                if path.is_file() and not skip.search(str(path)):
                    zf.write(path, f"{prefix}/{path.relative_to(src_root).as_posix()}")
    tmp.replace(target)
    return target


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=str(ROOT / "dist"))
    args = ap.parse_args()
    print(build(Path(args.out)))


if __name__ == "__main__":
    main()
