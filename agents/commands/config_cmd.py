"""``wiremap config show [--params FILE] [--set KEY=VALUE ...] [--world W] [--particles N] [--json]``:
the particle filter's effective configuration.

Prints every setting of :class:`mapping.filter.FilterConfig` as a TOML document that
``--params`` reads back (top-level keys, then one ``[group]`` table per concern); a setting
that ``--params``, ``--set`` or a flag changed from its default carries a comment naming where
the change came from.
With ``--world``, the world's defaults come first (:func:`agents.mapping_run.world_defaults`:
merge threshold 0.4 m and 6 particles for a world over 100 m, as ``wiremap bench accuracy``
runs it). ``--json`` prints ``{dotted key: value}`` instead.
"""

from __future__ import annotations

import argparse
import json
import re
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from agents.params import ConfigArgs, add_config_arguments, jsonable, resolve, to_toml

if TYPE_CHECKING:
    from mapping.filter import FilterConfig

HELP = "show the particle filter's effective configuration (TOML, readable by --params)"


def _plain(doc: str) -> str:
    """A docstring paragraph as terminal text: reST roles and literals without their markup
    (``:class:`a.b.C``` -> ``a.b.C``, double backquotes dropped)."""
    return re.sub(r":\w+:`([^`]*)`", r"\1", doc).replace("``", "")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", metavar="ACTION", parser_class=type(parser), required=True)
    show = sub.add_parser("show", help="print the effective configuration",
                          description=_plain(__doc__.split("\n\n")[1]))
    show.add_argument("--world", metavar="NAME|FILE",
                      help="apply this world's defaults (threshold, particles)")
    show.add_argument("--particles", type=int, default=None, help="number of particles")
    show.add_argument("--merge-threshold", type=float, default=None, metavar="M",
                      help="merge threshold, metres")
    show.add_argument("--max-range", type=float, default=None, metavar="M", help="sensing range, metres")
    show.add_argument("--json", action="store_true", help="print {dotted key: value} as JSON instead of TOML")
    add_config_arguments(show, "--particles, --merge-threshold, --max-range")


def run(args: argparse.Namespace) -> int:
    from agents import mapping_run as mr
    from mapping.config import config_items

    cargs = ConfigArgs.from_args(args)
    particles, thr, origin = 10, 0.2, "defaults"
    if args.world is not None:
        from agents.sim.world import load_world

        world = load_world(args.world)
        particles, thr = mr.world_defaults(world)
        origin = f"defaults for world {world.name} ({max(world.size):g} m across)"
    given = {
        "particles": ("--particles", args.particles),
        "merge_threshold": ("--merge-threshold", args.merge_threshold),
        "max_range": ("--max-range", args.max_range),
    }
    flags = {k: v for k, v in given.items() if v[1] is not None}
    def make(overrides: Mapping[str, Any]) -> FilterConfig:
        return mr.filter_config_for(particles, thr, 8.0, overrides=overrides)

    resolved = resolve(cargs, make, flags)
    items = config_items(resolved.config)
    if args.json:
        print(json.dumps(jsonable(items)))
        return 0
    defaults = config_items(make({}))
    changed = [k for k in resolved.overrides if items[k] != defaults[k]]
    notes = _sources(changed, cargs, flags)
    header = (
        f"wiremap filter configuration: {origin}"
        + (", changed where noted" if notes else "")
        + ".\nRead back with --params FILE; change one setting with --set group.key=value."
    )
    print(to_toml(items, notes, header), end="")
    return 0


def _sources(changed: list[str], cargs: ConfigArgs, flags: dict[str, tuple[str, Any]]) -> dict[str, str]:
    """Where each changed setting came from (the last layer that set it wins)."""
    out: dict[str, str] = {}
    for key in changed:
        if key in cargs.set_values:
            out[key] = "--set"
        elif key in flags:
            out[key] = flags[key][0]
        else:
            out[key] = f"--params {cargs.params}"
    return out

