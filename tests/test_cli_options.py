"""The command line's setting options come from the fields of `Settings` (`knob`), written once."""
import argparse
import dataclasses
import json
import re
from pathlib import Path

import pytest

from nbvh_core.app.cli_options import add_setting_options, request_from_args, setting_fields
from nbvh_core.planning.settings import SETTING_CHOICES, SETTING_LIMITS, Settings, knob, settings_from_dict

ROOT = Path(__file__).resolve().parents[1]


def _parser(cls=Settings, names=None) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(exit_on_error=False)
    add_setting_options(p, names, cls)
    return p


def test_a_field_added_with_help_is_an_option_in_the_request_and_in_the_record():
    """A new field declared on Settings with help: on the command line (flag, type, limits as declared), in the
    request it makes, and in the settings' record (what the file stores), with no other edit."""
    extended = dataclasses.make_dataclass(
        "Extended", [("shadow_rays", int, knob(4, help="rays per shadow test", limits=(1, 64)))], bases=(Settings,))
    args = _parser(extended).parse_args(["--shadow-rays", "9", "--encoding", "hashgrid", "--steps", "5"])
    spec = request_from_args(args, cls=extended)
    assert spec["shadow_rays"] == 9 and spec["encoding"] == "hashgrid"
    assert spec["time_limit_s"] == 0  # a step budget alone is steps only
    record = extended().with_overrides(**spec).to_dict()
    assert record["shadow_rays"] == 9 and record["steps"] == 5
    assert "--shadow-rays" not in _parser().format_help()  # it came from the field, nowhere else


def test_a_field_added_with_a_panel_label_is_on_the_add_on_s_panel_and_in_its_request():
    """The add-on's side of the same promise: a field declared with a panel label is in the schema the add-on reads
    (`planning.panel_schema`), becomes a Blender property of the declared kind, label, default and bounds
    (`addon.settings_fields`, no bpy needed to build its arguments), and the panel's value reaches the request and
    the record under the field's name; an enum's capitalised identifier goes back to its choice."""
    import sys
    from types import SimpleNamespace

    from nbvh_core.planning.panel_schema import panel_schema

    sys.path.insert(0, str(ROOT))
    from addon.settings_fields import panel_names, property_specs, request_fields

    extended = dataclasses.make_dataclass("Extended", [
        ("shadow_rays", int, knob(4, help="rays per shadow test", limits=(1, 64), panel="Shadow rays")),
        ("shadow_kind", str, knob("hard", choices=("hard", "soft"), help="the shadows", panel="Shadows",
                                  labels={"soft": ("Soft", "area light")}))], bases=(Settings,))
    schema = panel_schema(extended)["fields"]
    specs = {name: (kind, kwargs) for name, kind, kwargs in property_specs(schema)}
    assert specs["shadow_rays"] == ("IntProperty", {"name": "Shadow rays", "description": "rays per shadow test",
                                                    "default": 4, "min": 1, "max": 64})
    assert specs["shadow_kind"][1]["items"] == [("HARD", "Hard", ""), ("SOFT", "Soft", "area light")]
    assert panel_names(schema)[-2:] == ["shadow_rays", "shadow_kind"]
    assert specs["time_limit_s"] == ("FloatProperty", {"name": "Time limit (s)", "description": "training wall-clock "
                                                       "budget in seconds", "default": 200.0, "min": 5.0,
                                                       "max": 86400.0, "precision": 0})
    panel = SimpleNamespace(**{n: kw["default"] for n, (_, kw) in specs.items()})
    panel.shadow_rays, panel.shadow_kind, panel.mesh_layout = 9, "SOFT", "PLAIN"
    request = request_fields(panel, schema)
    assert (request["shadow_rays"], request["shadow_kind"], request["mesh_layout"]) == (9, "soft", "plain")
    record = extended().with_overrides(**request).to_dict()
    assert record["shadow_rays"] == 9 and record["shadow_kind"] == "soft" and record["time_limit_s"] == 200.0


def test_the_add_on_s_schema_file_is_the_one_the_declarations_make():
    """addon/settings_schema.json is generated (`python -m nbvh_core.planning.panel_schema`): never edited apart
    from the fields it comes from. Its defaults are the default preset's."""
    from nbvh_core.planning.panel_schema import SCHEMA_PATH, main, schema_text

    assert main(["--check"]) == 0 and SCHEMA_PATH.read_text() == schema_text()
    fields = {e["name"]: e for e in json.loads(SCHEMA_PATH.read_text())["fields"]}
    assert {"time_limit_s", "device", "force", "mesh_layout", "appearance_target"} <= set(fields)
    assert fields["time_limit_s"]["default"] == 200.0 and fields["mesh_layout"]["default"] == "compact"


def test_choices_and_limits_are_the_declared_ones_everywhere():
    """The parser refuses what the field does not declare; requests and files are checked by the same values."""
    p = _parser()
    with pytest.raises(argparse.ArgumentError):
        p.parse_args(["--encoding", "octree"])
    with pytest.raises(argparse.ArgumentError):
        p.parse_args(["--table-bits", "12"])
    declared = {f.name: f.metadata for f in dataclasses.fields(Settings)}
    assert SETTING_CHOICES == {n: m["choices"] for n, m in declared.items() if "choices" in m}
    assert SETTING_LIMITS == {n: m["limits"] for n, m in declared.items() if "limits" in m}
    with pytest.raises(ValueError, match="encoding"):
        settings_from_dict({"encoding": "octree"})
    with pytest.raises(ValueError, match="nodes"):
        settings_from_dict({"nodes": 70000})


def test_options_not_given_leave_the_preset_s_values_and_groups_exclude_each_other():
    args = _parser().parse_args([])
    assert all(v is None for v in request_from_args(args).values())
    with pytest.raises(argparse.ArgumentError):
        _parser().parse_args(["--budget-kb", "50", "--target-mse", "0.001"])
    flags = _parser(names=("force", "steps")).parse_args(["--force"])
    assert request_from_args(flags, ("force", "steps")) == {"force": True, "steps": None}
    with pytest.raises(ValueError, match="not command-line settings"):
        setting_fields(("levels",))  # declared without help: not offered


def test_the_command_line_writes_no_choices_of_its_own():
    """Every choice the CLI offers is a declared tuple or mapping, never a literal list in the parser."""
    source = (ROOT / "nbvh_core" / "app" / "cli.py").read_text()
    assert not re.findall(r"choices=\[", source)
