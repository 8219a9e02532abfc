"""`KEY=VALUE` settings from the command line, typed like the dataclass field they set.

One rule for every config the CLI exposes this way (``--pose-option``, ``--set``): numbers,
true/false (also yes/no, on/off, 1/0), ``none`` where the field may be None, and
comma-separated numbers for tuples. A field's meaning is its attribute docstring (the string
right after it), read by ``field_docs``: the one text that the flags' help is made from.
"""

from __future__ import annotations

import ast
import inspect
import textwrap
import types
import typing
from dataclasses import MISSING, fields, is_dataclass
from functools import cache

from .errors import ReconInputError


def typed_value(raw: str, kind):
    """raw text as a value of type `kind` (int, float, str, bool, tuple[...], X | None).
    Raises ValueError."""
    args = typing.get_args(kind)
    if typing.get_origin(kind) in (typing.Union, types.UnionType):
        if raw.lower() == "none" and type(None) in args:
            return None
        return typed_value(raw, next(a for a in args if a is not type(None)))
    if typing.get_origin(kind) is tuple:
        parts = [p for p in raw.split(",") if p.strip()]
        if args and args[-1] is not Ellipsis and len(parts) != len(args):
            raise ValueError(raw)
        return tuple(typed_value(p.strip(), args[0] if args else float) for p in parts)
    if kind is bool:
        value = {"true": True, "1": True, "yes": True, "on": True,
                 "false": False, "0": False, "no": False, "off": False}
        if raw.lower() not in value:
            raise ValueError(raw)
        return value[raw.lower()]
    if kind in (int, float, str):
        return kind(raw)
    raise ValueError(raw)


def type_name(kind) -> str:
    return str(kind).replace("typing.", "") if typing.get_args(kind) else kind.__name__


def scalar_fields(cls) -> dict[str, tuple[object, object]]:
    """{name: (type, default)} of the fields of dataclass `cls` that are not nested configs."""
    hints = typing.get_type_hints(cls)
    table = {}
    for f in fields(cls):
        if is_dataclass(hints[f.name]):
            continue
        table[f.name] = (hints[f.name], f.default if f.default is not MISSING else f.default_factory())
    return table


def split_option(text: str, what: str) -> tuple[str, str]:
    """KEY=VALUE -> (key with dashes as underscores, raw value); ReconInputError otherwise."""
    key, sep, raw = text.partition("=")
    key, raw = key.strip().replace("-", "_"), raw.strip()
    if not sep or not key or not raw:
        raise ReconInputError(f"{what} must be KEY=VALUE, got {text!r}")
    return key, raw


@cache
def field_docs(cls) -> dict[str, str]:
    """The attribute docstrings of dataclass `cls`: the string literal right after a field.

    Args:
        cls: a dataclass whose source Python can read.

    Returns:
        {field name: its docstring, dedented}; fields without one are left out.
    """
    tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    body = tree.body[0].body
    docs = {}
    for node, after in zip(body, body[1:]):
        if (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and isinstance(after, ast.Expr)
                and isinstance(after.value, ast.Constant) and isinstance(after.value.value, str)):
            docs[node.target.id] = inspect.cleandoc(after.value.value)
    return docs


def field_summary(cls, name: str) -> str:
    """The first paragraph of field `name`'s docstring on one line (the flag's help text).

    Args:
        cls: the dataclass that has the field.
        name: the field's name.

    Returns:
        The summary; KeyError when the field has no docstring.
    """
    return " ".join(field_docs(cls)[name].split("\n\n")[0].split())


__all__ = ["field_docs", "field_summary", "scalar_fields", "split_option", "type_name", "typed_value"]
