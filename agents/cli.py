"""The ``wiremap`` command line.

Each subcommand lives in its own module under :mod:`agents.commands` (``HELP``,
``add_arguments``, ``run``); only the chosen one is imported, so ``wiremap worlds`` does not pay
for importing zenoh or rerun. Errors a user can fix (:class:`agents.errors.UserError`, bad
files, bad flags, output paths that cannot be written) print one line and exit 2, before any
work where the arguments allow it; Ctrl-C exits 130 (:data:`agents.errors.INTERRUPTED`; ``map``
and ``run`` first write what they have).
"""

from __future__ import annotations

import argparse
import importlib
import signal
import sys
from collections.abc import Sequence

from agents.commands.bench import BENCHES  # names and help only (the benchmarks import lazily)
from agents.errors import INTERRUPTED, UserError

# command name -> (module, one-line help). The help text is repeated here so that
# `wiremap --help` can list every command without importing any of them.
COMMANDS: dict[str, tuple[str, str]] = {
    "map": ("agents.commands.map_cmd", "run one robot (simulated, CARMEN log, ROS bag), write its map"),
    "worlds": ("agents.commands.worlds", "list the built-in worlds"),
    "world": ("agents.commands.world", "draw a world or write it out as a world file"),
    "run": ("agents.commands.run", "the main job: router, N robots and the fusion service"),
    "robot": ("agents.commands.robot", "one robot agent process"),
    "play": ("agents.commands.play", "publish a log's scans and odometry as a ROS 2 robot would"),
    "fuse": ("agents.commands.fuse", "the fusion service"),
    "router": ("agents.commands.router", "a Zenoh router"),
    "watch": ("agents.commands.watch", "subscribe to the fused map and show each version"),
    "fleet": ("agents.commands.fleet", "administer a running fleet: forget a robot"),
    "replay": ("agents.commands.replay", "open the Rerun viewer on a recording"),
    "export": ("agents.commands.export", "export a map as GeoJSON, SVG, PNG or a ROS map"),
    "bench": ("agents.commands.bench", "benchmarks: " + ", ".join(BENCHES)),
    "config": ("agents.commands.config_cmd", "show the particle filter's effective configuration"),
}


# The arguments being parsed, for commands whose own subcommands import lazily (``bench``).
ARGV: list[str] = []


class _Parser(argparse.ArgumentParser):
    """argparse that reports bad flags as one line and exit status 2."""

    def error(self, message: str) -> None:  # type: ignore[override]
        sys.stderr.write(f"{self.prog}: error: {message}\n")
        raise SystemExit(2)


def build_parser(command: str | None) -> argparse.ArgumentParser:
    parser = _Parser(prog="wiremap", description="Multi-robot wireframe map sharing.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for name, (module_name, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if name == command:
            module = importlib.import_module(module_name)
            module.add_arguments(p)
            p.set_defaults(_module=module)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    code = _main(argv)
    if code == INTERRUPTED and argv is None:
        # The command's own process, stopping for Ctrl-C with what it has written: a further
        # Ctrl-C while the interpreter shuts down (its handlers reset to the default, and any
        # thread -- a BLAS pool's -- may take the signal) would kill it by the signal instead
        # of exiting 130. Ignored from here: the process is ending anyway.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    return code


def _main(argv: Sequence[str] | None) -> int:
    args_list = list(sys.argv[1:] if argv is None else argv)
    ARGV[:] = args_list
    command = next((a for a in args_list if not a.startswith("-")), None)
    parser = build_parser(command if command in COMMANDS else None)
    args = parser.parse_args(args_list)
    if getattr(args, "_module", None) is None:
        parser.print_help()
        return 2
    try:
        return int(args._module.run(args) or 0)
    except UserError as exc:
        sys.stderr.write(f"wiremap {getattr(args, '_label', None) or args.command}: {exc}\n")
        return 2
    except KeyboardInterrupt:
        sys.stderr.write("\nwiremap: interrupted\n")  # on a line of its own, after any progress line
        return INTERRUPTED
    except BrokenPipeError:
        return 0


if __name__ == "__main__":
    sys.exit(main())
