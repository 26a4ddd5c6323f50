"""``wiremap fleet forget ID [--connect ...] [--credentials FILE]``: administer a running fleet.

``forget ID`` asks the fusion service (a query on ``wiremap/<fleet>/admin/forget``, payload
``forget=ID``, checked by :func:`agents.fleet.validate.admin_request`) to remove
robot ``ID`` with no trace: its map, alignment, quarantined map; the store records why. In a
secure fleet only the fusion (admin) identity may ask (:func:`agents.fleet.secure.acl_config`):
pass its credentials (``wiremap run --secure --out DIR``: ``DIR/secure/credentials/fusion.json``).
A robot still running comes back with its next good map. Exit status 0 when the service
answered that it forgot the robot, 2 (one line) otherwise.
"""

from __future__ import annotations

import argparse
import json

from agents import argtypes
from agents.errors import UserError
from agents.fleet.bus import (
    StopFlag,
    add_bus_arguments,
    config_from_args,
    fleet_keys,
    open_session,
    valid_name,
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    p = sub.add_parser("forget", help="remove a robot from the fused map and the store, with no trace")
    p.add_argument("robot", metavar="ID", help="the robot id")
    p.add_argument("--timeout", type=argtypes.positive_float, default=5.0, metavar="S",
                   help="seconds to wait for the fusion service's answer (default 5)")  # fmt: skip
    add_bus_arguments(p)


def run(args: argparse.Namespace) -> int:
    if not valid_name(args.robot):
        raise UserError(f"{args.robot!r} is no robot id (letters, digits, _ . -)")
    keys = fleet_keys(args)
    cfg = config_from_args(args, "client")
    with StopFlag() as stop:
        session = open_session(cfg, stop.event, timeout=args.timeout)
        if session is None:
            return 1
        try:
            replies = list(session.get(keys.admin_forget, payload=f"forget={args.robot}".encode(),
                                       timeout=args.timeout))
        finally:
            session.close()
    for reply in replies:
        if reply.ok is not None:
            answer = json.loads(reply.ok.payload.to_bytes())
            if answer.get("ok"):
                had = "its map removed" if answer.get("had_map") else "it had no map"
                print(f"forgot {args.robot} ({had})")
                return 0
            raise UserError(f"the fusion service refused: {answer.get('error')}")
    raise UserError(
        "no answer from the fusion service on admin/forget (not running, or these credentials are not the admin's)"  # noqa: E501
    )
