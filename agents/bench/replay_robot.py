"""A lightweight robot process that replays recorded maps on the bus (for the fleet benchmarks).

``python -m agents.bench.replay_robot --id r3 --recording FILE [--id r4 --recording FILE ...]
[--rate HZ] [--corrupt P] [--seed S] [--log FILE] [--connect ...]``

Each robot behaves on the bus exactly like the robot agent (:mod:`agents.fleet.robot`), without
running a particle filter, so that two cores can carry 16 robots at 10 Hz and what a benchmark
measures is transport and fusion.

**Several robots in one process** (``--id``/``--recording`` repeated, in pairs): each robot
has its own Zenoh session (its own connection to the router, as a separate computer would),
its own liveliness token and keys, and its own schedule (the loop below, all robots served
from one thread, :func:`run_all`), with the same payloads and rates as a process of its own.
Only the operating-system process is shared: on a two-core machine sixteen Python processes
(plus the router and the fusion service) would
measure CPU contention between simulated robots rather than transport and fusion. Robot ``k``
(from 0) starts its first tick ``phase`` seconds late, drawn uniformly in ``[0, 1 / rate)``
from ``--seed`` (independent robots are not in step; a single robot starts at once), and its
corruption generator is seeded with ``seed + k``. ``--log`` and ``--status-file`` must then
contain ``{id}``, replaced by each robot's id. SIGUSR1 acts on every robot.

Per robot:

* ``robots/<id>/map``: a ``ROBOT_MAP`` (wire codec) built like the agent's: sender ``<id>``,
  frame ``odom/<id>``, ``origin`` the recorded start pose, the recording's resolution,
  contributor bits cleared, ``seq`` counting maps sent, ``stamp_ns`` the wall clock at the send,
  ``meta = {"boot": <process start ns>, "t": <sim s>, "step": <frame>}``; put with
  ``CongestionControl.BLOCK`` and, like the agent, with plain ``session.put`` (no declared
  publisher: those deliver only the first sample under the secure fleet's ACL);
* ``robots/<id>/pose`` at ``--pose-rate`` (10 Hz): :func:`agents.fleet.bus.encode_pose` with the
  recorded pose, ``fleet = origin * pose``, the recorded true pose and a status map
  (``step``, ``vertices``, ``edges``, ``maps_sent``, ``bytes_sent``, ``finished``, ``replay``);
* ``alive/<id>``: a liveliness token while the process runs.

Replay (choices):

* One recorded frame per tick at ``--rate``. A recording keeps only the frames whose travelling
  map changed (:func:`agents.bench.common.record_robot`), so every tick sends a changed map: the
  worst case for the fusion service (a real robot sends only on change).
* At the end of the recording it starts again from the first frame (``--no-loop``: it stops
  and only re-sends the last map every ``--heartbeat`` seconds, as the agent does when its route
  ends). The restart makes the robot's map shrink back, a change like any other.
* SIGUSR1 jumps to the last frame, sends it and stops looping: the benchmark does this at the
  end of its window so that the fused map it evaluates holds every robot's complete map.
* Each frame's body is encoded once (``wire_codec.BodyCache``, one per robot, as large as its
  recording); every send builds a new envelope around it. The bytes are those of a fresh
  encoding. A real robot's encoding runs on its own computer: on a benchmark's shared cores it
  would be taken from the fusers being measured (64 robots x 10 Hz: the replay process 0.55 ->
  0.23 core).
* ``--corrupt P``: each map payload is, with probability ``P`` (``--seed``), damaged before it
  is put: half of the time one byte is XOR-ed with a random non-zero value, otherwise the
  payload is cut to a random shorter length (possibly empty). The codec's CRC-32 rejects both.
  The map's ``seq`` is used up by the damaged payload.
* ``--log FILE``: one line appended per event, written with ``os.write`` right after ``put``
  returns (so it survives SIGKILL except for the very put in flight):
  ``B <boot> <pid>`` at start, ``M <boot> <seq> <valid 0|1> <bytes>`` per map payload.
"""

from __future__ import annotations

import argparse
import math
import os
import signal
import sys
import threading
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from agents.argtypes import non_negative_int
from agents.bench.common import Recording, load_recording
from agents.errors import UserError
from agents.fleet.bus import (
    StopFlag,
    add_bus_arguments,
    check_name,
    config_from_args,
    fleet_keys,
    open_session,
    watch_parent,
)
from agents.fleet.proc import freeze_heap
from agents.fleet.robot import robot_map_message, robot_puts

HELP = "replay recorded robot maps on the bus (benchmark robot)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--id", required=True, action="append",
        help="robot id (letters, digits, '_', '.', '-'); repeat for several"
    )
    parser.add_argument(
        "--recording", required=True, action="append", metavar="FILE",
        help="a recording (agents.bench.common); one per --id, in the same order",
    )
    parser.add_argument("--rate", type=float, default=10.0, metavar="HZ", help="maps per second (default 10)")
    parser.add_argument("--pose-rate", type=float, default=10.0, metavar="HZ",
                        help="poses per second (default 10)")
    parser.add_argument(
        "--heartbeat", type=float, default=2.0, metavar="S",
        help="re-send the map at least every S s (default 2)"
    )
    parser.add_argument("--corrupt", type=float, default=0.0, metavar="P",
                        help="damage each map with probability P")
    parser.add_argument("--seed", type=non_negative_int, default=0, help="seed of the corruption (default 0)")
    parser.add_argument("--no-loop", action="store_true",
                        help="play the recording once, then heartbeats only")
    parser.add_argument("--log", metavar="FILE",
                        help="append one line per map payload to FILE ({id}: the robot's id)")
    parser.add_argument(
        "--status-file", metavar="FILE",
        help="write the final status as JSON to FILE on exit ({id}: the robot's id)"
    )
    add_bus_arguments(parser)


def corrupt(data: bytes, rng: np.random.Generator) -> bytes:
    """A damaged copy of ``data``: one byte XOR-ed with a non-zero value, or a truncation."""
    if len(data) == 0:
        return data
    if rng.random() < 0.5:
        b = bytearray(data)
        pos = int(rng.integers(len(b)))
        b[pos] ^= int(rng.integers(1, 256))
        return bytes(b)
    return data[: int(rng.integers(len(data)))]


class ReplayRobot:
    """The replay loop (see the module docstring). ``session`` is an open Zenoh session."""

    def __init__(
        self,
        session: Any,
        keys: Any,
        robot: str,
        rec: Recording,
        *,
        rate: float = 10.0,
        pose_rate: float = 10.0,
        heartbeat: float = 2.0,
        corrupt_p: float = 0.0,
        seed: int = 0,
        loop: bool = True,
        log_fd: int | None = None,
        phase: float = 0.0,
    ) -> None:
        from wire_codec import BodyCache, encode

        self._encode = encode
        self._bodies = BodyCache(len(rec.frames) + 1)
        self.session = session
        self.keys = keys
        self.robot = robot
        self.rec = rec
        self.rate = rate
        self.pose_rate = pose_rate
        self.heartbeat = heartbeat
        self.corrupt_p = corrupt_p
        self.rng = np.random.default_rng(seed)
        self.loop = loop
        self.log_fd = log_fd
        self.phase = max(0.0, float(phase))
        self._next_tick = self._next_pose = 0.0  # set by begin()
        self._k = 0
        self._final_done = False
        self.boot = time.time_ns()
        self.final = threading.Event()
        self.seq = 0
        self.ticks = 0
        self.loops = 0
        self.current: int | None = None
        self.bytes_sent = 0
        self.valid_sent = 0
        self.corrupt_sent = 0
        self.pose_bytes = 0
        self.playing = True
        self._last_put = -math.inf
        self._token: Any = None
        self._pubs: dict[str, Any] = {}
        # sim time keeps increasing across loops (the fusion service shows the newest)
        ts = [f.t for f in rec.frames]
        self._loop_t = (ts[-1] - ts[0]) + (ts[1] - ts[0] if len(ts) > 1 else 0.5)

    def _write(self, line: str) -> None:
        if self.log_fd is not None:
            os.write(self.log_fd, line.encode())

    def start(self) -> None:
        self._token = self.session.liveliness().declare_token(self.keys.alive(self.robot))
        self._pubs = robot_puts(self.session, self.keys, self.robot)  # the agent's puts (no viz sent)
        self._write(f"B {self.boot} {os.getpid()}\n")

    def close(self) -> None:
        self._pubs.clear()
        if self._token is not None:
            try:
                self._token.undeclare()
            except Exception:
                pass
            self._token = None

    def publish_map(self, k: int) -> None:
        f = self.rec.frames[k]
        self.seq += 1
        msg = robot_map_message(
            self.robot, self.rec.start, self.rec.resolution, f.wireframe, f.pose, self.seq, time.time_ns(),
            {"boot": self.boot, "t": round(f.t + self.loops * self._loop_t, 6), "step": k},
        )
        data = self._encode(msg, cache=self._bodies)
        valid = True
        if self.corrupt_p > 0 and self.rng.random() < self.corrupt_p:
            data = corrupt(data, self.rng)
            valid = False
        self._pubs["map"].put(data)
        self._last_put = time.monotonic()
        self.current = k
        self.bytes_sent += len(data)
        if valid:
            self.valid_sent += 1
        else:
            self.corrupt_sent += 1
        self._write(f"M {self.boot} {self.seq} {int(valid)} {len(data)}\n")

    def status(self) -> dict[str, Any]:
        wf = self.rec.frames[self.current].wireframe if self.current is not None else None
        return {
            "step": self.ticks,
            "t": 0.0 if self.current is None else self.rec.frames[self.current].t,
            "vertices": 0 if wf is None else wf.n_vertices,
            "edges": 0 if wf is None else wf.n_edges,
            "maps_sent": self.seq,
            "valid_sent": self.valid_sent,
            "corrupt_sent": self.corrupt_sent,
            "bytes_sent": self.bytes_sent,
            "pose_bytes": self.pose_bytes,
            "finished": not self.playing,
            "replay": True,
        }

    def publish_pose(self) -> None:
        from agents.fleet.bus import encode_pose
        from mapping.se2 import Pose

        f = self.rec.frames[self.current] if self.current is not None else None
        odom = Pose.identity() if f is None else f.pose
        data = encode_pose(
            seq=self.ticks,
            t=0.0 if f is None else f.t,
            stamp_ns=time.time_ns(),
            odom=odom,
            fleet=self.rec.start.compose(odom),
            truth=None if f is None else f.truth,
            status=self.status(),
        )
        self._pubs["pose"].put(data)
        self.pose_bytes += len(data)

    def begin(self, now: float | None = None) -> None:
        """Start the replay clock (the first tick ``phase`` seconds from ``now``)."""
        now = time.monotonic() if now is None else now
        self._next_tick = self._next_pose = now + self.phase
        self._k = 0
        self._final_done = False

    def step(self) -> float:
        """Do what is due now (a map tick, the final map after SIGUSR1, a heartbeat, a pose);
        returns when something is next due (monotonic clock)."""
        n = len(self.rec.frames)
        period = 1.0 / self.rate
        now = time.monotonic()
        if self.final.is_set() and not self._final_done:
            self._final_done = True
            self.playing = False
            self.publish_map(n - 1)
        elif self.playing and now >= self._next_tick:
            self.publish_map(self._k)
            self.ticks += 1
            self._k += 1
            if self._k == n:
                if self.loop:
                    self._k = 0
                    self.loops += 1
                else:
                    self.playing = False
            self._next_tick += period
            if self._next_tick < time.monotonic() - period:
                self._next_tick = time.monotonic()  # fell behind: no burst to catch up
        now = time.monotonic()
        if not self.playing and self.current is not None and now - self._last_put >= self.heartbeat:
            self.publish_map(self.current)  # maps are whole states: re-sending is idempotent
        if now >= self._next_pose:
            self.publish_pose()
            self._next_pose = max(self._next_pose + 1.0 / self.pose_rate, now)
        wake = min(self._next_pose, self._last_put + self.heartbeat)
        if self.playing:
            wake = min(wake, self._next_tick)
        return wake

    def run(self, stop: Any) -> dict[str, Any]:
        """Replay until ``stop`` (a ``threading.Event`` or :class:`agents.fleet.bus.StopFlag`) is set."""
        run_all([self], stop)
        return self.status()


def run_all(bots: Sequence[ReplayRobot], stop: Any) -> None:
    """Replay several robots from one thread until ``stop`` is set: each robot's
    :meth:`ReplayRobot.step` when it is due (or its final map is asked for), then sleep until
    the next one is due (at most 0.1 s, so that SIGUSR1 and ``stop`` are seen quickly)."""
    now = time.monotonic()
    for b in bots:
        b.begin(now)
    due = [now] * len(bots)
    while not stop.is_set():
        now = time.monotonic()
        for i, b in enumerate(bots):
            if due[i] <= now or (b.final.is_set() and not b._final_done):
                due[i] = b.step()
        stop.wait(max(0.0, min(min(due) - time.monotonic(), 0.1)))


def _per_robot(template: str | None, rid: str, several: bool, flag: str) -> str | None:
    if template is None:
        return None
    if several and "{id}" not in template:
        raise UserError(f"{flag} must contain {{id}} when several robots share the process, got {template!r}")
    return template.replace("{id}", rid)


def run(args: argparse.Namespace) -> int:
    ids = [check_name(r) for r in args.id]
    if len(ids) != len(args.recording):
        raise UserError(f"give one --recording per --id ({len(ids)} ids, {len(args.recording)} recordings)")
    if len(set(ids)) != len(ids):
        raise UserError(f"robot ids must be distinct, got {' '.join(ids)}")
    for name, v in (("--rate", args.rate), ("--pose-rate", args.pose_rate), ("--heartbeat", args.heartbeat)):
        if not (math.isfinite(v) and v > 0):
            raise UserError(f"{name} must be a positive number, got {v}")
    if not 0.0 <= args.corrupt <= 1.0:
        raise UserError(f"--corrupt must be within [0, 1], got {args.corrupt}")
    several = len(ids) > 1
    recs = [load_recording(p) for p in args.recording]
    logs = [_per_robot(args.log, r, several, "--log") for r in ids]
    status_files = [_per_robot(args.status_file, r, several, "--status-file") for r in ids]
    keys = fleet_keys(args)
    phases = (np.random.default_rng(args.seed).uniform(0.0, 1.0 / args.rate, len(ids)) if several
              else np.zeros(1))

    def say(text: str) -> None:
        print(f"replay robot {' '.join(ids) if len(ids) <= 4 else f'{ids[0]}..{ids[-1]}'}: {text}",
              flush=True)

    fds: list[int | None] = []
    sessions: list[Any] = []
    bots: list[ReplayRobot] = []
    results: dict[str, dict[str, Any]] = {}
    try:
        for log in logs:
            fd = None
            if log:
                os.makedirs(os.path.dirname(os.path.abspath(log)), exist_ok=True)
                fd = os.open(log, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
            fds.append(fd)
        with StopFlag() as stop:
            watch_parent(args.parent_pid, stop)
            for k, (rid, rec) in enumerate(zip(ids, recs)):
                # one session per robot: its own link to the router, as on its own computer
                session = open_session(config_from_args(args, "client"), stop,
                                       on_wait=lambda t: say(f"waiting for a router ({t})"))
                if session is None:
                    return 0
                sessions.append(session)
                bots.append(ReplayRobot(
                    session, keys, rid, rec, rate=args.rate, pose_rate=args.pose_rate,
                    heartbeat=args.heartbeat,
                    corrupt_p=args.corrupt, seed=args.seed + k, loop=not args.no_loop, log_fd=fds[k],
                    phase=float(phases[k]),
                ))
            freeze_heap()  # no full collection of the modules' objects between two puts

            def final(*_a: Any) -> None:
                for b in bots:
                    b.final.set()

            old = signal.signal(signal.SIGUSR1, final)
            try:
                for bot in bots:
                    bot.start()
                for bot, rec in zip(bots, recs):
                    say(f"on the bus as {keys.robot_map(bot.robot)}: {len(rec.frames)} frames "
                        f"at {args.rate:g} Hz")

                run_all(bots, stop)  # one thread: the robots' puts need no interpreter-lock handoffs
                results.update({b.robot: b.status() for b in bots})
            finally:
                signal.signal(signal.SIGUSR1, old)
                for bot in bots:
                    bot.close()
    finally:
        for s in sessions:
            s.close()
        for fd in fds:
            if fd is not None:
                os.close(fd)
    for rid, sf in zip(ids, status_files):
        st = results.get(rid)
        if st is None:
            continue
        say(f"{rid} stopped: {st['maps_sent']} maps ({st['corrupt_sent']} damaged), {st['bytes_sent']} bytes")
        if sf:
            from agents.files.io import write_json

            write_json(sf, {"robot": rid, **st})
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m agents.bench.replay_robot", description=HELP)
    add_arguments(parser)
    args = parser.parse_args(argv)
    try:
        return run(args)
    except UserError as exc:
        sys.stderr.write(f"replay robot: {exc}\n")
        return 2


if __name__ == "__main__":
    sys.exit(main())
