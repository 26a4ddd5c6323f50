"""``wiremap bench fingerprint``: is the filter's output bit for bit what it was?

A refactoring, a speed-up or a library swap must leave the maps alone. This bench runs the
particle filter over simulated worlds exactly as ``wiremap bench accuracy`` does (the same
scans, configuration and seeds), and hashes what it produced: the pose after every step (a
hash of each 500-step prefix), the whole particle set and weights every 500 steps, at the end
and the best particle's map. Run it before and after a change and compare::

    wiremap bench fingerprint --world paper-small --seeds 5 --json > before.txt
    ... change ...
    wiremap bench fingerprint --world paper-small --seeds 5 --against before.txt

``--against FILE`` reads the JSON line of an earlier run (the last line of FILE) and compares
every run the two have in common, over the steps both cover: ``IDENTICAL`` or where the two
part (the first 500-step block whose poses differ, the first particle checkpoint that differs).
The exit status is 1 when a run differs, so a script can gate on it. ``--steps N`` stops each
run after N scans (for a quick check of long worlds: a multiple of 500 compares every block).

The JSON last line: ``{"world", "runs": {"WORLD:SEED": {"steps", "poses", "pose_blocks",
"checkpoints", "best", "seconds"}}}`` (hashes are the first 16 hex digits of SHA-256).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from agents.errors import UserError

HELP = "hash the filter's poses and particle sets, to check a change leaves them bit-identical"
BLOCK = 500  # steps per pose block and particle checkpoint


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--world", required=True, metavar="NAME|FILE", help="built-in world or world file")
    parser.add_argument("--seeds", type=int, default=3, metavar="K", help="number of seeds (default 3)")
    parser.add_argument("--first-seed", type=int, default=0, metavar="S", help="seeds S..S+K-1 (default 0)")
    parser.add_argument("--steps", type=int, default=None, metavar="N", help="stop each run after N scans")
    parser.add_argument("--against", default=None, metavar="FILE",
                        help="compare with an earlier run's JSON line (the last line of FILE)")
    parser.add_argument("--json", action="store_true", help="print the JSON summary as the last line")
    parser.add_argument("--quiet", action="store_true", help="no progress on stderr")


def _wireframe_hash(wf: Any) -> str:
    h = hashlib.sha256()
    from mapping.wireframe import mask_bytes

    for a in (wf.points, wf.labels, wf.edges, wf.likelihood, wf.sources):
        arr = np.ascontiguousarray(a)
        h.update(mask_bytes(arr) if a is wf.sources else arr.tobytes())  # the same bytes for uint64
        h.update(str(arr.shape).encode())
    return h.hexdigest()


def _particles_hash(filt: Any) -> str:
    joined = "".join(_wireframe_hash(w) for w in filt.particles).encode()
    return hashlib.sha256(joined + np.asarray(filt.weights).tobytes()).hexdigest()[:16]


def fingerprint(world: Any, seed: int, steps: int | None) -> dict[str, Any]:
    """Run the filter over ``world`` with ``seed`` as ``wiremap bench accuracy`` does and hash
    what it produced (module docstring)."""
    from agents.mapping_run import (
        SimOptions,
        filter_config_for,
        run_filter,
        seeds_for,
        simulate,
        world_defaults,
    )
    from mapping.filter import WireframeFilter

    particles, thr = world_defaults(world)
    options = SimOptions(sensor="corners", max_range=8.0, steps=steps)
    inputs = list(simulate(world, options, seed))
    cfg = filter_config_for(particles, thr, options.max_range)
    filt = WireframeFilter(cfg, seeds_for(seed)["filter"], initial_pose=inputs[0].true_pose)
    t0 = time.perf_counter()
    poses: list[tuple[float, float, float]] = []
    checkpoints: dict[str, str] = {}
    for st in run_filter(inputs, filt):
        poses.append((st.pose.x, st.pose.y, st.pose.theta))
        if (st.index + 1) % BLOCK == 0:
            checkpoints[str(st.index + 1)] = _particles_hash(filt)
    checkpoints["final"] = _particles_hash(filt)
    arr = np.asarray(poses, dtype=np.float64)
    return {
        "steps": len(poses),
        "poses": hashlib.sha256(arr.tobytes()).hexdigest()[:16],
        "pose_blocks": [
            hashlib.sha256(arr[:k].tobytes()).hexdigest()[:16] for k in range(BLOCK, len(arr) + 1, BLOCK)
        ],
        "checkpoints": checkpoints,
        "best": _wireframe_hash(filt.best)[:16],
        "seconds": round(time.perf_counter() - t0, 1),
    }


def compare(new: dict[str, Any], old: dict[str, Any]) -> str:
    """``IDENTICAL``, or where run ``new`` parts from run ``old`` (over the steps both cover)."""
    for i, (a, b) in enumerate(zip(new["pose_blocks"], old["pose_blocks"])):
        if a != b:
            return f"DIFFERENT: poses differ within steps {i * BLOCK + 1}-{(i + 1) * BLOCK}"
    for k, h in new["checkpoints"].items():
        if k != "final" and k in old["checkpoints"] and old["checkpoints"][k] != h:
            return f"DIFFERENT: particle sets differ at step {k}"
    if new["steps"] == old["steps"]:
        for key in ("poses", "best"):
            if new[key] != old[key]:
                return f"DIFFERENT: {key}"
        if new["checkpoints"]["final"] != old["checkpoints"]["final"]:
            return "DIFFERENT: final particle set"
        return "IDENTICAL"
    common = min(new["steps"], old["steps"])
    return (f"IDENTICAL over the first {common // BLOCK * BLOCK} steps "
            f"(runs of {new['steps']} and {old['steps']})")


def _earlier(path: str) -> dict[str, Any]:
    try:
        lines = Path(path).read_text().strip().splitlines()
        doc = json.loads(lines[-1]) if lines else None
    except (OSError, ValueError) as exc:
        raise UserError(f"--against {path}: cannot read a JSON line: {exc}") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("runs"), dict):
        raise UserError(f"--against {path}: not the JSON line of wiremap bench fingerprint")
    return doc["runs"]


def run(args: argparse.Namespace) -> int:
    from agents.sim.world import load_world

    if args.seeds < 1:
        raise UserError(f"--seeds must be >= 1, got {args.seeds}")
    if args.steps is not None and args.steps < 1:
        raise UserError(f"--steps must be >= 1, got {args.steps}")
    old = _earlier(args.against) if args.against else None
    try:
        world = load_world(args.world)
    except (OSError, ValueError) as exc:
        raise UserError(f"{args.world}: {exc}") from None
    runs: dict[str, Any] = {}
    differ = 0
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        name = f"{world.name}:{seed}"
        if not args.quiet:
            print(f"{name} ...", file=sys.stderr, flush=True)
        runs[name] = r = fingerprint(world, seed, args.steps)
        verdict = ""
        if old is not None:
            verdict = compare(r, old[name]) if name in old else "no earlier run"
            differ += verdict.startswith("DIFFERENT")
        print(f"{name:<20} {r['steps']:>6} steps  poses {r['poses']}  particles {r['checkpoints']['final']}  "
              f"{r['seconds']:>7.1f} s  {verdict}", flush=True)
    if args.json:
        print(json.dumps({"world": world.name, "runs": runs}))
    return 1 if differ else 0
