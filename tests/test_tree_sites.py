"""The fusion tree across two "sites" on one host: a network namespace (site B) joined to the
host (site A) by a veth pair (link-local addresses chosen per run, :func:`tests.test_partition.namespace`).

Site B (inside the namespace): its own router on the namespace's loopback and veth address,
connected to site A's router over the veth; robots r1-r4 (replay robots, synthetic maps) and
their regional fuser ``site-b`` connect to it. Site A (the host): a router, robots r5-r8, their
regional fuser ``site-a`` and the root. Both fusers run with ``--no-standby`` (robot maps stay
in their site; only partials cross). Both routers run with a Zenoh lease of
:data:`tests.test_partition.LEASE_S` (2 s; Zenoh's default is 10 s), so that the cut outlasts the
lease: the link between the sites is dropped, not merely quiet. The fused map arrives with all
eight robots; then site B's veth is down for ``WIREMAP_SITE_CUT_S`` (default 6: three leases)
seconds and up again: within ``HEAL_LIMIT_S`` the fused map carries site B's partial again and
site B's fuser holds each of its robots' maps sent up to the heal (its store); nothing is lost.
Skips (with the reason) where namespaces cannot be made.
"""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from agents.bench.common import Procs, read_state
from agents.bench.tree import synthetic_recordings
from agents.fleet.bus import FleetKeys, build_config, free_port, open_session
from tests.test_partition import LEASE_S, _ip, namespace, short_lease_config, wait
from wire_codec import decode

pytestmark = pytest.mark.fleet

CUT_S = float(os.environ.get("WIREMAP_SITE_CUT_S", str(3 * LEASE_S)))
HEAL_LIMIT_S = 20.0
FLEET = "sites"


class FusedLog:
    def __init__(self, endpoint: str) -> None:
        self.keys = FleetKeys(FLEET)
        self.lock = threading.Lock()
        self.items: list[tuple[float, Any]] = []
        self.session = open_session(build_config("client", None, [endpoint]), timeout=30)
        assert self.session is not None
        self.sub = self.session.declare_subscriber(self.keys.fused_map, self._cb)

    def _cb(self, sample: Any) -> None:
        m = decode(sample.payload.to_bytes())
        with self.lock:
            self.items.append((time.monotonic(), m))

    def first(self, after: float, pred: Any) -> tuple[float, Any] | None:
        with self.lock:
            for t, m in self.items:
                if t > after and pred(m):
                    return t, m
        return None

    def close(self) -> None:
        self.sub.undeclare()
        self.session.close()


def _sent(log: Path) -> int:
    """The newest seq a replay robot's log says it put."""
    best = 0
    try:
        for ln in log.read_text().splitlines():
            p = ln.split()
            if len(p) >= 4 and p[0] == "M" and p[3] == "1":
                best = max(best, int(p[2]))
    except OSError:
        pass
    return best


def test_tree_across_two_sites_survives_a_cut_link(tmp_path: Path) -> None:
    recs = synthetic_recordings("museum", 8, 0, tmp_path / "cache", 0.05)
    with namespace() as net:
        in_ns = ["ip", "netns", "exec", net["ns"]]
        pa_lo, pa_veth, pb = free_port(), free_port(), free_port()
        ep_a, ep_a_veth = f"tcp/127.0.0.1:{pa_lo}", f"tcp/{net['host_ip']}:{pa_veth}"
        ep_b = f"tcp/127.0.0.1:{pb}"  # the namespace's own loopback
        bus_a = ["--connect", ep_a, "--fleet", FLEET]
        bus_b = ["--connect", ep_b, "--fleet", FLEET]
        with Procs(tmp_path / "logs") as procs:
            router_cfg = ["--config", str(short_lease_config(tmp_path / "router.json5", "router"))]
            procs.start("router-a",
                        ["-m", "agents", "router", "--listen", ep_a, "--listen", ep_a_veth, *router_cfg])
            procs.start("router-b",
                        ["-m", "agents", "router", "--listen", ep_b, "--connect", ep_a_veth, *router_cfg],
                        prefix=in_ns)
            obs = FusedLog(ep_a)
            try:
                common = ["--threshold", "0.4", "--no-standby"]
                procs.start("site-b",
                            ["-m", "agents", "fuse", *bus_b, "--group", "site-b", "--robots", "r[1-4]",
                                       "--store", str(tmp_path / "store-b"), *common], prefix=in_ns)
                procs.start("site-a",
                            ["-m", "agents", "fuse", *bus_a, "--group", "site-a", "--robots", "r[5-8]",
                                       "--store", str(tmp_path / "store-a"), *common])
                procs.start("root",
                            ["-m", "agents", "fuse", *bus_a, "--of-groups", "site-a,site-b",
                             "--threshold", "0.4"])
                for name in ("site-a", "site-b", "root"):
                    procs.wait_log(name, "ready", 90)
                for k, rec in enumerate(recs):
                    rid = f"r{k + 1}"
                    argv = ["-m", "agents.bench.replay_robot", "--id", rid, "--recording", str(rec),
                            "--rate", "5", "--log", str(tmp_path / "sent" / f"{rid}.log")]
                    if k < 4:
                        procs.start(rid, [*argv, *bus_b], prefix=in_ns)
                    else:
                        procs.start(rid, [*argv, *bus_a])
                ids = tuple(f"r{k + 1}" for k in range(8))
                wait(lambda: obs.first(0.0, lambda m: m.robots == ids), 90,
                      "all 8 robots in the fused map", procs)
                t_before = time.monotonic()
                got = wait(lambda: obs.first(t_before,
                                              lambda m: "site-b" in m.meta.get("group_versions", {})), 10,
                            "a fused map", procs)
                vb_cut = got[1].meta["group_versions"]["site-b"]

                # --- cut site B off
                _ip("link", "set", net["veth_ns"], "down", ns=net["ns"])
                t_cut = time.monotonic()
                time.sleep(CUT_S)
                last = obs.first(t_cut, lambda m: True)
                assert last is None or last[1].robots == ids, (
                    "the fused map lost site B's robots during the cut"
                )
                if CUT_S >= 1.5 * LEASE_S:  # beyond the lease the link goes: site B's tokens with it
                    assert obs.first(t_cut, lambda m: set(ids[:4]) <= set(m.meta.get("stale", []))), (
                        "site B's robots were not stale during a cut longer than the lease"
                    )

                # --- heal
                _ip("link", "set", net["veth_ns"], "up", ns=net["ns"])
                t_heal = time.monotonic()
                sent_at_heal = {f"r{k}": _sent(tmp_path / "sent" / f"r{k}.log") for k in range(1, 5)}
                back = wait(
                    lambda: obs.first(
                        t_heal,
                        lambda m: (
                            m.meta.get("group_versions", {}).get("site-b", vb_cut) > vb_cut
                            and m.robots == ids
                        ),
                    ),
                    HEAL_LIMIT_S,
                    "site B's partial in the fused map again",
                    procs,
                )

                def held() -> bool:
                    robots = read_state(tmp_path / "store-b").get("robots") or {}
                    return all((robots.get(r) or {}).get("seq", 0) >= s for r, s in sent_at_heal.items())

                wait(held, HEAL_LIMIT_S, "site B's fuser holding every map sent up to the heal", procs)
                print(f"\nsite cut {CUT_S:g} s: site B's partial back in the fused map "
                      f"{back[0] - t_heal:.2f} s after the heal; fused versions during the cut served "
                      f"site B's last partial")
            finally:
                names = [f"r{k + 1}" for k in range(8)]
                procs.stop(names, 10)
                procs.stop(["site-a", "site-b"], 30)
                procs.stop(["root"], 20)
                obs.close()
                procs.stop(["router-b", "router-a"], 10)
