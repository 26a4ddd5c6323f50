"""``wiremap export MAP --format geojson|svg|png|rosmap --out PATH``.

``MAP`` is a ``.wfm`` file (exactly one :mod:`wire_codec` message, e.g. a saved fused map) or a
``.geojson`` written by ``wiremap`` (or any FeatureCollection of corner points and wall lines).

Formats:

* ``geojson`` -- the wireframe as GeoJSON (corners and directed walls); a ``.wfm``'s metadata
  (sender, version, robots, ...) goes on the collection's ``properties``;
* ``svg`` / ``png`` -- pictures (:mod:`agents.files.render`): walls coloured by likelihood, corners
  by label;
* ``rosmap`` -- a ROS ``map_server`` map for Nav2: ``PATH.pgm`` + ``PATH.yaml`` at
  ``--resolution`` metres per cell (see :mod:`agents.files.export` for the free / occupied / unknown
  rules). ``--out maps/floor`` writes ``maps/floor.pgm`` and ``maps/floor.yaml``; an ``--out``
  ending in ``.pgm`` or ``.yaml`` names one of the pair and the other gets the same stem.

Without ``--format`` the format follows ``--out``'s suffix (``.geojson``/``.json``, ``.svg``,
``.png``, ``.pgm``/``.yaml``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from agents import argtypes
from agents.errors import UserError

HELP = "export a map as GeoJSON, SVG, PNG or a ROS map"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from agents.files.export import DEFAULT_OPEN_RANGE, DEFAULT_RESOLUTION, DEFAULT_SENSOR_RANGE, FORMATS

    parser.add_argument("map", metavar="MAP", help="a .wfm (wire message) or .geojson map file")
    parser.add_argument(
        "--format",
        choices=FORMATS,
        help="output format (default: from --out's suffix)",
    )
    parser.add_argument(
        "--out",
        metavar="PATH",
        required=True,
        help="output file; for rosmap a stem: PATH.pgm + PATH.yaml (PATH may end in .pgm or .yaml)",
    )
    parser.add_argument(
        "--resolution",
        type=argtypes.positive_float,
        default=DEFAULT_RESOLUTION,
        metavar="M",
        help=f"rosmap cell size in metres (default {DEFAULT_RESOLUTION})",
    )
    parser.add_argument(
        "--trajectory",
        action="append",
        default=[],
        metavar="FILE|DIR",
        help="rosmap: a robot's track (wiremap map's trajectory.tsv: t x y theta; or x y theta; or "
        "x y), or a folder of them (wiremap run's tracks/, runs from known starts); what the "
        "sensor could see up to a wall of the map is free too (repeatable)",
    )
    parser.add_argument(
        "--sensor-range",
        type=argtypes.positive_float,
        default=None,
        metavar="M",
        help="with --trajectory: how far the sensor saw walls, metres "
        f"(default {DEFAULT_SENSOR_RANGE:g}, the simulator's)",
    )
    parser.add_argument(
        "--open-range",
        type=argtypes.non_negative_float,
        default=None,
        metavar="M",
        help="with --trajectory: free space around the track where no wall of the map is in range "
        f"(default {DEFAULT_OPEN_RANGE:g}: a real map lacks walls the scanner saw, and nothing "
        "beyond them is known to be free)",
    )
    parser.add_argument(
        "--min-likelihood",
        type=argtypes.probability,
        default=0.0,
        metavar="P",
        help="drop walls whose likelihood is below P first (default 0: keep all)",
    )


def run(args: argparse.Namespace) -> int:
    from agents.files.export import (
        DEFAULT_OPEN_RANGE,
        DEFAULT_SENSOR_RANGE,
        FORMATS,
        export_map,
        format_from_suffix,
        load_map,
        read_track,
        rosmap_paths,
    )

    fmt = args.format or format_from_suffix(args.out)
    if fmt is None:
        raise UserError(f"cannot tell the format from {args.out!r}: give --format ({'|'.join(FORMATS)})")
    from agents.files.io import check_output_file

    for path in rosmap_paths(args.out) if fmt == "rosmap" else (args.out,):
        check_output_file("--out", path)
    loaded = load_map(args.map)
    if args.trajectory and fmt != "rosmap":
        raise UserError("--trajectory is for --format rosmap (the free space of the occupancy grid)")
    if not args.trajectory and (args.sensor_range is not None or args.open_range is not None):
        raise UserError("--sensor-range and --open-range go with --trajectory")
    tracks = []
    if args.trajectory:
        files = []
        for t in map(Path, args.trajectory):  # a folder: every *.tsv in it (wiremap run's tracks/)
            found = sorted(t.glob("*.tsv")) if t.is_dir() else [t]
            if not found:
                raise UserError(f"--trajectory {t}: no .tsv track in this folder")
            files.extend(found)
        tracks = [read_track(t) for t in files]
    try:
        written = export_map(
            loaded, fmt, args.out, resolution=args.resolution, min_likelihood=args.min_likelihood,
            tracks=tracks,
            sensor_range=DEFAULT_SENSOR_RANGE if args.sensor_range is None else args.sensor_range,
            open_range=DEFAULT_OPEN_RANGE if args.open_range is None else args.open_range,
        )
    except ValueError as exc:
        raise UserError(str(exc)) from None
    except OSError as exc:
        raise UserError(f"cannot write {args.out}: {exc.strerror or exc}") from None
    wf = loaded.wireframe
    print(
        f"wrote {', '.join(str(p) for p in written)} ({fmt}; {wf.n_vertices} vertices, {wf.n_edges} edges)",
        flush=True,
    )
    if fmt == "rosmap":
        from agents.files.export import FREE, read_pgm

        pgm = next(p for p in written if str(p).endswith(".pgm"))
        if not (read_pgm(pgm.read_bytes()) == FREE).any():
            print("wiremap export: note: no free cell: free space is the inside of a closed room (the "
                  "map closes none) or, with --trajectory, what the robot saw, so a planner has "
                  "nowhere to go on this map", file=sys.stderr, flush=True)
    return 0
