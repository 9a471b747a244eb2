"""Typed settings: a dataclass field that knows what it allows, and the one check of them all.

Every setting of the recipes is a field of a settings dataclass with a docstring under it. Its
annotation gives its type (``bool`` takes only ``true`` or ``false``, ``int`` no boolean, ``float``
only finite numbers, ``X | None`` also null), and :func:`setting` attaches the values it allows
beyond that. :func:`check_fields` checks an instance, :func:`build` a dict of values before the
dataclass is built (refusing keys the class lacks); both raise one ``ValueError`` naming the key,
the value and what is allowed::

    train.num_envs must be an integer >= 1, got 0

The module imports nothing of the package, so every layer's settings use it.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

__all__ = [
    "Allowed",
    "above",
    "at_least",
    "build",
    "check_fields",
    "check_value",
    "interval",
    "one_of",
    "setting",
    "shown",
]


@dataclass(frozen=True)
class Allowed:
    """The values a setting allows beyond its type: a test and the words that say what passes."""

    test: Callable[[Any], bool]
    text: str


def at_least(minimum: float) -> Allowed:
    """``>= minimum``."""
    return Allowed(lambda value: value >= minimum, f">= {minimum:g}")


def above(minimum: float) -> Allowed:
    """``> minimum``."""
    return Allowed(lambda value: value > minimum, f"> {minimum:g}")


def interval(
    low: float, high: float, *, low_open: bool = False, high_open: bool = False
) -> Allowed:
    """In the interval from ``low`` to ``high``, ends included unless open.

    Example:
        >>> interval(0, 1, low_open=True).text
        'in (0, 1]'
    """
    return Allowed(
        lambda value: (
            (low < value if low_open else low <= value)
            and (value < high if high_open else value <= high)
        ),
        f"in {'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}",
    )


def one_of(*options: Any) -> Allowed:
    """One of ``options``."""
    return Allowed(lambda value: value in options, "one of " + ", ".join(map(str, options)))


def setting(default: Any, allowed: Allowed | None = None, *, null: str | None = None) -> Any:
    """A dataclass field with its ``default`` (a list is copied for each instance), the values
    it ``allowed`` beyond its type, and what null means where the annotation allows it."""
    metadata = {"allowed": allowed, "null": null}
    if isinstance(default, list):
        return dataclasses.field(default_factory=lambda: list(default), metadata=metadata)
    return dataclasses.field(default=default, metadata=metadata)


def check_fields(instance: Any, group: str) -> None:
    """Raises ``ValueError`` naming the first field of the dataclass ``instance`` whose value is
    not of its type or not allowed, as ``<group>.<field>``.

    Example:
        >>> @dataclass
        ... class Video:
        ...     steps: int = setting(256, at_least(0))
        >>> check_fields(Video(steps=-1), "video")
        Traceback (most recent call last):
        ...
        ValueError: video.steps must be an integer >= 0, got -1
    """
    hints = typing.get_type_hints(type(instance))
    for field in dataclasses.fields(instance):
        value = getattr(instance, field.name)
        _check_field(_key(group, field.name), value, hints[field.name], field)


def build(cls: type, values: Any, group: str) -> Any:
    """The dataclass ``cls`` built from the mapping ``values``: a key that ``cls`` lacks, a value
    of the wrong type or outside its allowed range is refused naming ``<group>.<key>``; an
    integer for a ``float`` field becomes a float; a dataclass field is built from its mapping in
    turn. A ``ValueError`` that building ``cls`` raises itself (its own checks) is named after
    ``group``.

    Example:
        >>> @dataclass
        ... class Video:
        ...     fps: float = setting(15.0, above(0))
        >>> build(Video, {"fps": 30}, "video")
        Video(fps=30.0)
        >>> build(Video, {"fsp": 30}, "video")
        Traceback (most recent call last):
        ...
        ValueError: video.fsp is not a setting; the settings of video are: fps
    """
    if not isinstance(values, dict):
        raise ValueError(f"{group} must be a mapping of settings, got {shown(values)}")
    fields = {field.name: field for field in dataclasses.fields(cls)}
    unknown = [key for key in values if key not in fields]
    if unknown:
        name = unknown[0] if isinstance(unknown[0], str) else shown(unknown[0])
        raise ValueError(
            f"{_key(group, name[:80])} is not a setting; the settings of "
            f"{group or 'the top level'} are: {', '.join(fields)}"
        )
    hints = typing.get_type_hints(cls)
    built = {}
    for key, value in values.items():
        kind = hints[key]
        if dataclasses.is_dataclass(kind) and isinstance(value, dict):
            value = build(kind, value, _key(group, key))
        _check_field(_key(group, key), value, kind, fields[key])
        built[key] = float(value) if _accepts(kind, float) and type(value) is int else value
    try:
        return cls(**built)
    except ValueError as error:  # the class's own checks, which may not know its group
        message = str(error)
        if group and not message.startswith(f"{group}."):
            message = f"{group}.{message}"
        raise ValueError(message) from None


def _key(group: str, name: str) -> str:
    return f"{group}.{name}" if group else name


def _accepts(kind: Any, base: type) -> bool:
    return kind is base or base in typing.get_args(kind)


def _check_field(key: str, value: Any, kind: Any, field: dataclasses.Field) -> None:
    check_value(key, value, kind, field.metadata.get("allowed"), null=field.metadata.get("null"))


def check_value(
    key: str, value: Any, kind: Any, allowed: Allowed | None = None, *, null: str | None = None
) -> None:
    """Raises ``ValueError`` naming ``key`` unless ``value`` is of the type ``kind`` and
    ``allowed``, as a field of that type checks it (``null``: what null means, if allowed).

    Example:
        >>> check_value("run.cpu_defaults", "model=small", list[str])
        Traceback (most recent call last):
        ...
        ValueError: run.cpu_defaults must be a list of strings, got 'model=small'
    """
    options = typing.get_args(kind) if isinstance(kind, types.UnionType) else (kind,)
    nullable = type(None) in options
    kind = next(option for option in options if option is not type(None))
    if value is None and nullable:
        return
    text = _TYPE_TEXT.get(kind) or _type_text(kind)
    if allowed is not None:
        text = f"{text} {allowed.text}" if kind in _TYPE_TEXT else allowed.text
    if nullable:
        text += f" or null ({null})" if null else " or null"
    if not (_is_a(value, kind) and (allowed is None or allowed.test(value))):
        raise ValueError(f"{key} must be {text}, got {shown(value)}")


def shown(value: Any, limit: int = 80) -> str:
    """``repr(value)``, cut to ``limit`` characters where longer, so that a message stays one line.

    Example:
        >>> shown("x" * 500, limit=12)
        "'xxxxxxxxxx... (502 characters)"
    """
    text = repr(value)
    return text if len(text) <= limit else f"{text[: limit - 1]}... ({len(text)} characters)"


_TYPE_TEXT = {int: "an integer", float: "a finite number", bool: "true or false"}


_ITEMS_TEXT = {int: "integers", float: "finite numbers", bool: "booleans", str: "strings"}


def _type_text(kind: Any) -> str:
    if kind is str:
        return "a string"
    if typing.get_origin(kind) is list:
        (item,) = typing.get_args(kind)
        return f"a list of {_ITEMS_TEXT[item]}"
    return f"a {getattr(kind, '__name__', kind)}"


def _is_a(value: Any, kind: Any) -> bool:
    if kind is bool:
        return isinstance(value, bool)
    if kind is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if kind is float:
        return (
            isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
        )
    if typing.get_origin(kind) is list:
        (item,) = typing.get_args(kind)
        return isinstance(value, list) and all(_is_a(entry, item) for entry in value)
    return isinstance(value, kind)
