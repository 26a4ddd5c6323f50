"""The fleet bus: key expressions, configuration, waiting for the router, payloads, routers."""

from __future__ import annotations

import argparse
import json
import os
import signal
import threading
from pathlib import Path

import numpy as np
import pytest
import zenoh
from hypothesis import given, settings
from hypothesis import strategies as st

from agents.errors import UserError
from agents.fleet.bus import (
    CLIENT_DEFAULTS,
    DEFAULT_ENDPOINT,
    ROUTER_DEFAULTS,
    FleetKeys,
    StopFlag,
    add_bus_arguments,
    build_config,
    check_name,
    decode_pose,
    decode_viz,
    encode_pose,
    encode_viz,
    fleet_keys,
    open_session,
)
from mapping.se2 import Pose
from mapping.wireframe import Wireframe
from tests.fleet_util import REPO, Fleet, client, free_port, in_process_router, tcp_endpoint

CONFIGS = REPO / "broker_config"


def cfg_get(cfg: zenoh.Config, key: str):
    return json.loads(cfg.get_json(key))


# ---------------------------------------------------------------------- keys
def test_fleet_keys_layout():
    k = FleetKeys("lab")
    assert k.robot_map("r1") == "wiremap/lab/robots/r1/map"
    assert k.robot_pose("r1") == "wiremap/lab/robots/r1/pose"
    assert k.robot_viz("r-2") == "wiremap/lab/robots/r-2/viz"
    assert k.alive("r1") == "wiremap/lab/alive/r1"
    assert k.fused_map == "wiremap/lab/fused/map"
    assert k.all_maps == "wiremap/lab/robots/*/map"
    assert k.all_alive == "wiremap/lab/alive/*"
    # wildcards are valid key expressions that include the concrete keys
    assert zenoh.KeyExpr(k.all_maps).includes(zenoh.KeyExpr(k.robot_map("r9")))
    assert not zenoh.KeyExpr(k.all_maps).includes(zenoh.KeyExpr(k.robot_pose("r9")))


def test_robot_of_parses_only_this_fleet():
    k = FleetKeys("lab")
    assert k.robot_of("wiremap/lab/robots/r7/map") == "r7"
    assert k.robot_of("wiremap/lab/alive/r7") == "r7"
    assert k.robot_of("wiremap/other/robots/r7/map") is None
    assert k.robot_of("wiremap/lab/fused/map") is None
    assert k.robot_of("wiremap/lab/robots/r7/map/extra") is None


@pytest.mark.parametrize("bad", ["", "a/b", "r*", "r 1", "$x", "-r", "x" * 64, "r?", "r#"])
def test_bad_names_are_user_errors(bad):
    with pytest.raises(UserError):
        check_name(bad)
    with pytest.raises(UserError):
        FleetKeys("ok").robot_map(bad)


@given(st.from_regex(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,20}", fullmatch=True))
@settings(max_examples=50, deadline=None)
def test_robot_of_round_trips(rid):
    k = FleetKeys("f1")
    for key in (k.robot_map(rid), k.robot_pose(rid), k.robot_viz(rid), k.alive(rid)):
        assert k.robot_of(key) == rid
        zenoh.KeyExpr(key)  # a valid key expression


# ---------------------------------------------------------------------- flags and configs
def test_add_bus_arguments():
    p = argparse.ArgumentParser()
    add_bus_arguments(p)
    a = p.parse_args(["--connect", "tcp/127.0.0.1:1", "--connect", "tcp/127.0.0.1:2", "--fleet", "x"])
    assert a.connect == ["tcp/127.0.0.1:1", "tcp/127.0.0.1:2"] and a.fleet == "x" and a.config is None
    assert not hasattr(a, "listen")
    assert fleet_keys(a).prefix == "wiremap/x"
    r = argparse.ArgumentParser()
    add_bus_arguments(r, router=True)
    assert r.parse_args(["--listen", "tcp/127.0.0.1:9"]).listen == ["tcp/127.0.0.1:9"]


def test_default_client_and_router_configs():
    c = build_config("client")
    assert cfg_get(c, "mode") == "client"
    assert cfg_get(c, "connect/endpoints") == [DEFAULT_ENDPOINT]
    assert cfg_get(c, "scouting/multicast/enabled") is False
    r = build_config("router")
    assert cfg_get(r, "mode") == "router"
    assert cfg_get(r, "listen/endpoints") == [DEFAULT_ENDPOINT]
    assert cfg_get(r, "scouting/multicast/enabled") is False
    # command-line endpoints override
    c2 = build_config("client", connect=["tcp/127.0.0.1:5"])
    assert cfg_get(c2, "connect/endpoints") == ["tcp/127.0.0.1:5"]
    assert CLIENT_DEFAULTS["mode"] == "client"


def test_broker_config_files():
    r = build_config("client", str(CONFIGS / "router.json5"))
    for k, v in ROUTER_DEFAULTS.items():  # the file is the embedded default
        assert cfg_get(r, k) == v, k
    c = build_config("router", str(CONFIGS / "client.json5"))
    assert cfg_get(c, "mode") == "client"  # the file's mode wins
    assert cfg_get(c, "connect/endpoints") == [DEFAULT_ENDPOINT]
    a = build_config("router", str(CONFIGS / "router-a.json5"))
    b = build_config("router", str(CONFIGS / "router-b.json5"))
    assert cfg_get(a, "mode") == cfg_get(b, "mode") == "router"
    a_port = cfg_get(a, "listen/endpoints")[0].rsplit(":", 1)[1]
    assert cfg_get(b, "connect/endpoints")[0].endswith(":" + a_port)  # B connects to A
    b2 = build_config("router", str(CONFIGS / "router-b.json5"), ["tcp/127.0.0.1:1"], ["tcp/127.0.0.1:2"])
    assert cfg_get(b2, "connect/endpoints") == ["tcp/127.0.0.1:1"]
    assert cfg_get(b2, "listen/endpoints") == ["tcp/127.0.0.1:2"]
    assert (CONFIGS / "README.md").is_file()


def test_bad_config_file(tmp_path):
    with pytest.raises(UserError, match="no such file"):
        build_config("client", str(tmp_path / "nope.json5"))
    bad = tmp_path / "bad.json5"
    bad.write_text("{ mode: ")
    with pytest.raises(UserError, match="not a valid"):
        build_config("client", str(bad))


# ---------------------------------------------------------------------- payloads
@given(
    st.tuples(*[st.floats(-1e4, 1e4)] * 3),
    st.booleans(),
    st.integers(0, 2**40),
)
@settings(max_examples=40, deadline=None)
def test_pose_round_trip(xyz, has_truth, seq):
    p = Pose(*xyz)
    data = encode_pose(
        seq=seq, t=1.5, stamp_ns=123, odom=p, fleet=p.compose(p), truth=p if has_truth else None,
        status={"step": 3, "maps_sent": 2},
    )
    d = decode_pose(data)
    assert d["seq"] == seq and d["t"] == 1.5 and d["stamp_ns"] == 123
    assert d["odom"].almost_equal(p) and d["fleet"].almost_equal(p.compose(p))
    assert (d["truth"] is not None) == has_truth
    assert d["status"] == {"step": 3, "maps_sent": 2}


def test_viz_round_trip_and_garbage():
    sq = Wireframe.from_polylines([[(0, 0), (2, 0), (2, 1), (0, 1)]])
    data = encode_viz(t=2.0, scan=sq, pose=Pose(1, 2, 0.5), particles=[sq, sq], weights=[0.25, 0.75])
    d = decode_viz(data)
    assert d["t"] == 2.0 and d["weights"] == [0.25, 0.75]
    assert d["scan"].almost_equal(sq, tol=1e-6) and len(d["particles"]) == 2
    for junk in (b"", b"\x00\x01", data[:-3], b"\x81\xa1t\x01"):
        with pytest.raises(ValueError):
            decode_viz(junk)
        with pytest.raises(ValueError):
            decode_pose(junk)


# ---------------------------------------------------------------------- sessions
@pytest.mark.fleet
def test_no_router_fails_fast_without_wait():
    port = free_port()
    with pytest.raises(UserError, match="cannot open"):
        open_session(build_config("client", None, [tcp_endpoint(port)]), wait=False)


@pytest.mark.fleet
def test_stop_flag_interrupts_the_wait():
    stop = threading.Event()
    cfg = build_config("client", None, [tcp_endpoint(free_port())])
    assert open_session(cfg, stop, on_wait=lambda _text: stop.set()) is None


@pytest.mark.fleet
def test_client_waits_for_a_router_started_later():
    port = free_port()
    ep = tcp_endpoint(port)
    holder: dict[str, object] = {}
    ready = threading.Event()

    def start_router(_text: str) -> None:
        # called once the first attempt failed: the router really comes up after the client
        holder["router"] = open_session(build_config("router", None, [], [ep]), wait=False)
        ready.set()

    s = open_session(build_config("client", None, [ep]), on_wait=start_router, timeout=20)
    try:
        assert ready.is_set() and s is not None
        assert len(s.info.routers_zid()) == 1
    finally:
        if s is not None:
            s.close()
        r = holder.get("router")
        if r is not None:
            r.close()  # type: ignore[attr-defined]


@pytest.mark.fleet
def test_pub_sub_and_liveliness_through_a_router():
    k = FleetKeys("t")
    with in_process_router() as ep, client(ep) as a, client(ep) as b:
        got = threading.Event()
        payloads: list[bytes] = []
        events: list[tuple[str, str]] = []
        alive_put, alive_del = threading.Event(), threading.Event()

        def on_sample(s):
            payloads.append(s.payload.to_bytes())
            got.set()

        def on_alive(s):
            events.append((str(s.kind), str(s.key_expr)))
            (alive_put if s.kind == zenoh.SampleKind.PUT else alive_del).set()

        sub = b.declare_subscriber(k.all_maps, on_sample)
        lsub = b.liveliness().declare_subscriber(k.all_alive, on_alive, history=True)
        tok = a.liveliness().declare_token(k.alive("r1"))
        assert alive_put.wait(5)
        # publish until the subscription has propagated (the first put may race it)
        for _ in range(100):
            a.put(k.robot_map("r1"), b"hello")
            if got.wait(0.1):
                break
        assert payloads and payloads[0] == b"hello"
        tok.undeclare()
        assert alive_del.wait(5)
        assert k.robot_of(events[-1][1]) == "r1"
        sub.undeclare()
        lsub.undeclare()


def test_stop_flag_catches_sigterm():
    with StopFlag() as stop:
        os.kill(os.getpid(), signal.SIGTERM)
        assert stop.wait(5)
        assert stop.signal == signal.SIGTERM
    assert signal.getsignal(signal.SIGTERM) is not None


# ---------------------------------------------------------------------- router processes
def _roundtrip(pub_ep: str, sub_ep: str, key: str) -> bytes:
    with client(pub_ep) as a, client(sub_ep) as b:
        got = threading.Event()
        box: list[bytes] = []

        def cb(s):
            box.append(s.payload.to_bytes())
            got.set()

        sub = b.declare_subscriber(key, cb)
        try:
            for _ in range(150):
                a.put(key, b"across")
                if got.wait(0.1):
                    break
        finally:
            sub.undeclare()
        return box[0] if box else b""


@pytest.mark.fleet
def test_router_process_routes_and_stops_on_sigterm(tmp_path: Path):
    port = free_port()
    ep = tcp_endpoint(port)
    with Fleet(tmp_path) as f:
        f.start("router", ["router", "--listen", ep])
        f.wait_log("router", "listening on")
        assert _roundtrip(ep, ep, "wiremap/t/robots/r1/map") == b"across"
        assert f.stop("router", signal.SIGTERM, timeout=5) == 0
        f.start("router2", ["router", "--listen", ep])
        f.wait_log("router2", "listening on")
        assert f.stop("router2", signal.SIGINT, timeout=5) == 0


@pytest.mark.fleet
def test_port_in_use_is_a_one_line_error(tmp_path: Path):
    with in_process_router() as ep, Fleet(tmp_path) as f:
        p = f.start("router", ["router", "--listen", ep])
        assert p.wait(timeout=20) == 2
        out = f.log("router")
        assert "Address already in use" in out and "Traceback" not in out


@pytest.mark.fleet
def test_two_routers_from_the_example_files(tmp_path: Path):
    """Router B (router-b.json5) connects to router A (router-a.json5); a client of B reaches a
    client of A. Ports are replaced by free ones on the command line."""
    pa, pb = free_port(), free_port()
    ea, eb = tcp_endpoint(pa), tcp_endpoint(pb)
    with Fleet(tmp_path) as f:
        # B first: it must wait for A by itself
        f.start("b", ["router", "--config", CONFIGS / "router-b.json5", "--listen", eb, "--connect", ea])
        f.wait_log("b", "listening on")
        f.start("a", ["router", "--config", CONFIGS / "router-a.json5", "--listen", ea])
        f.wait_log("a", "listening on")
        assert _roundtrip(eb, ea, "wiremap/t/robots/rb/map") == b"across"
        assert _roundtrip(ea, eb, "wiremap/t/fused/map") == b"across"


def test_numpy_free_port_distinct():
    ports = {free_port() for _ in range(5)}
    assert all(1024 < p < 65536 for p in ports)
    assert np.unique(list(ports)).size >= 1
