"""``python -m wire_codec encode|decode``: wire-map payloads from and to GeoJSON.

Examples
--------
::

    python -m wire_codec encode map.geojson --resolution 0.2 > map.wfm
    python -m wire_codec decode map.wfm --geojson back.geojson

``decode`` prints one line (kind, sender, version, vertices, edges, bytes). A payload that does
not decode exits 1 with the :class:`~wire_codec.CodecError` reason on one line; a missing or
unreadable file or a bad flag exits 2.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from mapping.se2 import Pose
from mapping.wireframe import Wireframe, mask_or
from wire_codec.codec import decode, encode, version_for
from wire_codec.errors import CodecError
from wire_codec.message import MapMessage, MessageKind

EXIT_BAD_PAYLOAD = 1
EXIT_USAGE = 2


class _UsageError(Exception):
    """A bad file or flag: one line on stderr, exit 2."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # type: ignore[override]
        sys.stderr.write(f"{self.prog}: error: {message}\n")
        raise SystemExit(EXIT_USAGE)


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="python -m wire_codec", description="Encode and decode wire-map payloads.")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser, required=True)
    e = sub.add_parser("encode", help="GeoJSON wireframe -> payload bytes (stdout or -o)")
    e.add_argument("geojson", help="a wireframe GeoJSON file (Wireframe.to_geojson), or - for stdin")
    e.add_argument("--resolution", type=float, default=0.2, help="quantisation step in metres (default 0.2)")
    e.add_argument("--kind", choices=("robot", "fused"),
                   help="default: fused if any wall has sources, else robot")
    e.add_argument("--sender", default="cli", help="sender id (default: cli)")
    e.add_argument("--frame", default=None,
                   help="frame name (default: odom/SENDER for robot maps, fleet for fused)")
    e.add_argument("--seq", type=int, default=0, help="sequence number (default 0)")
    e.add_argument("--stamp-ns", type=int, default=None, help="timestamp in ns (default: now)")
    e.add_argument("--pose", type=Pose.parse, default=Pose(), metavar="X,Y,THETA", help="sender pose")
    e.add_argument("--origin", type=Pose.parse, default=Pose(), metavar="X,Y,THETA",
                   help="start pose in the fleet frame")
    e.add_argument("--robots", default=None,
                   help="fused maps: comma-separated robot ids, bit k = k-th id (default r0,r1,...)")
    e.add_argument("-o", "--output", default=None, help="write here instead of stdout")
    d = sub.add_parser("decode", help="payload -> one-line summary (and GeoJSON)")
    d.add_argument("payload", help="a payload file, or - for stdin")
    d.add_argument("--geojson", default=None, help="also write the decoded wireframe here")
    return p


def _read(path: str) -> bytes:
    try:
        if path == "-":
            return sys.stdin.buffer.read()
        return Path(path).read_bytes()
    except FileNotFoundError:
        raise _UsageError(f"{path}: no such file") from None
    except OSError as exc:
        raise _UsageError(f"{path}: {exc.strerror}") from None


def _write_atomic(path: str, data: bytes) -> None:
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=f".{target.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, target)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def _encode(args: argparse.Namespace) -> int:
    raw = _read(args.geojson)
    try:
        wf = Wireframe.from_geojson(json.loads(raw.decode("utf-8")))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise _UsageError(f"{args.geojson}: not valid JSON: {exc}") from None
    except ValueError as exc:
        raise _UsageError(f"{args.geojson}: {exc}") from None
    has_sources = bool(wf.n_edges and wf.sources.any())
    kind = (MessageKind.FUSED_MAP if (args.kind or ("fused" if has_sources else "robot")) == "fused"
            else MessageKind.ROBOT_MAP)
    robots: tuple[str, ...] = ()
    if kind == MessageKind.FUSED_MAP:
        if args.robots:
            robots = tuple(r.strip() for r in args.robots.split(",") if r.strip())
        else:
            top = mask_or(wf.sources).bit_length() if wf.n_edges else 0
            robots = tuple(f"r{k}" for k in range(top))
    elif args.robots:
        raise _UsageError("--robots is for fused maps (--kind fused)")
    frame = (args.frame if args.frame is not None
             else ("fleet" if kind == MessageKind.FUSED_MAP else f"odom/{args.sender}"))
    message = MapMessage(
        kind=kind,
        sender=args.sender,
        seq=args.seq,
        stamp_ns=time.time_ns() if args.stamp_ns is None else args.stamp_ns,
        pose=args.pose,
        frame=frame,
        origin=args.origin,
        resolution=args.resolution,
        wireframe=wf,
        robots=robots,
    )
    data = encode(message)  # CodecError (EncodeError) -> exit 1 in main
    if args.output:
        _write_atomic(args.output, data)
    else:
        if sys.stdout.isatty():
            raise _UsageError("refusing to write binary to a terminal: redirect stdout or use -o FILE")
        sys.stdout.buffer.write(data)
        sys.stdout.buffer.flush()
    return 0


def _jsonable(value: Any) -> Any:
    if isinstance(value, bytes):
        return value.hex()
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_jsonable(v) for v in value]
    return value


def summary(message: MapMessage, n_bytes: int, version: int | None = None) -> str:
    """The one-line description ``decode`` prints (``version``: the message's format version,
    by default the one an encoder writes for it)."""
    v = version_for(len(message.robots)) if version is None else version
    return (
        f"kind={message.kind.name.lower()} sender={message.sender} version={v} "
        f"seq={message.seq} vertices={message.wireframe.n_vertices} edges={message.wireframe.n_edges} "
        f"bytes={n_bytes}"
    )


def _decode(args: argparse.Namespace) -> int:
    data = _read(args.payload)
    message = decode(data)
    print(summary(message, len(data), data[1]))  # decode checked: byte 1 is the version
    if args.geojson:
        props = {
            "kind": message.kind.name.lower(),
            "sender": message.sender,
            "seq": message.seq,
            "stamp_ns": message.stamp_ns,
            "frame": message.frame,
            "pose": list(message.pose.as_tuple()),
            "origin": list(message.origin.as_tuple()),
            "resolution": message.resolution,
            "robots": list(message.robots),
            "meta": _jsonable(message.meta),
        }
        _write_atomic(args.geojson,
                      (json.dumps(message.wireframe.to_geojson(props), indent=2) + "\n").encode())
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return _encode(args) if args.command == "encode" else _decode(args)
    except CodecError as exc:
        reason = " ".join(str(exc).split())
        sys.stderr.write(f"{type(exc).__name__}: {reason}\n")
        return EXIT_BAD_PAYLOAD
    except _UsageError as exc:
        sys.stderr.write(f"python -m wire_codec {args.command}: {exc}\n")
        return EXIT_USAGE
    except BrokenPipeError:
        return 0


if __name__ == "__main__":
    sys.exit(main())
