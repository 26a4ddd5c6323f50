"""``wiremap bench BENCH`` (one of :data:`BENCHES`): dispatches to :mod:`agents.bench`, after the
output directory every benchmark's ``--out`` names is checked (a one-line error before any work)."""

from __future__ import annotations

import argparse
import importlib

HELP = "benchmarks"
BENCHES: dict[str, tuple[str, str]] = {
    "accuracy": ("agents.bench.accuracy", "map quality over seeds, filter vs single-hypothesis baseline"),
    "speed": ("agents.bench.speed", "scan updates per second, step time, peak RSS"),
    "codec": ("agents.bench.codec", "wire codec size and speed against other encodings"),
    "fleet": ("agents.bench.fleet", "fleet latency, bandwidth and fused-map quality by fleet size"),
    "soak": ("agents.bench.soak", "long run with corrupt payloads and robot restarts"),
    "hostile": ("agents.bench.hostile",
                "one stolen robot: crashes, honest latency quiet vs attacked, fusion RSS"),
    "sensor": ("agents.bench.sensor", "corner-sensor label accuracy and split-and-merge corner error"),
    "register": ("agents.bench.register", "global registration of map pairs in unrelated frames"),
    "lidar": ("agents.bench.lidar", "the mapper on real CARMEN lidar logs against their truth"),
    "slam": ("agents.bench.slam", "the lidar SLAM alone on real CARMEN logs, median over start frames"),
    "scanners": ("agents.bench.scanners",
                 "the real-lidar path on common scanners (SICK, Hokuyo, RPLIDAR, LDS-01), simulated"),
    "live": ("agents.bench.live", "a live robot's mapper over a long shift: real logs driven back and forth"),
    "fingerprint": ("agents.bench.fingerprint",
                    "hash the filter's poses and particle sets (bit-identity check)"),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from agents.cli import ARGV

    sub = parser.add_subparsers(dest="bench", metavar="BENCH", parser_class=type(parser))
    chosen = next((a for a in ARGV[1:] if a in BENCHES), None)
    for name, (module_name, help_text) in BENCHES.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if name == chosen:
            module = importlib.import_module(module_name)
            module.add_arguments(p)
            p.set_defaults(_bench=module, _label=f"bench {name}")


def run(args: argparse.Namespace) -> int:
    module = getattr(args, "_bench", None)
    if module is None:
        from agents.errors import UserError

        raise UserError("choose a benchmark: " + ", ".join(BENCHES))
    if getattr(args, "out", None) is not None:
        from agents.files.io import check_output_dir

        check_output_dir("--out", args.out)
    return int(module.run(args) or 0)
