"""The particle filter's configuration on the command line: ``--params FILE`` and ``--set KEY=VALUE``.

``wiremap map``, ``robot``, ``run`` and ``bench accuracy`` build a
:class:`mapping.filter.FilterConfig` in three layers, each overriding the one before:

1. the command's defaults (for a world over 100 m: merge threshold 0.4 m, and 6 particles in
   ``bench accuracy`` and ``config show``, :func:`agents.mapping_run.world_defaults`);
2. ``--params FILE``: a TOML file whose top-level keys and ``[group]`` tables mirror the dotted
   keys (``[compass]`` / ``young_weight = 0.05`` is ``compass.young_weight``); ``wiremap config
   show`` writes one;
3. the command's own flags that name a setting (``--particles``, ``--merge-threshold`` or
   ``--threshold``, ``--max-range``): shorthands for ``--set particles=...`` and so on;
4. ``--set group.key=value`` (repeatable; the last one of a key wins).

So the command line beats the file, and ``--set`` beats everything. ``mutate`` follows the
particle count (one particle: no mutation) unless it is set itself.

Every key and value is checked before the command does any work: a bad one is a
:class:`~agents.errors.UserError` naming its source and key, e.g.
``--set compass.young_wieght: unknown key (did you mean compass.young_weight?)``.
This module does the reading and the messages; :func:`mapping.config.with_overrides` does the
coercion and validation.
"""

from __future__ import annotations

import argparse
import difflib
import json
import math
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from agents.errors import UserError
from mapping.config import ConfigError, config_items
from mapping.filter import FilterConfig

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - the declared dependency for Python 3.10
    import tomli as tomllib

__all__ = [
    "ConfigArgs",
    "Resolved",
    "add_config_arguments",
    "jsonable",
    "parse_toml",
    "resolve",
    "to_toml",
]

# A command's flags that set a configuration key: {dotted key: (flag, value)}, explicit ones only.
Flags = Mapping[str, tuple[str, Any]]


def add_config_arguments(parser: argparse.ArgumentParser, flags: str = "") -> None:
    """Add ``--params FILE`` and ``--set KEY=VALUE`` (``flags``: the command's own flags that
    set configuration keys, named in the help's precedence line)."""
    order = "the command's defaults < --params FILE" + (f" < {flags}" if flags else "") + " < --set"
    g = parser.add_argument_group(
        "filter configuration",
        f"Settings of the particle filter (list them with `wiremap config show`). Precedence: {order}.",
    )
    g.add_argument(
        "--params", metavar="FILE",
        help="TOML file of filter settings: top-level keys and [group] tables, "
             "as `wiremap config show` prints",
    )
    g.add_argument(
        "--set", dest="set", metavar="GROUP.KEY=VALUE", action="append", default=[], type=_key_value,
        help="one filter setting, e.g. compass.young_weight=0 (repeatable; wins over --params and the flags)",
    )


def _key_value(text: str) -> tuple[str, str]:
    key, eq, value = text.partition("=")
    if not eq or not key.strip():
        raise argparse.ArgumentTypeError(f"expected GROUP.KEY=VALUE, got {text!r}")
    return key.strip(), value.strip()


# ---------------------------------------------------------------------- reading
def parse_toml(text: str, name: str = "<params>") -> dict[str, Any]:
    """A TOML parameter file's settings as ``{dotted key: value}`` (tables flattened).

    Raises
    ------
    UserError
        The text is not TOML (the message names ``name``, the line and the column).
    """
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"--params {name}: not valid TOML: {exc}") from None
    return _flatten(doc, "")


def _flatten(table: Mapping[str, Any], prefix: str) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in table.items():
        if isinstance(value, dict):
            out.update(_flatten(value, f"{prefix}{key}."))
        else:
            out[prefix + key] = value
    return out


def _read_params(path: str) -> dict[str, Any]:
    try:
        with open(path, "rb") as fh:
            raw = fh.read()
    except FileNotFoundError:
        raise UserError(f"--params {path}: no such file") from None
    except IsADirectoryError:
        raise UserError(f"--params {path}: is a directory") from None
    except OSError as exc:
        raise UserError(f"--params {path}: cannot read: {exc.strerror or exc}") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise UserError(f"--params {path}: not UTF-8 text") from None
    return parse_toml(text, path)


@dataclass(frozen=True)
class ConfigArgs:
    """``--params`` and ``--set`` of one command line.

    Attributes
    ----------
    params : str or None
        The parameter file's path.
    file_values : dict
        Its settings, ``{dotted key: value}``.
    set_values : dict
        ``--set`` settings, ``{dotted key: text}`` (the last of a repeated key).
    """

    params: str | None = None
    file_values: dict[str, Any] = field(default_factory=dict)
    set_values: dict[str, str] = field(default_factory=dict)

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> ConfigArgs:
        """Read ``args.params`` (a :class:`UserError` when it cannot be read or parsed) and
        collect ``args.set``."""
        params = getattr(args, "params", None)
        file_values = _read_params(params) if params else {}
        return cls(params, file_values, dict(getattr(args, "set", None) or []))


@dataclass(frozen=True)
class Resolved:
    """A command's filter configuration.

    Attributes
    ----------
    config : FilterConfig
        The configuration the command runs.
    overrides : dict
        Everything applied over the command's defaults (file, flags, ``--set``): feeding it to
        the same ``make`` gives ``config`` again.
    recorded : dict
        The settings from ``--params`` and ``--set`` that took effect, as applied (typed,
        JSON-able: see :func:`jsonable`); what a report records so that a run can be repeated.
    """

    config: FilterConfig
    overrides: dict[str, Any]
    recorded: dict[str, Any]


def resolve(
    cargs: ConfigArgs, make: Callable[[Mapping[str, Any]], FilterConfig], flags: Flags | None = None
) -> Resolved:
    """The configuration ``make(overrides)`` with the file, then ``flags``, then ``--set`` over
    the command's defaults (``make({})``), every key and value checked.

    Raises
    ------
    UserError
        One line naming the source (``--params FILE``, the flag, ``--set``) and the key of the
        first unknown key or bad value.
    """
    flags = dict(flags or {})
    known = config_items(make({}))
    src = f"--params {cargs.params}"
    for key in cargs.file_values:
        _check_key(known, key, f"{src}: {key}")
    for key in cargs.set_values:
        _check_key(known, key, f"--set {key}")
    layers: list[tuple[str, dict[str, Any], Callable[[str], str]]] = [
        (src, dict(cargs.file_values), lambda k: f"{src}: {k} = {_toml_value(cargs.file_values[k])}"),
        ("the command's flags", {k: v for k, (_, v) in flags.items()}, lambda k: flags[k][0]),
        ("--set", dict(cargs.set_values), lambda k: f"--set {k}={cargs.set_values[k]}"),
    ]
    applied: dict[str, Any] = {}
    config = make({})
    for label, layer, where in layers:
        if not layer:
            continue
        try:
            config = make({**applied, **layer})
        except ConfigError as err:  # name the key when one alone is refused
            for key, value in layer.items():
                try:
                    make({**applied, key: value})
                except ConfigError as one:
                    raise UserError(f"{where(key)}: {_reason(key, one)}") from None
            raise UserError(f"{label}: {err}") from None
        applied.update(layer)
    items = config_items(config)
    kept = {k for k in cargs.file_values if k not in flags} | set(cargs.set_values)
    recorded = {k: items[k] for k in known if k in kept}
    return Resolved(config, applied, jsonable(recorded))


def _check_key(known: Mapping[str, Any], key: str, where: str) -> None:
    if key in known:
        return
    members = [k for k in known if k.startswith(key + ".")]
    if members:
        raise UserError(f"{where}: a group of settings; set one of them, e.g. {members[0]}")
    guess = difflib.get_close_matches(key, list(known), n=1, cutoff=0.6)
    if not guess:  # the group left out or wrong: match the last part alone
        leaf = key.rsplit(".", 1)[-1]
        leaves = {k.rsplit(".", 1)[-1]: k for k in known}
        close = difflib.get_close_matches(leaf, list(leaves), n=1, cutoff=0.75)
        guess = [leaves[close[0]]] if close else []
    hint = f" (did you mean {guess[0]}?)" if guess else " (`wiremap config show` lists them)"
    raise UserError(f"{where}: unknown key{hint}")


def _reason(key: str, err: ConfigError) -> str:
    """The error's message without the key it starts with (the caller names it)."""
    msg = str(err)
    for prefix in (f"invalid value for {key}: ", f"{key} "):
        if msg.startswith(prefix):
            return msg[len(prefix):]
    return msg


# ---------------------------------------------------------------------- writing
def jsonable(values: Mapping[str, Any]) -> dict[str, Any]:
    """``values`` for a JSON report: tuples as lists, infinities and NaN as the text ``--set``
    reads back (``"inf"``), everything else as it is."""

    def one(v: Any) -> Any:
        if isinstance(v, float) and not math.isfinite(v):
            return repr(v)
        if isinstance(v, (tuple, list)):
            return [one(x) for x in v]
        return v

    return {k: one(v) for k, v in values.items()}


def _toml_value(v: Any) -> str:
    if v is None:
        return '"none"'  # TOML has no null; with_overrides reads "none" as None
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return repr(v)  # shortest text that reads back to the same float; inf, -inf, nan are TOML
    if isinstance(v, str):
        return json.dumps(v)  # a TOML basic string
    if isinstance(v, (tuple, list)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"no TOML form for {v!r}")


def to_toml(values: Mapping[str, Any], notes: Mapping[str, str] | None = None, header: str = "") -> str:
    """``{dotted key: value}`` as a TOML document: top-level keys first, then one ``[group]``
    table per group (nested groups as ``[group.sub]``), in the order the keys come.

    Parameters
    ----------
    values : mapping
        Settings, e.g. :func:`mapping.config.config_items` of a configuration.
    notes : mapping, optional
        A comment to put after a key's line.
    header : str
        Comment lines for the top of the document (without ``#``).
    """
    notes = notes or {}
    tree: dict[str, Any] = {}
    for key, value in values.items():
        *groups, leaf = key.split(".")
        node = tree
        for g in groups:
            node = node.setdefault(g, {})
        node[leaf] = (key, value)
    lines = [f"# {ln}".rstrip() for ln in header.splitlines()]

    def emit(node: dict[str, Any], path: str) -> None:
        leaves = [v for v in node.values() if isinstance(v, tuple)]
        if path and (leaves or lines):
            lines.append("")
            lines.append(f"[{path}]")
        for name, item in node.items():
            if isinstance(item, tuple):
                key, value = item
                note = f"  # {notes[key]}" if key in notes else ""
                lines.append(f"{name} = {_toml_value(value)}{note}")
        for name, item in node.items():
            if isinstance(item, dict):
                emit(item, f"{path}.{name}" if path else name)

    emit(tree, "")
    return "\n".join(lines) + "\n"
