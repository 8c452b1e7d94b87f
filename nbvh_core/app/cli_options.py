"""The command line's setting options, generated from the fields of `Settings` (`planning.settings.knob`): a field
declared with help is an option (its flag, type, choices and help as declared; no default: the preset's value stands
unless the option is given), and the parsed options are the request `settings_from_request` reads. A field added
with help is on the command line, in the request and in the record (the file's settings) with no other edit.
"""
from __future__ import annotations

import argparse
import dataclasses

from ..planning.settings import Settings, field_kind

_TYPES = {"int": int, "float": float, "str": str}


def setting_fields(names: tuple[str, ...] | None = None, cls: type = Settings) -> list[dataclasses.Field]:
    """The fields of `cls` offered as options (declared with help), in declaration order; `names`: only these."""
    offered = [f for f in dataclasses.fields(cls) if "help" in f.metadata]
    if names is None:
        return offered
    missing = set(names) - {f.name for f in offered}
    if missing:
        raise ValueError(f"not command-line settings: {', '.join(sorted(missing))}")
    return [f for f in offered if f.name in names]


def flag_of(f: dataclasses.Field) -> str:
    """A field's option: its declared flag, else --NAME with dashes."""
    return f.metadata.get("flag") or "--" + f.name.replace("_", "-")


def add_setting_options(parser: argparse.ArgumentParser, names: tuple[str, ...] | None = None, cls: type = Settings,
                        group_extras: dict | None = None) -> None:
    """Add an option per offered field of `cls` (see `setting_fields`) to `parser`. The fields of one group go in
    one mutually exclusive group, together where its first field stands; group_extras[name](group) adds the caller's
    own options to it there (e.g. --quality to 'size': argparse wants a group's options side by side)."""
    fields = setting_fields(names, cls)
    done: set[str] = set()
    for f in fields:
        group = f.metadata.get("group")
        if group is None:
            _add_option(parser, f)
        elif group not in done:
            done.add(group)
            g = parser.add_mutually_exclusive_group()
            for member in (m for m in fields if m.metadata.get("group") == group):
                _add_option(g, member)
            if group_extras and group in group_extras:
                group_extras[group](g)


def _add_option(where, f: dataclasses.Field) -> None:
    meta, metavar = f.metadata, flag_of(f)[2:].upper().replace("-", "_")
    kind = field_kind(f)
    if kind == "bool":
        where.add_argument(flag_of(f), dest=f.name, action="store_true", default=None, help=meta["help"])
    else:
        where.add_argument(flag_of(f), dest=f.name, type=_TYPES[kind], choices=meta.get("choices"), default=None,
                           help=meta["help"], metavar=None if "choices" in meta else metavar)


def request_from_args(args: argparse.Namespace, names: tuple[str, ...] | None = None, cls: type = Settings) -> dict:
    """The parsed setting options as a request's fields ({name: value}, None where not given); a step budget given
    without a time limit is a budget in steps only (time_limit_s 0, as `settings_from_request` reads it)."""
    fields = setting_fields(names, cls)
    spec = {f.name: getattr(args, f.name, None) for f in fields}
    if spec.get("steps") is not None and "time_limit_s" in spec and spec["time_limit_s"] is None:
        spec["time_limit_s"] = 0
    return spec
