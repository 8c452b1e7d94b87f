"""The command line's setting options come from the fields of `Settings` (`knob`), written once."""
import argparse
import dataclasses
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
