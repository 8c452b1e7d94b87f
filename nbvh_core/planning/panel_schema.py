"""The add-on's settings, generated from the fields of `Settings` (`planning.settings.knob`): a field declared with
a `panel` label is a setting of the add-on's panel and of the request it sends. The add-on cannot import torch (so
not `Settings`): it reads this schema as JSON data (`addon/settings_schema.json`, written here and kept equal to the
declarations by a test), builds its properties from it and sends their values as the request's fields
(`addon/settings_fields.py`). Each entry: name, kind (bool | int | float | str), label, help, default (the default
preset's value: what a request without it gets), choices with their menu labels, and the panel's bounds.

    python -m nbvh_core.planning.panel_schema            # rewrite addon/settings_schema.json
    python -m nbvh_core.planning.panel_schema --check    # exit 1 when it differs from the declarations
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

from .settings import PRESETS, Settings, field_kind

#: Where the add-on reads its schema (shipped inside the add-on by build_addon.py).
SCHEMA_PATH = Path(__file__).resolve().parents[2] / "addon" / "settings_schema.json"


def panel_entry(f: dataclasses.Field, defaults: Settings) -> dict:
    """One field's entry (see the module docstring)."""
    meta = f.metadata
    entry = {"name": f.name, "kind": field_kind(f), "label": meta["panel"], "help": meta.get("help", ""),
             "default": getattr(defaults, f.name, f.default)}
    if "choices" in meta:
        labels = meta.get("labels") or {}
        entry["choices"] = [[c, *labels.get(c, (str(c).title(), ""))] for c in meta["choices"]]
    bounds = meta.get("panel_limits") or meta.get("limits")
    if bounds is not None:
        entry["min"], entry["max"] = bounds
    return entry


def panel_schema(cls: type = Settings, defaults: Settings | None = None) -> dict:
    """{'fields': [entry, ...]} of the fields of `cls` declared with a panel label, in declaration order; defaults
    from `defaults` (the 'default' preset; a field it lacks: its declared default)."""
    defaults = defaults if defaults is not None else PRESETS["default"]
    return {"fields": [panel_entry(f, defaults) for f in dataclasses.fields(cls) if "panel" in f.metadata]}


def schema_text(schema: dict | None = None) -> str:
    """The schema as the add-on's file holds it (stable key order, one trailing newline)."""
    return json.dumps(schema if schema is not None else panel_schema(), indent=1) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true", help="only compare; exit 1 when the file differs")
    args = ap.parse_args(argv)
    text = schema_text()
    if args.check:
        same = SCHEMA_PATH.exists() and SCHEMA_PATH.read_text() == text
        print(f"{SCHEMA_PATH.name}: {'current' if same else 'differs from the declarations: regenerate it'}")
        return 0 if same else 1
    SCHEMA_PATH.write_text(text)
    print(f"wrote {SCHEMA_PATH}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
