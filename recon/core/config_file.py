"""A run's settings from outside the flags: `recon run --config FILE` (a YAML or JSON file),
`--preset NAME` (a shipped config file, ``presets/NAME.yaml`` beside this module) and
`--set SECTION.KEY=VALUE` (one setting, typed like its field).

The file holds :class:`recon.core.config.PipelineConfig`'s fields by name, a section per
nested config: the layout of report.json's ``options``, so a report runs a result again.
Unknown keys are refused by name; ``inherit: NAME|PATH`` starts from another file
(``presets/defaults.yaml``: every setting at its default). Input and output always win; a flag
given with a non-default value overrides the file, and every ``--set`` overrides both.
More: docs/running.md#settings-in-a-file---config---preset---set
"""

from __future__ import annotations

import difflib
import json
import textwrap
import types
import typing
from dataclasses import fields, is_dataclass, replace
from pathlib import Path

from ..errors import ReconInputError
from ..options import field_docs, split_option, type_name, typed_value

PRESETS = Path(__file__).with_name("presets")
DEFAULTS = PRESETS / "defaults.yaml"
# Settings the invocation or the machine decides, not a config file: left out of defaults.yaml
# (a file that named them would pin, say, the device of whoever wrote it).
NOT_IN_DEFAULTS = frozenset({"input", "output", "overwrite", "rerun", "rerun_path", "device", "progress"})


def read_config_file(path: Path, _seen: tuple = ()) -> dict:
    """The settings mapping of a YAML or JSON file (a report.json: its ``options``), over
    the file it names with ``inherit:`` if any."""
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
    if "inherit" in data:
        data = dict(data)
        parent = _inherited(path, data.pop("inherit"))
        if parent.resolve() in _seen:
            raise ReconInputError(f"{path}: inherit: {parent} inherits from itself")
        data = _deep_merged(read_config_file(parent, (*_seen, path.resolve(), parent.resolve())), data)
    return data


def _inherited(path: Path, name) -> Path:
    """The file `inherit: name` of the config file `path` names: a shipped preset's, or a
    path relative to `path`."""
    if not isinstance(name, str) or not name:
        raise ReconInputError(f"{path}: inherit: expected a preset name or a file, got {name!r}")
    shipped = PRESETS / f"{name}.yaml"
    if "/" not in name and not name.endswith((".yaml", ".yml", ".json")) and shipped.is_file():
        return shipped
    return path.parent / name


def _deep_merged(base: dict, over: dict) -> dict:
    """`base` with `over`'s settings over it, sections merged key by key."""
    merged_values = dict(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(base.get(key), dict) and key != "pose_options":
            merged_values[key] = _deep_merged(base[key], value)
        else:
            merged_values[key] = value
    return merged_values


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
    """The shipped MEDeA presets (``presets/*.yaml`` but defaults.yaml, which they inherit)."""
    return sorted(p.stem for p in PRESETS.glob("*.yaml") if p != DEFAULTS)


# --------------------------------------------------------------------------- defaults.yaml


def defaults_yaml() -> str:
    """The text of ``presets/defaults.yaml``: every setting of PipelineConfig at its default
    (but NOT_IN_DEFAULTS), each under its field docstring's summary, a section per nested config."""
    from .config import PipelineConfig

    lines = ["# Every setting of `recon run` at its default, a section per stage: the names of --set and",
             "# of a --config file. Written from the dataclasses' fields by recon.core.config_file.",
             "# write_defaults (python scripts/write_defaults.py); do not edit. The presets inherit it.",
             "# The device, the Rerun mode and the input and output are the command line's."]
    _yaml_lines(PipelineConfig(Path(), Path()), "", lines)
    return "\n".join(lines) + "\n"


def write_defaults(path: Path = DEFAULTS) -> Path:
    """Write ``defaults_yaml()`` to `path` (the shipped presets/defaults.yaml)."""
    Path(path).write_text(defaults_yaml())
    return Path(path)


def _yaml_lines(config, indent: str, lines: list[str]) -> None:
    docs = field_docs(type(config))
    for f in fields(config):
        if f.name in NOT_IN_DEFAULTS:
            continue
        value = getattr(config, f.name)
        summary = " ".join(docs.get(f.name, "").split("\n\n")[0].split())
        lines += textwrap.wrap(summary, 100, initial_indent=f"{indent}# ", subsequent_indent=f"{indent}# ")
        if is_dataclass(value):
            lines.append(f"{indent}{f.name}:")
            _yaml_lines(value, indent + "  ", lines)
        else:
            lines.append(f"{indent}{f.name}: {_yaml_scalar(value)}")


def _yaml_scalar(value) -> str:
    """`value` as YAML that yaml.safe_load reads back as the same value (tuples as lists)."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        text = repr(value)
        return text.replace("e", ".0e", 1) if "e" in text and "." not in text else text
    if isinstance(value, int):
        return str(value)
    if isinstance(value, (tuple, list)):
        return "[" + ", ".join(_yaml_scalar(v) for v in value) + "]"
    if isinstance(value, dict):
        return json.dumps(value)
    return json.dumps(str(value))


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


def setting_default(name: str):
    """The default of dotted setting `name` of PipelineConfig (``fusion.voxel_size``)."""
    from .config import PipelineConfig

    value = PipelineConfig(Path(), Path())
    for part in name.split("."):
        value = getattr(value, part)
    return value


def with_values(config, values: dict):
    """A copy of dataclass `config` with each ``{dotted name: value}`` of `values` set, typed as given."""
    for name, value in values.items():
        config = _assigned(config, name.split("."), value)
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


__all__ = ["DEFAULTS", "changed_settings", "defaults_yaml", "format_setting", "merged", "preset_names", "preset_path",
           "read_config_file", "setting_default", "setting_types", "settings_listing", "updated", "with_settings",
           "with_values", "write_defaults"]
