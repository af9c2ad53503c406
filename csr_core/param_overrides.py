"""``NAME=VALUE`` overrides of a frozen params dataclass, for the diagnostics' ``--param`` options."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import fields, replace
from typing import Any, TypeVar

P = TypeVar("P", bound=Any)


def replace_fields(default: P, assignments: Sequence[str]) -> P:
    """``default`` (a params dataclass) with the fields of ``["name=value", ...]`` changed (values
    read as the field's default's type)."""
    defaults = {f.name: getattr(default, f.name) for f in fields(default)}
    changes: dict = {}
    for a in assignments:
        name, sep, value = a.partition("=")
        if not sep or name not in defaults:
            raise ValueError(f"{a!r}: expected NAME=VALUE with NAME a field of {type(default).__name__}")
        kind = type(defaults[name])
        changes[name] = value.lower() in ("1", "true", "yes") if kind is bool else kind(value)
    return replace(default, **changes)
