"""The panel's settings as the core declares them (`settings_schema.json`, written by
`nbvh_core.planning.panel_schema` from the `Settings` fields with a panel label): no bpy and no torch here, so the
mapping is tested without Blender. `panel.py` makes a Blender property of each entry (`property_specs`), draws them in
order, and `compress_ops` / `library_ops` send their values as the request's fields (`request_fields`): a knob
declared once in the core is on the panel and in the request with no edit here.

Enum items are (CHOICE in capitals, label, description) as Blender names them; the request gets the choice itself.
"""
from __future__ import annotations

import json
from pathlib import Path

SCHEMA_FILE = Path(__file__).with_name("settings_schema.json")


def load_schema(path: Path = SCHEMA_FILE) -> list[dict]:
    """The schema's entries (a JSON file: data, never code)."""
    return json.loads(path.read_text())["fields"]


def property_specs(schema: list[dict] | None = None) -> list[tuple[str, str, dict]]:
    """(name, bpy.props function name, its keyword arguments) per entry, in the schema's order."""
    out = []
    for e in schema if schema is not None else load_schema():
        common = {"name": e["label"], "description": e.get("help", "")}
        if "choices" in e:
            items = [(str(c).upper(), label, text) for c, label, text in e["choices"]]
            out.append((e["name"], "EnumProperty", dict(common, items=items, default=str(e["default"]).upper())))
        elif e["kind"] == "bool":
            out.append((e["name"], "BoolProperty", dict(common, default=bool(e["default"]))))
        else:
            kind = "IntProperty" if e["kind"] == "int" else "FloatProperty"
            cast = int if e["kind"] == "int" else float
            spec = dict(common, default=cast(e["default"]))
            if "min" in e:
                spec.update(min=cast(e["min"]), max=cast(e["max"]))
            if kind == "FloatProperty" and all(float(spec[k]).is_integer() for k in ("default", "min", "max")
                                               if k in spec):
                spec["precision"] = 0  # declared in whole numbers (seconds): shown as "200", not "200.00"
            out.append((e["name"], kind, spec))
    return out


def panel_names(schema: list[dict] | None = None) -> list[str]:
    """The settings the panel draws, in order."""
    return [e["name"] for e in (schema if schema is not None else load_schema())]


def request_fields(props, schema: list[dict] | None = None) -> dict:
    """{field: value} of the panel's settings on `props` (any object with those attributes), as the request names
    them: an enum's capitalised identifier back to its choice."""
    out = {}
    for e in schema if schema is not None else load_schema():
        value = getattr(props, e["name"])
        if "choices" in e:
            value = next(c for c, _, _ in e["choices"] if str(c).upper() == value)
        elif e["kind"] in ("int", "float"):
            value = int(value) if e["kind"] == "int" else float(value)
        out[e["name"]] = value
    return out
