"""One base for the typed configs (networks, training, data synthesis): ``replace``, ``to_dict`` and
``from_dict`` written once, with the unknown-field check every one of them needs.

A config is a dataclass that inherits :class:`Config`; its own ``__post_init__`` validates values
(``replace`` and ``from_dict`` run it again). ``legacy_fields`` names fields that older checkpoints
stored and the config no longer has (moved elsewhere); ``from_dict`` drops them, and only them. ``to_dict`` gives plain JSON types (tuples become
lists), so what a checkpoint stores compares equal to what it reads back; ``from_dict`` turns the
lists back into the tuples, nested configs and nested dataclasses the fields are annotated with.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import types
import typing
from typing import Any, ClassVar, TypeVar

__all__ = ["Config"]

C = TypeVar("C", bound="Config")


class Config:
    """Mixin for config dataclasses (see the module docstring)."""

    #: fields of older stored configs that ``from_dict`` drops (see the module docstring)
    legacy_fields: ClassVar[frozenset[str]] = frozenset()

    def replace(self: C, **changes: Any) -> C:
        """A copy with some fields changed (validated again); an unknown field is a one-line ValueError."""
        _check_fields(type(self), changes)
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        """Every field as plain JSON types (nested dataclasses as dicts, tuples as lists)."""
        return json.loads(json.dumps(dataclasses.asdict(self)))

    @classmethod
    def from_dict(cls: type[C], d: dict[str, Any]) -> C:
        """Inverse of :meth:`to_dict`: lists back to tuples and dicts back to the nested dataclasses the
        annotations name; a missing key takes its default; an unknown key is a one-line ValueError."""
        if not isinstance(d, dict):
            raise ValueError(f"{cls.__name__}: expected a mapping of fields, got {type(d).__name__}")
        d = {k: v for k, v in d.items() if k not in cls.legacy_fields}
        _check_fields(cls, d)
        hints = _type_hints(cls)
        return cls(**{k: _coerce(hints.get(k), v) for k, v in d.items()})


def _check_fields(cls: type, d: dict[str, Any]) -> None:
    bad = sorted(set(d) - {f.name for f in dataclasses.fields(cls)})
    if bad:
        raise ValueError(f"unknown {cls.__name__} field(s): {', '.join(bad)}")


@functools.cache
def _type_hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _coerce(hint: Any, value: Any) -> Any:
    """``value`` (plain JSON) as the annotation ``hint`` asks: tuples, nested dataclasses; anything
    else unchanged (the config's own validation judges it)."""
    if hint is None or value is None:
        return value
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):  # X | None: the first member the value fits
        for member in args:
            if member is not type(None):
                coerced = _coerce(member, value)
                if coerced is not value:
                    return coerced
        return value
    if origin is tuple and isinstance(value, (list, tuple)):
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(args[0], x) for x in value)
        if args and len(args) == len(value):
            return tuple(_coerce(a, x) for a, x in zip(args, value, strict=True))
        return tuple(value)
    if isinstance(hint, type) and dataclasses.is_dataclass(hint) and isinstance(value, dict):
        return hint.from_dict(value) if issubclass(hint, Config) else hint(**value)
    return value
