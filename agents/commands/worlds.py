"""``wiremap worlds``: list the built-in worlds (name, size, corners, walls, description)."""

from __future__ import annotations

import argparse
import json
import sys

HELP = "list the built-in worlds"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="print a JSON list instead of a table")


def run(args: argparse.Namespace) -> int:
    from agents.sim.builtin import BUILTINS
    from agents.sim.world import load_world

    rows = []
    for name, spec in BUILTINS.items():
        info = load_world(name).summary()
        info["description"] = spec.description
        rows.append(info)
    if args.json:
        sys.stdout.write(json.dumps(rows, indent=2) + "\n")
        return 0
    header = f"{'name':<12} {'size (m)':>11} {'corners':>7} {'walls':>5}  description"
    lines = [header]
    for r in rows:
        w, h = r["size_m"]
        size = f"{w:g} x {h:g}"
        lines.append(f"{r['name']:<12} {size:>11} {r['corners']:>7} {r['walls']:>5}  {r['description']}")
    sys.stdout.write("\n".join(lines) + "\n")
    return 0
