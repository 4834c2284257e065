"""The documentation of a config field, read from its class's own source, and what an option
that sets it says in ``--help``: so that the help cannot drift from the field.

A field's documentation is its ``#:`` comment lines (above it or on its line), else its plain
comments there (``#``), else the sentences of its class's docstring that start with it in
double backquotes (``window_m``: ...), else the short ones that name it. Its unit comes from its
name (``_m``: metres, ``_hz``, ``_mps``, ...), its metavar from its type.
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import inspect
import io
import re
import textwrap
import tokenize
import types
import typing
from typing import Any

#: A field name's ending and its unit.
UNITS = {"_m": "m", "_hz": "Hz", "_mps": "m/s", "_s": "s", "_deg": "deg", "_dps": "deg/s"}


@functools.cache
def field_docs(cls: type) -> dict[str, str]:
    """Each documented field of the dataclass ``cls``: name -> its documentation (one line)."""
    try:
        source = textwrap.dedent(inspect.getsource(cls))
    except (OSError, TypeError):
        return {}
    comments: dict[int, str] = {}
    code_rows: set[int] = set()
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.COMMENT:
            comments[tok.start[0]] = tok.string
        elif tok.type not in (tokenize.NL, tokenize.NEWLINE, tokenize.INDENT, tokenize.DEDENT):
            code_rows.add(tok.start[0])
    sentences = re.split(r"(?<=[.;])\s+", " ".join((cls.__doc__ or "").split()))
    docs = {}
    for node in ast.parse(source).body[0].body:  # type: ignore[attr-defined]
        if not (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)):
            continue
        name, row, above = node.target.id, node.lineno - 1, []
        while row in comments and row not in code_rows:
            above.insert(0, comments[row])
            row -= 1
        own = [comments[r] for r in range(node.lineno, node.end_lineno + 1) if r in comments]
        ours = [c for c in above + own if c.startswith("#:")] or above + own
        named = [s for s in sentences if re.match(rf"``{name}(=[^`]*)?``", s)] or [
            s for s in sentences if re.search(rf"``{name}``", s) and len(s) < 160
        ]  # a sentence about the field, else a short one naming it
        if text := " ".join(c.lstrip("#:").strip() for c in ours) or " ".join(named):
            docs[name] = _plain(text)
    return docs


def _plain(text: str) -> str:
    """reST markup as plain text: ``x`` -> x, :func:`~a.b` -> b."""
    text = re.sub(r":\w+:`~?(?:[\w.]*\.)?([^`]+)`", r"\1", text)
    return text.replace("``", "")


def unit(name: str) -> str | None:
    """The unit a field's name ends with (``window_m`` -> ``m``), or None."""
    return next((u for end, u in UNITS.items() if name.endswith(end)), None)


def metavar(tp: Any) -> str:
    """How an option of type ``tp`` is written: ``[on|off]``, ``FLOAT``, ``TEXT,...``, ``X0,Y0``."""
    args = [a for a in typing.get_args(tp) if a is not type(None)]
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        return metavar(args[0]) + "|none" if len(args) == 1 else "JSON"
    if tp is bool:
        return "[on|off]"
    if typing.get_origin(tp) is tuple:
        return f"{metavar(args[0])},..."
    if dataclasses.is_dataclass(tp):
        return ",".join(f.name.upper() for f in dataclasses.fields(tp) if f.init)
    return {int: "INT", float: "FLOAT", str: "TEXT"}.get(tp, "JSON")


def field_help(cls: type, key: str) -> tuple[Any, str, Any]:
    """The field at dotted ``key`` of the dataclass ``cls``: (its type, its documentation with
    its unit, its default)."""
    tp: Any = cls
    default: Any = None
    doc = ""
    for part in key.split("."):
        owner = next(a for a in (tp, *typing.get_args(tp)) if dataclasses.is_dataclass(a))
        tp = typing.get_type_hints(owner)[part]
        f = next(f for f in dataclasses.fields(owner) if f.name == part)
        if default is not None and hasattr(default, part):
            default = getattr(default, part)
        elif f.default is not dataclasses.MISSING:
            default = f.default
        else:
            default = f.default_factory()  # type: ignore[misc]
        doc = field_docs(owner).get(part, "")
    if (u := unit(key)) and f"({u}" not in doc:
        doc = f"{doc} ({u})" if doc else f"in {u}"
    return tp, doc, default


def shown(value: Any) -> str:
    """A default as an option is written: on|off, a,b, none."""
    if isinstance(value, bool):
        return "on" if value else "off"
    if isinstance(value, tuple) and not dataclasses.is_dataclass(value):
        return ",".join(map(str, value)) or "()"
    return "none" if value is None else str(value)
