"""Configuration trees: frozen dataclasses nested by concern, named by dotted keys.

A configuration such as :class:`mapping.filter.FilterConfig` is a frozen dataclass whose fields
are plain values (``bool``, ``int``, ``float``, ``str``, ``X | None``, ``tuple[X, ...]``) or
further frozen dataclasses, one per concern (``compass``, ``cleanup``, ...). A leaf is named by
the path of field names down to it, ``"compass.young_weight"``.

* :func:`config_items` lists every leaf as ``{dotted key: value}``;
* :func:`with_overrides` returns a copy with some leaves replaced, coercing each value (a
  Python value or its text, e.g. from a command line) to the field's type, and re-running every
  touched dataclass's validation (``__post_init__``);
* :func:`check_number` is the range check the configuration dataclasses validate with.

Both functions are generic over nested frozen dataclasses and do no I/O: reading a parameter file
or parsing ``--set key=value`` belongs to the caller.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import types
import typing
from collections.abc import Mapping
from typing import Any, TypeVar

__all__ = ["ConfigError", "UnknownKeyError", "check_number", "config_items", "with_overrides"]

C = TypeVar("C")

_NONE_WORDS = ("none", "null")
_BOOL_WORDS = {"true": True, "false": False}


class ConfigError(ValueError):
    """A configuration value that cannot be applied; the message names the dotted key."""


class UnknownKeyError(ConfigError, KeyError):
    """A dotted key that names no setting of the configuration."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0]) if self.args else ""


def check_number(
    name: str,
    value: object,
    low: float = -math.inf,
    high: float = math.inf,
    *,
    open_low: bool = False,
    integer: bool = False,
    finite: bool = True,
) -> None:
    """Raise ``ValueError`` naming ``name`` unless ``value`` is a number in range.

    Parameters
    ----------
    name : str
        The field's name, for the message.
    value : object
        The value to check; ``bool`` is not a number here.
    low, high : float
        Bounds, inclusive (``low`` exclusive with ``open_low``).
    integer : bool
        Require an integer.
    finite : bool
        Reject infinities (NaN is always rejected).

    Raises
    ------
    ValueError
        ``"<name> must be <a number|an integer> <range>, got <value>"``.
    """
    kind = numbers.Integral if integer else numbers.Real
    ok = isinstance(value, kind) and not isinstance(value, bool)
    if ok:
        v = float(value)  # type: ignore[arg-type]
        ok = not math.isnan(v) and (math.isfinite(v) or not finite)
        ok = ok and (v > low if open_low else v >= low) and v <= high
    if ok:
        return
    what = "an integer" if integer else "a number"
    if high == math.inf:
        where = f"{'>' if open_low else '>='} {low:g}"
    else:
        where = f"within {'(' if open_low else '['}{low:g}, {high:g}]"
    raise ValueError(f"{name} must be {what} {where}, got {value!r}")


def _is_config(value: object) -> bool:
    return dataclasses.is_dataclass(value) and not isinstance(value, type)


def _fields(config: object) -> list[dataclasses.Field[Any]]:
    return [f for f in dataclasses.fields(config) if f.init]  # type: ignore[arg-type]


def config_items(config: object) -> dict[str, Any]:
    """Every setting of a configuration tree as ``{dotted key: value}``, in field order.

    Parameters
    ----------
    config : dataclass instance
        The configuration; fields that are dataclasses are groups, listed by their own settings.

    Returns
    -------
    dict
        E.g. ``{"particles": 10, ..., "compass.enabled": True, "compass.min_sigma": 0.0026, ...}``.

    Raises
    ------
    TypeError
        When ``config`` is not a dataclass instance.
    """
    if not _is_config(config):
        raise TypeError(f"not a configuration dataclass: {config!r}")
    out: dict[str, Any] = {}
    for f in _fields(config):
        value = getattr(config, f.name)
        if _is_config(value):
            out.update({f"{f.name}.{k}": v for k, v in config_items(value).items()})
        else:
            out[f.name] = value
    return out


def with_overrides(config: C, overrides: Mapping[str, Any]) -> C:
    """A copy of ``config`` with the settings named by dotted keys replaced.

    Parameters
    ----------
    config : dataclass instance
        A (frozen) configuration tree.
    overrides : mapping
        ``{"compass.young_weight": 0.05, "cleanup.drop_gap_bridges": "false", ...}``. A value is
        coerced to its field's type: ``bool`` from ``true``/``false`` (any case), ``int`` and
        ``float`` from numbers or their text, ``None`` (or the text ``none``/``null``) for an
        optional field, a tuple from a sequence or comma-separated text.

    Returns
    -------
    same type as ``config``
        A new tree; groups without overrides are the same objects as in ``config``.

    Raises
    ------
    UnknownKeyError
        A key names no setting (or names a group rather than one of its settings).
    ConfigError
        A value cannot be coerced to its field's type, or the group's validation rejects it;
        the message names the key.
    """
    return _override(config, overrides, "")


def _override(config: C, overrides: Mapping[str, Any], prefix: str) -> C:
    if not _is_config(config):
        raise TypeError(f"not a configuration dataclass: {config!r}")
    fields = {f.name: f for f in _fields(config)}
    hints = _type_hints(config)
    direct: dict[str, Any] = {}
    nested: dict[str, dict[str, Any]] = {}
    for key, value in overrides.items():
        full = prefix + key
        head, dot, rest = key.partition(".")
        if head not in fields or (dot and not rest):
            raise UnknownKeyError(f"unknown configuration key {full!r}")
        current = getattr(config, head)
        if _is_config(current):
            if not dot:
                raise UnknownKeyError(f"{full!r} is a group of settings: set one of them, e.g. {full}.<key>")
            nested.setdefault(head, {})[rest] = value
        elif dot:
            raise UnknownKeyError(f"unknown configuration key {full!r} ({prefix + head} is not a group)")
        else:
            direct[head] = _coerce(full, value, hints.get(head, type(current)))
    for head, sub in nested.items():
        direct[head] = _override(getattr(config, head), sub, f"{prefix}{head}.")
    if not direct:
        return config
    try:
        return dataclasses.replace(config, **direct)  # type: ignore[type-var]
    except (ValueError, TypeError) as err:
        if isinstance(err, ConfigError):
            raise
        keys = ", ".join(prefix + k for k in direct if k not in nested)
        raise ConfigError(f"invalid value for {keys}: {err}") from err


def _type_hints(config: object) -> dict[str, Any]:
    try:
        return typing.get_type_hints(type(config))
    except (NameError, TypeError):  # an annotation that cannot be resolved: fall back to the values
        return {}


def _coerce(key: str, value: Any, tp: Any) -> Any:
    """``value`` as an instance of the annotated type ``tp`` (see :func:`with_overrides`)."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin is typing.Union or origin is types.UnionType:
        options = [a for a in args if a is not type(None)]
        if len(options) < len(args) and (
            value is None or (isinstance(value, str) and value.strip().lower() in _NONE_WORDS)
        ):
            return None
        if len(options) == 1:
            return _coerce(key, value, options[0])
        raise ConfigError(f"{key}: cannot set a field of type {tp}")
    if tp is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.strip().lower() in _BOOL_WORDS:
            return _BOOL_WORDS[value.strip().lower()]
        raise ConfigError(f"{key} must be true or false, got {value!r}")
    if tp is int:
        if isinstance(value, numbers.Integral) and not isinstance(value, bool):
            return int(value)
        if isinstance(value, str):
            try:
                return int(value.strip())
            except ValueError:
                pass
        raise ConfigError(f"{key} must be an integer, got {value!r}")
    if tp is float:
        if isinstance(value, numbers.Real) and not isinstance(value, bool):
            return float(value)
        if isinstance(value, str):
            try:
                return float(value.strip())
            except ValueError:
                pass
        raise ConfigError(f"{key} must be a number, got {value!r}")
    if tp is str:
        if isinstance(value, str):
            return value
        raise ConfigError(f"{key} must be text, got {value!r}")
    if origin is tuple:
        items = value
        if isinstance(value, str):
            text = value.strip().strip("()[]").strip()
            items = [t for t in (s.strip() for s in text.split(",")) if t] if text else []
        if not isinstance(items, (list, tuple)):
            raise ConfigError(f"{key} must be a sequence, got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(f"{key}[{i}]", v, args[0]) for i, v in enumerate(items))
        if len(items) != len(args):
            raise ConfigError(f"{key} must have {len(args)} items, got {value!r}")
        return tuple(_coerce(f"{key}[{i}]", v, a) for i, (v, a) in enumerate(zip(items, args)))
    raise ConfigError(f"{key}: cannot set a field of type {tp}")
