"""``wiremap world show NAME|FILE``: draw a world (PNG or SVG) or write it out as a world file.

Examples::

    wiremap world show paper-small --png paper-small.png
    wiremap world show museum --png museum.png --plan --seed 3
    wiremap world show office --geojson office.geojson     # a file load_world reads back
    wiremap world show office --png office.png --plan --robots 4 --unknown-starts --seed 1
    wiremap world show my-floor.geojson --svg floor.svg

Without an output flag it prints the world's summary. ``--plan`` draws a coverage route planned
from the world (``--robots N`` splits it into N robot routes, each in its own colour;
``--unknown-starts`` draws the routes of ``wiremap run --unknown-starts`` with the same seed); a
route given in the world file is drawn in any case. With ``--geojson`` and ``--plan`` (one robot),
the planned route is written into the world file as its ``route``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING

from agents.argtypes import image_size, non_negative_int
from agents.errors import UserError

if TYPE_CHECKING:
    import numpy as np

    from agents.sim.world import World

HELP = "draw a world or write it out as a world file"

_ROUTE_COLORS = [(0, 160, 60), (30, 110, 230), (230, 120, 0), (170, 40, 190), (0, 170, 170), (200, 30, 90)]


SHOW_DESCRIPTION = """\
Draw a world (PNG or SVG, outside the free space shaded) or write it out as a world file.

examples:
  wiremap world show paper-small --png paper-small.png
  wiremap world show museum --png museum.png --plan --seed 3
  wiremap world show office --geojson office.geojson     # a world file to edit
  wiremap world show office --png office.png --plan --robots 4 --unknown-starts --seed 1
  wiremap world show my-floor.geojson --svg floor.svg

Without an output flag it prints the world's summary. --plan draws a coverage route planned
from the world (--robots N splits it into N robot routes, each in its own colour;
--unknown-starts draws the routes `wiremap run --unknown-starts` drives with the same --seed); a
route given in the world file is drawn in any case."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", metavar="ACTION", parser_class=type(parser))
    show = sub.add_parser(
        "show",
        help="draw a world or write it out",
        description=SHOW_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    show.add_argument("world", metavar="NAME|FILE", help="built-in world name or a .geojson world file")
    show.add_argument("--png", metavar="PATH", help="write a PNG picture")
    show.add_argument("--svg", metavar="PATH", help="write an SVG picture")
    show.add_argument("--geojson", metavar="PATH", help="write the world as a world file")
    show.add_argument("--plan", action="store_true", help="plan and draw a coverage route")
    show.add_argument("--robots", type=int, default=1, metavar="N", help="split the route among N robots")
    show.add_argument("--unknown-starts", action="store_true",
                      help="with --plan: the routes `wiremap run --unknown-starts` drives (N robots at "
                           "random starts sharing the coverage out; same --seed, same routes)")
    show.add_argument("--seed", type=non_negative_int, default=0,
                      help="random seed for the route planner (default 0)")
    show.add_argument("--clearance", type=float, default=0.4, help="route clearance from walls, m")
    show.add_argument("--spacing", type=float, default=None, help="route coverage spacing, m")
    show.add_argument("--max-px", type=image_size, default=1600,
                      help="larger side of the PNG in pixels (>= 64)")


def run(args: argparse.Namespace) -> int:
    if getattr(args, "action", None) != "show":
        raise UserError("choose an action: show")
    import numpy as np
    import shapely

    from agents.files.io import check_output_file, write_atomic, write_json
    from agents.sim.world import load_world

    for flag in ("--png", "--svg", "--geojson"):
        path = getattr(args, flag[2:])
        if path:
            check_output_file(flag, path)
    if args.robots < 1:
        raise UserError("--robots must be at least 1")
    if args.unknown_starts and not args.plan:
        raise UserError("--unknown-starts draws planned routes: add --plan")
    world = load_world(args.world)
    routes = []
    if args.plan:
        from agents.sim.route import plan_routes, route_length

        t0 = time.perf_counter()
        try:
            if args.unknown_starts:
                from agents.fleet.unknown_run import random_routes

                routes = random_routes(world, args.robots, np.random.default_rng(args.seed),
                                       clearance=args.clearance, spacing=args.spacing)
            else:
                routes = plan_routes(
                    world,
                    args.robots,
                    np.random.default_rng(args.seed),
                    clearance=args.clearance,
                    spacing=args.spacing,
                    use_world_route=False,
                )
        except ValueError as exc:
            raise UserError(str(exc)) from None
        took = time.perf_counter() - t0
        total = sum(route_length(r) for r in routes)
        sys.stderr.write(f"planned {len(routes)} route(s), {total:.0f} m in {took:.2f} s\n")
    elif world.route is not None:
        routes = [np.asarray(world.route.coords)[:, :2]]

    if args.geojson:
        out = world
        if args.plan and len(routes) == 1:
            out = dataclasses.replace(world, route=shapely.LineString(routes[0]))
        write_json(args.geojson, out.to_geojson())
    if args.png:
        write_atomic(args.png, world_png(world, routes, max_px=args.max_px))
    if args.svg:
        write_atomic(args.svg, world_svg(world, routes))
    if not (args.png or args.svg or args.geojson):
        sys.stdout.write(json.dumps(world.summary(), indent=2) + "\n")
    return 0


def world_png(world: World, routes: Sequence[np.ndarray] = (), *, max_px: int = 1600) -> bytes:
    """The world as a PNG: solid grey, free space white, walls black, corners red, routes."""
    from agents.files.render import Canvas, draw_wireframe

    canvas = Canvas(world.bounds(), max_px=max_px, background=(150, 150, 150))
    canvas.polygon_fill(world.free_space, (255, 255, 255))
    w = max(1.5, min(3.0, canvas.scale * 0.06))
    for k, r in enumerate(routes):
        canvas.polyline(r, _ROUTE_COLORS[k % len(_ROUTE_COLORS)], 1.5)
    draw_wireframe(canvas, world.truth, edge_color=(0, 0, 0), width=w, point_radius=w + 1.0)
    for k, r in enumerate(routes):
        canvas.point(r[0], _ROUTE_COLORS[k % len(_ROUTE_COLORS)], w + 3.0, "square")
    return canvas.to_png()


def world_svg(world: World, routes: Sequence[np.ndarray] = ()) -> str:
    """The world's truth wireframe as SVG, with every route in its colour (as on the PNG)."""
    from agents.files.render import wireframe_svg

    lines = [(r, _ROUTE_COLORS[k % len(_ROUTE_COLORS)]) for k, r in enumerate(routes)]
    return wireframe_svg(world.truth, trajectories=lines, arrows=True, title=world.name)
