"""Command-line options read from a stage config's dataclass: each field's name, type,
default and help (its comment in the source) are written once, in the dataclass, and a
`murm` subcommand's options are generated from them.

A field `noise_std: float | None = None  # the expert noise's std` becomes
`--noise-std NOISE_STD` (a float, default None); a field without a default is a required
option, a `bool` one a flag, a `tuple[str, ...]` one a comma-separated list. The help is
the comment at the end of the field's line, else the comment lines right above it.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import io
import textwrap
import tokenize
import types
import typing
from collections.abc import Iterable


def field_comments(cls: type) -> dict[str, str]:
    """Each field's comment in the class's source: at the end of its last line, else the
    comment lines right above it (joined)."""
    source = textwrap.dedent(inspect.getsource(cls))
    lines = source.splitlines()
    trailing = {}  # line number -> the comment after the code on that line
    for token in tokenize.generate_tokens(io.StringIO(source).readline):
        if token.type == tokenize.COMMENT and lines[token.start[0] - 1][: token.start[1]].strip():
            trailing[token.start[0]] = token.string.lstrip("#").strip()
    comments = {}
    for node in ast.parse(source).body[0].body:
        if not (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)):
            continue
        if node.end_lineno in trailing:
            comments[node.target.id] = trailing[node.end_lineno]
            continue
        above, number = [], node.lineno - 1
        while number >= 1 and lines[number - 1].strip().startswith("#"):
            above.insert(0, lines[number - 1].strip().lstrip("#").strip())
            number -= 1
        if above:
            comments[node.target.id] = " ".join(above)
    return comments


def _option_type(hint) -> tuple[type, bool]:
    """The type an option's value converts to, and whether None is allowed."""
    args = typing.get_args(hint)
    if typing.get_origin(hint) in (typing.Union, types.UnionType) and type(None) in args:
        (inner,) = [a for a in args if a is not type(None)]
        return inner, True
    return hint, False


def _comma_separated(value: str) -> tuple[str, ...]:
    return tuple(value.split(","))


def add_config_arguments(parser: argparse.ArgumentParser, cls: type, names: Iterable[str]) -> None:
    """One option per field of `cls` named in `names`, from the field's type, default and comment."""
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    comments = field_comments(cls)
    for name in names:
        field = fields[name]
        option = "--" + name.replace("_", "-")
        kind, _ = _option_type(hints[name])
        help_text = comments.get(name, "").replace("%", "%%")
        if field.default is not dataclasses.MISSING:
            default = field.default
        elif field.default_factory is not dataclasses.MISSING:
            default = field.default_factory()
        else:
            parser.add_argument(option, required=True, type=kind, help=help_text or None)
            continue
        if kind is bool:
            parser.add_argument(
                option, action="store_true" if not default else argparse.BooleanOptionalAction, help=help_text or None
            )
            continue
        if typing.get_origin(kind) is tuple:
            shown = ",".join(default)
            parser.add_argument(
                option,
                type=_comma_separated,
                default=default,
                metavar="A,B,...",
                help=f"{help_text} (comma-separated; default: {shown})".strip(),
            )
            continue
        if default is not None:
            help_text = f"{help_text} (default: %(default)s)".strip()
        parser.add_argument(option, type=kind, default=default, help=help_text or None)


def config_arguments(args: argparse.Namespace, names: Iterable[str]) -> dict:
    """The parsed values of the options `add_config_arguments` made, as keyword arguments."""
    return {name: getattr(args, name) for name in names}


def default_of(cls: type, name: str):
    """The default of `cls`'s field `name`: a grid spec that mirrors a stage config's field
    takes the stage's default from here instead of writing it again."""
    field = {f.name: f for f in dataclasses.fields(cls)}[name]
    if field.default is dataclasses.MISSING:
        raise ValueError(f"{cls.__name__}.{name} has no plain default")
    return field.default
