"""Network partition: a robot cut off from the network, then healed, reaches the fused map again.

The robot agent runs in its own network namespace, joined to the host by a veth pair with
link-local addresses (``169.254.A.B/30``, chosen per run; traffic never leaves this machine). The
router listens on the host end of the pair (for the robot) and on 127.0.0.1 (for the fusion
service and this test's observer). The router and the robot run with a Zenoh lease of
``LEASE_S`` (2 s, from a ``--config`` file written by the test; Zenoh's default is 10 s), so that
a short cut is already a long one for Zenoh. The cut takes the namespace's end of the pair down
for ``WIREMAP_PARTITION_S`` seconds (default 6: three leases, so the router drops the robot's
session and its liveliness token, and the robot must reconnect by itself), then brings it up
again.

Measured after the heal: the robot's newest map ``seq`` (``maps_sent`` in its first pose message
after the heal) must be in the fusion service's store (``state.json``, written after the fused
map that includes it is published) within ``HEAL_LIMIT_S``; the time from the heal to the first
fused publish after that map reached the host is printed (``pytest -s``) as the figure.

Skipped, with the reason, when not root, without ``ip``, or when ``ip netns add`` (or the veth
set-up) is refused (e.g. CI containers without CAP_NET_ADMIN). The namespace has a unique name
per run and is deleted in a ``finally``.
"""

from __future__ import annotations

import json
import os
import random
import shutil
import subprocess
import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from agents.bench.common import Procs, read_state
from agents.fleet.bus import FleetKeys, build_config, decode_pose, free_port, open_session
from wire_codec import decode

pytestmark = pytest.mark.fleet

LEASE_S = 2.0  # the router's and the robot's Zenoh lease (Zenoh's default: 10 s)
PARTITION_S = float(os.environ.get("WIREMAP_PARTITION_S", str(3 * LEASE_S)))
HEAL_LIMIT_S = 20.0
FLEET = "partition"


def _ip(*args: str, ns: str | None = None, check: bool = True) -> subprocess.CompletedProcess[str]:
    cmd = ["ip", *(["netns", "exec", ns, "ip"] if ns else []), *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=20, check=check)


def _free_subnet() -> tuple[str, str]:
    """Host and namespace addresses of a /30 in 169.254.100-249.x not used on this host."""
    used = subprocess.run(["ip", "-o", "-4", "addr", "show"], capture_output=True, text=True,
                          check=False).stdout
    rnd = random.Random(uuid.uuid4().int)
    for _ in range(100):
        a, b = rnd.randint(100, 249), 4 * rnd.randint(0, 63)
        if f"169.254.{a}." not in used:
            return f"169.254.{a}.{b + 1}", f"169.254.{a}.{b + 2}"
    pytest.skip("no free link-local /30 found")


@contextmanager
def namespace() -> Iterator[dict[str, str]]:
    """A network namespace joined to the host by a veth pair; deleted on exit."""
    if not hasattr(os, "geteuid") or os.geteuid() != 0:
        pytest.skip("network namespaces need root")
    if shutil.which("ip") is None:
        pytest.skip("no `ip` command (iproute2)")
    tag = uuid.uuid4().hex[:8]
    ns, vh, vn = f"wiremap-{tag}", f"wmh{tag}", f"wmn{tag}"
    r = _ip("netns", "add", ns, check=False)
    if r.returncode != 0:
        pytest.skip(f"`ip netns add` refused: {r.stderr.strip()}")
    try:
        host_ip, ns_ip = _free_subnet()
        steps = [
            (None, ("link", "add", vh, "type", "veth", "peer", "name", vn)),
            (None, ("link", "set", vn, "netns", ns)),
            (None, ("addr", "add", f"{host_ip}/30", "dev", vh)),
            (None, ("link", "set", vh, "up")),
            (ns, ("addr", "add", f"{ns_ip}/30", "dev", vn)),
            (ns, ("link", "set", vn, "up")),
            (ns, ("link", "set", "lo", "up")),
        ]
        for where, args in steps:
            r = _ip(*args, ns=where, check=False)
            if r.returncode != 0:
                pytest.skip(f"veth set-up refused (ip {' '.join(args)}): {r.stderr.strip()}")
        yield {"ns": ns, "veth_host": vh, "veth_ns": vn, "host_ip": host_ip, "ns_ip": ns_ip}
    finally:
        _ip("netns", "del", ns, check=False)  # takes the pair with it
        _ip("link", "del", vh, check=False)


class Observer:
    """The test's view of the bus (on 127.0.0.1): r1's maps and poses, the fused maps."""

    def __init__(self, endpoint: str) -> None:
        self.keys = FleetKeys(FLEET)
        self.lock = threading.Lock()
        self.maps: list[tuple[float, int]] = []  # (arrival, seq)
        self.poses: list[tuple[float, int]] = []  # (arrival, maps_sent)
        # (arrival, version, robots, stale)
        self.fused: list[tuple[float, int, tuple[str, ...], list[str]]] = []
        self.session = open_session(build_config("client", None, [endpoint]), timeout=30)
        assert self.session is not None
        self.subs = [
            self.session.declare_subscriber(self.keys.robot_map("r1"), self._on_map),
            self.session.declare_subscriber(self.keys.robot_pose("r1"), self._on_pose),
            self.session.declare_subscriber(self.keys.fused_map, self._on_fused),
        ]

    def _on_map(self, sample: Any) -> None:
        m = decode(sample.payload.to_bytes())
        with self.lock:
            self.maps.append((time.monotonic(), int(m.seq)))

    def _on_pose(self, sample: Any) -> None:
        p = decode_pose(sample.payload.to_bytes())
        with self.lock:
            self.poses.append((time.monotonic(), int(p["status"].get("maps_sent", 0))))

    def _on_fused(self, sample: Any) -> None:
        m = decode(sample.payload.to_bytes())
        stale = list(m.meta.get("stale", [])) if isinstance(m.meta, dict) else []
        with self.lock:
            self.fused.append((time.monotonic(), int(m.seq), tuple(m.robots), stale))

    def first(self, what: str, after: float, pred: Any = None) -> tuple[Any, ...] | None:
        with self.lock:
            for item in getattr(self, what):
                if item[0] > after and (pred is None or pred(item)):
                    return item
        return None

    def close(self) -> None:
        for s in self.subs:
            s.undeclare()
        self.session.close()


def wait(cond: Any, timeout: float, what: str, procs: Procs) -> Any:
    deadline = time.monotonic() + timeout
    while True:
        v = cond()
        if v:
            return v
        dead = procs.dead()
        if dead:
            raise AssertionError(
                f"{dead} exited while waiting for {what}: " + "".join(procs.log(d)[-2000:] for d in dead)
            )
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(0.05)


def short_lease_config(path: Path, mode: str) -> Path:
    """A Zenoh configuration file (``--config``): ``mode``, multicast scouting off (as the
    embedded defaults) and a lease of :data:`LEASE_S` (keep-alives four times a lease, Zenoh's
    default ratio)."""
    cfg = {
        "mode": mode,
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"link": {"tx": {"lease": int(LEASE_S * 1000), "keep_alive": 4}}},
    }
    path.write_text(json.dumps(cfg))
    return path


def store_seq(store: Path) -> int:
    return int(((read_state(store).get("robots") or {}).get("r1") or {}).get("seq", 0))


def test_robot_cut_off_then_healed_reaches_the_fused_map(tmp_path: Path) -> None:
    from agents.sim.route import plan_routes
    from agents.sim.world import load_world

    with namespace() as net:
        world = load_world("paper-small")
        route = plan_routes(world, 1, np.random.default_rng(0))[0]  # ~120 m: still mapping after the heal
        (tmp_path / "route.json").write_text(json.dumps({"route": route.tolist()}))
        p_veth, p_lo = free_port(), free_port()
        ep_veth, ep_lo = f"tcp/{net['host_ip']}:{p_veth}", f"tcp/127.0.0.1:{p_lo}"
        store = tmp_path / "store"
        with Procs(tmp_path / "logs") as procs:
            procs.start("router", ["-m", "agents", "router", "--listen", ep_veth, "--listen", ep_lo,
                                   "--config", str(short_lease_config(tmp_path / "router.json5", "router"))])
            obs = Observer(ep_lo)
            try:
                procs.start("fuse",
                            ["-m", "agents", "fuse", "--connect", ep_lo, "--fleet", FLEET, "--store",
                             str(store)])
                procs.wait_log("fuse", "fusion service ready", 60)
                procs.start(
                    "r1",
                    ["-m", "agents", "robot", "--id", "r1", "--world", "paper-small", "--route",
                     str(tmp_path / "route.json"),
                     "--rate", "4", "--viz-rate", "0", "--connect", ep_veth, "--fleet", FLEET,
                     "--config", str(short_lease_config(tmp_path / "robot.json5", "client"))],
                    prefix=["ip", "netns", "exec", net["ns"]],
                )
                wait(lambda: obs.first("fused", 0.0, lambda f: "r1" in f[2]), 60,
                     "r1 in the fused map", procs)
                time.sleep(1.0)

                # --- cut
                _ip("link", "set", net["veth_ns"], "down", ns=net["ns"])
                t_cut = time.monotonic()
                with obs.lock:
                    seq_at_cut = max((m[1] for m in obs.maps), default=0)
                time.sleep(PARTITION_S)
                # nothing of r1's crossed while cut (1 s of grace for what was in flight)
                assert obs.first("maps", t_cut + 1.0) is None, "r1's maps crossed a downed link"
                last_fused = obs.fused[-1] if obs.fused else None
                assert last_fused is not None and "r1" in last_fused[2], "the fused map lost r1's walls"
                stale_seen = obs.first("fused", t_cut, lambda f: "r1" in f[3]) is not None

                # --- heal
                _ip("link", "set", net["veth_ns"], "up", ns=net["ns"])
                t_heal = time.monotonic()
                pose = wait(lambda: obs.first("poses", t_heal), HEAL_LIMIT_S,
                            "r1's first pose after the heal", procs)
                newest = int(pose[1])
                assert newest > seq_at_cut, "r1 did not map while cut off"
                arrived = wait(
                    lambda: obs.first("maps", t_heal, lambda m: m[1] >= newest), HEAL_LIMIT_S,
                    "r1's newest map", procs
                )
                fused = wait(lambda: obs.first("fused", arrived[0]), HEAL_LIMIT_S,
                             "a fused map after it", procs)
                wait(lambda: store_seq(store) >= newest, HEAL_LIMIT_S,
                     f"seq {newest} of r1 in the store", procs)
                t_store = time.monotonic()
                back_s = arrived[0] - t_heal
                heal_s = fused[0] - t_heal
                print(
                    f"\npartition {PARTITION_S:g} s: r1 reconnected and its newest map (seq {newest}, "
                    f"{newest - seq_at_cut} maps made while cut) reached the host {back_s:.2f} s "
                    f"after the heal, "
                    f"the fused map {heal_s:.2f} s after, the store {t_store - t_heal:.2f} s after; "
                    f"r1 marked stale during the cut: {stale_seen}"
                )
                assert heal_s < HEAL_LIMIT_S
                assert "r1" in fused[2]
                if PARTITION_S >= 1.5 * LEASE_S:  # beyond the lease the token goes, and comes back
                    assert stale_seen, "r1's liveliness token did not go during a cut longer than the lease"
                    wait(lambda: obs.first("fused", t_heal, lambda f: "r1" not in f[3]), HEAL_LIMIT_S,
                         "r1 no longer stale", procs)
            finally:
                procs.stop(["r1"], 10)
                obs.close()
                procs.stop(["fuse"], 30)
                procs.stop(["router"], 10)
