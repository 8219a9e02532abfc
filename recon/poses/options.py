"""The pose estimators' settings as the command line sees them (``--pose-option KEY=VALUE``).

This module owns which fields of ``FrontendConfig`` and ``SfMConfig`` can be set that way,
their listing, and the checks that name a setting outside the range its field declares
(``recon.poses.config.bounded``), for the command line and for Python callers of
``estimate_poses`` alike. The typing of ``KEY=VALUE`` text is the shared rule of :mod:`recon.options`.

The configs are imported inside the functions: they pull in the estimators (torch, OpenCV),
which ``import recon.poses`` should not.
"""

from __future__ import annotations

import math
import textwrap
from dataclasses import fields, replace
from functools import cache

from recon.errors import ReconInputError
from recon.options import field_summary, scalar_fields, split_option, type_name, typed_value


def _option_fields() -> dict[str, tuple[str, object, object]]:
    """{name: (owner, type, default)} of the scalar fields of FrontendConfig and SfMConfig
    (a name both have, such as calibrate_lens, sets both)."""
    from recon.poses.config import FrontendConfig
    from recon.poses.sfm.mapper import SfMConfig

    table: dict[str, tuple[str, object, object]] = {}
    for cls in (FrontendConfig, SfMConfig):
        for name, (kind, default) in scalar_fields(cls).items():
            owner = table[name][0] + ", " + cls.__name__ if name in table else cls.__name__
            table[name] = (owner, kind, default)
    return table


@cache
def _bounds() -> dict[str, object]:
    """{setting: its Bounds} of the fields of FrontendConfig and SfMConfig that declare one
    (``recon.poses.config.bounded``): outside them a setting makes no sense or breaks the
    estimator. Settings not listed take any finite value."""
    from recon.poses.config import FrontendConfig
    from recon.poses.sfm.mapper import SfMConfig

    return {f.name: f.metadata["bounds"] for cls in (FrontendConfig, SfMConfig) for f in fields(cls)
            if "bounds" in f.metadata}


def _check_value(name: str, value, bounds) -> None:
    """ReconInputError when scalar setting `name` is outside `bounds` (its field's Bounds or None)
    or not finite; None, booleans and nested configs pass (the command line gives None only to fields that may be None,
    ``parse_pose_option``; Python callers are trusted with it)."""
    if value is None or isinstance(value, bool) or not isinstance(value, (int, float, tuple, str)):
        return
    numbers = value if isinstance(value, tuple) else (value,)
    finite = all(isinstance(v, str) or math.isfinite(v) for v in numbers)
    if not finite or (bounds is not None and not bounds.test(value)):
        raise ReconInputError(f"pose option {name} must be {bounds.words if bounds else 'finite'}, got {value!r}")


def check_pose_config(config) -> None:
    """ReconInputError naming the first setting of a FrontendConfig or SfMConfig (and the
    FrontendConfig inside an SfMConfig) outside its range."""
    from recon.poses.config import FrontendConfig

    for f in fields(config):
        value = getattr(config, f.name)
        if isinstance(value, FrontendConfig):
            check_pose_config(value)
        else:  # flow and BA settings (nested configs) are set in Python and not checked here
            _check_value(f.name, value, f.metadata.get("bounds"))


def configure_frontend(options: dict, device: str = "cpu", base=None):
    """The FrontendConfig of `base` (the defaults when None) with those of `options` that are
    its fields (others are SfM's), checked, and with its bundle adjustment on `device`."""
    from recon.poses.config import FrontendConfig

    own = {k: v for k, v in options.items() if k in FrontendConfig.__dataclass_fields__}
    config = replace(base or FrontendConfig(), **own)
    check_pose_config(config)
    return config.on_device(device)


def check_pose_options(options: dict) -> None:
    """ReconInputError naming the keys of `options` that are no field of FrontendConfig or
    SfMConfig (nested configs such as ``flow`` included; the command line sets scalars only)."""
    from recon.poses.config import FrontendConfig
    from recon.poses.sfm.mapper import SfMConfig

    unknown = set(options) - set(FrontendConfig.__dataclass_fields__) - set(SfMConfig.__dataclass_fields__)
    if unknown:
        raise ReconInputError(
            f"unknown pose option(s): {', '.join(sorted(unknown))} (`--pose-option list` shows the options)"
        )
    for name, value in options.items():
        _check_value(name, value, _bounds().get(name))


def parse_pose_option(text: str) -> tuple[str, object]:
    """KEY=VALUE from the command line as (key, value typed like the field), for a scalar
    field of FrontendConfig or SfMConfig: numbers, true/false, none where the field may be
    None, comma-separated numbers for tuples. Raises ReconInputError."""
    key, raw = split_option(text, "pose option")
    settable = _option_fields()
    if key not in settable:
        check_pose_options({key: None})
        raise ReconInputError(
            f"pose option {key} is a nested config; set its fields in Python (recon.poses.estimate_poses)"
        )
    kind = settable[key][1]
    try:
        value = typed_value(raw, kind)
    except ValueError:
        raise ReconInputError(f"pose option {key}: {raw!r} is not a valid {type_name(kind)}") from None
    check_pose_options({key: value})
    return key, value


def format_pose_option(key: str, value) -> str:
    """KEY=VALUE as parse_pose_option reads it back (for commands echoed to the user)."""
    if isinstance(value, tuple):
        text = ",".join(str(v) for v in value)
    else:
        text = str(value).lower() if value is None or isinstance(value, bool) else str(value)
    return f"{key}={text}"


def _summaries(name: str) -> list[str]:
    """The summary of setting `name` (its field's docstring, first paragraph), one per config
    that has the field when they differ, each then led by the config's name."""
    from recon.poses.config import FrontendConfig
    from recon.poses.sfm.mapper import SfMConfig

    texts = {cls.__name__: field_summary(cls, name) for cls in (FrontendConfig, SfMConfig)
             if name in cls.__dataclass_fields__}
    if len(set(texts.values())) == 1:
        return [next(iter(texts.values()))]
    return [f"{owner}: {text}" for owner, text in texts.items()]


def pose_option_table(width: int = 100) -> str:
    """The pose options (`--pose-option KEY=VALUE`), a line each with type, default and owner,
    and under it, indented, what the setting does.

    Args:
        width: the column the summaries are wrapped at.

    Returns:
        The table, lines joined by newlines, options sorted by name.
    """
    rows = [(name, type_name(kind), repr(default), owner)
            for name, (owner, kind, default) in sorted(_option_fields().items())]
    widths = [max(len(r[i]) for r in rows) for i in range(3)]
    lines = []
    for n, t, d, o in rows:
        lines.append(f"{n:<{widths[0]}}  {t:<{widths[1]}}  {d:<{widths[2]}}  {o}")
        lines += [textwrap.fill(text, width, initial_indent=_INDENT, subsequent_indent=_INDENT)
                  for text in _summaries(n)]
    return "\n".join(lines)


_INDENT = " " * 4


__all__ = ["check_pose_config", "check_pose_options", "format_pose_option", "parse_pose_option", "pose_option_table"]
