"""`recon run --config FILE`: a run's settings from a YAML or JSON file.

The file holds :class:`recon.core.config.PipelineConfig`'s fields by name, a section (a mapping)
for each nested config (``medea``, ``mvs``, ``fusion``, ``polish_config``): the same
names and layout as ``report.json``'s ``options``, so a report itself (or its
``options``) can be given to run a result again with exactly its settings. Keys the config
does not have are refused with their name. The command line's input and output always
win; any other flag given with a value other than its default overrides the file.
"""

from __future__ import annotations

import json
import types
import typing
from dataclasses import fields, is_dataclass, replace
from pathlib import Path

from ..errors import ReconInputError


def read_config_file(path: Path) -> dict:
    """The settings mapping of a YAML or JSON file (a report.json: its ``options``)."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as error:
        raise ReconInputError(f"{path}: cannot read the config file ({error.strerror or error})") from None
    try:
        if path.suffix.lower() == ".json":
            data = json.loads(text)
        else:
            import yaml

            data = yaml.safe_load(text)
    except (ValueError, ImportError) as error:
        raise ReconInputError(f"{path}: not a JSON or YAML config ({str(error).splitlines()[0]})") from None
    except Exception as error:  # yaml.YAMLError and its kin
        raise ReconInputError(f"{path}: not a YAML config ({str(error).splitlines()[0]})") from None
    if isinstance(data, dict) and isinstance(data.get("options"), dict) and "input" in data:
        data = data["options"]  # a report.json
    if not isinstance(data, dict):
        raise ReconInputError(f"{path}: a config file holds a mapping of settings, got {type(data).__name__}")
    return data


def _typed(kind, value, where: str):
    """`value` (from JSON/YAML) as the annotated type `kind`: nested dataclasses from
    mappings, tuples and paths from their plain forms; other values as they are."""
    origin = typing.get_origin(kind)
    if origin in (typing.Union, types.UnionType):
        if value is None:
            return None
        kind = next(a for a in typing.get_args(kind) if a is not type(None))
        origin = typing.get_origin(kind)
    if is_dataclass(kind):
        if not isinstance(value, dict):
            raise ReconInputError(f"config {where}: expected a section (a mapping), got {value!r}")
        return updated(kind(), value, where)
    if kind is Path or (isinstance(kind, type) and issubclass(kind, Path)):
        return None if value is None else Path(value)
    if origin is tuple and isinstance(value, (list, tuple)):
        return tuple(value)
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    return value


def updated(config, values: dict, where: str = ""):
    """A copy of dataclass `config` with `values` ({field: plain value}) set, nested
    sections merged into the nested configs."""
    hints = typing.get_type_hints(type(config))
    known = {f.name for f in fields(config)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise ReconInputError(f"config{' ' + where if where else ''}: unknown setting(s) {', '.join(unknown)} "
                              f"(known: {', '.join(sorted(known))})")
    changes = {}
    for name, value in values.items():
        here = f"{where}.{name}" if where else name
        current = getattr(config, name)
        if is_dataclass(current) and isinstance(value, dict):
            changes[name] = updated(current, value, here)
        else:
            changes[name] = _typed(hints[name], value, here)
    return replace(config, **changes)


def merged(file_values: dict, cli_config, cli_defaults):
    """The run's config: `cli_defaults` (the config of a bare `recon run IN -o OUT`) with
    the file's settings, then every setting in which `cli_config` (the command line as
    given) differs from `cli_defaults`; input and output always the command line's."""
    config = updated(cli_defaults, file_values)
    return _overlay(config, cli_config, cli_defaults, top=True)


def _overlay(config, cli, defaults, top: bool = False):
    changes = {}
    for f in fields(config):
        given, default = getattr(cli, f.name), getattr(defaults, f.name)
        if is_dataclass(given):
            changes[f.name] = _overlay(getattr(config, f.name), given, default)
        elif (top and f.name in ("input", "output")) or given != default:
            changes[f.name] = given
    return replace(config, **changes)


__all__ = ["merged", "read_config_file", "updated"]
