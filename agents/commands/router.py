"""``wiremap router``: a Zenoh router in a Python process (the wheel has no ``zenohd``).

The same JSON5 files run under ``zenohd -c FILE`` on machines that have it; see
``broker_config/README.md``.
"""

from __future__ import annotations

import argparse
import json
import sys

from agents.fleet.bus import StopFlag, add_bus_arguments, config_from_args, open_session

HELP = "a Zenoh router"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_bus_arguments(parser, router=True)


def run(args: argparse.Namespace) -> int:
    cfg = config_from_args(args, "router")
    with StopFlag() as stop:
        session = open_session(cfg, stop, wait=False)
        assert session is not None  # wait=False never returns None
        try:
            try:
                listen = json.loads(cfg.get_json("listen/endpoints"))
            except Exception:
                listen = []
            print(
                f"wiremap router: {session.zid()} listening on {', '.join(map(str, listen)) or '(nothing)'}",
                flush=True,
            )
            while not stop.wait(0.5):
                pass
        finally:
            session.close()
    print("wiremap router: stopped", file=sys.stderr, flush=True)
    return 0
