"""What a config section says about its fields: their types, their documentation (the docstring
under each field) and the allowed values of its modes (``Literal`` fields). ``ultraboneudf config``
and the checks of :mod:`.overrides` read them."""

from __future__ import annotations

import typing
from dataclasses import fields
from functools import cache
from typing import Any, Literal

from ..errors import InputError


@cache
def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


@cache
def field_docs(cls: type) -> dict[str, str]:
    """The docstring under each field of a config section (the string literal that follows its
    annotation in the class body), ``""`` where there is none. Read from the source, which is the
    one place the fields are documented."""
    import ast
    import inspect
    import textwrap

    body = ast.parse(textwrap.dedent(inspect.getsource(cls))).body[0].body
    docs: dict[str, str] = {}
    for node, after in zip(body, body[1:] + [None]):
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            doc = ""
            if isinstance(after, ast.Expr) and isinstance(after.value, ast.Constant) \
                    and isinstance(after.value.value, str):
                doc = " ".join(after.value.value.split())
            docs[node.target.id] = doc
    return {f.name: docs.get(f.name, "") for f in fields(cls)}


def choices(section: Any, name: str) -> tuple[str, ...] | None:
    """The allowed values of a mode field (annotated ``Literal[...]``) of a config section (a class
    or an instance), or ``None`` when the field is not a mode."""
    cls = section if isinstance(section, type) else type(section)
    hint = _hints(cls).get(name)
    return typing.get_args(hint) if typing.get_origin(hint) is Literal else None


def check_choices(section: Any) -> None:
    """Raise :class:`InputError` naming the ``--set`` key and the allowed values for every mode field
    of ``section`` that holds a value outside its ``Literal`` type."""
    for f in fields(section):
        _check_choice(section, f.name, getattr(section, f.name))


def _check_choice(section: Any, name: str, value: Any) -> None:
    allowed = choices(section, name)
    if allowed is not None and value not in allowed:
        raise InputError(f"unknown {section.SECTION}.{name} {value!r}; choose one of {', '.join(allowed)}")
