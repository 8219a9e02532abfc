"""A run's settings from outside the flags: `recon run --config FILE` (a YAML or JSON file),
`--preset NAME` (a shipped config file, ``presets/NAME.yaml`` beside this module) and
`--set SECTION.KEY=VALUE` (one setting, typed like its field).

The file holds :class:`recon.core.config.PipelineConfig`'s fields by name, a section (a mapping)
for each nested config (``medea``, ``mvs``, ``fusion``, ``polish_config``): the same
names and layout as ``report.json``'s ``options``, so a report itself (or its
``options``) can be given to run a result again with exactly its settings. Keys the config
does not have are refused with their name. The command line's input and output always
win; any other flag given with a value other than its default overrides the file, and
every ``--set`` overrides both. The names ``--set`` takes are the file's, dotted
(``medea.stage1.epochs``, ``fusion.voxel_size``, ``frame_budget``): ``recon run --set list``
prints them all with their types and defaults.
"""

from __future__ import annotations

import difflib
import json
import types
import typing
from dataclasses import fields, is_dataclass, replace
from pathlib import Path

from ..errors import ReconInputError
from ..options import split_option, type_name, typed_value

PRESETS = Path(__file__).with_name("presets")


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


def preset_path(name: str) -> Path:
    """The shipped config file of preset `name` (``presets/NAME.yaml``)."""
    path = PRESETS / f"{name}.yaml"
    if not path.is_file():
        raise ReconInputError(f"--preset {name}: no such preset (known: {', '.join(preset_names())}; looked in "
                              f"{PRESETS})")
    return path


def preset_names() -> list[str]:
    return sorted(p.stem for p in PRESETS.glob("*.yaml"))


# --------------------------------------------------------------------------- --set


def _leaves(config, prefix: str = ""):
    """(dotted name, annotated type, value) of every setting of dataclass `config`, the
    nested sections flattened (``medea.stage1.epochs``), in field order."""
    hints = typing.get_type_hints(type(config))
    for f in fields(config):
        value = getattr(config, f.name)
        if is_dataclass(value):
            yield from _leaves(value, f"{prefix}{f.name}.")
        else:
            yield f"{prefix}{f.name}", hints[f.name], value


def setting_types(config) -> dict[str, object]:
    """{dotted name: annotated type} of every setting of dataclass `config`."""
    return {name: kind for name, kind, _ in _leaves(config)}


def setting_value(raw: str, kind, name: str):
    """`raw` text as a value of the annotated type `kind` (options.typed_value, plus paths,
    Literal choices and JSON mappings); ReconInputError naming the setting otherwise."""
    args = [a for a in typing.get_args(kind) if a is not type(None)]
    optional = typing.get_origin(kind) in (typing.Union, types.UnionType) and type(None) in typing.get_args(kind)
    if optional and raw.lower() == "none":
        return None
    base = args[0] if optional and len(args) == 1 else kind
    try:
        if base is Path:
            return Path(raw)
        if typing.get_origin(base) is typing.Literal:
            if raw not in typing.get_args(base):
                raise ValueError(raw)
            return raw
        if base is dict or typing.get_origin(base) is dict:
            value = json.loads(raw)
            if not isinstance(value, dict):
                raise ValueError(raw)
            return value
        return typed_value(raw, kind)
    except ValueError:
        raise ReconInputError(f"--set {name}: {raw!r} is not a valid {type_name(kind)}") from None


def with_settings(config, items: list[str]):
    """A copy of `config` with every ``SECTION.KEY=VALUE`` of `items` set, in order."""
    table = setting_types(config)
    for item in items:
        name, raw = split_option(item, "--set")
        if name not in table:
            close = difflib.get_close_matches(name, list(table), n=3)
            hint = f"did you mean {', '.join(close)}?" if close else "recon run --set list names them all"
            raise ReconInputError(f"--set {name}: no such setting ({hint})")
        config = _assigned(config, name.split("."), setting_value(raw, table[name], name))
    return config


def _assigned(config, path: list[str], value):
    if len(path) == 1:
        return replace(config, **{path[0]: value})
    return replace(config, **{path[0]: _assigned(getattr(config, path[0]), path[1:], value)})


def format_setting(value) -> str:
    """The text --set takes for `value` (setting_value's inverse)."""
    if value is None:
        return "none"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (tuple, list)):
        return ",".join(format_setting(v) for v in value)
    if isinstance(value, dict):
        return json.dumps(value, separators=(",", ":"))
    return str(value)


def changed_settings(config, defaults) -> list[str]:
    """``NAME=VALUE`` for every setting in which `config` differs from `defaults`: the
    --set arguments that make `defaults` into `config`."""
    return [f"{name}={format_setting(value)}"
            for (name, _, value), (_, _, default) in zip(_leaves(config), _leaves(defaults)) if value != default]


def settings_listing(config) -> str:
    """Every setting --set takes, with its type and its value in `config` (the defaults)."""
    rows = [(name, type_name(kind), format_setting(value)) for name, kind, value in _leaves(config)]
    widths = [max(len(r[i]) for r in rows) for i in range(2)]
    return "\n".join(f"{n:<{widths[0]}}  {k:<{widths[1]}}  {v}" for n, k, v in rows)


__all__ = ["changed_settings", "format_setting", "merged", "preset_names", "preset_path", "read_config_file",
           "setting_types", "settings_listing", "updated", "with_settings"]
